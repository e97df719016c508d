"""Per-cell and per-run results as plain data: a cell's summary row, the run's analysis, and the helpers that
reduce per-frame arrays (NaN frames left out) and format numbers for people."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..cells import CellRecord, is_camera_ladder
from ..constants import REPORT_HORIZONS_S
from ..metrics.trajectory import CONVENTIONS, at_horizons


def finite_mean(values: Any) -> float:
    """Mean over finite entries (NaN frames left out); NaN when none is finite."""
    arr = np.asarray(values, dtype=float)
    ok = np.isfinite(arr)
    return float(arr[ok].mean()) if ok.any() else math.nan


def format_value(value: Any, digits: int = 3, missing: str = "n/a") -> str:
    """A number for people: `digits` decimals, `missing` for None / NaN / inf; other values as str."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return missing
    if isinstance(value, bool):
        return "yes" if value else "no"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


@dataclass
class CellSummary:
    """One row of cells.csv / one certificate cell: every metric of a cell as plain builtins.

    Collision rates are fractions (0..1) of frames x steps. ``endpoint_shift`` is the mean 3 s endpoint
    distance from clean's plan; ``energy`` mean bit-1 density relative to clean's. ``separable_from_null``
    is None for the clean and null cells themselves.
    """

    cell: str
    family: str
    severity: int
    frames: int
    l2_avg: float
    retention: float
    retention_ci_low: float
    retention_ci_high: float
    metrics: dict[str, float] = field(default_factory=dict)
    separable_from_null: bool | None = None
    conformance_errors: int = 0  #: frames whose planner broke the contract (every seed run counted)
    data_errors: int = 0  #: frames whose images could not be produced (the data's fault, not the planner's)

    def flat(self) -> dict[str, Any]:
        """One flat mapping (the CSV row / certificate cell without provenance)."""
        out = asdict(self)
        out.update(out.pop("metrics"))
        return out


def horizon_metrics(record: CellRecord) -> dict[str, float]:
    """L2, collision and VRU-collision at 1/2/3 s in both conventions, plus both L2 averages and jerk."""
    out: dict[str, float] = {}
    for conv in CONVENTIONS:
        for key, arr in (("l2", record.l2), ("collision", record.collision), ("vru", record.collision_vru)):
            per_h = at_horizons(arr, conv)  # (F, 3)
            for j, h in enumerate(REPORT_HORIZONS_S):
                out[f"{key}_{h}s_{conv}"] = finite_mean(per_h[:, j])
        out[f"l2_avg_{conv}"] = finite_mean(record.l2_avg_per_frame(conv))
    out["jerk"] = finite_mean(record.jerk)
    return out


@dataclass
class RunAnalysis:
    """Everything the reports show, as plain builtins (summaries aside, which ``to_builtins`` flattens)."""

    summaries: list[CellSummary]
    thresholds: dict[str, dict[str, Any]]
    axes: dict[str, Any]
    verdict: dict[str, Any]
    null_control: dict[str, Any] | None
    floor: dict[str, Any]
    settings: dict[str, Any]
    axes_pdms: dict[str, Any] = field(default_factory=dict)  #: the axes on PDMS retention (spec 3)

    def to_builtins(self) -> dict[str, Any]:
        out = asdict(self)
        out["summaries"] = [s.flat() for s in self.summaries]
        return out

    def s5(self) -> dict[str, float]:
        """S5 retention per ladder family."""
        return {s.family: s.retention for s in self.summaries
                if s.severity == 5 and is_camera_ladder(s.family)}


#: The time parts a cell records (``CellRecord.seconds``), as the cost ledger reports them.
COST_PARTS: tuple[str, ...] = ("decode", "inject", "planner", "metrics", "pdms", "check")


def cost_ledger(records: Iterable[CellRecord]) -> dict[str, Any]:
    """What the run cost: predictions made (frames predicted, every seed run counted) and reused (frames whose
    inputs equal clean's, given the clean plan instead of a call; `CellRecord.reused`), and seconds
    decoding, injecting, planning, scoring and checking inputs, in total and per cell; the planner's frames per
    second. Seconds are process CPU-wall time inside the cells (workers add up), not the run's wall time; with
    --drivedegrade-prefetch the parts overlap, so they may add up to more than the wall.

    ``wall``: the seconds each process spent inside cells (``processes``, largest first, with its
    ``planner_busy``) and their sum; ``planner_busy``: the share of that wall time the planner was computing
    (1.0: it never waited for the suite). None where the records carry no wall time (stored before it was kept).
    """
    per_cell: dict[str, dict[str, float]] = {}
    totals = dict.fromkeys(COST_PARTS, 0.0)
    walls: dict[str, list[float]] = {}
    predictions = reused = 0
    for record in records:
        runs = [record, *getattr(record, "seed_runs", [])]
        saved = sum(int(getattr(r, "reused", 0)) for r in runs)
        made = sum(len(r.frames) for r in runs) - saved
        spent = {part: sum(float(r.seconds.get(part, 0.0)) for r in runs) for part in COST_PARTS}
        per_cell[record.cell] = {"predictions": made, "reused": saved, **spent,
                                 "wall": sum(float(r.seconds.get("total", 0.0)) for r in runs)}
        predictions += made
        reused += saved
        for part in COST_PARTS:
            totals[part] += spent[part]
        for r in runs:
            _add_walls(walls, r.seconds)
    processes = sorted(({"wall": w, "planner_busy": _share(p, w)} for w, p in walls.values()),
                       key=lambda p: -float(p["wall"] or 0.0))
    wall = sum(w for w, _ in walls.values())
    return {"predictions": predictions, "reused": reused, "seconds": totals, "cells": per_cell,
            "planner_frames_per_second": predictions / totals["planner"] if totals["planner"] > 0 else None,
            "wall": wall if walls else None, "planner_busy": _share(sum(p for _, p in walls.values()), wall),
            "processes": processes}


def _add_walls(walls: dict[str, list[float]], seconds: Mapping[str, float]) -> None:
    """A record's wall and planner seconds per process (``wall@KEY``, ``planner@KEY``: `stream.process_key`)."""
    for key, value in seconds.items():
        kind, at, process = key.partition("@")
        if at and kind in ("wall", "planner"):
            walls.setdefault(process, [0.0, 0.0])[kind == "planner"] += float(value)


def _share(part: float, whole: float) -> float | None:
    return min(1.0, part / whole) if whole > 0 else None
