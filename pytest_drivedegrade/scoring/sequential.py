"""Adaptive certification from cell records (spec 4 section 14): the units a run draws (`UnitPlan`), a cell's
per-unit figures, where its stopping rule stops (`cell_outcome`), a family's severity schedule (`family_plan`),
and the certificate's ``adaptive`` section (`adaptive_section`).

Pure functions over records, shared by the plugin's runner (which stops a cell after the unit where
`cell_outcome` says it settled) and by `drivedegrade verify` (which recomputes every stop from the stored
per-frame results): one rule, so the two cannot disagree.

**The guarantee (a union bound over cells, not decisions).** Each stopping cell's decisions come from one
two-sided confidence sequence for its retention (the levels neither one-sided test rejects, each side at
``alpha_side``), so a cell's interval and every decision it settles hold together with probability at least
1 - 2 alpha_side, at whatever unit it stopped. With ``alpha_side = alpha / (2 C)``, C the cells that could stop
(counted before the run), every interval, settled decision, threshold interval and axis interval of the run
holds at once with probability at least 1 - alpha. Sharper than a bound over decisions: an S5 cell's third
level (the flat line) costs nothing extra.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..cells import DIAGNOSTIC, CellRecord, is_camera_ladder
from ..constants import ADAPTIVE_METHOD, EGO_BLIND, EGO_NOISE
from ..data.frame import Frame
from .adaptive import (
    DEFAULT_BOUND,
    MIN_DISTINCT,
    SEVERITIES,
    CellStop,
    Settlement,
    Unit,
    axis_settled,
    cut_units,
    settle_retention,
    violations,
)
from .retention import THRESHOLD_LEVELS, tolerance_threshold

#: Units of a planner with `reset` (a temporal one): windows of WINDOW consecutive scored frames, each after up
#: to WARMUP unscored frames of its scene with `reset` at the warm-up's start, so a planner that remembers at most
#: WARMUP frames sees the history a full run gives it. A planner with neither `reset` nor `context` keeps no scene
#: state: its units are single frames. One taking `context` without `reset` gets whole scenes (its memory, if
#: any, is not cut where a scene is; single frames gave frame_dropout S5 retention 1.03 against the full run's 0.44).
WINDOW, WARMUP = 8, 2
#: A planner with `reset` gets whole scenes as units when the run has fewer scenes than this: exact (each unit
#: runs as the full run does, from its scene's start), and with few scenes windows rarely stop a cell before
#: the data run out (temporal_cnn on the embedded world's 6 scenes: 24 of its 37 visited cells used all 30
#: windows, whose 2-frame warm-up left their values off the full run's by up to 0.006).
SCENE_UNITS_BELOW = 30
#: The sequence cells stop on (`adaptive.settle_mean`): "betting" (without replacement), valid at every sample
#: size for figures in the stated, checked range. "asymptotic-wor" stays an option of the functions with its own
#: weaker sentence (`guarantee`): issue 36 measured its family-wise error at 12.9 % against 5 % claimed.
METHOD = ADAPTIVE_METHOD
#: Cells that run every unit and take no decision: clean (every cell pairs with it) and the null control.
FULL_CELLS = ("clean", "null")
#: The search range and steps of a cell's interval (`retention_span`): 4 / 2**16, about 6e-5.
SPAN_TOP, SPAN_STEPS = 4.0, 16


def draw_seed(seed: int, fingerprint: str, baseline: str | None = None) -> int:
    """The seed of a run's draw order: from the corruption seed, the candidate planner's fingerprint and the
    baseline certificate's digest (a gate run), so that nobody writing the planner can know which units are read
    first without knowing the planner's own final bytes (a change to the planner redraws the order)."""
    text = f"drivedegrade-draw-order|{int(seed)}|{fingerprint}|{baseline or ''}"
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") >> 1


