"""Closed-loop figures per cell (SPEC section 13) from run lists alone: a run as a `RunRow` (DS, completion,
end, trace digest, infractions by kind: what the certificate holds of it), a cell's figures (DS mean and std over
scored runs, identification bounds with unscored runs at 0 and at 100, completion, infractions), and the null
control (for a planner that does not read the rear cameras, `closed-blackout-s3` equals `closed-clean` run for
run; otherwise a clean rerun's wander). `scoring.closed_loop` puts the cells together (retention, axes, verdict).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from .cells import NULL_CELL, SWAP, Json, as_int, as_map, as_opt_float, closed_id, trace_digest
from .results import END_UNSCORED, RunResult

CLEAN = closed_id("clean", 0)
NULL = closed_id(*NULL_CELL)
REMOVAL = closed_id("blackout", 5)
SWAP_CELL = closed_id(SWAP, 0)
#: The suffix of a swapped route's name (`swap.swapped_route`).
SWAP_SUFFIX = "-swap"


@dataclass(frozen=True)
class RunRow:
    """One run as the analysis (and the certificate) holds it: route, seed, DS and completion (None:
    unscored), why it ended, its trace's digest and its at-fault infractions by kind."""

    route: str
    seed: int
    ds: float | None
    completion: float | None
    end: str
    trace: str = ""
    infractions: Mapping[str, int] = field(default_factory=dict)

    @classmethod
    def of(cls, run: RunResult) -> RunRow:
        counts: dict[str, int] = {}
        for i in run.infractions:
            counts[i.kind] = counts.get(i.kind, 0) + 1
        return cls(run.route, int(run.seed), run.ds, run.completion, run.end if run.ds is not None else END_UNSCORED,
                   trace_digest(run), dict(sorted(counts.items())))

    def to_list(self) -> list[Json]:
        kinds: dict[str, Json] = dict(self.infractions)
        return [self.route, self.seed, self.ds, self.completion, self.end, self.trace, kinds]

    @classmethod
    def from_list(cls, row: Sequence[object]) -> RunRow:
        """Inverse of `to_list`; ValueError saying what is malformed."""
        route, seed, ds, completion, end, trace, infractions = row
        return cls(str(route), as_int(seed, "seed"), as_opt_float(ds, "ds"), as_opt_float(completion, "completion"),
                   str(end), str(trace), {str(k): as_int(v, "count") for k, v in as_map(infractions).items()})

    def same(self, other: RunRow) -> bool:
        """Bit-identical runs: the same route and seed, trace digest, DS and end."""
        return (self.route, self.seed, self.trace, self.ds, self.end) == \
            (other.route, other.seed, other.trace, other.ds, other.end)


def distinct_runs(rows: Sequence[RunRow]) -> int:
    """How many of the runs are distinct: runs of one route with the same trace digest, DS and end replay one
    another (a deterministic cell under two seeds) and count once; a run without a trace digest counts alone."""
    seen = {(r.route, r.trace, r.ds, r.end) for r in rows if r.trace}
    return len(seen) + sum(1 for r in rows if not r.trace)


def _mean(values: Sequence[float]) -> float | None:
    return float(np.mean(values)) if values else None


