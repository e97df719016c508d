"""Adaptive certification statistics (issue 22): known answers, hypothesis properties, and the simulation study
(error rate under optional stopping at most alpha for the adaptive rule, above it for the naive bootstrap rule).

The synthetic populations here are shared with ``benchmarks/adaptive.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.data.frame import Command, EgoStatus, Frame
from pytest_drivedegrade.scoring.adaptive import (
    GateBaseline,
    Settlement,
    alpha_per_decision,
    axis_settled,
    cell_levels,
    cut_units,
    gate_cell,
    retention_interval,
    run_cell,
    schedule_family,
    settle_mean,
    settle_retention,
    settled,
    violations,
)

BOUND = 5.0


def population(rng: np.random.Generator, n: int, r: float, noise: float = 0.3, bound: float = BOUND,
               clean: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Paired per-unit mean L2 (clean, cell) in [0, bound] whose population retention is exactly `r`: clean
    lognormal around 0.8 m (or `clean`), the cell clean / r times lognormal noise of log-sd `noise`, rescaled
    (units held at the bound left there) until sum(clean) / sum(cell) == r."""
    if clean is None:
        clean = np.minimum(rng.lognormal(np.log(0.8), 0.45, n), bound / 2)
    cell = np.minimum(clean / r * rng.lognormal(-noise ** 2 / 2, noise, n), bound)
    for _ in range(50):
        free = cell < bound
        need = clean.sum() / r - cell[~free].sum()
        cell[free] *= need / cell[free].sum()
        if cell.max() <= bound:
            break
        cell = np.minimum(cell, bound)
    assert abs(clean.sum() / cell.sum() - r) < 1e-9
    return clean, cell


def wrong(side: str, r: float, level: float) -> bool:
    """A settled claim contradicts the truth ("below" means r < level, "above" r >= level)."""
    return (side == "below" and r >= level) or (side == "above" and r < level)


def naive_stop(clean: np.ndarray, cell: np.ndarray, level: float, rng: np.random.Generator, *,
               resamples: int = 100, first: int = 20, growth: float = 1.25) -> tuple[str, int]:
    """The naive rule: look at n = 20, 25, 31, ... units; stop when the paired percentile bootstrap 95% CI of
    retention clears `level`, claiming that side; at the end, the exact answer."""
    n_all, n = len(clean), first
    while n < n_all:
        idx = rng.integers(0, n, (resamples, n))
        r = clean[:n][idx].sum(axis=1) / cell[:n][idx].sum(axis=1)
        low, high = np.percentile(r, [2.5, 97.5])
        if high < level:
            return "below", n
        if low >= level:
            return "above", n
        n = int(n * growth) + 1
    return ("below" if clean.sum() / cell.sum() < level else "above"), n_all


def error_rates(r: float, level: float, runs: int, n: int, seed: int, method: str = "betting",
                alpha: float = 0.05, naive: bool = True) -> tuple[float, float, float]:
    """(adaptive error rate, naive error rate (NaN when `naive` is off), adaptive mean share of units used) over
    `runs` populations."""
    rng = np.random.default_rng(seed)
    bad_a = bad_n = 0
    used = 0.0
    for _ in range(runs):
        clean, cell = population(rng, n, r)
        truth = float(np.mean(clean) / np.mean(cell))  # the full run's value, rounding included
        d = settle_retention(clean, cell, level, population=n, alpha=alpha, bound=BOUND, method=method)
        bad_a += wrong(d.side, truth, level)
        used += d.units / n
        bad_n += wrong(naive_stop(clean, cell, level, rng)[0], truth, level) if naive else 0
    return bad_a / runs, (bad_n / runs if naive else float("nan")), used / runs


# -- known answers ----------------------------------------------------------------------------------------------

def test_a_constant_stream_settles_and_the_exhausted_population_is_exact() -> None:
    # x varied in [0.5, 1], null mean 0: the betting test crosses 1/alpha after a few units.
    d = settle_mean(np.random.default_rng(0).uniform(0.5, 1.0, 200), 0.0, -1.0, 1.0, 200, 0.05)
    assert (d.side, d.how) == ("above", "evidence") and d.units < 20
    # x = 1 everywhere: a degenerate prefix carries no information about the units left, so no evidence settles
    # it (issue 36); only exhaustion does, once the 99 units left cannot pull the sum below 0.
    d = settle_mean(np.ones(200), 0.0, -1.0, 1.0, 200, 0.05)
    assert (d.side, d.how, d.units) == ("above", "exhausted", 101)
    # mean exactly 0 (a tie): no test settles it, and exhaustion does not either (rounding must not decide).
    x = np.tile([1.0, -1.0], 50)
    assert settle_mean(x, 0.0, -1.0, 1.0, 100, 1e-6).side == "open"
    # a retention exactly on the level with every unit seen: the full run's comparison, "above" (not below).
    clean, cell = np.tile([1.0, 0.8], 50), np.tile([1.0, 1.0], 50)
    d = settle_retention(clean, cell, 0.9, population=100, alpha=1e-6, bound=BOUND)
    assert (d.side, d.how, d.units) == ("above", "exhausted", 100)


