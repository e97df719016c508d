"""Known answers for the intervals of issue 15: thresholds, axes and verdict from one joint paired bootstrap, and
corruption seeds folded in by a two-level bootstrap (seeds, then frames)."""

from __future__ import annotations

import json
import math
from math import comb
from pathlib import Path

import numpy as np
import pytest
from test_analysis import GROUPS, ORDER, record, synthetic_run

from pytest_drivedegrade.cells import CellRecord
from pytest_drivedegrade.certificate.seal import canonicalize
from pytest_drivedegrade.scoring import baseline as bl
from pytest_drivedegrade.scoring import intervals as iv
from pytest_drivedegrade.scoring import retention as rt
from pytest_drivedegrade.scoring.analyse import analyse_run
from pytest_drivedegrade.settings import RunSettings

GOLDEN = Path(__file__).parents[1] / "data" / "golden" / "analysis_seeds1.json"


def err_record(cell: str, errors, runs=()) -> CellRecord:
    """A cell whose per-frame l2_avg is exactly `errors` (plans = ground truth + (e, 0) at every step)."""
    fam, sev = (cell.rsplit("-s", 1)[0], int(cell.rsplit("-s", 1)[1])) if "-s" in cell else (cell, 0)
    e = np.asarray(errors, dtype=float)
    gt = np.zeros((len(e), 6, 2))
    rec = record(cell, fam, sev, gt + np.stack([e, 0 * e], axis=-1)[:, None, :], gt)
    if runs:
        rec.seed_runs = [err_record(cell, r) for r in runs]
        rec.seeds = list(range(1 + len(runs)))
    return rec


def binom_cdf(k: int, n: int, p: float = 0.5) -> float:
    return sum(comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(0, k + 1))


# --- the vectorised pieces equal their definitions ----------------------------------------------------------


def test_vectorised_thresholds_equal_tolerance_threshold_row_by_row():
    rng = np.random.default_rng(3)
    curves = rng.uniform(0.6, 1.05, size=(400, 5))
    curves[::7] = np.sort(curves[::7], axis=1)[:, ::-1]  # monotone rows
    curves[5, 2] = np.nan  # a NaN point is skipped, as in the scalar definition
    curves[9, 0] = np.inf
    curves[11] = 0.95  # never below 0.90
    for level in (0.90, 0.75):
        got = iv.thresholds_per_resample([1, 2, 3, 4, 5], curves, level)
        for row, value in zip(curves, got):
            want = rt.tolerance_threshold(dict(zip(range(1, 6), row.tolist())), level)
            assert (math.isinf(value) and want is None) or value == want


def test_percentile_interval_treats_never_as_plus_infinity_and_writes_null():
    assert iv.percentile_interval(np.array([1.0, 2.0, 3.0, 4.0, 5.0])) == pytest.approx((1.1, 4.9))
    assert iv.percentile_interval(np.array([1.0] * 90 + [math.inf] * 10)) == (1.0, None)
    assert iv.percentile_interval(np.array([math.inf] * 100)) == (None, None)
    assert iv.percentile_interval(np.array([math.nan] * 3)) is None


def test_frame_counts_are_draws_with_replacement():
    counts = iv.frame_counts(np.random.default_rng(0), 500, 17)
    assert counts.shape == (500, 17) and (counts.sum(axis=1) == 17).all()
    assert abs(counts.mean() - 1.0) < 1e-12 and 0.8 < counts.var() < 1.1  # binomial(17, 1/17): variance 0.94


# --- known answers ------------------------------------------------------------------------------------------


def test_constant_per_frame_errors_give_a_point_interval():
    """Every frame equally damaged: every resample has the same curve, so each interval is the point itself."""
    n = 25
    recs = [err_record("clean", np.ones(n))]
    recs += [err_record(f"fog-s{s}", np.full(n, 1 / r)) for s, r in zip(range(1, 6), (1.0, 0.95, 0.8, 0.7, 0.6))]
    res = analyse_run(recs, groups=GROUPS, n_resamples=200)
    s10, s25 = res.thresholds["fog"].levels["s10"], res.thresholds["fog"].levels["s25"]
    assert s10.ci == pytest.approx((s10.value, s10.value)) and s10.never == 0.0
    assert s10.value == pytest.approx(2 + 0.05 / 0.15)
    assert s25.ci == pytest.approx((s25.value, s25.value)) and s25.value == pytest.approx(3.5)