@dataclass(frozen=True)
class UnitPlan:
    """The run's sampling units in draw order: `cut_units` of the scored frames under the draw seed, and what that
    seed was derived from (`draw_seed`: the corruption seed, the planner's fingerprint, the baseline's digest)."""

    units: tuple[Unit, ...]
    seed: int
    window: int = WINDOW
    source: dict[str, object] = field(default_factory=dict, compare=False)

    @classmethod
    def of(cls, frames: Sequence[Frame], seed: int, temporal: bool = True, scenes: bool = False) -> UnitPlan:
        """The plan of a planner with `reset` (`temporal`: windows after a warm-up, or whole scenes when the run has
        few), one taking `context` without `reset` (`scenes`: whole scenes) or neither (single frames)."""
        if scenes or (temporal and len({f.scene_token for f in frames}) < SCENE_UNITS_BELOW):
            whole = tuple(cut_units(frames, window=None, seed=seed))
            return cls(whole, int(seed), max((len(u.scored) for u in whole), default=1))
        window = WINDOW if temporal else 1  # single frames: their warm-up frames are recorded, never run
        return cls(tuple(cut_units(frames, window=window, warmup=WARMUP, seed=seed)), int(seed), window)

    @classmethod
    def drawn(cls, frames: Sequence[Frame], seed: int, fingerprint: str, baseline: str | None, *,
              temporal: bool, scenes: bool) -> UnitPlan:
        """`of` under the run's draw seed (`draw_seed`), recording what it came from."""
        plan = cls.of(frames, draw_seed(seed, fingerprint, baseline), temporal, scenes)
        return cls(plan.units, plan.seed, plan.window, {"seed": int(seed), "planner_fingerprint": fingerprint,
                                                        "baseline_digest": baseline})

    @property
    def kind(self) -> str:
        """"frames" (single frames), "scenes" (whole scenes, no warm-up) or "windows"."""
        if self.window == 1:
            return "frames"
        return "scenes" if all(not u.warmup for u in self.units) else "windows"

    @classmethod
    def matching(cls, frames: Sequence[Frame], seed: int, units: int, fingerprint: str | None = None,
                 baseline: str | None = None) -> UnitPlan:
        """The plan a run used, read off its clean cell's unit count (single frames, windows or whole scenes);
        under the draw seed of `fingerprint` and `baseline` when a fingerprint is given."""
        def make(temporal: bool, scenes: bool) -> UnitPlan:
            if fingerprint is None:
                return cls.of(frames, seed, temporal, scenes)
            return cls.drawn(frames, seed, fingerprint, baseline, temporal=temporal, scenes=scenes)

        options = (make(False, False), make(True, False), make(False, True))
        return next((p for p in options if p.population == units), options[1])

    @property
    def population(self) -> int:
        return len(self.units)

    def to_builtins(self) -> dict[str, object]:
        """The cut as the certificate records it: [first scored frame, warm-up frames, scored frames] per unit,
        in draw order (frame indices into the cells' frame lists), and the draw seed's source."""
        out: dict[str, object] = {"window": self.window, "seed": self.seed,
                                  "warmup": max((len(u.warmup) for u in self.units), default=0),
                                  "units": [[u.scored[0], len(u.warmup), len(u.scored)] for u in self.units]}
        if self.source:
            out["draw"] = dict(self.source)
        return out

    @classmethod
    def from_builtins(cls, data: Mapping[str, object]) -> UnitPlan:
        rows, seed, window = data.get("units"), data.get("seed"), data.get("window")
        if not isinstance(rows, list) or not isinstance(seed, int) or not isinstance(window, int) or window < 1:
            raise ValueError("the adaptive section's unit plan needs `units` (a list), `seed` and `window` "
                             "(integers)")
        units = tuple(Unit("", tuple(range(int(a) - int(w), int(a))), tuple(range(int(a), int(a) + int(n))))
                      for a, w, n in rows)
        draw = data.get("draw")
        return cls(units, seed, window, dict(draw) if isinstance(draw, Mapping) else {})

    def seed_problem(self, fingerprint: object, baseline: object) -> str | None:
        """Whether the draw seed is the one the planner's fingerprint and the baseline's digest give (None: it is)."""
        src = self.source
        if not src:
            return "the plan does not record what its draw seed came from (a spec-4 certificate)"
        if src.get("planner_fingerprint") != fingerprint:
            return (f"the draw seed came from planner fingerprint {src.get('planner_fingerprint')}, the certificate's "
                    f"planner is {fingerprint}")
        if src.get("baseline_digest") != baseline:
            return f"the draw seed came from baseline {src.get('baseline_digest')}, the run's is {baseline}"
        want = draw_seed(int(str(src.get("seed", 0))), str(fingerprint), None if baseline is None else str(baseline))
        return None if want == self.seed else f"the draw seed {self.seed} is not the one its source gives ({want})"

    def draw_order_problem(self) -> str | None:
        """Whether the units are the seeded permutation of themselves in frame order (None: they are)."""
        canonical = sorted(self.units, key=lambda u: u.scored[0])
        order = np.random.default_rng(self.seed).permutation(len(canonical))
        if [canonical[i].scored for i in order] != [u.scored for u in self.units]:
            return f"the units are not drawn in the order seed {self.seed} gives"
        return None

    def passes(self, units: int, warm: bool) -> int:
        """Forward passes of the first `units` units in one cell (warm-up frames only for a planner that resets)."""
        return sum(u.passes if warm else len(u.scored) for u in self.units[:units])