def test_a_stream_that_cannot_reach_the_level_is_settled_by_exhaustion() -> None:
    # 10 units at -1: after 6 seen, four more at +1 would leave the sum at -2, so "below" is certain at unit 6
    # (and not at 5: five at +1 would bring it to 0, which is not below).
    d = settle_mean(-np.ones(10), 0.0, -1.0, 1.0, 10, 1e-9)
    assert (d.side, d.how, d.units) == ("below", "exhausted", 6)


def test_retention_decisions_follow_the_paired_sign() -> None:
    rng = np.random.default_rng(3)
    clean, cell = population(rng, 600, 0.6)
    stop = run_cell(clean, cell, (0.9, 0.75), alpha=0.01, bound=BOUND)
    assert [d.side for d in stop.decisions] == ["below", "below"]
    assert stop.reason == "settled" and stop.units < 600
    assert set(settled(stop.decisions)) == {0.9, 0.75}
    assert settled([Settlement(0.9, "open", 5, "")]) == {}


def test_with_no_data_left_every_decision_is_the_full_runs() -> None:
    rng = np.random.default_rng(4)
    clean, cell = population(rng, 80, 0.9)  # exactly on the 0.90 boundary: not below
    stop = run_cell(clean, cell, (0.9,), alpha=1e-6, bound=BOUND)
    assert stop.decisions[0].side == "above" and stop.reason == "data" and stop.units == 80


def test_max_units_leaves_a_decision_open() -> None:
    rng = np.random.default_rng(5)
    clean, cell = population(rng, 500, 0.9)
    stop = run_cell(clean, cell, (0.9,), alpha=0.01, bound=BOUND, max_units=30)
    assert stop.decisions[0].side == "open" and stop.units == 30 and stop.reason == "data"


def test_levels_and_alpha_split() -> None:
    assert cell_levels(3, axis=True) == (0.9, 0.75)
    assert cell_levels(5, axis=True, flat=0.95) == (0.9, 0.75, 0.95)
    assert cell_levels(5, axis=False) == (0.9, 0.75)
    assert alpha_per_decision(0.05, 10) == pytest.approx(0.005)


def test_an_axis_settles_from_its_cells_intervals() -> None:
    side, low, high = axis_settled([(0.7, 0.8), (0.6, 0.9)], 0.95)
    assert side == "below" and (low, high) == pytest.approx((0.65, 0.85))
    assert axis_settled([(0.96, 1.0), (0.97, 1.01)], 0.95)[0] == "above"
    assert axis_settled([(0.9, 1.0), (0.97, 1.01)], 0.95)[0] == "open"


def test_the_interval_covers_the_truth_and_shrinks() -> None:
    rng = np.random.default_rng(6)
    clean, cell = population(rng, 400, 0.8)
    small = retention_interval(clean[:100], cell[:100], alpha=0.025, population=400, bound=BOUND)
    large = retention_interval(clean[:400], cell[:400], alpha=0.025, population=400, bound=BOUND)
    assert small[0] <= 0.8 <= small[1] and large[0] <= 0.8 <= large[1]
    assert large[1] - large[0] < small[1] - small[0]


def test_units_cut_whole_scenes_or_windows_with_warmup() -> None:
    ego = EgoStatus((0.0, 0.0), (0.0, 0.0), 0.0)
    frames = [Frame(f"f{i}", "a" if i < 20 else "b", i, {}, ego, Command.STRAIGHT, np.zeros((6, 2)),
                    np.ones(6, bool)) for i in range(25)]
    scenes = cut_units(frames, window=None, seed=1)
    assert sorted(len(u.scored) for u in scenes) == [5, 20] and all(not u.warmup for u in scenes)
    windows = cut_units(frames, window=8, warmup=2, seed=1)
    assert sorted(i for u in windows for i in u.scored) == list(range(25))  # every frame scored once
    by_start = {u.scored[0]: u for u in windows}
    assert by_start[0].warmup == () and by_start[8].warmup == (6, 7) and by_start[20].warmup == ()
    assert all(len({frames[i].scene_token for i in u.warmup + u.scored}) == 1 for u in windows)
    assert [u.scored for u in windows] == [u.scored for u in cut_units(frames, window=8, warmup=2, seed=1)]
    assert [u.scored for u in windows] != [u.scored for u in cut_units(frames, window=8, warmup=2, seed=2)]
    assert sum(u.passes for u in windows) == 25 + 2 * 2


