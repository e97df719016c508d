"""The sequential gate (spec 4 section 14): with --drivedegrade-baseline and --drivedegrade-adaptive, each cell
tests "retention dropped by more than the tolerance" against the baseline's per-frame results, paired unit by unit
(`scoring.adaptive.gate_cell`: the baseline's own difference is a control variate, so an unchanged planner
settles "no regression" almost at once), on the units the cell ran.

The run fails only on a regression settled at level alpha: each gated cell's test runs at alpha / G (G the cells
gated, a union bound), so the chance that any "regression" is a false alarm is at most alpha. A cell whose test
did not settle with the data it has is named, never failed; a severity the schedule skipped has no units to test.
"""

from __future__ import annotations

import base64
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..cells import CellRecord
from .adaptive import GateBaseline, Settlement, gate_cell, gate_range, gate_settle
from .sequential import FULL_CELLS, METHOD, UnitPlan, unit_sums


@dataclass(frozen=True)
class GateResult:
    """Per cell: a settled regression (with the baseline's and this run's retention on the units tested), settled
    "no regression", open, skipped, or not gateable (the baseline lacks the cell or some of its units)."""

    regressions: list[tuple[str, float, float]] = field(default_factory=list)
    passed: list[str] = field(default_factory=list)
    open: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    ungated: list[str] = field(default_factory=list)

    @property
    def failed(self) -> bool:
        return bool(self.regressions)


def sequential_gate(current: Mapping[str, CellRecord], baseline: Mapping[str, CellRecord], plan: UnitPlan, *,
                    tolerance: float, alpha: float) -> GateResult:
    """Gate every stopping cell of `current` against the same cell of `baseline` (per-frame records over the same
    frames, clean included in both)."""
    out = GateResult()
    gated = [c for c in sorted(current) if c not in FULL_CELLS]
    level = alpha / max(1, len(gated))
    clean, base_clean = current["clean"].l2_avg_per_frame(), baseline["clean"].l2_avg_per_frame()
    n = plan.population
    for cell in gated:
        record, base = current[cell], baseline.get(cell)
        units = int(record.units or 0)
        if units == 0:
            out.skipped.append(cell)
            continue
        if base is None or base.frames != record.frames or not np.isfinite(base.l2_avg_per_frame()).all():
            out.ungated.append(cell)
            continue
        base_m = base.l2_avg_per_frame()
        a, b = unit_sums(plan, clean, record.l2_avg_per_frame(), units)
        bc, bx = unit_sums(plan, base_clean, base_m, n)
        now = GateBaseline(np.concatenate([a, np.zeros(n - units)]), np.concatenate([b, np.zeros(n - units)]))
        d = gate_cell(now.clean, now.cell, GateBaseline(bc, bx), list(range(units)), tolerance=tolerance,
                      alpha=level, method=METHOD)
        if d.side == "below":
            out.regressions.append((cell, float(np.sum(bc) / np.sum(bx)), float(np.sum(a) / np.sum(b))))
        elif d.side == "above":
            out.passed.append(cell)
        else:
            out.open.append(cell)
    return out


def gate_lines(result: GateResult, tolerance: float, alpha: float) -> list[str]:
    """The terminal's lines on the sequential gate."""
    lines = [f"REGRESSION {cell}: retention {now:.3f} on the units tested, baseline {base:.3f}: dropped by more "
             f"than {tolerance:g}, settled at level {alpha:g}" for cell, base, now in result.regressions]
    if result.open:
        lines.append(f"baseline (sequential): not settled with the data available ({len(result.open)} cell(s)): "
                     f"{', '.join(result.open)}")
    if result.ungated:
        lines.append(f"baseline (sequential): not gated, the baseline lacks their per-frame results on every unit "
                     f"({len(result.ungated)} cell(s)): {', '.join(result.ungated)}")
    lines.append(f"baseline (sequential, alpha {alpha:g}): {len(result.regressions)} regression(s) beyond tolerance "
                 f"{tolerance:g}, {len(result.passed)} cell(s) settled as no regression, {len(result.skipped)} "
                 "skipped severities not gated (monotone retention between the visited ones)")
    return lines


# -- what verify needs to recompute a gate run's stops ----------------------------------------------------------

def _pack(values: np.ndarray) -> str:
    """float64 values exactly, as base64 of their little-endian bytes (the certificate rounds its floats)."""
    return base64.b64encode(np.ascontiguousarray(values, dtype="<f8").tobytes()).decode("ascii")


def unpack(text: str) -> np.ndarray:
    """The values `_pack` wrote."""
    return np.frombuffer(base64.b64decode(text.encode("ascii"), validate=True), dtype="<f8").astype(float)


def gate_settlement(a: np.ndarray, b: np.ndarray, level: float, mean: float, differences: np.ndarray,
                    population: int, alpha: float, span: tuple[float, float]) -> Settlement:
    """`gate_cell`'s test from its parts: this run's per-unit figures `a`, `b` (clean, cell; draw order), the level
    k = r_base - tolerance, the baseline's control variates d_u = base_clean_u - k base_cell_u on those units with
    their population mean, and the test's range (`adaptive.gate_range`)."""
    return gate_settle(a, b, level, differences, mean, population, alpha, span, method=METHOD)