def unit_sums(plan: UnitPlan, clean: np.ndarray, cell: np.ndarray, units: int) -> tuple[np.ndarray, np.ndarray]:
    """Per unit (the first `units` in draw order), the summed per-frame L2 of clean and of the cell over the
    scored frames finite in both, divided by the window: their ratio over units is the frame-level retention, and a
    short unit (a scene's end) weighs what its frames weigh."""
    a, b = np.zeros(units), np.zeros(units)
    for k, u in enumerate(plan.units[:units]):
        idx = np.asarray(u.scored)
        a[k], b[k] = unit_figure(clean[idx], cell[idx], plan.window)
    return a, b


def unit_figure(clean: np.ndarray, cell: np.ndarray, window: int) -> tuple[float, float]:
    """One unit's (clean, cell) figure from its scored frames' per-frame L2 (see `unit_sums`)."""
    ok = np.isfinite(clean) & np.isfinite(cell)
    return float(np.sum(clean[ok])) / window, float(np.sum(cell[ok])) / window


def levels_of(family: str, severity: int, axis_families: Sequence[str], flat: float) -> tuple[float, ...]:
    """The levels the certificate decides from a cell: a camera family's two thresholds, and the flat line where
    an axis reads it (an axis family's S5; ego_noise S5 and ego_blind, the ego axis, decide the flat line only).
    None for blind and ego_noise S1-S4: the certificate takes no decision from them, so they run no unit."""
    if family in (EGO_NOISE, EGO_BLIND):
        return (flat,) if (family, severity) in ((EGO_NOISE, 5), (EGO_BLIND, 0)) else ()
    if not is_camera_ladder(family):
        return ()
    base = tuple(THRESHOLD_LEVELS.values())
    return base + (flat,) if family in axis_families and severity == 5 else base


def stopping_cells(cells: Sequence[tuple[str, int]]) -> int:
    """C of the union bound: the run's cells that stop adaptively (all but clean and the null control)."""
    return sum(1 for f, _ in cells if f not in FULL_CELLS)


def alpha_side(alpha: float, cells: Sequence[tuple[str, int]]) -> float:
    """Each one-sided test's level: alpha / (2 C) (see the module docstring)."""
    return alpha / (2 * max(1, stopping_cells(cells)))


def stop_at(a: np.ndarray, b: np.ndarray, levels: Sequence[float], *, population: int, alpha: float,
            method: str = METHOD) -> CellStop | None:
    """The stopping rule after the units `a`, `b` (clean, cell; draw order): a `CellStop` once every level is
    settled or the population is used up, else None. Settlements are first crossings, so a rule checked after
    every unit stops exactly at ``max(d.units)``."""
    decisions = tuple(settle_retention(a, b, c, population=population, alpha=alpha, method=method) for c in levels)
    if all(d.side != "open" for d in decisions):
        used = max((d.units for d in decisions), default=0)
        return CellStop(used, "data" if used == population else "settled", decisions)
    return CellStop(len(a), "data", decisions) if len(a) >= population else None


def retention_span(a: np.ndarray, b: np.ndarray, *, population: int, alpha: float,
                   method: str = METHOD) -> tuple[float, float]:
    """The cell's anytime-valid interval: the highest level settled "above" and the lowest settled "below",
    by bisection on [0, SPAN_TOP] (rounded outwards to 1e-4)."""
    def side(c: float) -> str:
        return settle_retention(a, b, c, population=population, alpha=alpha, method=method).side

    lo, hi = 0.0, SPAN_TOP
    for _ in range(SPAN_STEPS):  # the highest level still "above"
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if side(mid) == "above" else (lo, mid)
    low = lo
    lo, hi = 0.0, SPAN_TOP
    for _ in range(SPAN_STEPS):  # the lowest level settled "below"
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if side(mid) == "below" else (mid, hi)
    return math.floor(low * 1e4) / 1e4, math.ceil(hi * 1e4) / 1e4