# -- severity scheduling ----------------------------------------------------------------------------------------

def visit(curve: dict[int, float]) -> tuple[dict[int, dict[float, str]], tuple[int, ...], tuple[str, ...]]:
    """Run the scheduler on an exactly known curve (decisions are the true signs)."""
    seen: dict[int, dict[float, str]] = {}
    while True:
        plan = schedule_family(seen)
        if plan.next_severity is None:
            return seen, plan.skipped, plan.violations
        r = curve[plan.next_severity]
        seen[plan.next_severity] = {c: "below" if r < c else "above" for c in (0.9, 0.75)}


def test_a_flat_family_needs_only_s5() -> None:
    seen, skipped, found = visit({1: 1.0, 2: 0.99, 3: 0.99, 4: 0.98, 5: 0.97})
    assert list(seen) == [5] and skipped == (1, 2, 3, 4) and found == ()
    assert "non-increasing" in schedule_family(seen).assumption


def test_bisection_locates_both_thresholds() -> None:
    curve = {1: 0.97, 2: 0.93, 3: 0.86, 4: 0.79, 5: 0.70}  # s10 between S2 and S3, s25 between S4 and S5
    seen, skipped, _ = visit(curve)
    assert {2, 3, 4, 5} <= set(seen) and len(seen) <= 4 and set(skipped) == set(range(1, 6)) - set(seen)


def test_crossing_at_s1() -> None:
    seen, _, _ = visit({1: 0.85, 2: 0.8, 3: 0.7, 4: 0.6, 5: 0.5})
    assert 1 in seen and 5 in seen


def test_a_visible_rise_is_flagged_and_the_family_visited_in_full() -> None:
    seen, skipped, found = visit({1: 0.95, 2: 0.85, 3: 0.80, 4: 0.95, 5: 0.70})
    assert found and "S2" in found[0] and "S4" in found[0]
    assert sorted(seen) == [1, 2, 3, 4, 5] and skipped == ()


def test_interval_rise_is_a_violation() -> None:
    got = violations({2: {}, 4: {}}, {2: (0.7, 0.8), 4: (0.85, 0.9)})
    assert got and "S2" in got[0]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.3, 1.0), min_size=5, max_size=5))
def test_on_a_monotone_curve_the_scheduled_thresholds_are_the_full_ones(values: list[float]) -> None:
    from pytest_drivedegrade.scoring.retention import tolerance_threshold

    curve = dict(zip(range(1, 6), sorted(values, reverse=True), strict=True))
    seen, skipped, found = visit(curve)
    assert found == () and 5 in seen and set(skipped) | set(seen) == set(range(1, 6))
    part = {s: curve[s] for s in seen}
    for c in (0.9, 0.75):
        assert tolerance_threshold(part, c) == tolerance_threshold(curve, c)


# -- the gate ---------------------------------------------------------------------------------------------------

def test_gate_settles_an_unchanged_planner_and_catches_a_regression() -> None:
    rng = np.random.default_rng(7)
    clean, cell = population(rng, 400, 0.8)
    base = GateBaseline(clean, cell)
    order = list(rng.permutation(400))
    # unchanged: every paired difference 0, no information, so "no regression" only once the data run out
    same = gate_cell(clean, cell, base, order, tolerance=0.02, alpha=0.01)
    assert (same.side, same.how) == ("above", "exhausted") and same.units == 399
    better = cell * rng.lognormal(0, 0.02, 400) * 0.97  # changed, a little better: the bound settles it
    got = gate_cell(clean, better, base, order, tolerance=0.02, alpha=0.01)
    assert (got.side, got.how) == ("above", "evidence") and got.units < 400
    worse = cell.copy()
    worse[:200] = np.minimum(worse[:200] * 1.3, BOUND)  # retention drops by far more than the tolerance
    caught = gate_cell(clean, worse, base, order, tolerance=0.02, alpha=0.01)
    assert caught.side == "below" and caught.units < 400
    worse[0] = BOUND * 1.3  # a unit beyond the stated bound: nothing clipped, the test waits for every unit
    assert gate_cell(clean, worse, base, order, tolerance=0.02, alpha=0.01).units == 400