def gate_record(current: Mapping[str, CellRecord], baseline: Mapping[str, CellRecord], plan: UnitPlan, *,
                tolerance: float, alpha: float) -> dict[str, dict[str, object]]:
    """Per cell a gate run stopped on the sequential gate's test (the baseline has every unit of it): the test's
    level and the baseline's population mean (exact, `float.hex`), the baseline's control variates on the units the
    cell ran (exact, `_pack`) and where the test settled at `alpha` (the level each cell stopped on), so `verify`
    recomputes each stop from the certificate and the cells' per-frame results alone."""
    out: dict[str, dict[str, object]] = {}
    base_clean, n = baseline.get("clean"), plan.population
    if base_clean is None or "clean" not in current:
        return out
    clean = current["clean"].l2_avg_per_frame()
    for cell in sorted(c for c in current if c not in FULL_CELLS):
        record, base = current[cell], baseline.get(cell)
        units = int(record.units or 0)
        if units == 0 or base is None or not np.isfinite(base.l2_avg_per_frame()).all():
            continue
        ref = GateBaseline(*unit_sums(plan, base_clean.l2_avg_per_frame(), base.l2_avg_per_frame(), n))
        level = ref.retention() - tolerance
        d = ref.clean - level * ref.cell
        span = gate_range(level, d)
        a, b = unit_sums(plan, clean, record.l2_avg_per_frame(), units)
        got = gate_settlement(a, b, level, float(np.mean(d)), d[:units], n, alpha, span)
        out[cell] = {"baseline_retention": ref.retention(), "level": level.hex(), "mean": float(np.mean(d)).hex(),
                     "range": [span[0].hex(), span[1].hex()],
                     "differences": _pack(d[:units]), "side": got.side, "units": got.units, "how": got.how}
    return out


# -- an adaptive baseline gating a full run ---------------------------------------------------------------------

def interval_gate(current: Mapping[str, object], baseline: Mapping[str, object], tolerance: float) -> GateResult:
    """A full run gated by an adaptive baseline: the baseline's retention is known only to lie in its anytime-valid
    interval [lo, hi] (``adaptive.cells``/``axes``: all of them hold at once with probability 1 - alpha), so a cell
    or axis regressed, settled, when this run's retention < lo - tolerance, settled as no regression when it is
    >= hi - tolerance, and is open in between; a severity the baseline skipped has no interval and is not gated.
    A regression is then wrong with probability at most the baseline's alpha. On L2 retention (its intervals')."""
    out = GateResult()
    section = baseline.get("adaptive")
    spans: dict[str, object] = {}
    if isinstance(section, Mapping):
        for part in ("cells", "axes"):
            got = section.get(part)
            spans.update({(k if part == "cells" else f"axis {k}"): v
                          for k, v in (got.items() if isinstance(got, Mapping) else ())})
    rows = current.get("cells")
    mine = {str(r.get("cell")): r.get("retention") for r in (rows if isinstance(rows, list) else [])
            if isinstance(r, Mapping) and r.get("cell") not in FULL_CELLS}
    axes = current.get("axes")
    mine.update({f"axis {a}": axes.get(a) for a in ("quality", "removal")} if isinstance(axes, Mapping) else {})
    for name, now in mine.items():
        entry = spans.get(name)
        span = entry.get("interval") if isinstance(entry, Mapping) else None
        if now is None and entry is None:  # neither run has it (an axis of families not run)
            continue
        if not isinstance(now, (int, float)) or not isinstance(span, list) or len(span) != 2:
            (out.skipped if isinstance(entry, Mapping) else out.ungated).append(name)
        elif now < span[0] - tolerance:
            out.regressions.append((name, float(span[0]), float(now)))
        elif now >= span[1] - tolerance:
            out.passed.append(name)
        else:
            out.open.append(name)
    return out


def interval_lines(result: GateResult, tolerance: float, baseline: Mapping[str, object]) -> list[str]:
    """The terminal's lines on a full run gated by an adaptive baseline's intervals."""
    section = baseline.get("adaptive")
    alpha = section.get("alpha") if isinstance(section, Mapping) else None
    lines = [f"REGRESSION {cell}: retention {now:.3f}, below the adaptive baseline's interval (low end {low:.3f}) by "
             f"more than {tolerance:g}, settled at the baseline's level {alpha}"
             for cell, low, now in result.regressions]
    if result.open:
        lines.append(f"baseline (adaptive, intervals): not settled, within {tolerance:g} of the baseline's interval "
                     f"({len(result.open)}): {', '.join(result.open)}")
    if result.skipped or result.ungated:
        lines.append(f"baseline (adaptive, intervals): not gated, the adaptive baseline has no interval for "
                     f"{', '.join(result.skipped + result.ungated)} (a skipped severity, a cell that decides nothing, "
                     "or one it did not run)")
    lines.append(f"baseline (adaptive, intervals, alpha {alpha}): {len(result.regressions)} regression(s) beyond "
                 f"tolerance {tolerance:g}, {len(result.passed)} settled as no regression")
    return lines