@dataclass(frozen=True)
class Outcome:
    """A cell's adaptive result read off its record: units used, stop reason ("settled", "data", "skipped",
    "full"), the decisions, the interval (None for a skipped or full cell) and the unit figures seen beyond the
    stated bound (nothing is clipped: such a cell decides from every unit)."""

    units: int
    reason: str
    decisions: tuple[Settlement, ...]
    interval: tuple[float, float] | None
    beyond: int = 0


def cell_outcome(plan: UnitPlan, clean: np.ndarray, record: CellRecord, levels: Sequence[float], *,
                 alpha: float, method: str = METHOD) -> Outcome:
    """Where the stopping rule stops on `record`'s units (its stored `units` prefix), and its interval there;
    `clean` is clean's per-frame L2 (at least on those units' frames)."""
    units = int(record.units or 0)
    if record.family in FULL_CELLS:
        return Outcome(units, "full", (), None)
    if units == 0:
        return Outcome(0, "skipped", (), None)
    a, b = unit_sums(plan, clean, record.l2_avg_per_frame(), units)
    beyond = int(np.sum(a > DEFAULT_BOUND) + np.sum(b > DEFAULT_BOUND))
    if units == plan.population:  # every unit ran: the population's exact value, and decisions from it
        r = float(np.sum(a) / np.sum(b))
        exact = tuple(Settlement(c, "below" if r < c else "above", units, "exhausted") for c in levels)
        return Outcome(units, "data", exact, (math.floor(r * 1e4) / 1e4, math.ceil(r * 1e4) / 1e4), beyond)
    # settlements are first crossings that read only the units before them, so the rule checked after every
    # unit stops where this one call on the whole prefix says (fewer units than stored: it ran too far)
    got = stop_at(a, b, levels, population=plan.population, alpha=alpha, method=method) or CellStop(units, "open", ())
    # a cell may run past its own stop (the sequential gate's test had not settled): an anytime-valid interval
    # holds at any unit, so it is taken over every unit the cell ran
    span = retention_span(a, b, population=plan.population, alpha=alpha, method=method)
    return Outcome(got.units, got.reason, got.decisions, span, beyond)


def family_plan(outcomes: Mapping[int, Outcome]) -> tuple[int | None, tuple[int, ...], str, tuple[str, ...]]:
    """(next severity or None, skipped, assumption, violations seen) of a camera family from its visited cells:
    every severity, S5 first (monotonicity is not assumed: a planner bad only at S4 broke it unseen, issue 36)."""
    visited = {s: {d.level: d.side for d in o.decisions} for s, o in outcomes.items()}
    spans = {s: o.interval for s, o in outcomes.items() if o.interval is not None}
    todo = [s for s in sorted(SEVERITIES, reverse=True) if s not in outcomes]
    return (todo[0] if todo else None), (), "", violations(visited, spans)


def threshold_spans(outcomes: Mapping[int, Outcome]) -> dict[str, list[float | None]]:
    """s10 / s25 intervals of a family from its cells' intervals, skipped severities bounded by monotone
    retention (a skipped S's retention lies below the nearest visited lower severity's high end and above the
    nearest visited higher one's low end): [first crossing of the low curve, of the high curve]; None: never."""
    spans = {s: o.interval for s, o in outcomes.items() if o.interval is not None}
    low = {s: spans[s][0] if s in spans else max((spans[t][0] for t in spans if t > s), default=0.0)
           for s in SEVERITIES}
    high = {s: spans[s][1] if s in spans else min((spans[t][1] for t in spans if t < s), default=SPAN_TOP)
            for s in SEVERITIES}
    return {k: [tolerance_threshold(low, c), tolerance_threshold(high, c)] for k, c in THRESHOLD_LEVELS.items()}


def cell_entry(record: CellRecord, outcome: Outcome, population: int) -> dict[str, object]:
    """One cell's row of the ``adaptive`` section."""
    entry: dict[str, object] = {"units": outcome.units, "population": population, "stop": outcome.reason,
                                "passes": int(record.passes or 0)}
    if outcome.interval is not None:
        entry["interval"] = list(outcome.interval)
        entry["decisions"] = {f"{d.level:g}": {"side": d.side, "units": d.units, "how": d.how}
                             for d in outcome.decisions}
    if outcome.beyond:  # the stated bound failed on a unit seen: the cell ran every unit and is exact
        entry["beyond_bound_units"] = outcome.beyond
    if outcome.units != int(record.units or 0):
        entry["stored_units"] = int(record.units or 0)
    return entry


