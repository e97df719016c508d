"""Per-cell and per-run results as plain data: a cell's summary row, the run's analysis, and the helpers that
reduce per-frame arrays (NaN frames left out) and format numbers for people."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from copy import deepcopy
from dataclasses import asdict, dataclass, field, fields
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import ArrayLike

from ..cells import DIAGNOSTIC, INPUT_FAMILIES, CellRecord, is_camera_ladder
from ..constants import REPORT_HORIZONS_S
from ..metrics.trajectory import CONVENTIONS, at_horizons

if TYPE_CHECKING:
    from .command import CommandProbe
    from .reliance import Reliance


def finite_mean(values: ArrayLike) -> float:
    """Mean over finite entries (NaN frames left out); NaN when none is finite."""
    arr = np.asarray(values, dtype=float)
    ok = np.isfinite(arr)
    return float(arr[ok].mean()) if ok.any() else math.nan


def format_value(value: object, digits: int = 3, missing: str = "n/a") -> str:
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


#: Plain JSON data (what a certificate section is made of).
Builtins = dict[str, object]
#: An interval [low, high]; a None bound is open (+inf: a threshold some resamples never reach).
Interval = tuple[float | None, float | None]
#: The axes over the camera families (SPEC section 5), each with an interval on L2 retention. The names are the
#: fields of `Axes` and `AxisIntervals`, the certificate's ``axes`` keys and the reports' rows.
AXES: tuple[str, ...] = ("quality", "removal", "gap", "mean")
#: The axes beside them: S5 retention of dropout and occlusion, and the ego axis (SPEC section 10).
BESIDE_AXES: tuple[str, ...] = ("dropout", "occlusion")
EGO_AXES: tuple[str, ...] = ("ego", "ego_removal")


def _interval(ci: Interval | None) -> list[float | None] | None:
    return None if ci is None else list(ci)


def _number(value: object) -> float | None:
    """A certificate's value as a float; None for null or anything that is not a number."""
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


@dataclass(frozen=True)
class AxisIntervals:
    """The 95 % intervals of the four axes from the joint bootstrap (None: not computed or an axis missing)."""

    quality: Interval | None = None
    removal: Interval | None = None
    gap: Interval | None = None
    mean: Interval | None = None

    def of(self, axis: str) -> Interval | None:
        """The interval of `axis` (one of `AXES`)."""
        return cast("Interval | None", getattr(self, axis))


@dataclass(frozen=True)
class Axes:
    """S5 retention axes of a run (SPEC sections 5 and 10): an axis whose families were not all run is None.

    ``missing`` names the families not run at S5; ``partial`` the cells with failed frames the figures rest on;
    ``intervals`` is None for the axes on PDMS retention (the resamples are of L2 retention).
    """

    quality: float | None
    removal: float | None
    gap: float | None
    mean: float | None
    dropout: float | None = None
    occlusion: float | None = None
    missing: tuple[str, ...] = ()
    ego: float | None = None
    ego_removal: float | None = None
    intervals: AxisIntervals | None = None
    partial: tuple[str, ...] = ()

    def value(self, axis: str) -> float | None:
        """The value of `axis` (a name of `AXES`, `BESIDE_AXES` or `EGO_AXES`)."""
        return cast("float | None", getattr(self, axis))

    def interval(self, axis: str) -> Interval | None:
        return None if self.intervals is None else self.intervals.of(axis)

    def to_builtins(self) -> Builtins:
        """The certificate's ``axes`` / ``axes_pdms`` section: the intervals as ``<axis>_ci`` keys (L2 only)."""
        out: Builtins = {name: getattr(self, name) for name in (*AXES, *BESIDE_AXES)}
        out["missing"] = list(self.missing)
        out.update((name, getattr(self, name)) for name in EGO_AXES)
        if self.intervals is not None:
            out.update((f"{name}_ci", _interval(self.intervals.of(name))) for name in AXES)
        out["partial"] = list(self.partial)
        return out

    @classmethod
    def from_builtins(cls, data: object) -> Axes:
        """A certificate's axes section read back (absent or non-numeric values as None)."""
        got: Mapping[str, object] = data if isinstance(data, Mapping) else {}
        values = {name: _number(got.get(name)) for name in (*AXES, *BESIDE_AXES, *EGO_AXES)}
        intervals = AxisIntervals(**{name: _read_interval(got.get(f"{name}_ci")) for name in AXES}) \
            if any(f"{name}_ci" in got for name in AXES) else None
        return cls(**values, missing=_names(got.get("missing")), intervals=intervals,
                   partial=_names(got.get("partial")))


