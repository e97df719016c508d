"""The pieces of NAVSIM's two-stage pseudo-simulation built so far (issue 39): its aggregation (known answers
worked from NAVSIM v2.2's scene_aggregator.py / run_pdm_score.py) and the second stage's cameras, rendered by the
world at a start pose off the logged one."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.metrics.pdms.two_stage import (
    SIGMA_SQUARED,
    group_score,
    stage_two_weights,
    two_stage_score,
    weighted_average,
)


def test_weights_are_navsims_gaussian_kernel_normalised():
    d = math.sqrt(SIGMA_SQUARED)  # d^2 = sigma^2: exp(-1/2) before normalising
    w = stage_two_weights((10.0, 5.0), [(10.0, 5.0), (10.0 + d, 5.0), (10.0, 5.0 - d)])
    k = math.exp(-0.5)
    assert w == pytest.approx([1 / (1 + 2 * k), k / (1 + 2 * k), k / (1 + 2 * k)], abs=1e-15)
    assert w.sum() == pytest.approx(1.0)


def test_weights_fall_back_to_uniform_when_every_start_is_far():
    assert stage_two_weights((0.0, 0.0), [(100.0, 0.0), (0.0, -80.0)]).tolist() == [0.5, 0.5]
    assert stage_two_weights((0.0, 0.0), [(np.nan, 0.0)]).tolist() == [1.0]
    assert stage_two_weights((0.0, 0.0), np.zeros((0, 2))).shape == (0,)


def test_group_and_two_stage_scores_known_answers():
    assert weighted_average([1.0, 0.5], [3.0, 1.0]) == pytest.approx(0.875)
    assert math.isnan(weighted_average([], [])) and math.isnan(weighted_average([1.0], [0.0]))
    assert group_score(0.9, [1.0, 0.5], [0.75, 0.25]) == pytest.approx(0.7875)
    assert two_stage_score((0.9, [1.0, 0.5], [0.75, 0.25]), (1.0, [0.0], [1.0])) == pytest.approx(0.39375)
    with pytest.raises(ValueError, match="2 scores for 1 weights"):
        weighted_average([1.0, 0.5], [1.0])


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    from pytest_drivedegrade.data.world import write_world

    return write_world(tmp_path_factory.mktemp("two-stage") / "w", scenes=2, workers=1)


FRONT = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT")


def test_stage_two_images_differ_from_the_logged_ones_and_equal_a_fresh_render(world):
    from pytest_drivedegrade.closedloop import camera
    from pytest_drivedegrade.closedloop.routes import load_routes
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    route = load_routes(world)[0]
    keyframe = 6  # where a plan made at keyframe 0 ends (3 s)
    frame = next(f for f in NuScenesReader(world).frames() if f.scene_name == route.name and f.index == keyframe)
    logged = {cam: NuScenesReader.load_image(frame.cameras[cam]) for cam in FRONT}
    assert frame.pose is not None
    x, y, yaw = frame.pose
    assert camera.images_at(route, FRONT, (x, y, yaw), keyframe).keys() == logged.keys()
    at_log = camera.images_at(route, FRONT, (x, y, yaw), keyframe)
    assert all(np.array_equal(at_log[c], logged[c]) for c in FRONT)  # the renderer is the data's
    # a start 0.5 m to the left of the logged ego, turned 3 degrees (a NAVSIM-style perturbed start state)
    moved = (x - 0.5 * math.sin(yaw), y + 0.5 * math.cos(yaw), yaw + math.radians(3.0))
    stage_two = camera.images_at(route, FRONT, moved, keyframe)
    for cam in FRONT:
        assert stage_two[cam].shape == logged[cam].shape
        assert np.abs(stage_two[cam].astype(int) - logged[cam]).mean() > 1.0, cam
    camera._BACKDROPS.clear()  # nothing kept from the first render: built again from the scene
    fresh = camera.images_at(route, FRONT, moved, keyframe)
    assert all(np.array_equal(fresh[c], stage_two[c]) for c in FRONT)


# -- stage two of a cell ---------------------------------------------------------------------------------------------

def test_start_poses_are_offsets_in_the_ego_frame():
    from pytest_drivedegrade.closedloop.twostage import STAGE_TWO_STARTS, start_poses

    (x, y, yaw), = start_poses((1.0, 2.0, math.pi / 2), ((1.0, 0.5, 0.1),))
    assert (x, y, yaw) == pytest.approx((0.5, 3.0, math.pi / 2 + 0.1))
    assert start_poses((1.0, 2.0, 0.3))[0] == (1.0, 2.0, 0.3) and len(STAGE_TWO_STARTS) == 7


def test_a_moved_frame_sees_the_logged_future_from_its_pose(world):
    from pytest_drivedegrade.closedloop.twostage import stage_two_frame, start_poses
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    frame = next(f for f in NuScenesReader(world).scorable_frames() if f.index == 6)
    assert frame.pose is not None
    same = stage_two_frame(frame, frame.pose, 0)
    assert np.allclose(same.gt_future, frame.gt_future, atol=1e-9) and same.pose == frame.pose
    assert np.allclose(same.ego.velocity, frame.ego.velocity) and same.past_motion is None
    left = stage_two_frame(frame, start_poses(frame.pose, ((0.0, 0.5, 0.0),))[0], 1)
    assert np.allclose(left.gt_future, frame.gt_future - [0.0, 0.5], atol=1e-9)  # half a metre left: all 0.5 right
    for a, b in zip(left.agents, frame.agents):
        assert np.allclose(a.center, np.asarray(b.center) - [0.0, 0.5], atol=1e-9)
    turned = stage_two_frame(frame, (frame.pose[0], frame.pose[1], frame.pose[2] + 0.2), 2)
    assert np.allclose(np.hypot(*turned.gt_future.T), np.hypot(*frame.gt_future.T))  # a rotation about the ego
    assert turned.token == f"{frame.token}~stage2~2"


class _Spy:
    """Reads the front cameras; plans constant velocity; keeps what it was given."""

    name = "spy"
    cameras = FRONT

    def __init__(self) -> None:
        self.seen: list[dict[str, np.ndarray]] = []

    def predict(self, images, ego, cmd):
        self.seen.append({c: np.array(images[c]) for c in FRONT})
        t = 0.5 * np.arange(1, 7)
        return np.stack([ego.velocity[0] * t, ego.velocity[1] * t], axis=1)


@pytest.mark.parametrize("family, severity", [("clean", 0), ("jpeg", 3)])
def test_stage_two_of_a_cell(world, family, severity):
    """Stage two renders at the start poses (the logged one gives the logged keyframe's images, under the cell's
    operator with the per-frame seed rule keyed by the stage-two token), plans there and scores; the frame's
    two-stage EPDMS is stage one's times stage two's; the images equal a fresh render under the operator."""
    from pytest_drivedegrade.closedloop import camera
    from pytest_drivedegrade.closedloop.twostage import STAGE_TWO_STARTS, stage_two_cell, stage_two_world, start_poses
    from pytest_drivedegrade.corruptions.api import corrupt_sample
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    context = RunContext.open(RunSettings(data=world, frames=3))
    spy = _Spy()
    record = context.run_cell(spy, family, severity)
    spy.seen.clear()
    result = stage_two_cell(context, spy, record)
    later = {f.index: f for f in NuScenesReader(world).scorable_frames()}
    have = [i for i, f in enumerate(context.frames) if f.index + 6 in later]
    assert have and result.frames == len(have) and len(spy.seen) == len(have) * len(STAGE_TWO_STARTS)
    for i in have:
        assert 0.0 <= result.stage_two[i] <= 1.0
        assert result.two_stage[i] == pytest.approx(record.epdms[i] * result.stage_two[i])
    first = later[context.frames[have[0]].index + 6]
    logged = {c: NuScenesReader.load_image(first.cameras[c]) for c in FRONT}

    def corrupted(images, n):
        return corrupt_sample(images, family, severity, seed=context.seed, frame=f"{first.token}~stage2~{n}") \
            if family != "clean" else images

    expected = corrupted(logged, 0)
    assert all(np.array_equal(spy.seen[0][c], expected[c]) for c in FRONT)  # at the logged pose: the data's
    assert all(not np.array_equal(spy.seen[1][c], expected[c]) for c in FRONT)  # half a metre left: not
    route = stage_two_world(context).routes[first.scene_name]
    fresh = corrupted(camera.images_at(route, FRONT, start_poses(first.pose)[1], first.index), 1)
    assert all(np.array_equal(spy.seen[1][c], fresh[c]) for c in FRONT)  # a fresh render, corrupted alike


def test_stage_two_from_the_logged_pose_scores_as_the_cell_scored_that_keyframe(world):
    """From the logged pose, stage two is the cell's own frame at that keyframe: the same plan (constant velocity
    from the same state), the same terms; its EPDMS is the cell's without the terms stage two does not score (ec:
    no previous plan; hc: no past)."""
    from pytest_drivedegrade.closedloop.twostage import stage_two_cell
    from pytest_drivedegrade.metrics.pdms.extended import ExtendedTerms, epdms_score
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    context = RunContext.open(RunSettings(data=world))
    spy = _Spy()
    record = context.run_cell(spy, "clean", 0)
    at_log = stage_two_cell(context, spy, record, offsets=((0.0, 0.0, 0.0),))
    for j in (6, 12, 20):
        assert context.frames[j].index == j
        i = j - 6  # the frame whose stage two starts at keyframe j
        terms = ExtendedTerms(*(float(record.array(k)[j]) for k in ("nc", "dac", "ddc", "tlc", "ep", "ttc", "lk")),
                              1.0)
        assert at_log.stage_two[i] == pytest.approx(epdms_score(terms, math.nan), abs=1e-9), j


def test_epdms2_retention_summary_and_gate():
    """A cell's two-stage figures (`pdms_metrics`): the means over the frames that have a stage two, the paired
    retention over frames finite in both; absent without a stage two; the baseline gate reads `epdms2_retention`
    under --drivedegrade-metric epdms2 and names the metric."""
    from pytest_drivedegrade.cells import CellRecord
    from pytest_drivedegrade.scoring.baseline import cell_regression
    from pytest_drivedegrade.scoring.retention import pdms_metrics
    from pytest_drivedegrade.scoring.verdict import retention_of

    def record(cell, epdms2, stage2):
        n = len(epdms2)
        return CellRecord(cell, cell.split("-")[0], 3 if "-" in cell else 0, [f"t{i}" for i in range(n)],
                          np.zeros((n, 6, 2)), np.zeros((n, 6)), np.zeros((n, 6)), np.zeros((n, 6)), np.zeros(n),
                          np.zeros(n), epdms=np.ones(n), epdms2=np.array(epdms2), epdms_stage2=np.array(stage2))

    clean = record("clean", [0.8, 0.4, np.nan, 0.6], [0.8, 0.4, np.nan, 0.6])
    cell = record("jpeg-s3", [0.4, 0.4, 0.9, np.nan], [0.4, 0.4, 0.9, np.nan])
    got = pdms_metrics(cell, clean, n_resamples=0)
    assert got["epdms2"] == pytest.approx((0.4 + 0.4 + 0.9) / 3) and got["epdms2_frames"] == 3
    assert got["epdms2_retention"] == pytest.approx(0.8 / 1.2)  # frames 0 and 1: finite in both
    assert "epdms2" not in pdms_metrics(record("clean", [np.nan] * 2, [np.nan] * 2),
                                        record("clean", [np.nan] * 2, [np.nan] * 2), n_resamples=0)

    class Summary:
        metrics = got
        retention = 1.0

    assert retention_of(Summary(), "epdms2") == pytest.approx(0.8 / 1.2)  # type: ignore[arg-type]
    baseline = {"cells": [{"cell": "jpeg-s3", "retention": 0.5, "epdms2_retention": 0.9}]}
    reg = cell_regression("jpeg-s3", 0.7, baseline, 0.05, "epdms2")
    assert reg is not None and reg.baseline == 0.9 and "two-stage EPDMS retention" in reg.message()
    assert cell_regression("jpeg-s3", 0.7, baseline, 0.05, "l2") is None  # L2: baseline 0.5, no drop