def ladder_outcomes(records: Mapping[str, CellRecord], plan: UnitPlan, *, alpha: float, flat: float,
                    axis_families: Sequence[str]) -> dict[str, Outcome]:
    """Every record's `Outcome` (clean must be among them)."""
    clean = records["clean"].l2_avg_per_frame()
    return {c: cell_outcome(plan, clean, r, levels_of(r.family, r.severity, axis_families, flat), alpha=alpha)
            for c, r in records.items()}


def _per_family(records: Mapping[str, CellRecord], outcomes: Mapping[str, Outcome]) -> dict[str, dict[int, Outcome]]:
    fams: dict[str, dict[int, Outcome]] = {}
    for c, r in records.items():
        if is_camera_ladder(r.family) and r.family not in DIAGNOSTIC:
            fams.setdefault(r.family, {})[r.severity] = outcomes[c]
    return fams


def family_entries(records: Mapping[str, CellRecord], outcomes: Mapping[str, Outcome]) -> dict[str, dict[str, object]]:
    """Per camera family: visited and skipped severities, the assumption, violations seen, s10 / s25 intervals."""
    out: dict[str, dict[str, object]] = {}
    for fam, cells in sorted(_per_family(records, outcomes).items()):
        visited = {s: o for s, o in cells.items() if o.reason != "skipped"}
        _, _, assumption, seen = family_plan(visited)
        out[fam] = {"visited": sorted(visited), "skipped": sorted(s for s in cells if s not in visited),
                    "assumption": assumption if len(visited) < len(cells) else "",
                    "violations": list(seen), **threshold_spans(visited)}
    return out


def axis_entries(outcomes: Mapping[str, Outcome], records: Mapping[str, CellRecord], quality: Sequence[str],
                 removal: str, flat: float) -> dict[str, dict[str, object]]:
    """The camera axes' intervals against the flat line (`axis_settled` of their S5 cells' intervals)."""
    s5 = {r.family: outcomes[c].interval for c, r in records.items() if r.severity == 5}
    out: dict[str, dict[str, object]] = {}
    for name, fams in (("quality", tuple(quality)), ("removal", (removal,))):
        spans = [s5.get(f) for f in fams]
        if not fams or any(s is None for s in spans):
            continue
        side, low, high = axis_settled([s for s in spans if s is not None], flat)
        out[name] = {"interval": [round(low, 4), round(high, 4)], "side": side}
    return out


def _assumes(method: str, beyond: int) -> str:
    """What the cells' sequences assume, by method."""
    if method == "betting":
        return (f"Assumptions: each unit's mean L2 lies in [0, {DEFAULT_BOUND:g} m], checked on every unit run ("
                f"{beyond} unit figure(s) beyond it, whose cells ran every unit and report the population's exact "
                "value; nothing clipped); the betting sequences then hold at every sample size (Waudby-Smith & "
                "Ramdas, without replacement); no decision on fewer than "
                f"{MIN_DISTINCT} distinct unit figures; ")
    return (f"Assumptions (weaker): the {method} sequences hold only as the units grow (finite variance; not at a "
            "handful of units, and on skewed populations their error was measured above alpha: issue 36 found "
            f"12.9 % against 5 %); per-unit mean L2 in [0, {DEFAULT_BOUND:g} m] checked ({beyond} beyond it); ")


def guarantee(alpha: float, a_side: float, cells: int, axes: Mapping[str, Mapping[str, object]],
              families: Mapping[str, Mapping[str, object]], beyond: int, kind: str, method: str = METHOD) -> str:
    """The sentence the certificate states about its label."""
    skipped = sorted(f for f, e in families.items() if e.get("skipped"))
    seen = sorted(f for f, e in families.items() if e.get("violations"))
    open_axes = [a for a, e in axes.items() if e.get("side") == "open"]
    text = (f"Union bound over the {cells} stopping cells' {method} confidence sequences (each side at alpha/(2C) "
            f"= {a_side:.3g}): with probability at least {1 - alpha:g} every cell interval, settled decision, "
            f"threshold interval and axis interval here holds at once, whenever each cell stopped; ")
    text += (f"the {' and '.join(open_axes)} axis did not settle against the flat line, so the label is NOT "
             "covered. " if open_axes else "the axes settled against the flat line, so the label is wrong with "
             f"probability at most {alpha:g}. ")
    text += _assumes(method, beyond)
    text += ("whole scenes as units (each runs as in the full run, from its scene's start)"
             if kind == "scenes" else
             f"windows of {WINDOW} scored frames after {WARMUP} warm-up frames with reset stand for the full stream "
             f"(a planner that remembers at most {WARMUP} frames)" if kind == "windows" else
             "single frames as units (a planner with neither reset nor context keeps no scene state; frame_dropout's "
             "held frames are replayed from the scene's start, so each unit sees the full run's images)")
    text += "; the draw order seeded from the planner's fingerprint (and the baseline's digest in a gate run)"
    if skipped:
        text += f"; retention non-increasing in severity where severities were skipped ({', '.join(skipped)})"
    if seen:
        text += f"; monotonicity violated in a visited pair of {', '.join(seen)} (every severity was visited)"
    return text + "."