@pytest.mark.parametrize("method", ["betting", "asymptotic-wor"])
def test_a_quiet_prefix_never_settles_no_regression(method: str) -> None:
    """Issue 36: a regression on 10 of 204 units not among the first drawn gave paired differences all 0, the
    plug-in variance 0, and the old gate settled "no regression" at unit 10 whatever the regression's size."""
    rng = np.random.default_rng(4)
    clean, cell = population(rng, 204, 0.8)
    base = GateBaseline(clean, cell)
    order = list(rng.permutation(204))
    worse = cell.copy()
    worse[order[-10:]] = np.minimum(cell[order[-10:]] * 4, BOUND)  # the changed units come last in the draw
    for k in (10, 50, 150, 194):
        got = gate_cell(clean, worse, base, order, tolerance=0.02, alpha=2.9e-4, max_units=k, method=method)
        assert got.side == "open", (k, got)
    end = gate_cell(clean, worse, base, order, tolerance=0.02, alpha=2.9e-4, method=method)
    assert end.side == "below" and end.units > 194


def test_a_regression_on_five_percent_of_units_is_not_passed_by_betting() -> None:
    """The asymptotic sequence passes this one ("above" after 382 of 400 units: its variance estimate trusts the
    units seen); betting with the bound stated does not."""
    rng = np.random.default_rng(7)
    clean, cell = population(rng, 400, 0.8)
    base = GateBaseline(clean, cell)
    order = list(rng.permutation(400))
    worse = cell.copy()
    bad = np.array(order[-20:])
    worse[bad] = np.minimum(worse[bad] * 3, BOUND)
    assert float(clean.sum() / worse.sum()) < base.retention() - 0.05
    assert gate_cell(clean, worse, base, order, tolerance=0.02, alpha=0.01).side == "below"
    assert gate_cell(clean, worse, base, order, tolerance=0.02, alpha=0.01, method="asymptotic-wor").side == "above"


# -- the simulation study ---------------------------------------------------------------------------------------

@pytest.mark.parametrize(("r", "level"), [(0.9, 0.9), (0.89, 0.9), (0.75, 0.75)])
def test_optional_stopping_error_at_most_alpha_and_the_naive_rule_exceeds_it(r: float, level: float) -> None:
    runs = 300
    adaptive, naive, _ = error_rates(r, level, runs=runs, n=300, seed=int(r * 1000))
    # alpha = 0.05; the bound leaves three binomial standard errors of slack for 300 runs.
    assert adaptive <= 0.05 + 3 * (0.05 * 0.95 / runs) ** 0.5
    if r == level:  # on the line: the naive rule claims "below" far more often than alpha
        assert naive > 0.05 + 3 * (0.05 * 0.95 / runs) ** 0.5


def test_the_asymptotic_rule_keeps_alpha_on_the_boundary() -> None:
    adaptive, _, _ = error_rates(0.9, 0.9, runs=200, n=300, seed=11, method="asymptotic")
    assert adaptive <= 0.05 + 3 * (0.05 * 0.95 / 200) ** 0.5


@pytest.mark.parametrize(("r", "level"), [(0.9, 0.9), (0.89, 0.9)])
def test_the_without_replacement_rule_keeps_alpha_on_the_boundary(r: float, level: float) -> None:
    adaptive, _, _ = error_rates(r, level, runs=300, n=300, seed=13, method="asymptotic-wor")
    assert adaptive <= 0.05 + 3 * (0.05 * 0.95 / 300) ** 0.5


def test_the_without_replacement_rule_settles_near_the_line_sooner_as_the_units_run_out() -> None:
    """A population 0.02 above the level: the with-replacement sequence needs nearly every unit (or never
    settles), the finite-population one far fewer, and both say "above"."""
    rng = np.random.default_rng(21)
    clean, cell = population(rng, 400, 0.92, noise=0.1)
    iid = settle_retention(clean, cell, 0.9, population=400, alpha=0.001, bound=BOUND, method="asymptotic")
    wor = settle_retention(clean, cell, 0.9, population=400, alpha=0.001, bound=BOUND, method="asymptotic-wor")
    assert wor.side == iid.side == "above"
    assert wor.units < 0.9 * iid.units