def _names(value: object) -> tuple[str, ...]:
    return tuple(map(str, value)) if isinstance(value, (list, tuple)) else ()


def _read_interval(value: object) -> Interval | None:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        return None
    return _number(value[0]), _number(value[1])


@dataclass(frozen=True)
class Threshold:
    """One tolerance threshold of a family: the severity where retention first falls below its level (None:
    never), its 95 % interval and the share of resamples that never fall below (None: no intervals)."""

    value: float | None
    ci: Interval | None = None
    never: float | None = None


@dataclass(frozen=True)
class FamilyThresholds:
    """A family's thresholds by level name (``THRESHOLD_LEVELS``: s10, s25), and whether a cell of the family has
    failed frames (``partial``)."""

    levels: Mapping[str, Threshold]
    partial: bool = False

    def to_builtins(self) -> Builtins:
        out: Builtins = {key: t.value for key, t in self.levels.items()}
        for key, t in self.levels.items():
            out[f"{key}_ci"] = _interval(t.ci)
            out[f"{key}_never"] = t.never
        out["partial"] = self.partial
        return out

    @classmethod
    def from_builtins(cls, data: object) -> FamilyThresholds:
        """A certificate's thresholds entry read back (levels s10, s25; absent values as None)."""
        got: Mapping[str, object] = data if isinstance(data, Mapping) else {}
        return cls({key: Threshold(_number(got.get(key)), _read_interval(got.get(f"{key}_ci")),
                                   _number(got.get(f"{key}_never"))) for key in ("s10", "s25")},
                   bool(got.get("partial", False)))


@dataclass(frozen=True)
class NullControl:
    """The null control against clean (``scoring.verdict.null_control``): passed is None when nothing was
    compared; ``max_l2_change`` is the wander cells are separated from."""

    passed: bool | None
    max_abs_diff: float | None
    max_l2_change: float | None
    frames_changed: int
    frames_compared: int

    def to_builtins(self) -> Builtins:
        return {name: getattr(self, name) for name in NULL_CONTROL_FIELDS}


NULL_CONTROL_FIELDS: tuple[str, ...] = ("passed", "max_abs_diff", "max_l2_change", "frames_changed",
                                        "frames_compared")


def null_control_section(nc: NullControl | None) -> Builtins:
    """The certificate's ``null_control``: the control with ``ran``; three nulls when no null cell ran."""
    got = nc.to_builtins() if nc is not None else {"passed": None, "max_abs_diff": None, "max_l2_change": None}
    return {**got, "ran": got["passed"] is not None}


@dataclass(frozen=True)
class Floor:
    """The ego-only floor's clean L2 against the planner blinded (blind) and at removal S5, and the floor's own
    ego_blind retention (``ego_removal``, when the ego cells ran; left out of the certificate otherwise)."""

    l2_avg: float | None
    blackout_s5_l2_avg: float | None
    blackout_s5_below_floor: bool | None
    blind_l2_avg: float | None
    blind_below_floor: bool | None
    ego_removal: float | None = None

    def to_builtins(self) -> Builtins:
        out: Builtins = {"l2_avg": self.l2_avg, "blackout_s5_l2_avg": self.blackout_s5_l2_avg,
                               "blackout_s5_below_floor": self.blackout_s5_below_floor,
                               "blind_l2_avg": self.blind_l2_avg, "blind_below_floor": self.blind_below_floor}
        if self.ego_removal is not None:
            out["ego_removal"] = self.ego_removal
        return out


@dataclass(frozen=True)
class FailedCell:
    """A cell with failed frames: frames run (every seed run counted), planner contract failures, data faults."""

    frames: int
    conformance_errors: int
    data_errors: int

    def to_builtins(self) -> dict[str, int]:
        return {"frames": self.frames, "conformance_errors": self.conformance_errors,
                "data_errors": self.data_errors}


@dataclass(frozen=True)
class Verdict:
    """The run's label and its prose (SPEC section 5), the metric it is put on, the ego label, the bootstrap's
    confidence, and why it is undetermined when cells have failed frames (SPEC section 11).

    ``computed_label`` is the label the axes give, kept when failed frames make ``label`` undetermined.
    """

    label: str
    case: str
    flat: float
    text: str
    negative_gap: bool
    metric: str = "l2"
    ego_label: str = "undetermined"
    confidence: float | None = None
    borderline: bool = False
    reason: str | None = None
    failed_cells: Mapping[str, FailedCell] = field(default_factory=dict)
    computed_label: str | None = None

    def to_builtins(self) -> Builtins:
        out: Builtins = {f.name: getattr(self, f.name) for f in fields(self)}
        out["failed_cells"] = {cell: c.to_builtins() for cell, c in self.failed_cells.items()}
        return out