def partial_note(outcomes: Mapping[str, Outcome], population: int) -> tuple[list[str], str]:
    """A gate run's cells that neither settled their decisions nor ran every unit, and what that means."""
    partial = sorted(c for c, o in outcomes.items() if o.reason == "open" and o.units < population)
    if not partial:
        return [], ""
    return partial, (f"{len(partial)} cell(s) are partial (the gate's test stopped them before their own decisions "
                     "settled or every unit ran): the certificate's retentions, axes and verdict are point figures "
                     "on the units each cell ran and are NOT certified; only this section's intervals are")


def adaptive_section(records: Mapping[str, CellRecord], plan: UnitPlan, cells: Sequence[tuple[str, int]], *,
                     alpha: float, flat: float, quality: Sequence[str], removal: str,
                     rule: str = "certify") -> dict[str, object]:
    """The certificate's ``adaptive`` section, from the records alone (what `verify` recomputes). `rule`:
    "certify" (cells stop when their decisions settle) or "gate" (a gate run: cells stop when the sequential
    gate's test settles, so decisions may stay open: such cells are listed as partial)."""
    a_side = alpha_side(alpha, cells)
    outcomes = ladder_outcomes(records, plan, alpha=a_side, flat=flat, axis_families=(*quality, removal))
    fams = family_entries(records, outcomes)
    axes = axis_entries(outcomes, records, quality, removal, flat)
    beyond = sum(o.beyond for o in outcomes.values())
    passes = sum(int(r.passes or 0) for r in records.values())
    out: dict[str, object] = {
        "enabled": True, "alpha": alpha, "method": METHOD, "alpha_side": a_side, "rule": rule,
        "cells_counted": stopping_cells(cells), "plan": plan.to_builtins(),
        "cells": {c: cell_entry(records[c], o, plan.population) for c, o in sorted(outcomes.items())},
        "families": fams, "axes": axes, "passes": passes,
        "full_passes": len(records) * sum(len(u.scored) for u in plan.units),
        "guarantee": guarantee(alpha, a_side, stopping_cells(cells), axes, fams, beyond, plan.kind)}
    if rule == "gate":
        partial, note = partial_note(outcomes, plan.population)
        out["partial_cells"] = partial
        out["guarantee"] = str(out["guarantee"]) + " A gate run: each cell stopped when its test against the " \
            "baseline settled, so its own decisions may be open" + (f"; {note}." if note else ".")
    return out


def summary_line(section: Mapping[str, object]) -> str:
    """The terminal's line on an adaptive run: passes against a full run's, and how the cells stopped."""
    cells = section.get("cells")
    stops: dict[str, int] = {}
    for entry in (cells.values() if isinstance(cells, Mapping) else ()):
        reason = str(entry.get("stop")) if isinstance(entry, Mapping) else "?"
        stops[reason] = stops.get(reason, 0) + 1
    passes, full = section.get("passes"), section.get("full_passes")
    share = f" ({passes / full:.1%})" if isinstance(passes, int) and isinstance(full, int) and full else ""
    how = ", ".join(f"{n} {reason}" for reason, n in sorted(stops.items()))
    partial = section.get("partial_cells")
    note = f"; {len(partial)} partial cell(s): the axes and verdict above are point figures on the units they ran, " \
        "NOT certified" if isinstance(partial, list) and partial else ""
    return (f"adaptive (alpha {section.get('alpha')}, {section.get('method')}): {passes} forward passes against "
            f"{full} for a full run{share}; cells: {how}{note}")
