"""PDMS per cell (spec 3) and the ego ladder (SPEC section 10): stored records without PDMS arrays, PDMS retention
and axes_pdms, the verdict on PDMS, the ego perturbation and the ego axis, with known answers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_analysis import GROUPS, synthetic_run

from pytest_drivedegrade.cells import PDMS_FIELDS, RECORD_VERSION, CellRecord, cell_id, is_ego, run_order
from pytest_drivedegrade.constants import PAST_STEPS
from pytest_drivedegrade.corruptions import ego as E  # noqa: N812
from pytest_drivedegrade.data.frame import EgoStatus
from pytest_drivedegrade.report.columns import CSV, PDMS
from pytest_drivedegrade.scoring import verdict as vd
from pytest_drivedegrade.scoring.analyse import analyse_run
from pytest_drivedegrade.scoring.retention import pdms_metrics


def with_pdms(rec: CellRecord, pdms: np.ndarray) -> CellRecord:
    rec.pdms = np.asarray(pdms, dtype=float)
    for k in ("nc", "dac", "ttc", "ep", "comfort"):
        setattr(rec, k, np.ones(len(rec.frames)))
    rec.map_scored = np.ones(len(rec.frames))
    return rec


def test_a_record_stored_before_pdms_loads_with_nan_and_the_run_key_changed():
    recs, _ = synthetic_run(4)
    data = recs[0].to_builtins()
    for k in (*PDMS_FIELDS, "map_scored"):
        data.pop(k)
    old = CellRecord.from_builtins(json.loads(json.dumps(data)))
    assert all(np.isnan(getattr(old, k)).all() and getattr(old, k).shape == (4,) for k in PDMS_FIELDS)
    assert RECORD_VERSION >= 2
    fresh = with_pdms(recs[1], np.linspace(0.2, 0.9, 4))
    back = CellRecord.from_builtins(json.loads(json.dumps(fresh.to_builtins(), allow_nan=True)))
    np.testing.assert_array_equal(back.pdms, fresh.pdms)


def test_pdms_retention_is_a_reward_ratio_with_a_paired_ci():
    recs, _ = synthetic_run(40)
    clean = with_pdms(recs[0], np.full(40, 0.8))
    cell = with_pdms(recs[3], np.full(40, 0.6))
    m = pdms_metrics(cell, clean, n_resamples=200)
    assert m["pdms"] == pytest.approx(0.6) and m["pdms_retention"] == pytest.approx(0.75)
    assert m["pdms_retention_ci_low"] == pytest.approx(0.75) == m["pdms_retention_ci_high"]  # constant frames
    assert pdms_metrics(clean, clean)["pdms_retention"] == 1.0
    unscored = pdms_metrics(recs[4], recs[4])
    assert math.isnan(unscored["pdms"]) and math.isnan(unscored["pdms_retention"])
    assert set(PDMS) <= set(CSV)


def test_axes_pdms_and_the_verdict_on_pdms():
    """L2 says camera-reliant; PDMS is flat everywhere (every plan drives fine): axes_pdms at 1.000 and, with
    metric="pdms", the verdict is put on PDMS: flat on both axes. Its plans move with the cameras (the L2 cells show
    it), so since issue 40 the label is camera-sensitive (plans move, the score holds), never "not shown to use its
    cameras"."""
    recs, _ = synthetic_run(20)
    for r in recs:
        with_pdms(r, np.full(20, 0.9))
    on_l2 = analyse_run(recs, groups=GROUPS, n_resamples=50)
    on_pdms = analyse_run(recs, groups=GROUPS, n_resamples=50, metric="pdms")
    assert on_l2.verdict.label == "camera-reliant" and on_l2.verdict.metric == "l2"
    assert on_pdms.axes_pdms.quality == pytest.approx(1.0) and on_pdms.axes_pdms.removal == pytest.approx(1.0)
    assert on_pdms.verdict.label == "camera-sensitive" and on_pdms.verdict.metric == "pdms"
    assert on_pdms.verdict.case == "accuracy-holds" and on_pdms.verdict.text.startswith("On PDMS retention: ")
    assert on_pdms.axes == on_l2.axes and on_pdms.settings["verdict_metric"] == "pdms"
    with pytest.raises(Exception, match="metric"):
        analyse_run(recs, groups=GROUPS, metric="mse")


# -- the ego ladder -----------------------------------------------------------------------------------------

EGO = EgoStatus((8.0, 0.1), (0.5, -0.2), 0.05, np.stack([np.linspace(-16, -4, PAST_STEPS), np.zeros(PAST_STEPS)], 1))
BUS = np.arange(18, dtype=float)


