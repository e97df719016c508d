"""Issue 40 (plan movement beside accuracy): hidden-behaviour planners as synthetic records with known answers.

A planner whose plans move with its cameras while its error holds or falls has flat camera axes exactly like a
planner that ignores its images; only the second may be worded "cannot tell it apart from a planner that ignores
images". Each planner below is a set of cell records whose plans are built to a known behaviour.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_analysis import GROUPS, ORDER, record
from test_trust2_units import _cert

from pytest_drivedegrade.certificate.consistency import check_verdict
from pytest_drivedegrade.certificate.reliance_check import expected_label
from pytest_drivedegrade.scoring.analyse import analyse_run
from pytest_drivedegrade.scoring.records import Axes, AxisIntervals
from pytest_drivedegrade.scoring.reliance import CAMERA_SENSITIVE, plan_movement, read_movement
from pytest_drivedegrade.scoring.verdict import verdict

IGNORES = "cannot tell it apart from a planner that ignores images"


def planner_run(n: int, plans_of, seed: int = 0):
    """Records for clean, null, blind and every family S1..S5 whose plans are ``plans_of(gt, clean, fam, sev)``
    (clean's own are ``plans_of(gt, None, "clean", 0)``); null is clean's, bit for bit."""
    rng = np.random.default_rng(seed)
    t = np.arange(1, 7) * 0.5
    speed = rng.uniform(2, 8, size=(n, 1))
    gt = np.stack([speed * t, 0.05 * speed * t**2 * rng.normal(size=(n, 1))], axis=-1)
    clean = plans_of(gt, None, "clean", 0, rng)
    recs = [record("clean", "clean", 0, clean, gt), record("null", "null", 0, clean.copy(), gt),
            record("blind", "blind", 0, plans_of(gt, clean, "blind", 0, rng), gt)]
    recs += [record(f"{f}-s{s}", f, s, plans_of(gt, clean, f, s, rng), gt) for f in ORDER for s in range(1, 6)]
    return recs


def _bias(gt: np.ndarray) -> np.ndarray:
    """A weak planner's error: 2 m lateral at 3 s, growing with time, alike on every frame."""
    return np.broadcast_to(np.stack([np.zeros(6), np.linspace(0.3, 2.0, 6)], axis=-1), gt.shape)


def misled(gt, clean, fam, sev, rng):
    """Plans move under corruption while the error falls: the worse the images, the less of its bias is left
    (a weak planner misled by what it sees; issue 40's LAW port). Clean keeps its whole bias."""
    keep = 1.0 if clean is None else (0.4 if fam == "blind" else 1.0 - 0.1 * sev)
    return gt + _bias(gt) * keep + 0.01 * rng.normal(size=gt.shape)


def mirrored(gt, clean, fam, sev, rng):
    """Plans move under corruption, error unchanged frame by frame: the lateral error flips side."""
    if clean is None:
        return gt + _bias(gt)
    flip = fam == "blind" or sev >= 3
    return gt + _bias(gt) * np.array([1.0, -1.0 if flip else 1.0])


def ignores(gt, clean, fam, sev, rng):
    """Never reads its images: every cell plans what clean planned, bit for bit."""
    return gt + _bias(gt) if clean is None else clean.copy()


def test_a_planner_misled_by_its_images_is_never_worded_as_ignoring_them_and_verify_agrees() -> None:
    res = analyse_run(planner_run(24, misled), groups=GROUPS, n_resamples=200)
    v = res.verdict
    assert res.axes.quality is not None and res.axes.quality > 1.0 and res.axes.removal > 1.0
    assert (v.label, v.case, v.computed_label) == (CAMERA_SENSITIVE, "gains-from-loss", CAMERA_SENSITIVE)
    assert IGNORES not in v.text and "accuracy rises when image quality degrades" in v.text
    assert "9 of 9" not in v.text and "11 of 11 camera cells beyond the null's wander of 0 m" in v.text
    assert v.confidence == pytest.approx(1.0)  # every resample is flat on both axes
    assert res.reliance is not None and res.reliance.of("presence").moves is True
    assert res.reliance.of("ego").moves is None and res.reliance.of("command").shift is None  # not run
    cert = _with_reliance(res)
    assert check_verdict(cert, cert["cells"], GROUPS) == []
    forged = dict(cert, verdict={**cert["verdict"], "label": "not-shown-to-use-cameras"})
    assert any("verdict.label: certificate says 'not-shown-to-use-cameras'" in p and "'camera-sensitive'" in p
               for p in check_verdict(forged, forged["cells"], GROUPS))


def test_a_planner_whose_plans_move_while_its_error_holds_is_camera_sensitive() -> None:
    res = analyse_run(planner_run(16, mirrored), groups=GROUPS, n_resamples=100)
    v = res.verdict
    assert res.axes.quality == pytest.approx(1.0, abs=1e-9) and res.axes.removal == pytest.approx(1.0, abs=1e-9)
    assert (v.label, v.case) == (CAMERA_SENSITIVE, "accuracy-holds")
    assert "reads its cameras without gaining accuracy from them" in v.text and IGNORES not in v.text


def test_a_planner_that_truly_ignores_its_images_still_is_not_shown_to_use_cameras() -> None:
    res = analyse_run(planner_run(16, ignores), groups=GROUPS, n_resamples=100)
    v = res.verdict
    assert (v.label, v.case) == ("not-shown-to-use-cameras", "both-flat")
    assert IGNORES in v.text and "Its plans do not move" in v.text and "0 of 11 camera cells" in v.text
    assert res.reliance is not None and not res.reliance.cameras_move()
    cert = _with_reliance(res)
    assert check_verdict(cert, cert["cells"], GROUPS) == []


def test_movement_within_the_nulls_wander_is_not_movement() -> None:
    shifts = {"fog-s5": 0.2, "blackout-s5": 0.05, "blind": 0.3, "ego_blind": 0.31}
    got = plan_movement(shifts, 0.3, quality=("fog", "snow"))
    assert got.of("quality").cells == ("fog-s5",) and got.of("quality").moves is False
    assert got.of("presence").shift == pytest.approx(0.175) and got.of("presence").moves is False
    assert got.of("ego").moved == ("ego_blind",) and got.of("command").moves is None
    assert not got.cameras_move() and plan_movement(shifts, 0.0, quality=("fog",)).cameras_move()


@pytest.mark.parametrize("q, r, q_ci, r_ci, label, says, never", [
    # quality flat with its interval above 1 while removal falls: the gain is said, never "stays flat"
    (1.08, 0.80, (1.03, 1.12), (0.7, 0.9), "quality-insensitive", "accuracy rises when image quality degrades",
     "planning stays flat when image quality degrades"),
    # an interval reaching 1: no gain claimed, the old words stand
    (1.08, 0.80, (0.99, 1.12), (0.7, 0.9), "quality-insensitive", "planning stays flat when image quality",
     "rises"),
    # removal raising accuracy beyond its interval on a quality-reliant planner
    (0.80, 1.10, (0.7, 0.9), (1.05, 1.2), "camera-reliant", "removing cameras raises its accuracy",
     "removing cameras leaves it flat"),
])
def test_retention_above_one_beyond_its_interval_is_its_own_finding(q, r, q_ci, r_ci, label, says, never) -> None:
    axes = Axes(q, r, q - r, None, intervals=AxisIntervals(quality=q_ci, removal=r_ci))
    moved = plan_movement({"fog-s5": 1.0, "blackout-s5": 1.0}, 0.0, quality=("fog",))
    v = read_movement(verdict(axes, 0.95), axes, moved)
    assert v.label == label and says in v.text and never not in v.text


def test_a_certificate_of_spec_4_keeps_the_axes_label() -> None:
    """Without a reliance section (spec 4 and earlier) a moving planner's not-shown label is read as written."""
    res = analyse_run(planner_run(12, mirrored), groups=GROUPS, n_resamples=50)
    cert = _with_reliance(res)
    old = {k: v for k, v in cert.items() if k != "reliance"}
    old["verdict"] = {**old["verdict"], "label": "not-shown-to-use-cameras", "computed_label": None}
    old["verdict"].pop("computed_label")
    assert check_verdict(old, old["cells"], GROUPS) == []
    assert expected_label(cert["axes"], 0.95, None) == "not-shown-to-use-cameras"


def test_a_tampered_reliance_section_is_named() -> None:
    res = analyse_run(planner_run(12, mirrored), groups=GROUPS, n_resamples=50)
    cert = _with_reliance(res)
    cert["reliance"] = {**cert["reliance"], "quality": {**cert["reliance"]["quality"], "moved": []}}
    problems = check_verdict(cert, cert["cells"], GROUPS)
    assert any(p.startswith("reliance.quality.moved: certificate says []") for p in problems)


def _with_reliance(res) -> dict:
    """`_cert` with the cells' endpoint shifts and the reliance section, as the certificate carries them."""
    cert = _cert(res)
    shifts = {s.cell: s.metrics["endpoint_shift"] for s in res.summaries}
    cert["cells"] = [{**c, "endpoint_shift": round(shifts[c["cell"]], 6)} for c in cert["cells"]]
    cert["reliance"] = res.reliance.to_builtins()
    return cert


def test_the_profile_shows_each_input_with_what_accuracy_did() -> None:
    from pytest_drivedegrade.report.junit import suite_properties
    from pytest_drivedegrade.report.profile import profile_lines, profile_rows, reliance_profile

    res = analyse_run(planner_run(16, misled), groups=GROUPS, n_resamples=100)
    rows = {r["input"]: r for r in profile_rows(res.reliance, res.axes, 0.95)}
    assert list(rows) == ["quality", "presence", "ego", "command"]
    assert rows["quality"]["accuracy"] == "rises" and rows["presence"]["moves"] is True
    assert rows["ego"]["shift"] is None and rows["command"]["accuracy"] == "n/a"  # not probed, never a zero
    lines = profile_lines(res.reliance, res.axes, 0.95)
    assert lines[2] == "  ego status: not probed" and "(rises)" in lines[0]
    props = dict(suite_properties(res))
    assert props["drivedegrade_reliance_presence_moves"] == "true"
    assert props["drivedegrade_reliance_command_shift"] == "none"
    assert props["drivedegrade_reliance_quality_shift"] == pytest.approx(res.reliance.of("quality").shift, abs=1e-6)
    chart = reliance_profile(res.reliance, res.axes, 0.95, planner="misled")
    assert chart is not None and chart.startswith("data:image/png;base64,")
    assert reliance_profile(None, res.axes, 0.95, planner="old") is None


def test_compare_notes_a_certificate_without_plan_movement() -> None:
    from pytest_drivedegrade.certificate.compare import certificate_row, movement_notes

    new = {"spec_version": "5.0.0", "reliance": {"wander": 0.0}, "verdict": {"label": "camera-sensitive"}}
    old = {"spec_version": "4.1.0", "verdict": {"label": "not-shown-to-use-cameras"}}
    notes = movement_notes([("a.json", new), ("b.json", old)])
    assert len(notes) == 1 and notes[0].startswith("b.json (spec 4.1.0) records no plan movement")
    assert movement_notes([("a.json", old), ("b.json", old)]) == []
    assert certificate_row(old)["plan_movement"] == "not recorded" and certificate_row(new)["plan_movement"] == \
        "recorded"


def test_the_floor_warning_says_what_it_knows_and_a_miswired_adapter_is_one_cause() -> None:
    from types import SimpleNamespace

    from pytest_drivedegrade.report.terminal import floor_warning

    got = floor_warning(SimpleNamespace(summaries=[SimpleNamespace(cell="clean", l2_avg=2.6)],
                                        floor=SimpleNamespace(l2_avg=0.34)))
    assert got is not None and "clean L2 2.600 m, floor 0.340 m, 7.6x" in got
    assert "usually means" not in got and "Causes include a miswired adapter" in got
    assert "weaker than ego status" in got and "perception-free" in got


def test_command_blind_gives_every_frame_the_constant_command_and_runs_after_the_ego_cells() -> None:
    from pytest_drivedegrade.cells import cell_id, is_camera_ladder, is_input, run_order
    from pytest_drivedegrade.corruptions.command import NEUTRAL_COMMAND, command_for
    from pytest_drivedegrade.data.frame import Command

    assert Command(NEUTRAL_COMMAND) is Command.STRAIGHT
    assert [command_for(c, "command_blind") for c in Command] == [Command.STRAIGHT] * 3
    assert all(type(command_for(c, "command_blind")) is Command for c in Command)
    assert [command_for(c, f) for c in Command for f in ("clean", "ego_blind", "fog")] == \
        [c for c in Command for _ in range(3)]
    assert cell_id("command_blind", 0) == "command_blind" and is_input("command_blind")
    assert not is_camera_ladder("command_blind")
    assert run_order(["fog"], [5])[-4:] == [("command_blind", 0), ("command_swap", 0), ("blind", 0), ("null", 0)]
    assert ("command_blind", 0) not in run_order(["fog"], [5], ego=("ego_noise", "ego_blind"))
