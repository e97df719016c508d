"""The planner contract: output validation, declared cameras, names and fingerprints (pytest_drivedegrade.planning)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.errors import DriveDegradeError, InvalidInput, PlannerOutputError
from pytest_drivedegrade.planning import (
    Command,
    EgoStatus,
    Planner,
    planner_cameras,
    planner_fingerprint,
    planner_name,
    predict_checked,
    validate_output,
)

GOOD = np.arange(12, dtype=np.float32).reshape(6, 2)


def test_valid_output_comes_back_as_a_float64_copy() -> None:
    out = validate_output(GOOD, "tok")
    assert out.dtype == np.float64 and out.shape == (6, 2)
    np.testing.assert_array_equal(out, GOOD)
    out[0, 0] = 99.0
    assert GOOD[0, 0] == 0.0  # a copy: the planner's own buffer is never aliased


def test_lists_and_tensors_are_accepted() -> None:
    np.testing.assert_array_equal(validate_output(GOOD.tolist(), "tok"), GOOD)
    tensor = torch.from_numpy(GOOD.copy()).requires_grad_(True)
    np.testing.assert_array_equal(validate_output(tensor * 1.0, "tok"), GOOD)


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        (np.zeros((5, 2)), r"shape \(5, 2\)"),
        (np.zeros(12), r"shape \(12,\)"),
        (np.zeros((6, 2), dtype=np.int64), "dtype int64"),
        (np.zeros((6, 2), dtype=bool), "dtype bool"),
        (np.full((6, 2), np.nan), "not finite .first at step 0, coordinate 0"),
        (np.where(np.eye(6, 2, k=-3) > 0, np.inf, 0.0), "not finite .first at step 3, coordinate 0"),
        (None, "is None"),
        ("left", "dtype <U4"),
        ([[1.0, 2.0], [3.0]], "not an array"),
    ],
)
def test_violations_name_the_frame_and_show_the_value(value, problem) -> None:
    with pytest.raises(PlannerOutputError, match=problem) as info:
        validate_output(value, "frame-abc123")
    message = str(info.value)
    assert "'frame-abc123'" in message and "(6, 2) float array" in message
    assert isinstance(info.value, DriveDegradeError)


def test_message_shows_the_offending_numbers() -> None:
    bad = np.array([[1.5, math.nan]] * 6)
    with pytest.raises(PlannerOutputError, match=r"1\.5, +nan"):
        validate_output(bad, "t")


def test_huge_values_are_truncated_in_the_message() -> None:
    with pytest.raises(PlannerOutputError) as info:
        validate_output(np.zeros((1000, 1000)), "t")
    assert len(str(info.value)) < 800


class Straight:
    def predict(self, images, ego, cmd):
        return np.stack([np.arange(1, 7) * ego.velocity[0] * 0.5, np.zeros(6)], axis=1)


def test_protocol_and_predict_checked() -> None:
    assert isinstance(Straight(), Planner) and not isinstance(object(), Planner)
    ego = EgoStatus((4.0, 0.0), (0.0, 0.0), 0.0)
    out = predict_checked(Straight(), {}, ego, Command.STRAIGHT, "tok")
    np.testing.assert_allclose(out[:, 0], [2, 4, 6, 8, 10, 12])


def test_command_order_is_uniads() -> None:
    assert (Command.RIGHT, Command.LEFT, Command.STRAIGHT) == (0, 1, 2)


class Declares:
    def __init__(self, **attrs):
        self.__dict__.update(attrs)

    def predict(self, images, ego, cmd):
        return GOOD


def test_cameras_default_to_all_six_and_keep_canonical_order() -> None:
    assert planner_cameras(Declares()) == CAMERAS
    assert planner_cameras(Declares(cameras=None)) == CAMERAS
    assert planner_cameras(Declares(cameras=["CAM_BACK", "CAM_FRONT", "CAM_FRONT"])) == ("CAM_FRONT", "CAM_BACK")
    assert planner_cameras(Declares(cameras=())) == ()


@pytest.mark.parametrize(
    ("cameras", "message"),
    [
        ("CAM_FRONT", r"the string 'CAM_FRONT'; write cameras = \('CAM_FRONT',\)"),
        (("CAM_FRONT", "cam_back"), r"unknown camera\(s\) \['cam_back'\]; valid names are CAM_FRONT, "),
        (3, "collection of camera names"),
    ],
)
def test_bad_camera_declarations_are_clear(cameras, message) -> None:
    with pytest.raises(InvalidInput, match=message):
        planner_cameras(Declares(cameras=cameras))


def test_name_default_and_validation() -> None:
    assert planner_name(Declares(), "myplanner") == "myplanner"
    assert planner_name(Declares(name=" uniad "), "x") == "uniad"
    for bad in ("", "../etc", "a/b", 5):
        with pytest.raises(InvalidInput):
            planner_name(Declares(name=bad), "x")


def test_fingerprint_tracks_source_weights_and_declarations(tmp_path) -> None:
    src = tmp_path / "p.py"
    src.write_text("# planner v1\n")
    net = torch.nn.Linear(2, 2)
    a = Declares(model=net)
    fp1 = planner_fingerprint(a, src)
    assert fp1 == planner_fingerprint(a, src) and len(fp1) == 64
    with torch.no_grad():
        net.weight[0, 0] += 1e-3
    fp2 = planner_fingerprint(a, src)
    assert fp2 != fp1  # weights changed
    src.write_text("# planner v2\n")
    assert planner_fingerprint(a, src) != fp2  # source changed
    b = Declares(fingerprint="w-1")
    assert planner_fingerprint(b, src) != planner_fingerprint(Declares(fingerprint="w-2"), src)
    assert planner_fingerprint(Declares(fingerprint=lambda: "w-1"), src) == planner_fingerprint(b, src)
    assert planner_fingerprint(b, src) != planner_fingerprint(Declares(fingerprint="w-1", cameras=()), src)


def test_fingerprint_without_a_path_uses_the_class_source() -> None:
    assert planner_fingerprint(Straight()) == planner_fingerprint(Straight(), None)
    assert planner_fingerprint(Straight()) != planner_fingerprint(Declares())


def test_names_are_printable_bidi_free_and_short() -> None:
    for bad, what in (("evil\u202eplanner", "bidirectional control character U\\+202E at position 4"),
                      ("a\u2066b", "bidirectional control character U\\+2066"),
                      ("tab\there", "non-printable character U\\+0009 at position 3"),
                      ("x" * 65, "is 65 characters long")):
        with pytest.raises(InvalidInput, match=what):
            planner_name(Declares(name=bad), "x")
    assert planner_name(Declares(name="ü" * 64), "x") == "ü" * 64
    with pytest.raises(InvalidInput, match="file name"):
        planner_name(Declares(), "bad\u202ename")


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_precision_tensors_are_accepted(dtype) -> None:
    """Trust case 12: a bfloat16 / float16 plan (a model under autocast) is a float plan, widened to float64,
    not "predict() raised" (numpy has no bfloat16, so ``tensor.numpy()`` itself fails)."""
    plan = torch.tensor(GOOD + 0.5, dtype=dtype)
    out = validate_output(plan, "tok")
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, plan.double().numpy())
    np.testing.assert_array_equal(out, GOOD + 0.5)  # halves are exact in both formats
    with pytest.raises(PlannerOutputError, match="not finite"):
        validate_output(torch.full((6, 2), float("nan"), dtype=dtype), "tok")


@pytest.mark.parametrize(("value", "distance"), [(1e200, "1e\\+200 m"), (1e308, "1e\\+308 m"), (1000.1, "1000.14 m"),
                                                   (-1000.1, "1000.14 m")])
def test_waypoints_beyond_a_kilometre_are_contract_failures(value, distance) -> None:
    """Trust case 9: a huge but finite plan (1e200) is refused naming the frame, the step and the value, instead
    of overflowing every metric with no error reported; 1 km from the ego is the physical bound."""
    plan = GOOD.astype(np.float64)
    plan[4, 0] = value
    with pytest.raises(PlannerOutputError, match=f"frame 'tok-9'.* waypoint {distance} from the ego at step 4 "
                                                 r".*beyond the physical bound of 1000 m"):
        validate_output(plan, "tok-9")
    plan[4, 0] = 999.0  # just inside: accepted
    assert validate_output(plan, "tok")[4, 0] == 999.0
