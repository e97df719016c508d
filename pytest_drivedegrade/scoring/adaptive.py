"""Anytime-valid adaptive certification (spec 4 section 14): statistics only, pure numpy.

**What is estimated.** A cell's retention over a finite population of N sampling units (scenes, or windows of
frames, see `cut_units`): r = sum_u clean_u / sum_u cell_u, with clean_u, cell_u a unit's mean L2 (equal-length
units make this the frame-level M(clean)/M(cell) of ``retention``). Units are drawn in a seeded random order
*without replacement*, so when the data run out the answer is the full run's, exactly.

**Decisions are signs of paired means.** For a level c, r < c  <=>  mean_u (clean_u - c * cell_u) < 0. Each
decision is settled by two one-sided betting tests (Waudby-Smith & Ramdas 2023, "Estimating means of bounded
random variables by betting", JRSS-B; their without-replacement form, arXiv 2006.04347) on the paired
differences x_u = clean_u - c * cell_u: "below" rejects H0 mean >= 0, "above" rejects H0 mean <= 0 (so "above"
claims r >= c; r exactly on the level is "not below", as in ``tolerance_threshold``). The capital
K_t = prod (1 + lambda_t (m_t - x_t)) with m_t the null's conditional mean of the next unit (finite population)
is a non-negative supermartingale under H0 for any predictable bet lambda_t in [0, 1/(hi - m_t)]; Ville's
inequality gives P(sup_t K_t >= 1/a) <= a, whatever stopping time is used. Bets are aGRAPA (an approximate Kelly
bet from the running mean and variance), capped at half the admissible bet. A decision also settles, without
error, once the units left cannot change its sign ("exhausted").

A second method, "asymptotic" (Waudby-Smith, Arnold, Wu, Wang & Ramdas 2024, "Time-uniform central limit theory
and asymptotic confidence sequences", Ann. Statist.), needs a finite variance only and is valid as the units grow:
far cheaper, but it trusts the units seen (`benchmarks/adaptive.py` measures both; spec/README says when each
meets issue 22's targets).

Why betting and not a ratio CS: a confidence sequence for the ratio needs a delta-method (asymptotic) argument;
the linearised sign test is exact, nonasymptotic and uses the pairing (per-unit difficulty cancels in x_u).

**Assumption (stated and checked):** every unit's figure lies in the stated range [lo, hi] (per-unit mean L2 in
[0, B], B fixed before the run, `DEFAULT_BOUND`). Nothing is clipped: a unit seen outside the range voids the
sequence for that decision (the bets assumed the range), so it settles only when every unit has run, from the
population's exact value (`settle_mean`: `out_of_range`). The bound sets the cost: a bet can never risk more than
a unit at the bound could take, so a loose B slows every decision.

**No decision on a degenerate prefix.** Evidence settles a decision only once the units seen hold at least
MIN_DISTINCT distinct values: a prefix of identical figures (a gate's paired differences all zero because the
changed frames were not drawn yet) carries no information about the units left, whatever a bet would say.

**Error control.** Of the two one-sided tests of a decision at most one null is false-and-harmful (on the
boundary only "below" is wrong), so each side runs at the decision's level a_d and the decision errs with
probability <= a_d. Across the certificate's K decisions a union bound: a_d = alpha / K, K counted before the run
(every decision every cell could take), which bounds the chance that *any* settled decision is wrong by alpha.
The label rests on the axes, so an axis (a mean of S5 retentions) is decided against the flat line from its
cells' intervals (`axis_settled`), not cell by cell.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..constants import DEFAULT_FLAT
from ..data.frame import Frame
from .retention import THRESHOLD_LEVELS

#: The stated bound B on a unit's mean L2, metres (checked on every unit seen; see the module docstring).
DEFAULT_BOUND = 5.0
#: The share of the admissible bet ever staked (Waudby-Smith & Ramdas use 1/2 to 3/4).
BET_CAP = 0.5
SEVERITIES = (1, 2, 3, 4, 5)
#: The two ways a decision can be settled (see `settle_mean`).
METHODS = ("betting", "asymptotic", "asymptotic-wor")
#: The asymptotic CS is tuned to be tightest near this many units, and is not used before a few units.
ASYMPTOTIC_TSTAR = 100.0
ASYMPTOTIC_MIN_UNITS = 10
#: The share of its level the without-replacement asymptotic sequence spends (a margin for small samples).
WOR_LEVEL_SHARE = 0.5
#: Evidence settles nothing before the units seen hold this many distinct values (see the module docstring).
MIN_DISTINCT = 3


@dataclass(frozen=True)
class Settlement:
    """One decision "is the mean of x below or above m": side "below" / "above" / "open", the units seen when it
    settled, and how ("evidence": a test's capital crossed 1/a; "exhausted": the units left cannot change it)."""

    level: float
    side: str
    units: int
    how: str


def _bets(z: np.ndarray, m_z: np.ndarray, est_z: np.ndarray, var: np.ndarray, below: bool) -> np.ndarray:
    """aGRAPA bets on scaled data in [0, 1]: (edge / (var + edge^2)), clipped to [0, BET_CAP x admissible]."""
    edge = (m_z - est_z) if below else (est_z - m_z)
    room = (1.0 - m_z) if below else m_z  # how far the worst unit can move against the bet
    lam = np.clip(edge / (var + edge ** 2 + 1e-12), 0.0, None)
    return np.minimum(lam, BET_CAP / np.maximum(room, 1e-12))


def _asymptotic_hits(x: np.ndarray, m: float, alpha: float, population: int = 0) -> dict[str, np.ndarray]:
    """Where the asymptotic CS (Waudby-Smith, Arnold, Wu, Wang & Ramdas 2024, Gaussian mixture, rho tuned for
    t* = 100 units; two-sided at 2 alpha = one alpha per side) lies wholly below / at or above m.

    With `population` N ("asymptotic-wor"), the sum is the without-replacement martingale of Waudby-Smith &
    Ramdas 2020 (NeurIPS, "Confidence sequences for sampling without replacement"): under H0 "the population's
    mean is m" the unit t has conditional mean m_t = (N m - S_{t-1}) / (N - t + 1), so M_t = sum (x_i - m_i)
    is a martingale with the same increments' variance, held against the same boundary (t times the half
    width). The mean's interval then shrinks like 1 / (N (H_N - H_{N-t})) instead of 1 / t: no gain early,
    about 2x at t = 0.8 N, and exact at t = N. Using the whole level, its error on a boundary reached 0.053 at
    alpha 0.05 (the CLT's small-sample excess, which the with-replacement form's slack hid), so it runs at
    WOR_LEVEL_SHARE of its level with the unbiased variance (`benchmarks/adaptive.py` measures it)."""
    t = np.arange(1, len(x) + 1, dtype=float)
    mean = np.cumsum(x) / t
    var = np.maximum(np.cumsum(x ** 2) / t - mean ** 2, 0.0)
    if population:
        var, alpha = var * t / np.maximum(t - 1.0, 1.0), alpha * WOR_LEVEL_SHARE
    a2 = 2.0 * alpha
    rho2 = (-2.0 * math.log(a2) + math.log(-2.0 * math.log(a2) + 1.0)) / ASYMPTOTIC_TSTAR
    half = np.sqrt(var) * np.sqrt(2.0 * (t * rho2 + 1.0) / (t ** 2 * rho2) * np.log(np.sqrt(t * rho2 + 1.0) / a2))
    ok = t >= ASYMPTOTIC_MIN_UNITS
    if not population:
        return {"below": ok & (mean + half < m), "above": ok & (mean - half >= m)}
    seen = np.concatenate([[0.0], np.cumsum(x)[:-1]])  # S_{t-1}
    drift = np.cumsum(x - (population * m - seen) / np.maximum(population - t + 1.0, 1.0))
    return {"below": ok & (drift < -t * half), "above": ok & (drift >= t * half)}


def settle_mean(x: Sequence[float] | np.ndarray, m: float, lo: float, hi: float, population: int, alpha: float,
                level: float = math.nan, method: str = "betting") -> Settlement:
    """Settle "mean over the population of x below m, or at/above m" from the stream `x` (units in draw order,
    each in [lo, hi]), at error level `alpha` per decision; "open" when neither test crossed yet. `method`
    "betting" (nonasymptotic, the default) or "asymptotic" (`_asymptotic_hits`: needs finite variance only,
    valid as the units grow; exhaustion still uses [lo, hi])."""
    xs = np.asarray(x, dtype=float)
    n, width = len(xs), hi - lo
    if n == 0:
        return Settlement(level, "open", 0, "")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if out_of_range(xs, lo, hi):  # the range the bets assumed does not hold: only the whole population decides
        return exact_sign(xs, m, population, level)
    clt = None if method == "betting" else _asymptotic_hits(xs, m, alpha, population if method != "asymptotic" else 0)
    z, mz0 = (xs - lo) / width, (m - lo) / width
    t = np.arange(1, n + 1, dtype=float)
    seen = np.concatenate([[0.0], np.cumsum(z)[:-1]])  # sum of z before unit t
    left = population - t + 1
    m_z = (population * mz0 - seen) / left  # the null's conditional mean of unit t
    mean_prev = (0.5 + seen) / t  # running mean before unit t (a prior of 1/2)
    sq = np.concatenate([[0.0], np.cumsum((z - (0.5 + np.cumsum(z)) / (t + 1)) ** 2)[:-1]])
    var = (0.25 + sq) / t
    est_z = np.clip((population * mean_prev - seen) / left, 0.0, 1.0)
    threshold = math.log(1.0 / alpha)
    informative = distinct_so_far(xs) >= MIN_DISTINCT
    first: dict[str, tuple[int, str]] = {}
    for side in ("below", "above"):
        below = side == "below"
        if clt is None:
            lam = _bets(z, m_z, est_z, var, below)
            gain = lam * ((m_z - z) if below else (z - m_z))
            crossed = np.cumsum(np.log1p(np.maximum(gain, -1.0 + 1e-15))) >= threshold
        else:
            crossed = clt[side]
        total = seen + z  # sum of z through unit t; the best / worst the rest can add is (N - t) or 0
        slack = 1e-9 * population  # rounding never settles a population that sits on the line
        certain = (total + (population - t)) < population * mz0 - slack if below else total >= population * mz0 + slack
        hit_e, hit_c = np.flatnonzero(crossed & informative), np.flatnonzero(certain)
        cands = [(int(hit_e[0]) + 1, "evidence")] if len(hit_e) else []
        cands += [(int(hit_c[0]) + 1, "exhausted")] if len(hit_c) else []
        if cands:
            first[side] = min(cands)
    if not first:
        return Settlement(level, "open", n, "")
    side = min(first, key=lambda s: first[s])
    return Settlement(level, side, *first[side])


def out_of_range(xs: np.ndarray, lo: float, hi: float) -> bool:
    """Whether a figure lies outside the stated range (a small rounding margin allowed)."""
    slack = 1e-9 * max(1.0, hi - lo)
    return bool(np.any(xs < lo - slack) or np.any(xs > hi + slack) or not np.all(np.isfinite(xs)))


def exact_sign(xs: np.ndarray, m: float, population: int, level: float) -> Settlement:
    """The decision when only the whole population can settle it: open before every unit has run, then the
    population mean's side of `m` (exact; "above" includes the line)."""
    if len(xs) < population or not np.all(np.isfinite(xs)):
        return Settlement(level, "open", len(xs), "")
    return Settlement(level, "below" if float(np.mean(xs)) < m else "above", population, "exhausted")


def distinct_so_far(xs: np.ndarray) -> np.ndarray:
    """After each unit, how many distinct values (to 1e-12) the units so far hold (capped at MIN_DISTINCT)."""
    out = np.full(len(xs), MIN_DISTINCT, dtype=int)
    seen: list[float] = []
    for i, v in enumerate(xs):
        if all(abs(v - u) > 1e-12 for u in seen):
            seen.append(float(v))
            if len(seen) == MIN_DISTINCT:
                return out
        out[i] = len(seen)
    return out


def clip_units(values: Sequence[float] | np.ndarray, bound: float = DEFAULT_BOUND) -> tuple[np.ndarray, int]:
    """Per-unit mean L2 clipped to [0, bound], and how many units were clipped."""
    v = np.asarray(values, dtype=float)
    return np.clip(v, 0.0, bound), int(np.sum(v > bound))


def settle_retention(clean: np.ndarray, cell: np.ndarray, level: float, *, population: int, alpha: float,
                     bound: float = DEFAULT_BOUND, method: str = "betting") -> Settlement:
    """Settle r < level ("below") or r >= level ("above") from paired per-unit mean L2 in draw order (not clipped:
    a unit outside [0, bound] leaves the decision to the whole population, `settle_mean`)."""
    a, b = np.asarray(clean, dtype=float), np.asarray(cell, dtype=float)
    if len(a) == population and population > 0:  # all data: the full run's own comparison decides a tie
        exact = "below" if float(np.mean(a)) / float(np.mean(b)) < level else "above"
        got = settle_mean(a - level * b, 0.0, -level * bound, bound, population, alpha, level, method)
        return got if got.units < population else Settlement(level, exact, population, "exhausted")
    return settle_mean(a - level * b, 0.0, -level * bound, bound, population, alpha, level, method)


def settled(decisions: Sequence[Settlement]) -> dict[float, Settlement]:
    """level -> settlement, for the decisions that are settled (side "below" or "above")."""
    return {d.level: d for d in decisions if d.side != "open"}


@dataclass(frozen=True)
class CellStop:
    """A cell's adaptive run: units used, why it stopped ("settled", or "data" when the population ran out
    first), and each decision's settlement."""

    units: int
    reason: str
    decisions: tuple[Settlement, ...]


def run_cell(clean: np.ndarray, cell: np.ndarray, levels: Sequence[float], *, alpha: float,
             bound: float = DEFAULT_BOUND, max_units: int | None = None, method: str = "betting") -> CellStop:
    """The stopping rule: draw units until every decision in `levels` is settled, or the data (or `max_units`)
    run out. `clean`/`cell` hold the whole population in draw order; the rule reads only the prefix it uses."""
    n = len(clean) if max_units is None else min(len(clean), max_units)
    decisions = tuple(settle_retention(clean[:n], cell[:n], c, population=len(clean), alpha=alpha, bound=bound,
                                       method=method) for c in levels)
    if all(d.side != "open" for d in decisions):
        used = max(d.units for d in decisions)
        reason = "data" if used == len(clean) and any(d.how == "exhausted" for d in decisions) else "settled"
        return CellStop(used, reason, decisions)
    return CellStop(n, "data", decisions)


def cell_levels(severity: int, axis: bool, flat: float = DEFAULT_FLAT) -> tuple[float, ...]:
    """The levels a ladder cell decides: the two thresholds, and the flat line for an axis family's S5."""
    levels = tuple(THRESHOLD_LEVELS.values())
    return levels + (flat,) if axis and severity == 5 else levels


def axis_settled(intervals: Sequence[tuple[float, float]], flat: float = DEFAULT_FLAT) -> tuple[str, float, float]:
    """An axis (the mean of S5 retentions) against the flat line from its cells' anytime-valid intervals: the
    mean of the lows and of the highs bounds the mean whenever every cell's interval holds (the union bound
    already spent on the cells), so the axis is "below" / "above" (at or above) the line once that interval
    clears it, else "open". Returns (side, low, high)."""
    low = float(np.mean([i[0] for i in intervals]))
    high = float(np.mean([i[1] for i in intervals]))
    side = "below" if high < flat else "above" if low >= flat else "open"
    return side, low, high


def alpha_per_decision(alpha: float, decisions: int) -> float:
    """The union bound: each of `decisions` (counted before the run) at alpha / decisions."""
    return alpha / max(1, decisions)


def retention_interval(clean: np.ndarray, cell: np.ndarray, *, alpha: float, bound: float = DEFAULT_BOUND,
                       population: int | None = None, grid: np.ndarray | None = None,
                       method: str = "betting") -> tuple[float, float]:
    """Anytime-valid interval for r from the units seen: the levels neither test rejects (coverage 1 - 2 alpha,
    one alpha per side). Levels on `grid` (default 0.00 .. 2.00 by 0.005)."""
    levels = np.round(np.arange(0.0, 2.0001, 0.005), 3) if grid is None else grid
    pop = len(clean) if population is None else population
    low, high = -math.inf, math.inf
    for c in levels:
        d = settle_retention(clean, cell, float(c), population=pop, alpha=alpha, bound=bound, method=method)
        if d.side == "above":
            low = max(low, float(c))
        elif d.side == "below":
            high = min(high, float(c))
    return low, high


# -- sampling units --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Unit:
    """One sampling unit: frames (indices into the stream) of one scene; `warmup` frames are run, not scored,
    and the planner is `reset` before the first of them (or of `scored` when there is no warm-up)."""

    scene_token: str
    warmup: tuple[int, ...]
    scored: tuple[int, ...]

    @property
    def passes(self) -> int:
        """Forward passes the unit costs in one cell."""
        return len(self.warmup) + len(self.scored)


def cut_units(frames: Sequence[Frame], *, window: int | None = 8, warmup: int = 2, seed: int = 0) -> list[Unit]:
    """Cut a stream (scene by scene, timestamp order) into units, in a seeded random order.

    `window=None`: whole scenes (exact for any temporal planner: its state runs from the scene start as in a
    full run). Otherwise windows of `window` consecutive scored frames, each preceded by up to `warmup` unscored
    frames of the same scene with `reset` at the warm-up's start: finer units stop earlier, and a planner whose
    memory is at most `warmup` frames (BEVFormer/UniAD keep one previous BEV) sees the history a full run gives.
    The first window of a scene has no warm-up (the scene start is where a full run begins too).
    """
    scenes: dict[str, list[int]] = {}
    for i, frame in enumerate(frames):
        scenes.setdefault(frame.scene_token, []).append(i)
    units: list[Unit] = []
    for token, idx in scenes.items():
        step = len(idx) if window is None else window
        for start in range(0, len(idx), step):
            units.append(Unit(token, tuple(idx[max(0, start - warmup):start]) if window else (),
                              tuple(idx[start:start + step])))
    order = np.random.default_rng(seed).permutation(len(units))
    return [units[i] for i in order]


# -- severity scheduling ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Schedule:
    """The next severity of a family to visit (None: the family is done), the severities skipped, the
    assumption a skip rests on, and the monotonicity violations seen among visited severities."""

    next_severity: int | None
    skipped: tuple[int, ...]
    assumption: str
    violations: tuple[str, ...]


def violations(visited: Mapping[int, Mapping[float, str]],
               intervals: Mapping[int, tuple[float, float]] | None = None) -> tuple[str, ...]:
    """Visited pairs s1 < s2 where retention settled higher at s2: below a level at s1 and above it at s2, or
    (with intervals) s2's interval entirely above s1's."""
    found = []
    sev = sorted(visited)
    for i, s1 in enumerate(sev):
        for s2 in sev[i + 1:]:
            for c, side in visited[s1].items():
                if side == "below" and visited[s2].get(c) == "above":
                    found.append(f"retention rises from S{s1} (below {c:g}) to S{s2} (at or above {c:g})")
            if intervals and s1 in intervals and s2 in intervals and intervals[s2][0] > intervals[s1][1]:
                found.append(f"retention rises from S{s1} {intervals[s1]} to S{s2} {intervals[s2]}")
    return tuple(found)


def _bracket(visited: Mapping[int, Mapping[float, str]], level: float) -> tuple[int, int | None]:
    """(highest visited severity settled at/above `level`, or 0; lowest settled below it, or None)."""
    above = [s for s, d in visited.items() if d.get(level) == "above"]
    below = [s for s, d in visited.items() if d.get(level) == "below"]
    return max(above, default=0), min(below, default=None)


def schedule_family(visited: Mapping[int, Mapping[float, str]], *,
                    levels: Sequence[float] = tuple(THRESHOLD_LEVELS.values()),
                    intervals: Mapping[int, tuple[float, float]] | None = None) -> Schedule:
    """Bisection for s*10 and s*25 under monotone retention, S5 first.

    A level is located when no visited severity is below it ("never"), S1 is below it (1.00), or the first
    severity below it and the one before are both visited (the interpolation's two ends). A violation seen
    among the visited severities drops the assumption: the rest of the family is visited.
    """
    seen = violations(visited, intervals)
    todo = [s for s in SEVERITIES if s not in visited]
    if seen:
        return Schedule(todo[0] if todo else None, (), "none: the family is visited in full", seen)
    if 5 not in visited:
        return Schedule(5, (), "", ())
    open_ranges = []
    for c in levels:
        lo, hi = _bracket(visited, c)
        if hi is not None and hi > 1 and hi - lo > 1:
            open_ranges.append((lo, hi))
    if not open_ranges:
        shown = ", ".join(f"S{s}" for s in sorted(visited))
        return Schedule(None, tuple(todo), f"retention non-increasing in severity between the visited {shown}", ())
    mids = {(lo + hi + 1) // 2 if lo else max(1, (lo + hi) // 2) for lo, hi in open_ranges}
    best = max(sorted(mids), key=lambda s: sum(lo < s < hi for lo, hi in open_ranges))
    return Schedule(best, (), "", ())


# -- the sequential gate ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class GateBaseline:
    """A full baseline run's per-unit mean L2 (clean and the cell, indexed like the current run's units)."""

    clean: np.ndarray
    cell: np.ndarray

    def retention(self) -> float:
        return float(np.sum(self.clean) / np.sum(self.cell))


def gate_cell(clean: np.ndarray, cell: np.ndarray, baseline: GateBaseline, order: Sequence[int], *,
              tolerance: float, alpha: float, bound: float = DEFAULT_BOUND,
              max_units: int | None = None, method: str = "betting") -> Settlement:
    """Sequential test of "retention dropped by more than `tolerance`" (side "below": a regression, r_now <
    r_base - tolerance; "above": none), paired with the baseline unit by unit.

    With k = r_base - tolerance, r_now < k <=> mean(clean - k cell) < 0. The baseline's own difference on the
    same unit is a control variate whose population mean is known from the full baseline, so the test runs on
    e_u = (clean_u - k cell_u) - (base_clean_u - k base_cell_u) against m = -mean(base_clean - k base_cell). A
    prefix of e_u all equal (an unchanged planner, or a change on frames not drawn yet) settles nothing
    (MIN_DISTINCT), so "no regression" is said only when the betting bound itself excludes a drop beyond the
    tolerance, or every unit has run. `order` lists the units drawn (indices into the population arrays `clean`,
    `cell` and the baseline's).
    """
    k = baseline.retention() - tolerance
    bc, bx = np.asarray(baseline.clean, dtype=float), np.asarray(baseline.cell, dtype=float)
    idx = np.asarray(order[: len(order) if max_units is None else max_units], dtype=int)
    a, b = np.asarray(clean, dtype=float)[idx], np.asarray(cell, dtype=float)[idx]
    return gate_test(a, b, k, bc - k * bx, idx, alpha, bound, method)


def gate_range(k: float, base: np.ndarray, bound: float = DEFAULT_BOUND) -> tuple[float, float]:
    """The range of e_u = (clean_u - k cell_u) - d_u when this run's figures lie in [0, bound]: d_u (the baseline's
    control variates) are known before the run, so the range holds them as they are, clipped nowhere."""
    return (-abs(k) * bound - float(np.max(base, initial=0.0)),
            (1.0 + abs(k)) * bound - float(np.min(base, initial=0.0)))


def gate_test(a: np.ndarray, b: np.ndarray, k: float, base: np.ndarray, idx: np.ndarray, alpha: float,
              bound: float = DEFAULT_BOUND, method: str = "betting") -> Settlement:
    """The gate's test from its parts: this run's figures `a`, `b` on the units `idx` drawn, the level k and the
    baseline's control variates `base` (d_u = base_clean_u - k base_cell_u) over the whole population."""
    return gate_settle(a, b, k, base[idx], float(np.mean(base)), len(base), alpha, gate_range(k, base, bound),
                       bound, method)


def gate_settle(a: np.ndarray, b: np.ndarray, k: float, diffs: np.ndarray, mean: float, population: int,
                alpha: float, span: tuple[float, float], bound: float = DEFAULT_BOUND,
                method: str = "betting") -> Settlement:
    """`gate_test` from what a certificate records: the control variates on the units run, their population
    mean and the range (`gate_range`). A unit of this run outside [0, bound] leaves the test to the whole
    population (the range assumed it)."""
    e, m = (a - k * b) - diffs, -mean
    if out_of_range(a, 0.0, bound) or out_of_range(b, 0.0, bound):
        return exact_sign(e, m, population, k)
    return settle_mean(e, m, span[0], span[1], population, alpha, k, method)