def test_threshold_distribution_is_the_binomial_one():
    """S3's per-frame error is 1 or 1.6 (half the frames each), every other severity loses nothing. A resample
    with k of the F frames at 1.6 has r3 = 1 / (1 + 0.6 k / F); it crosses 0.75 (at S3 exactly) iff
    k / F > 5/9, so the share of resamples that never cross is P(Binomial(F, 1/2) <= floor(5F/9))."""
    n, r = 18, 4000
    e3 = np.array([1.0, 1.6] * (n // 2))
    recs = [err_record("clean", np.ones(n))]
    recs += [err_record(f"fog-s{s}", e3 if s == 3 else np.ones(n)) for s in range(1, 6)]
    res = analyse_run(recs, groups=GROUPS, n_resamples=r)
    p_never = binom_cdf(10, n)  # k <= 10 of 18, since 10/18 = 0.556 <= 5/9 = 0.5556
    assert res.thresholds["fog"].levels["s25"].never == pytest.approx(p_never, abs=4 * math.sqrt(p_never / r))
    assert res.thresholds["fog"].levels["s25"].value is None  # the point curve: r3 = 1 / 1.3 = 0.77, not below 0.75
    # s*10: r3 < 0.9 iff k/F > 1/5.4, almost always; crossing s = 2 + 0.1 / (1 - r3) = 2 + (1 + 0.6k/F) / (6k/F)
    low, high = res.thresholds["fog"].levels["s10"].ci
    k_hi, k_lo = 9 + 2 * 2.12, 9 - 2 * 2.12  # 97.5 % and 2.5 % of Binomial(18, 1/2), with normal slack

    def s10(k):
        return 2 + (1 + 0.6 * k / n) / (6 * k / n)

    assert s10(k_hi + 1) <= low <= high <= s10(k_lo - 1)
    p10 = binom_cdf(3, n)  # r3 >= 0.9 iff k / F <= 1 / 5.4, i.e. k <= 3
    assert res.thresholds["fog"].levels["s10"].never == pytest.approx(p10, abs=4 * math.sqrt(p10 / r))


def flat_line_run(n: int, removal: float) -> list[CellRecord]:
    """Nine quality families whose S5 retention sits exactly on the flat line 0.95 with frame noise symmetric
    about it (per frame 1/0.95 * (1 + d), d spread evenly over +-0.3 and summing to zero), blackout at
    `removal`."""
    d = np.linspace(-0.3, 0.3, n)
    d -= d.mean()
    recs = [err_record("clean", np.ones(n)), err_record("blackout-s5", np.full(n, 1 / removal))]
    recs += [err_record(f"{fam}-s5", (1 + d) / 0.95) for fam in ORDER[:9]]
    return recs


def test_a_verdict_on_the_flat_line_has_confidence_near_one_half():
    res = analyse_run(flat_line_run(40, removal=0.5), groups=GROUPS, n_resamples=2000)
    assert res.axes.quality == pytest.approx(0.95, abs=1e-9)
    assert res.verdict.label == "quality-insensitive"  # at the flat line is not below it
    assert 0.44 <= res.verdict.confidence <= 0.56
    assert res.verdict.borderline and "Borderline" in res.verdict.text
    low, high = res.axes.interval("quality")
    assert low < 0.95 < high
    assert res.axes.interval("removal") == pytest.approx((0.5, 0.5))


def test_a_clear_verdict_is_not_borderline():
    recs, _ = synthetic_run(40)
    res = analyse_run(recs, groups=GROUPS, n_resamples=300)
    assert res.verdict.label == "camera-reliant" and res.verdict.confidence == 1.0
    assert not res.verdict.borderline and "Borderline" not in res.verdict.text
    for key in ("quality", "removal", "gap", "mean"):
        low, high = res.axes.interval(key)
        assert low <= res.axes.value(key) <= high


def test_intervals_shrink_as_frames_grow():
    """Sixteen times the frames should narrow every interval about four-fold (1 / sqrt(F)): at least halve it."""
    widths = []
    for n in (20, 320):
        res = analyse_run(synthetic_run(n, seed=1)[0], groups=GROUPS, n_resamples=400)
        w = {k: res.axes.interval(k)[1] - res.axes.interval(k)[0] for k in ("quality", "removal", "gap", "mean")}
        w["s10"] = res.thresholds["fog"].levels["s10"].ci[1] - res.thresholds["fog"].levels["s10"].ci[0]
        widths.append(w)
    for key, small in widths[0].items():
        assert 0 < widths[1][key] < small / 2, key


# --- seeds: the two-level bootstrap ---------------------------------------------------------------------------


def test_one_seed_records_keep_their_pre_seed_form():
    rec = err_record("fog-s1", np.ones(4))
    assert "seed_runs" not in rec.to_builtins() and "seeds" not in rec.to_builtins()
    multi = err_record("snow-s1", np.ones(4), runs=[np.full(4, 2.0)])
    back = CellRecord.from_builtins(json.loads(json.dumps(multi.to_builtins())))
    assert back.seeds == [0, 1] and len(back.seed_runs) == 1
    assert back.seed_runs[0].l2.tolist() == multi.seed_runs[0].l2.tolist()


def test_seed_retention_is_the_mean_over_seeds_and_seeds_widen_the_interval():
    """Every frame equally damaged within a seed, seeds differing: a frame bootstrap alone would give a point;
    the seed level spreads the resamples between the per-seed retentions."""
    n = 30
    clean = err_record("clean", np.ones(n))
    one = err_record("snow-s5", np.full(n, 1 / 0.9))
    three = err_record("snow-s5", np.full(n, 1 / 0.9), runs=[np.full(n, 1 / 0.7), np.full(n, 1 / 0.8)])
    assert rt.record_retention(clean, three) == pytest.approx(0.8)
    single = analyse_run([clean, one], groups=GROUPS, n_resamples=500)
    multi = analyse_run([clean, three], groups=GROUPS, n_resamples=500, seeds=3)
    s1 = next(s for s in single.summaries if s.cell == "snow-s5")
    s3 = next(s for s in multi.summaries if s.cell == "snow-s5")
    assert s1.retention_ci_low == pytest.approx(s1.retention_ci_high)  # frames alone: no spread
    assert s3.retention == pytest.approx(0.8)
    assert 0.7 - 1e-12 <= s3.retention_ci_low < 0.8 < s3.retention_ci_high <= 0.9 + 1e-12
    assert multi.settings["seeds"] == 3 and multi.settings["seed_values"] == [0, 1, 2]
    assert multi.settings["intervals"]["scheme"] == "seeds then frames"


def test_seed_metrics_are_means_over_the_runs():
    n = 6
    clean = err_record("clean", np.ones(n))
    multi = err_record("snow-s5", np.full(n, 2.0), runs=[np.full(n, 4.0)])
    s = rt.summarise_cell(multi, clean, ci=(0.1, 0.2))
    assert s.l2_avg == pytest.approx(3.0) and s.metrics["l2_3s_stp3"] == pytest.approx(3.0)
    assert s.retention == pytest.approx((0.5 + 0.25) / 2) and (s.retention_ci_low, s.retention_ci_high) == (0.1, 0.2)


# --- seeds=1 is the pre-interval output plus new fields ---------------------------------------------------------


def test_one_seed_analysis_equals_the_pre_interval_golden_but_for_new_fields():
    recs, _ = synthetic_run(40)
    got = canonicalize(analyse_run(recs, groups=GROUPS, floor_l2=5.0).to_builtins())
    golden = json.loads(GOLDEN.read_text())
    # the golden predates the PDMS columns and the ego axis (issue 12): compare what it has, field for field
    assert len(got["summaries"]) == len(golden["summaries"])
    assert [{k: s[k] for k in g} for s, g in zip(got["summaries"], golden["summaries"])] == golden["summaries"]
    assert got["floor"] == golden["floor"]
    assert got["null_control"] == {**golden["null_control"], "frames_compared": 40}
    for fam, t in golden["thresholds"].items():
        assert {k: got["thresholds"][fam][k] for k in t} == t
        assert set(got["thresholds"][fam]) - set(t) == {"s10_ci", "s25_ci", "s10_never", "s25_never", "partial"}
        assert got["thresholds"][fam]["partial"] is False
    assert {k: got["axes"][k] for k in golden["axes"]} == golden["axes"]
    assert set(got["axes"]) - set(golden["axes"]) == {"quality_ci", "removal_ci", "gap_ci", "mean_ci", "ego",
                                                      "ego_removal", "partial"}
    assert got["axes"]["partial"] == [] and got["verdict"]["reason"] is None
    assert {k: got["verdict"][k] for k in golden["verdict"]} == golden["verdict"]
    assert {k: got["settings"][k] for k in golden["settings"]} == golden["settings"]
    assert got["settings"]["seeds"] == 1 and got["settings"]["seed_values"] == [0]


def test_intervals_can_be_left_out():
    recs, _ = synthetic_run(12)
    res = analyse_run(recs, groups=GROUPS, n_resamples=100, intervals=False)
    assert res.axes.interval("quality") is None and res.verdict.confidence is None
    assert res.thresholds["fog"].levels["s10"].ci is None and not res.settings["intervals"]["computed"]


# --- the baseline gate compares like with like ----------------------------------------------------------------


def test_baseline_with_another_seed_count_is_refused_with_a_clear_message():
    recs, _ = synthetic_run(10)
    cert = {"spec_version": "2.0.0", "dataset": {"fingerprint": "d"}, "cells": [], "axes": {},
            "settings": {"seeds": 3}}
    old = {**cert, "settings": {}}  # a certificate from before seeds: one seed
    with pytest.raises(bl.BaselineError, match=r"1 corruption seed.*uses 3.*--drivedegrade-seeds 1"):
        bl.compare_to_baseline(cert, old)
    assert bl.compare_to_baseline(cert, cert) == {"cells": [], "axes": []}
    bl.check_baseline_compatible(old, spec_version="2.0.0", dataset_fingerprint="d", settings=RunSettings(seeds=1))
    with pytest.raises(bl.BaselineError, match="seed"):
        bl.check_baseline_compatible(old, spec_version="2.0.0", dataset_fingerprint="d", settings=RunSettings(seeds=2))


# --- the report and the terminal show them ----------------------------------------------------------------------


def test_report_terminal_and_junit_show_the_intervals():
    from pytest_drivedegrade.certificate.seal import Provenance
    from pytest_drivedegrade.report.html import render_report
    from pytest_drivedegrade.report.junit import suite_properties
    from pytest_drivedegrade.report.terminal import summary_lines

    res = analyse_run(flat_line_run(40, removal=0.5), groups=GROUPS, n_resamples=300)
    lines = summary_lines(res, [])
    assert any(line.startswith("axes 95% intervals: quality [0.9") for line in lines)
    assert any(line.startswith("verdict confidence: 0.") and "BORDERLINE" in line for line in lines)
    page = render_report(res, Provenance("demo", "p", "d", "val", "2.0.0"))
    assert "borderline</b>" in page and "Verdict\n    confidence 0." in page and "95%: 0.9" in page
    props = dict(suite_properties(res))
    assert 0.3 < props["drivedegrade_verdict_confidence"] < 0.7
    assert props["drivedegrade_axis_removal_ci_low"] == pytest.approx(0.5)