#: The verdict's fields, in the certificate's order (its keys).
VERDICT_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(Verdict))


@dataclass
class RunAnalysis:
    """Everything the reports show: cell summaries and typed figures; ``to_builtins`` gives the plain data the
    certificate is made of. ``settings`` is the analysis's settings as builtins."""

    summaries: list[CellSummary]
    thresholds: dict[str, FamilyThresholds]
    axes: Axes
    verdict: Verdict
    null_control: NullControl | None
    floor: Floor
    settings: dict[str, Any]
    axes_pdms: Axes  #: the axes on PDMS retention (spec 3)
    axes_epdms: Axes | None = None  #: the axes on EPDMS retention (spec 4.1)
    axes_epdms2: Axes | None = None  #: the axes on two-stage EPDMS retention (--drivedegrade-two-stage)
    reliance: Reliance | None = None  #: each input's plan movement (spec 5, issue 40)
    command: CommandProbe | None = None  #: the command_swap cell's following figure (spec 5, issue 40)

    def to_builtins(self) -> Builtins:
        return {"summaries": [s.flat() for s in self.summaries],
                "thresholds": {fam: t.to_builtins() for fam, t in self.thresholds.items()},
                "axes": self.axes.to_builtins(), "verdict": self.verdict.to_builtins(),
                "null_control": None if self.null_control is None else self.null_control.to_builtins(),
                "floor": self.floor.to_builtins(), "settings": deepcopy(self.settings),
                "axes_pdms": self.axes_pdms.to_builtins(),
                **({} if self.axes_epdms is None else {"axes_epdms": self.axes_epdms.to_builtins()}),
                **({} if self.axes_epdms2 is None else {"axes_epdms2": self.axes_epdms2.to_builtins()}),
                **({} if self.reliance is None else {"reliance": self.reliance.to_builtins()}),
                **({} if self.command is None else {"command": self.command.to_builtins()})}

    def two_stage_sections(self) -> Builtins:
        """The certificate's two-stage sections (--drivedegrade-two-stage): ``axes_epdms2`` and ``two_stage`` (how
        stage two was scored: `metrics.pdms.two_stage.certificate_section`); none in a one-stage run."""
        from ..metrics.pdms.two_stage import certificate_section

        if self.axes_epdms2 is None:
            return {}
        return {"axes_epdms2": self.axes_epdms2.to_builtins(), "two_stage": certificate_section()}

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
    records_seen: list[CellRecord] = []
    for record in records:
        records_seen.append(record)
        runs = [record, *getattr(record, "seed_runs", [])]
        saved = sum(int(getattr(r, "reused", 0)) for r in runs)
        made = sum(len(r.frames) if getattr(r, "passes", None) is None else r.passes for r in runs) - saved
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
    # --drivedegrade-two-stage: the stage-two calls, in the planner's seconds (a one-stage ledger keeps its form)
    staged = int(sum(float(r.seconds.get("stage_two_calls", 0.0)) for r in records_seen))
    return {"predictions": predictions, "reused": reused, "seconds": totals, "cells": per_cell,
            **({"stage_two_calls": staged} if staged else {}),
            "planner_frames_per_second": (predictions + staged) / totals["planner"] if totals["planner"] > 0 else None,
            "wall": wall if walls else None, "planner_busy": _share(sum(p for _, p in walls.values()), wall),
            "processes": processes}


def _add_walls(walls: dict[str, list[float]], seconds: Mapping[str, float]) -> None:
    """A record's wall and planner seconds per process (``wall@KEY``, ``planner@KEY``: `pacing.process_key`)."""
    for key, value in seconds.items():
        kind, at, process = key.partition("@")
        if at and kind in ("wall", "planner"):
            walls.setdefault(process, [0.0, 0.0])[kind == "planner"] += float(value)


def _share(part: float, whole: float) -> float | None:
    return min(1.0, part / whole) if whole > 0 else None


def report_order(family: str, severity: int, families: Sequence[str]) -> tuple[int, int, str, int]:
    """Sort key of the report: clean, null, blind, then families in ladder order (unknown ones by name), S1..S5."""
    if family in DIAGNOSTIC:
        return (0, DIAGNOSTIC.index(family), "", 0)
    if family in INPUT_FAMILIES:  # after the camera ladder: ego_noise S1..S5, ego_blind, then command_blind
        return (2, INPUT_FAMILIES.index(family), family, int(severity))
    rank = families.index(family) if family in families else len(families)
    return (1, rank, family, int(severity))
