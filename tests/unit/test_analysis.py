"""Known answers and properties of the analysis layer: retention, bootstrap, thresholds, axes, verdict, baseline.

``synthetic_run`` builds a whole run of cell records without a planner; the certificate and report tests
import it from here.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.cells import CellRecord
from pytest_drivedegrade.errors import InvalidInput
from pytest_drivedegrade.scoring import baseline as bl
from pytest_drivedegrade.scoring import records as rc
from pytest_drivedegrade.scoring import retention as rt
from pytest_drivedegrade.scoring import verdict as vd
from pytest_drivedegrade.scoring.analyse import analyse_run
from pytest_drivedegrade.scoring.verdict import FamilyGroups

ORDER = ("gaussian_blur", "motion_blur", "gaussian_noise", "low_light", "jpeg", "downscale", "color_quant", "fog",
         "snow", "frame_dropout", "blackout", "bit_error", "raindrop", "occlusion", "mud_splash", "lens_dirt")
GROUPS = FamilyGroups(quality=ORDER[:9], core=ORDER[:12], order=ORDER)


def record(cell: str, family: str, severity: int, plans: np.ndarray, gt: np.ndarray, bit1: float = 0.45,
           collide_every: int = 0) -> CellRecord:
    """A record whose per-step L2 is the true distance between `plans` (F, 6, 2) and `gt` (F, 6, 2)."""
    n = len(plans)
    col = np.zeros((n, 6))
    if collide_every:
        col[::collide_every, 3:] = 1
    return CellRecord(cell, family, severity, [f"tok{i:03d}" for i in range(n)], plans,
                      np.linalg.norm(plans - gt, axis=-1), col, col * 0, np.linalg.norm(plans[:, :3], axis=(1, 2)),
                      np.full(n, bit1), {"total": 1.0}, [])


def synthetic_run(n_frames: int = 30, damage=None, families=ORDER, seed: int = 0, null_wander: float = 0.0):
    """Records for clean, null, blind and every family S1..S5, plus the ground truth by frame token.

    Each cell's plan error is clean's error scaled by (1 + damage(family, severity)), so its retention is
    close to 1 / (1 + damage). The default damage makes a camera-reliant planner.
    """
    rng = np.random.default_rng(seed)
    damage = damage or (lambda fam, s: (0.06 if fam in ORDER[:9] else 0.12) * s * s / 5)
    t = np.arange(1, 7) * 0.5
    speed = rng.uniform(2, 8, size=(n_frames, 1))
    gt = np.stack([speed * t, 0.1 * speed * t**2 * rng.normal(size=(n_frames, 1))], axis=-1)
    base = rng.normal(size=(n_frames, 6, 2)) * 0.25 * t[None, :, None]

    def cell(cell_id, fam, sev, d, extra=0.0):
        noise = rng.normal(size=base.shape) * 0.02 * d
        plans = gt + base * (1 + d) + noise + extra
        return record(cell_id, fam, sev, plans, gt, bit1=0.45 * (1 - 0.05 * d), collide_every=max(1, 12 - sev))

    recs = [record("clean", "clean", 0, gt + base, gt, collide_every=12),
            record("null", "null", 0, gt + base + null_wander, gt, collide_every=12),
            cell("blind", "blind", 0, 1.2)]
    recs += [cell(f"{f}-s{s}", f, s, damage(f, s)) for f in families for s in range(1, 6)]
    return recs, {f"tok{i:03d}": gt[i] for i in range(n_frames)}


# --- records ------------------------------------------------------------------------------------------------


def test_record_round_trips_through_json_bit_exactly() -> None:
    recs, _ = synthetic_run(5)
    rec = recs[4]
    rec.l2[2, 3] = np.nan  # a frame that failed conformance
    back = CellRecord.from_builtins(json.loads(json.dumps(rec.to_builtins())))
    assert back.plans.tobytes() == rec.plans.tobytes() and back.frames == rec.frames
    np.testing.assert_array_equal(back.l2, rec.l2)
    np.testing.assert_array_equal(back.collision, rec.collision)
    assert all(type(v) in (float, int) for row in rec.to_builtins()["collision"] for v in row)


def test_record_rejects_wrong_shapes_by_name() -> None:
    with pytest.raises(InvalidInput, match="plans has shape"):
        CellRecord("x", "x", 1, ["a"], np.zeros((1, 5, 2)), np.zeros((1, 6)), np.zeros((1, 6)), np.zeros((1, 6)),
                   [0.0], [0.5])


# --- retention and bootstrap ---------------------------------------------------------------------------------


def test_retention_known_answers() -> None:
    assert rt.retention(1.0, 2.0) == 0.5
    assert rt.retention(1.0, 2.0, "reward") == 2.0
    assert rt.retention(0.0, 0.0) == 1.0
    assert rt.retention(1.0, 0.0) == math.inf
    np.testing.assert_allclose(rt.retention(np.array([1.0, 3.0]), np.array([4.0, 3.0])), [0.25, 1.0])
    with pytest.raises(InvalidInput):
        rt.retention(1.0, 1.0, "loss")


def test_summary_retention_is_clean_over_cell_l2_avg() -> None:
    """Hand-computed: stp3 L2 at 1/2/3 s is the mean of steps 1-2 / 1-4 / 1-6, l2_avg their mean.

    clean frame 0: L2 1..6 -> (1.5 + 2.5 + 3.5) / 3 = 2.5; frame 1: all 2 -> 2.0; M(clean) = 2.25.
    cell frame 0: 2, 4, .., 12 -> 5.0; frame 1: all 3 -> 3.0; M(cell) = 4.0; retention 2.25 / 4.0 = 0.5625.
    """
    zeros = np.zeros((2, 6))
    clean_plans = np.zeros((2, 6, 2))
    cell_plans = clean_plans.copy()
    cell_plans[:, 5] = (3.0, 4.0)  # the 3 s waypoint moved 5 m
    clean = CellRecord("clean", "clean", 0, ["f0", "f1"], clean_plans,
                       np.array([[1.0, 2, 3, 4, 5, 6], [2.0] * 6]), zeros, zeros, [0.0, 0.0], [0.5, 0.5])
    cell = CellRecord("fog-s3", "fog", 3, ["f0", "f1"], cell_plans,
                      np.array([[2.0, 4, 6, 8, 10, 12], [3.0] * 6]), zeros, zeros, [0.0, 0.0], [0.4, 0.4])
    s = rt.summarise_cell(cell, clean, n_resamples=200)
    assert s.retention == pytest.approx(0.5625, abs=1e-12)
    assert s.l2_avg == pytest.approx(4.0) and s.metrics["l2_avg_stp3"] == pytest.approx(4.0)
    assert s.metrics["l2_avg_uniad"] == pytest.approx(((4 + 8 + 12) / 3 + 3.0) / 2)  # steps 2, 4, 6
    # stp3 L2 at 3 s is the mean of all six steps; uniad at 3 s is the last step.
    assert s.metrics["l2_3s_stp3"] == pytest.approx((7.0 + 3.0) / 2)
    assert s.metrics["l2_3s_uniad"] == pytest.approx((12.0 + 3.0) / 2)
    assert s.metrics["l2_1s_uniad"] == pytest.approx((4.0 + 3.0) / 2)
    assert s.metrics["endpoint_shift"] == pytest.approx(5.0)
    assert s.metrics["energy"] == pytest.approx(0.8)
    assert s.frames == 2 and s.retention_ci_low <= s.retention <= s.retention_ci_high


def test_bootstrap_is_deterministic_and_contains_the_estimate() -> None:
    rng = np.random.default_rng(1)
    a = rng.gamma(2.0, 1.0, 200)
    b = a * 1.3 + rng.gamma(1.0, 0.3, 200)
    ci = rt.bootstrap_retention_ci(a, b, seed=7)
    assert ci == rt.bootstrap_retention_ci(a, b, seed=7)
    assert ci != rt.bootstrap_retention_ci(a, b, seed=8)
    assert ci[0] < rt.retention(a.mean(), b.mean()) < ci[1]
    assert rt.bootstrap_retention_ci(a, b, seed=7, chunk_elems=1000) == ci  # chunking does not change it


def test_paired_bootstrap_known_answers() -> None:
    """Pairing: a cell exactly twice as bad on every frame, however unequal the frames, has retention 0.5 in
    every resample, so the CI is the point (0.5, 0.5) (resampling clean and cell apart would spread it
    over 0.01..100). Two frames, clean (1, 3), cell (2, 2): a resample is (0, 0), (1, 1) or mixed with
    probability 1/4, 1/4, 1/2, retention 0.5, 1.5 or 1.0, so the 95 % interval is (0.5, 1.5)."""
    clean = np.array([0.1, 1.0, 10.0, 100.0, 3.0, 0.5])
    assert rt.bootstrap_retention_ci(clean, 2 * clean, n_resamples=500) == (0.5, 0.5)
    assert rt.bootstrap_retention_ci(2 * clean, clean, kind="reward", n_resamples=500) == (0.5, 0.5)
    assert rt.bootstrap_retention_ci([1.0, 3.0], [2.0, 2.0], n_resamples=2000) == (0.5, 1.5)


def test_bootstrap_ci_shrinks_with_more_frames() -> None:
    rng = np.random.default_rng(2)
    a, noise = rng.gamma(2.0, 1.0, 2000), rng.gamma(2.0, 0.5, 2000)
    widths = [np.diff(rt.bootstrap_retention_ci(a[:n], a[:n] + noise[:n])).item() for n in (25, 400)]
    assert widths[1] < widths[0] / 2.5  # ~ 1 / sqrt(16) = 1/4 in theory


def test_bootstrap_drops_nan_frames_and_handles_none_left() -> None:
    a, b = np.array([1.0, np.nan, 2.0, 3.0]), np.array([2.0, 5.0, np.nan, 6.0])
    assert rt.bootstrap_retention_ci(a, b, n_resamples=50) == rt.bootstrap_retention_ci(a[[0, 3]], b[[0, 3]],
                                                                                         n_resamples=50)
    assert all(math.isnan(v) for v in rt.bootstrap_retention_ci([np.nan], [1.0]))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(0.01, 50.0), min_size=1, max_size=40))
def test_identical_cells_retain_everything(values: list[float]) -> None:
    arr = np.array(values)
    assert rt.retention(arr.mean(), arr.mean()) == 1.0
    assert rt.bootstrap_retention_ci(arr, arr, n_resamples=100) == pytest.approx((1.0, 1.0))


# --- tolerance thresholds ------------------------------------------------------------------------------------


@pytest.mark.parametrize(("curve", "level", "expected"), [
    ({1: 0.95, 2: 0.85, 3: 0.7, 4: 0.6, 5: 0.5}, 0.90, 1.5),  # 1 + (0.95 - 0.90) / (0.95 - 0.85)
    ({1: 0.95, 2: 0.85, 3: 0.80, 4: 0.70, 5: 0.5}, 0.75, 3.5),  # 3 + (0.80 - 0.75) / (0.80 - 0.70)
    ({1: 0.99, 2: 0.98, 3: 0.96, 4: 0.93, 5: 0.87}, 0.90, 4.5),
    ({1: 0.80, 2: 0.70, 3: 0.6, 4: 0.5, 5: 0.4}, 0.90, 1.0),  # S1 already below
    ({1: 0.99, 2: 0.98, 3: 0.97, 4: 0.96, 5: 0.95}, 0.90, None),  # never reached
    ({1: 0.95, 2: 0.90, 3: 0.90, 4: 0.90, 5: 0.90}, 0.90, None),  # exactly at the level is not below
    ({1: 0.95, 2: 0.92, 3: 0.90, 4: 0.89, 5: 0.8}, 0.90, 3.0),  # crossing right at S3
    ({1: 0.85, 2: 0.95, 3: 0.97, 4: 0.97, 5: 0.97}, 0.90, 1.0),  # first crossing counts
    ({3: 0.95, 5: 0.85}, 0.90, 4.0),  # a subset of severities: interpolate between those measured
    ({1: 0.95, 2: float("nan"), 3: 0.85}, 0.90, 2.0),  # NaN skipped: between S1 and S3
])
def test_tolerance_threshold_known_answers(curve, level, expected) -> None:
    got = rt.tolerance_threshold(curve, level)
    assert got == (None if expected is None else pytest.approx(expected))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.3, 1.1), min_size=5, max_size=5), st.lists(st.floats(0.0, 0.3), min_size=5, max_size=5))
def test_thresholds_monotone(upper: list[float], drop: list[float]) -> None:
    """A curve lower everywhere crosses no later; s*10 never comes after s*25."""
    high = dict(zip(range(1, 6), upper))
    low = {s: r - d for (s, r), d in zip(high.items(), drop)}
    inf = lambda v: math.inf if v is None else v  # noqa: E731
    for level in (0.90, 0.75):
        assert inf(rt.tolerance_threshold(low, level)) <= inf(rt.tolerance_threshold(high, level)) + 1e-9
    assert inf(rt.tolerance_threshold(high, 0.90)) <= inf(rt.tolerance_threshold(high, 0.75)) + 1e-9


# --- axes and verdict ----------------------------------------------------------------------------------------


def s5(quality: float, removal: float, other: float = 1.0) -> dict[str, float]:
    out = {f: quality for f in ORDER[:9]} | {f: other for f in ORDER[9:]}
    return out | {"blackout": removal}


def test_axes_known_answer() -> None:
    values = s5(0.9, 0.6, 0.8)
    values["gaussian_blur"] = 0.0  # mean of nine: (8 * 0.9 + 0) / 9 = 0.8
    ax = vd.compute_axes(values, GROUPS)
    assert ax.quality == pytest.approx(0.8) and ax.removal == pytest.approx(0.6)
    assert ax.gap == pytest.approx(0.2)
    assert ax.mean == pytest.approx((0.8 * 9 + 0.8 + 0.6 + 0.8) / 12)
    assert ax.dropout == pytest.approx(0.8) and ax.occlusion == pytest.approx(0.8)
    assert ax.missing == ()


def test_quality_axis_is_the_mean_of_the_nine_quality_families_only() -> None:
    """Nine quality families at 0.1, 0.2, .., 0.9 average 0.5 whatever the other seven hold; the mean axis
    takes the twelve core families: (4.5 + 0.3 + 0.2 + 0.1) / 12."""
    values = {f: (i + 1) / 10 for i, f in enumerate(ORDER[:9])}
    values |= {"frame_dropout": 0.3, "blackout": 0.2, "bit_error": 0.1, "raindrop": 0.0, "occlusion": 0.0,
               "mud_splash": 0.0, "lens_dirt": 0.0}
    ax = vd.compute_axes(values, GROUPS)
    assert ax.quality == pytest.approx(0.5, abs=1e-12) and ax.removal == 0.2
    assert ax.gap == pytest.approx(0.3, abs=1e-12) and ax.mean == pytest.approx(5.1 / 12, abs=1e-12)
    values["occlusion"] = values["raindrop"] = 1.0  # contamination and occlusion stay off the quality axis
    assert vd.compute_axes(values, GROUPS).quality == pytest.approx(0.5, abs=1e-12)


def test_missing_family_makes_its_axis_none() -> None:
    values = s5(0.99, 0.5)
    del values["fog"], values["occlusion"]
    ax = vd.compute_axes(values, GROUPS)
    assert ax.quality is None and ax.gap is None and ax.mean is None
    assert ax.removal == 0.5 and ax.occlusion is None and ax.missing == ("fog", "occlusion")
    assert vd.verdict(ax).label == "undetermined"


@pytest.mark.parametrize(("q", "r", "label", "case"), [
    (0.99, 0.97, "not-shown-to-use-cameras", "both-flat"),
    (0.95, 0.95, "not-shown-to-use-cameras", "both-flat"),  # at the flat line counts as flat
    (0.98, 0.60, "quality-insensitive", "removal-only"),
    (0.80, 0.60, "camera-reliant", "both-below"),
    (0.80, 0.99, "camera-reliant", "quality-only"),
    (0.80, 0.95, "camera-reliant", "quality-only"),  # removal exactly on the flat line is flat
    (0.95, 0.60, "quality-insensitive", "removal-only"),  # quality exactly on the flat line is flat
    (0.949999, 0.99, "camera-reliant", "quality-only"),  # a millionth below the line is below
])
def test_verdict_labels(q, r, label, case) -> None:
    v = vd.verdict(vd.compute_axes(s5(q, r), GROUPS), flat=0.95)
    assert (v.label, v.case, v.flat) == (label, case, 0.95)
    assert f"{q:.3f}" in v.text and f"{r:.3f}" in v.text
    assert v.negative_gap is (q < r)
    assert ("Negative gap" in v.text) is (q < r)


def test_flat_is_a_parameter() -> None:
    ax = vd.compute_axes(s5(0.93, 0.92), GROUPS)
    assert vd.verdict(ax, flat=0.95).label == "camera-reliant"
    assert vd.verdict(ax, flat=0.90).label == "not-shown-to-use-cameras"


def test_flat_line_known_answers() -> None:
    """The line is 0.95 unless given; the axes are compared at six decimals (the certificate's), so a value
    that rounds onto the line is on it; each side of a line at 0.80 gives its own case."""
    on_line = rc.Axes(quality=0.9499996, removal=0.97, gap=0.0, mean=None)
    assert vd.verdict(on_line).flat == 0.95 and vd.verdict(on_line).case == "both-flat"
    below = rc.Axes(quality=0.9499994, removal=0.97, gap=0.0, mean=None)
    assert (vd.verdict(below).label, vd.verdict(below).case) == ("camera-reliant", "quality-only")
    at = lambda q, r: vd.verdict(rc.Axes(quality=q, removal=r, gap=q - r, mean=None), flat=0.80)  # noqa: E731
    assert (at(0.81, 0.79).label, at(0.81, 0.79).case) == ("quality-insensitive", "removal-only")
    assert (at(0.79, 0.81).label, at(0.79, 0.81).case) == ("camera-reliant", "quality-only")
    assert (at(0.79, 0.79).case, at(0.80, 0.80).case) == ("both-below", "both-flat")
    assert "flat line 0.80" in at(0.81, 0.79).text


def test_family_groups_from_the_registry_match_the_spec() -> None:
    pytest.importorskip("pytest_drivedegrade.corruptions.registry")
    groups = FamilyGroups.from_registry()
    assert groups.quality == GROUPS.quality and groups.core == GROUPS.core and groups.removal == "blackout"


# --- null control, floor, whole run --------------------------------------------------------------------------


def test_null_control_identical_and_wandering() -> None:
    plans = np.random.default_rng(0).normal(size=(4, 6, 2))
    assert vd.null_control(plans, plans.copy()) == rc.NullControl(passed=True, max_abs_diff=0.0, max_l2_change=0.0,
                                                                  frames_changed=0, frames_compared=4)
    moved = plans.copy()
    moved[2, 5] += [0.3, 0.4]
    nc = vd.null_control(plans, moved)
    assert nc.passed is False and nc.frames_changed == 1
    assert nc.max_abs_diff == pytest.approx(0.4) and nc.max_l2_change == pytest.approx(0.5)


def test_cells_within_the_null_wander_are_not_separable() -> None:
    recs, _ = synthetic_run(8, null_wander=0.5)
    res = analyse_run(recs, groups=GROUPS, n_resamples=50)
    sep = {s.cell: s.separable_from_null for s in res.summaries}
    assert res.null_control.passed is False
    assert sep["clean"] is None and sep["null"] is None
    assert sep["blind"] is True and sep["gaussian_blur-s1"] is False
    clean_run = analyse_run(synthetic_run(8)[0], groups=GROUPS, n_resamples=50)
    assert clean_run.null_control.passed is True
    assert all(s.separable_from_null for s in clean_run.summaries if s.cell not in ("clean", "null"))


def test_floor_comparison() -> None:
    summaries = [rc.CellSummary("blackout-s5", "blackout", 5, 3, 1.2, 0.5, 0.4, 0.6),
                 rc.CellSummary("blind", "blind", 0, 3, 2.5, 0.3, 0.2, 0.4)]
    floor = vd.floor_comparison(2.0, summaries)
    assert floor.to_builtins() == {"l2_avg": 2.0, "blackout_s5_l2_avg": 1.2, "blackout_s5_below_floor": True,
                                   "blind_l2_avg": 2.5, "blind_below_floor": False}  # no ego_removal: not run
    assert vd.floor_comparison(2.0, summaries, ego_removal=0.7).to_builtins()["ego_removal"] == 0.7
    assert vd.floor_comparison(None, summaries).blind_below_floor is None


def test_analyse_run_is_order_independent_and_complete() -> None:
    recs, _ = synthetic_run(12)
    res = analyse_run(recs, groups=GROUPS, n_resamples=100, floor_l2=5.0)
    shuffled = recs[:]
    random.Random(3).shuffle(shuffled)
    again = analyse_run([r.to_builtins() for r in shuffled], groups=GROUPS, n_resamples=100, floor_l2=5.0)
    assert json.dumps(again.to_builtins()) == json.dumps(res.to_builtins())
    assert [s.cell for s in res.summaries][:4] == ["clean", "null", "blind", "gaussian_blur-s1"]
    assert res.summaries[0].retention == 1.0 and len(res.summaries) == 3 + 16 * 5
    assert res.verdict.label == "camera-reliant" and res.floor.blind_below_floor is True
    assert res.thresholds["blackout"].levels["s10"].value is not None and set(res.thresholds) == set(ORDER)


def test_failed_frames_drop_out_of_that_cells_comparison_only() -> None:
    recs, _ = synthetic_run(6)
    clean, cell = recs[0], recs[5]
    cell.l2[2] = np.nan
    s = rt.summarise_cell(cell, clean, n_resamples=50)
    keep = [0, 1, 3, 4, 5]
    expected = clean.l2_avg_per_frame()[keep].mean() / cell.l2_avg_per_frame()[keep].mean()
    assert s.frames == 5 and s.retention == pytest.approx(expected)
    assert len(analyse_run(recs + [recs[5]], groups=GROUPS, n_resamples=20).summaries) == len(recs)


def test_analyse_run_needs_clean() -> None:
    recs, _ = synthetic_run(3)
    with pytest.raises(InvalidInput, match="no clean cell"):
        analyse_run(recs[1:], groups=GROUPS)


# --- baseline gate -------------------------------------------------------------------------------------------


def cert_like(retentions: dict[str, float], axes: dict[str, float], spec="1.0.0", data="d1") -> dict:
    return {"spec_version": spec, "dataset": {"fingerprint": data}, "axes": axes,
            "cells": [{"cell": c, "retention": r} for c, r in retentions.items()]}


def test_baseline_comparison_catches_regressions_beyond_tolerance() -> None:
    base = cert_like({"fog-s5": 0.90, "jpeg-s5": 0.80, "blur-s1": 0.99}, {"quality": 0.9, "removal": 0.7})
    assert bl.compare_to_baseline(base, base, 0.02) == {"cells": [], "axes": []}
    now = cert_like({"fog-s5": 0.85, "jpeg-s5": 0.79, "blur-s1": 0.999, "new-s1": 0.1},
                    {"quality": 0.87, "removal": 0.69})
    out = bl.compare_to_baseline(now, base, 0.02)
    assert [(r.name, r.baseline, r.current) for r in out["cells"]] == [("fog-s5", 0.90, 0.85)]
    assert [r.name for r in out["axes"]] == ["axis:quality"]
    assert "0.850 vs baseline 0.900" in out["cells"][0].message()
    assert bl.compare_to_baseline(now, base, 0.06)["cells"] == []
    assert bl.cell_regression("fog-s5", 0.85, base, 0.02).drop == pytest.approx(0.05)


@pytest.mark.parametrize(("spec", "data", "match"), [("2.0.0", "d1", "spec version"),
                                                      ("1.0.0", "d2", "dataset fingerprint")])
def test_incompatible_baseline_is_a_clear_error(spec, data, match) -> None:
    base = cert_like({}, {})
    with pytest.raises(bl.BaselineError, match=match):
        bl.compare_to_baseline(cert_like({}, {}, spec, data), base)


# --- partial results (Trust case 9) ----------------------------------------------------------------------------


def fail_frames(rec: CellRecord, frames: list[int], *, data: bool = False) -> CellRecord:
    """`rec` with `frames` failed as the run records them: NaN rows and one message each."""
    for i in frames:
        for name in ("plans", "l2", "collision", "collision_vru"):
            getattr(rec, name)[i] = np.nan
        rec.jerk[i] = rec.bit1[i] = np.nan
        (rec.data_errors if data else rec.errors).append(f"frame 'tok{i:03d}': failed")
    return rec


def test_failed_frames_make_the_verdict_undetermined_with_the_reason() -> None:
    """Trust case 9: a cell with failed frames (planner or data) makes the verdict `undetermined`, the reason
    naming the cells and their counts; the axes are still computed (the label they give kept, flagged)."""
    recs, _ = synthetic_run(8)
    whole = analyse_run(recs, groups=GROUPS, n_resamples=50)
    assert whole.verdict.label == "camera-reliant" and whole.verdict.reason is None
    by = {r.cell: r for r in recs}
    fail_frames(by["jpeg-s5"], [1, 2])
    fail_frames(by["fog-s2"], [3], data=True)
    res = analyse_run(recs, groups=GROUPS, n_resamples=50)
    v = res.verdict
    assert v.label == "undetermined" and v.case == "failed-frames" and v.ego_label == "undetermined"
    assert v.computed_label == "camera-reliant" and v.borderline is False
    assert v.reason == ("2 cells with failed frames: jpeg-s5 (2 of 8 frames: 2 planner contract failures), "
                        "fog-s2 (1 of 8 frames: 1 data error)")
    assert v.failed_cells == {"jpeg-s5": rc.FailedCell(frames=8, conformance_errors=2, data_errors=0),
                              "fog-s2": rc.FailedCell(frames=8, conformance_errors=0, data_errors=1)}
    assert v.to_builtins()["failed_cells"]["fog-s2"] == {"frames": 8, "conformance_errors": 0, "data_errors": 1}
    assert v.reason in v.text
    assert res.axes.quality is not None and res.axes.partial == ("jpeg-s5", "fog-s2")
    assert res.thresholds["jpeg"].partial is True and res.thresholds["snow"].partial is False
    summary = {s.cell: s for s in res.summaries}
    assert (summary["jpeg-s5"].conformance_errors, summary["jpeg-s5"].data_errors) == (2, 0)
    assert (summary["fog-s2"].conformance_errors, summary["fog-s2"].data_errors, summary["fog-s2"].frames) == (0, 1, 7)


def test_a_cell_with_no_scored_frame_has_no_retention_and_the_null_control_is_not_run() -> None:
    """Trust case 9: a clean cell whose every frame failed shows no retention (NaN, not 1.0 over 0 frames), and
    the null control, with nothing compared, is not run (passed None), not passed."""
    recs, _ = synthetic_run(5)
    by = {r.cell: r for r in recs}
    fail_frames(by["clean"], list(range(5)))
    fail_frames(by["null"], list(range(5)))
    res = analyse_run(recs, groups=GROUPS, n_resamples=20)
    clean = res.summaries[0]
    assert clean.cell == "clean" and clean.frames == 0 and math.isnan(clean.retention)
    assert math.isnan(clean.retention_ci_low) and math.isnan(clean.retention_ci_high)
    assert res.null_control == rc.NullControl(passed=None, max_abs_diff=None, max_l2_change=None,
                                              frames_changed=0, frames_compared=0)
    assert res.verdict.label == "undetermined" and "clean (5 of 5 frames" in res.verdict.reason
    assert all(math.isnan(s.retention) for s in res.summaries)


def test_record_keeps_data_errors_apart_through_builtins() -> None:
    """Trust case 10: data faults travel in their own list (record version 3) and count apart."""
    recs, _ = synthetic_run(4)
    rec = fail_frames(fail_frames(recs[4], [0]), [2], data=True)
    back = CellRecord.from_builtins(json.loads(json.dumps(rec.to_builtins())))
    assert back.errors == ["frame 'tok000': failed"] and back.data_errors == ["frame 'tok002': failed"]
    assert back.failed_frames() == (1, 1)
    from pytest_drivedegrade.cells import RECORD_VERSION

    assert RECORD_VERSION >= 3


# --- the typed analysis emits the certificate's sections as before ------------------------------------------------


def test_typed_sections_emit_the_certificate_keys_in_their_order() -> None:
    """Each section's keys, in the order the dict-based analysis wrote them (the certificate's JSON)."""
    recs, _ = synthetic_run(8)
    out = analyse_run(recs, groups=GROUPS, n_resamples=30, floor_l2=5.0).to_builtins()
    camera = ["quality", "removal", "gap", "mean", "dropout", "occlusion", "missing", "ego", "ego_removal"]
    assert list(out) == ["summaries", "thresholds", "axes", "verdict", "null_control", "floor", "settings",
                         "axes_pdms", "axes_epdms", "reliance"]
    assert list(out["axes"]) == [*camera, "quality_ci", "removal_ci", "gap_ci", "mean_ci", "partial"]
    assert list(out["axes_pdms"]) == [*camera, "partial"]  # the resamples are of L2: no intervals on PDMS
    assert list(out["verdict"]) == ["label", "case", "flat", "text", "negative_gap", "metric", "ego_label",
                                    "confidence", "borderline", "reason", "failed_cells", "computed_label"]
    assert list(out["thresholds"]["fog"]) == ["s10", "s25", "s10_ci", "s10_never", "s25_ci", "s25_never", "partial"]
    assert list(out["null_control"]) == ["passed", "max_abs_diff", "max_l2_change", "frames_changed",
                                         "frames_compared"]
    assert list(out["floor"]) == ["l2_avg", "blackout_s5_l2_avg", "blackout_s5_below_floor", "blind_l2_avg",
                                  "blind_below_floor"]
    ci = out["axes"]["quality_ci"]
    assert isinstance(ci, list) and len(ci) == 2 and out["axes"]["missing"] == [] and out["axes"]["partial"] == []
    sections = {k: v for k, v in out.items() if k != "summaries"}  # summaries hold NaN (PDMS not scored)
    assert json.loads(json.dumps(sections)) == sections  # plain builtins only


def test_the_declared_names_are_the_dataclass_fields() -> None:
    """AXES / BESIDE_AXES / EGO_AXES name fields of Axes and AxisIntervals; the levels are THRESHOLD_LEVELS."""
    names = {f.name for f in dataclasses.fields(rc.Axes)}
    assert set(rc.AXES) | set(rc.BESIDE_AXES) | set(rc.EGO_AXES) <= names
    assert tuple(f.name for f in dataclasses.fields(rc.AxisIntervals)) == rc.AXES
    recs, _ = synthetic_run(6)
    res = analyse_run(recs, groups=GROUPS, n_resamples=20)
    assert all(tuple(t.levels) == tuple(rt.THRESHOLD_LEVELS) for t in res.thresholds.values())


def test_axes_read_back_from_a_certificate_equal_the_analysis() -> None:
    recs, _ = synthetic_run(8)
    res = analyse_run(recs, groups=GROUPS, n_resamples=30)
    for axes in (res.axes, res.axes_pdms):
        assert rc.Axes.from_builtins(axes.to_builtins()) == axes
    assert rc.Axes.from_builtins({"quality": "0.9", "removal": True}) == rc.Axes(None, None, None, None)
    fog = res.thresholds["fog"]
    assert rc.FamilyThresholds.from_builtins(fog.to_builtins()) == fog
    assert rc.null_control_section(None) == {"passed": None, "max_abs_diff": None, "max_l2_change": None,
                                             "ran": False}
    assert rc.null_control_section(res.null_control)["ran"] is True