@dataclass(frozen=True)
class CellFigures:
    """One closed cell's figures."""

    cell: str
    family: str
    severity: int
    rows: tuple[RunRow, ...]
    retention: float | None = None
    retention_low: float | None = None
    retention_high: float | None = None
    separable_from_null: bool | None = None
    #: paired route-level 95 % intervals (`routestats`): of retention, and of the mean DS difference from clean
    retention_ci: tuple[float, float] | None = None
    difference_ci: tuple[float, float] | None = None

    @property
    def scored(self) -> list[float]:
        return [r.ds for r in self.rows if r.ds is not None]

    @property
    def unscored(self) -> int:
        return len(self.rows) - len(self.scored)

    @property
    def mean(self) -> float | None:
        return _mean(self.scored)

    @property
    def std(self) -> float | None:
        return float(np.std(self.scored)) if self.scored else None

    @property
    def bounds(self) -> tuple[float | None, float | None]:
        """Mean DS with every unscored run at 0 and at 100 (None for a cell without runs)."""
        if not self.rows:
            return None, None
        total, n = sum(self.scored), len(self.rows)
        return total / n, (total + 100.0 * self.unscored) / n

    @property
    def completion(self) -> float | None:
        return _mean([r.completion for r in self.rows if r.completion is not None])

    @property
    def infractions(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for r in self.rows:
            for k, v in r.infractions.items():
                counts[k] = counts.get(k, 0) + v
        return dict(sorted(counts.items()))

    def figures(self) -> dict[str, Json]:
        low, high = self.bounds
        kinds: dict[str, Json] = dict(self.infractions)
        rows: list[Json] = [r.to_list() for r in self.rows]
        rci, dci = self.retention_ci or (None, None), self.difference_ci or (None, None)
        return {"cell": self.cell, "family": self.family, "severity": self.severity, "runs": len(self.rows),
                "n": distinct_runs(self.rows), "routes": len({r.route for r in self.rows}),
                "unscored": self.unscored, "retention_ci_low": rci[0], "retention_ci_high": rci[1],
                "ds_difference_ci_low": dci[0], "ds_difference_ci_high": dci[1], "ds_mean": self.mean,
                "ds_std": self.std, "ds_low": low, "ds_high": high,
                "completion": self.completion, "infractions": kinds, "retention": self.retention,
                "retention_low": self.retention_low, "retention_high": self.retention_high,
                "separable_from_null": self.separable_from_null, "run_rows": rows}


def first_difference(clean: Sequence[RunRow], other: Sequence[RunRow]) -> RunRow | None:
    """The first run of `other` that is not bit-identical to clean's run in the same place (None: all are)."""
    for a, b in zip(clean, other):
        if not a.same(b):
            return b
    return other[len(clean)] if len(other) > len(clean) else clean[len(other)] if len(clean) > len(other) else None


def parting_step(clean: RunResult, other: RunResult, plan_every: int) -> int:
    """The planner step at which two runs' paths part: the first 10 Hz pose that differs, as the planner call
    whose plan drove it (a run that ended earlier parts where it ended)."""
    a, b = np.asarray(clean.trace), np.asarray(other.trace)
    n = min(len(a), len(b))
    differ = np.flatnonzero(np.any(a[:n].view(np.uint64) != b[:n].view(np.uint64), axis=1)) if n else np.array([])
    first = int(differ[0]) if len(differ) else n
    return max(first - 1, 0) // plan_every


@dataclass(frozen=True)
class NullFigures:
    """The null control: `mode` "identical" (blackout S3 must equal clean run for run) or "wander" (a clean
    rerun), whether it passed (identical mode), the first run that differs, the step where its path parts from
    clean's (when the traces were at hand), the wander (|mean DS of the null - clean's|) and the null's bounds."""

    mode: str
    passed: bool | None
    first_route: str | None = None
    first_seed: int | None = None
    first_step: int | None = None
    wander: float | None = None
    low: float | None = None
    high: float | None = None
    rows: tuple[RunRow, ...] = ()
    #: the null band (`routestats.band`): the interval of the null's paired DS difference from clean, with 0
    band: tuple[float, float] | None = None

    def figures(self) -> dict[str, Json]:
        rows: list[Json] = [r.to_list() for r in self.rows]
        band = self.band or (None, None)
        return {"mode": self.mode, "passed": self.passed, "first_route": self.first_route,
                "first_seed": self.first_seed, "first_step": self.first_step, "wander": self.wander,
                "low": self.low, "high": self.high, "band_low": band[0], "band_high": band[1], "run_rows": rows}


def null_figures(cells: Mapping[str, CellFigures], reads_rear: bool, null_rows: Sequence[RunRow],
                 first_step: int | None) -> NullFigures | None:
    """The null control's figures (None when its cells did not run): `reads_rear` picks the mode."""
    clean = cells.get(CLEAN)
    if clean is None:
        return None
    if reads_rear:
        if not null_rows:
            return None
        other = CellFigures(NULL, "clean", 0, tuple(null_rows))
        mode = "wander"
    else:
        if NULL not in cells:
            return None
        other, mode = cells[NULL], "identical"
    first = first_difference(clean.rows, other.rows)
    passed = first is None if mode == "identical" else None
    lows = [v for v in (clean.bounds[0], other.bounds[0]) if v is not None]
    highs = [v for v in (clean.bounds[1], other.bounds[1]) if v is not None]
    wander = None if clean.mean is None or other.mean is None else abs(other.mean - clean.mean)
    return NullFigures(mode, passed, None if first is None else first.route, None if first is None else first.seed,
                       None if first is None else first_step, wander, min(lows, default=None),
                       max(highs, default=None), tuple(other.rows) if mode == "wander" else ())


def swap_figures(cells: Mapping[str, CellFigures]) -> dict[str, Json] | None:
    """The command swap in the closed loop (None when its cell did not run): its runs are over other routes than
    clean's (the junction routes swapped, ``<route>-swap``), so it is never paired with clean run for run, has no
    retention and no axis; beside its own figures stand clean's over the same junction routes unswapped.
    ``command_followed`` is the swapped routes' mean completion: 1 when the planner went where it was told."""
    swap = cells.get(SWAP_CELL)
    if swap is None:
        return None
    routes = {r.route[:-len(SWAP_SUFFIX)] for r in swap.rows if r.route.endswith(SWAP_SUFFIX)}
    clean = cells.get(CLEAN)
    same = CellFigures(CLEAN, "clean", 0, tuple(r for r in clean.rows if r.route in routes)) if clean else None
    complete = [r for r in swap.rows if r.completion is not None and r.completion >= 1.0]
    return {"cell": SWAP_CELL, "routes": len(routes), "runs": len(swap.rows), "unscored": swap.unscored,
            "command_followed": swap.completion, "complete_runs": len(complete), "ds_mean": swap.mean,
            "clean_runs": None if same is None else len(same.rows),
            "clean_completion": None if same is None else same.completion,
            "clean_ds_mean": None if same is None else same.mean}