def test_ego_cells_follow_the_ladder_and_stay_outside_the_camera_axes():
    order = [cell_id(f, s) for f, s in run_order(["jpeg"], [1, 2, 3, 4, 5])]
    assert order[-10:] == ["ego_noise-s1", "ego_noise-s2", "ego_noise-s3", "ego_noise-s4", "ego_noise-s5",
                           "ego_blind", "command_blind", "command_swap", "blind", "null"]  # command cells: issue 40
    assert is_ego("ego_noise") and is_ego("ego_blind") and not is_ego("blind")


@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
def test_ego_noise_has_the_spec_sigmas_and_is_seeded(severity):
    sd = E.sigmas(severity)
    assert (sd["velocity"], sd["acceleration"], sd["yaw_rate"], sd["past_xy"]) == \
        ((0.1, 0.2, 0.4, 0.8, 1.6)[severity - 1], (0.1, 0.2, 0.4, 0.8, 1.6)[severity - 1],
         (0.01, 0.02, 0.04, 0.08, 0.16)[severity - 1], (0.05, 0.1, 0.2, 0.4, 0.8)[severity - 1])
    a, bus_a = E.perturb(EGO, BUS, "ego_noise", severity, seed=0, frame="tok")
    b, bus_b = E.perturb(EGO, BUS, "ego_noise", severity, seed=0, frame="tok")
    c, _ = E.perturb(EGO, BUS, "ego_noise", severity, seed=1, frame="tok")
    assert a.velocity == b.velocity and np.array_equal(bus_a, bus_b) and a.velocity != c.velocity
    dv = np.subtract(a.velocity, EGO.velocity)
    assert np.allclose(bus_a[13:15] - BUS[13:15], dv) and bus_a[12] - BUS[12] == pytest.approx(a.yaw_rate - 0.05)
    assert np.allclose(bus_a[7:9] - BUS[7:9], np.subtract(a.acceleration, EGO.acceleration))
    assert np.array_equal(bus_a[:7], BUS[:7]) and np.array_equal(bus_a[16:], BUS[16:])  # pose and heading kept
    assert not a.past_xy.flags.writeable and not bus_a.flags.writeable


def test_ego_noise_spread_matches_the_sigma():
    draws = np.array([E.perturb(EGO, None, "ego_noise", 5, seed=0, frame=f"t{i}")[0].velocity for i in range(3000)])
    assert np.std(draws[:, 0] - 8.0) == pytest.approx(1.6, rel=0.06)
    rng = E.rng_for(0, "t0", "EGO", "ego_noise", 5)  # the seed names the camera EGO
    assert draws[0, 0] - 8.0 == pytest.approx(rng.normal(0.0, 1.6))


def test_ego_blind_zeroes_the_motion_and_keeps_the_rest():
    out, bus = E.perturb(EGO, BUS, "ego_blind", 0, seed=0, frame="tok")
    assert out.velocity == (0.0, 0.0) and out.acceleration == (0.0, 0.0) and out.yaw_rate == 0.0
    assert not out.past_xy.any() and out.past_xy.shape == EGO.past_xy.shape
    assert not bus[7:16].any() and np.array_equal(bus[:7], BUS[:7]) and np.array_equal(bus[16:], BUS[16:])
    same, same_bus = E.perturb(EGO, BUS, "null", 0, seed=0, frame="tok")
    assert same is EGO and same_bus is BUS  # other cells (the null control) untouched


def test_ego_axis_and_label():
    recs, _ = synthetic_run(20)
    recs[0] = with_pdms(recs[0], np.full(20, 0.9))
    clean = recs[0]
    noisy = CellRecord("ego_noise-s5", "ego_noise", 5, clean.frames, clean.plans, clean.l2 * 1.02, clean.collision,
                       clean.collision_vru, clean.jerk, clean.bit1)
    blind = CellRecord("ego_blind", "ego_blind", 0, clean.frames, clean.plans, clean.l2 * 3.0, clean.collision,
                       clean.collision_vru, clean.jerk, clean.bit1)
    out = analyse_run([*recs, noisy, blind], groups=GROUPS, n_resamples=50)
    assert out.axes.ego == pytest.approx(1 / 1.02) and out.axes.ego_removal == pytest.approx(1 / 3)
    assert out.verdict.ego_label == "ego-reliant"
    assert "ego_noise" not in out.s5()
    assert out.axes.quality == analyse_run(recs, groups=GROUPS, n_resamples=50).axes.quality
    assert vd.ego_label(0.97) == "ego-insensitive" and vd.ego_label(None) == "undetermined"
    assert analyse_run(recs, groups=GROUPS, n_resamples=50).verdict.ego_label == "undetermined"
