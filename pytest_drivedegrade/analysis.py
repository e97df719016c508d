"""From per-cell records to the numbers of the certificate: retention, bootstrap CI, thresholds, axes, verdict.

Pure functions over plain data (SPEC section 5); nothing here reads files, imports pytest or touches a planner.
The plugin hands every finished cell over as a ``CellRecord`` (plain builtins across the xdist boundary and on
disk) and calls ``analyse_run`` once on the controller; the report layer renders what comes back.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .constants import DEFAULT_FLAT, DEFAULT_TOLERANCE, HORIZON_STEPS, REPORT_HORIZONS_S
from .errors import DriveDegradeError, InvalidInput
from .metrics import CONVENTIONS, at_horizons, l2_avg

#: Cells that are not ladder families, in the order they are reported.
DIAGNOSTIC_CELLS: tuple[str, ...] = ("clean", "null", "blind")
#: Retention levels of the two tolerance thresholds s*10 and s*25.
THRESHOLD_LEVELS: dict[str, float] = {"s10": 0.90, "s25": 0.75}
VERDICT_LABELS: tuple[str, ...] = ("camera-reliant", "quality-insensitive", "not-shown-to-use-cameras")
DEFAULT_RESAMPLES = 1000


class BaselineError(DriveDegradeError):
    """A baseline certificate that cannot be compared: another spec version or data set, or malformed."""


@dataclass
class CellRecord:
    """Everything one finished cell yields, per frame; the frame order is the same in every cell of a run.

    Arrays: ``plans`` (F, 6, 2) metres; ``l2``, ``collision``, ``collision_vru`` (F, 6) per step; ``jerk`` and
    ``bit1`` (F,). A frame whose planner output failed conformance carries NaN and is left out of means.
    """

    cell: str
    family: str
    severity: int
    frames: list[str]
    plans: np.ndarray
    l2: np.ndarray
    collision: np.ndarray
    collision_vru: np.ndarray
    jerk: np.ndarray
    bit1: np.ndarray
    seconds: dict[str, float] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        n = len(self.frames)
        self.frames = [str(f) for f in self.frames]
        self.severity = int(self.severity)
        for name, shape in (("plans", (n, HORIZON_STEPS, 2)), ("l2", (n, HORIZON_STEPS)), ("jerk", (n,)),
                            ("collision", (n, HORIZON_STEPS)), ("collision_vru", (n, HORIZON_STEPS)), ("bit1", (n,))):
            arr = np.asarray(getattr(self, name), dtype=float)
            arr = arr.reshape(shape) if arr.size == 0 else arr
            if arr.shape != shape:
                raise InvalidInput(f"cell {self.cell!r}: {name} has shape {arr.shape}, expected {shape}")
            setattr(self, name, arr)

    def to_builtins(self) -> dict[str, Any]:
        """Plain lists / floats / ints / strs only: safe for xdist, JSON and ``user_properties``."""
        out = {k: getattr(self, k) for k in ("cell", "family", "severity", "frames")}
        out.update({k: getattr(self, k).tolist() for k in ("plans", "l2", "jerk", "bit1")})
        out.update({k: [[int(v) if v == v else -1 for v in row] for row in getattr(self, k)]
                    for k in ("collision", "collision_vru")})
        out["seconds"] = {str(k): float(v) for k, v in self.seconds.items()}
        out["errors"] = [str(e) for e in self.errors]
        return out

    @classmethod
    def from_builtins(cls, data: Mapping[str, Any]) -> "CellRecord":
        """Inverse of ``to_builtins``; a collision of -1 (a NaN frame) comes back as NaN."""
        try:
            kw = {k: data[k] for k in ("cell", "family", "severity", "frames", "plans", "l2", "jerk", "bit1")}
            for k in ("collision", "collision_vru"):
                arr = np.asarray(data[k], dtype=float)
                kw[k] = np.where(arr < 0, np.nan, arr)
        except KeyError as exc:
            raise InvalidInput(f"cell record lacks the field {exc.args[0]!r}") from None
        return cls(**kw, seconds=dict(data.get("seconds", {})), errors=list(data.get("errors", [])))

    def endpoint_shift(self, clean: CellRecord) -> np.ndarray:
        """Per frame, how far (m) the 3 s waypoint moved from clean's plan (NaN where either failed)."""
        return np.linalg.norm(self.plans[:, -1] - clean.plans[:, -1], axis=-1)

    def l2_avg_per_frame(self, convention: str = "stp3") -> np.ndarray:
        """Per-frame mean of the 1/2/3 s L2 under `convention`: the M of retention, one value per frame."""
        return np.asarray(l2_avg(self.l2, convention))


@dataclass(frozen=True)
class FamilyGroups:
    """Which families form each axis: read off the injector registry, or given (tests, custom ladders)."""

    quality: tuple[str, ...]
    core: tuple[str, ...]
    removal: str = "blackout"
    beside: tuple[str, ...] = ("frame_dropout", "occlusion")
    order: tuple[str, ...] = ()  # report order of every known family

    @classmethod
    def from_registry(cls, families: Mapping[str, Any] | None = None) -> "FamilyGroups":
        """Groups from ``FAMILIES`` (imported only now): quality = axis "quality"; core = ``.core`` when the
        family objects carry it, else every family outside the contamination group."""
        if families is None:
            from .corruptions.registry import FAMILIES as families  # noqa: N811 - lazy, heavy import
        names = tuple(families)
        quality = tuple(n for n in names if getattr(families[n], "axis", None) == "quality")
        if all(hasattr(families[n], "core") for n in names):
            core = tuple(n for n in names if families[n].core)
        else:
            core = tuple(n for n in names if getattr(families[n], "group", None) != "contamination")
        return cls(quality=quality, core=core, order=names)


def _finite_mean(values: np.ndarray) -> float:
    """Mean over finite entries (NaN frames left out); NaN when none is finite."""
    arr = np.asarray(values, dtype=float)
    ok = np.isfinite(arr)
    return float(arr[ok].mean()) if ok.any() else math.nan


def retention(m_clean: Any, m_cell: Any, kind: str = "error") -> Any:
    """r = M(clean) / M(s) for an error metric, M(s) / M(clean) for a reward metric; vectorised.

    Higher is better and 1.0 means no measurable damage. Both zero -> 1.0 (nothing to lose); a zero
    denominator otherwise -> inf. Returns a float for scalar input.
    """
    if kind not in ("error", "reward"):
        raise InvalidInput(f"retention kind must be 'error' or 'reward', got {kind!r}")
    num, den = (m_clean, m_cell) if kind == "error" else (m_cell, m_clean)
    num, den = np.asarray(num, dtype=float), np.asarray(den, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where((num == 0) & (den == 0), 1.0, num / den)
    return float(r) if r.ndim == 0 else r


def bootstrap_retention_ci(clean: Any, cell: Any, *, kind: str = "error", n_resamples: int = DEFAULT_RESAMPLES,
                           seed: int = 0, confidence: float = 0.95,
                           chunk_elems: int = 2_000_000) -> tuple[float, float]:
    """Paired frame-level percentile bootstrap CI of retention.

    Each resample draws frame indices with replacement and applies the *same* indices to clean and the cell,
    so per-frame difficulty cancels. Frames not finite in both are dropped first. The generator is seeded
    with `seed` only, so every cell of a run sees the same resamples and the result is order-independent.
    Vectorised in chunks of about `chunk_elems` indices. (NaN, NaN) when no frame is usable.
    """
    a, b = np.asarray(clean, dtype=float), np.asarray(cell, dtype=float)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    n = len(a)
    if n == 0 or n_resamples < 1:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    per_chunk = max(1, chunk_elems // n)
    ratios = []
    for start in range(0, n_resamples, per_chunk):
        # One double per index (not ``integers``, whose 32-bit buffering depends on the chunk shape), so the
        # resamples are the same whatever the chunk size.
        idx = (rng.random((min(per_chunk, n_resamples - start), n)) * n).astype(np.intp)
        ratios.append(retention(a[idx].mean(axis=1), b[idx].mean(axis=1), kind))
    r = np.concatenate(ratios)
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(r, [tail, 100.0 - tail])
    return float(low), float(high)


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
    conformance_errors: int = 0

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
                out[f"{key}_{h}s_{conv}"] = _finite_mean(per_h[:, j])
        out[f"l2_avg_{conv}"] = _finite_mean(record.l2_avg_per_frame(conv))
    out["jerk"] = _finite_mean(record.jerk)
    return out


def paired_retention(m_clean: np.ndarray, m_cell: np.ndarray, kind: str = "error") -> float:
    """Retention over the frames finite in both the cell and clean (the bootstrap's frames); NaN when none."""
    paired = np.isfinite(m_clean) & np.isfinite(m_cell)
    return float(retention(_finite_mean(m_clean[paired]), _finite_mean(m_cell[paired]), kind))


def summarise_cell(record: CellRecord, clean: CellRecord, *, convention: str = "stp3", kind: str = "error",
                   n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> CellSummary:
    """A cell's metrics, its retention against `clean` and the paired bootstrap CI."""
    if record.frames != clean.frames:
        raise InvalidInput(f"cell {record.cell!r} was scored on other frames than the clean cell")
    m_clean, m_cell = clean.l2_avg_per_frame(convention), record.l2_avg_per_frame(convention)
    metrics = horizon_metrics(record)
    metrics["endpoint_shift"] = _finite_mean(record.endpoint_shift(clean))
    metrics["energy"] = float(retention(_finite_mean(clean.bit1), _finite_mean(record.bit1), "reward"))
    if record.cell == clean.cell:
        r, ci = 1.0, (1.0, 1.0)
    else:
        r = paired_retention(m_clean, m_cell, kind)
        ci = bootstrap_retention_ci(m_clean, m_cell, kind=kind, n_resamples=n_resamples, seed=seed)
    return CellSummary(record.cell, record.family, record.severity, int(np.isfinite(m_cell).sum()),
                       _finite_mean(m_cell), r, ci[0], ci[1], metrics, conformance_errors=len(record.errors))


def tolerance_threshold(curve: Mapping[int, float], level: float) -> float | None:
    """Severity at which retention first falls *below* `level`, linearly interpolated.

    `curve` maps severity (1..5, any subset) to retention. Retention exactly at `level` is not below. Walking
    up the measured severities, the first one below `level` is the crossing: interpolate between it and the
    measured severity just before it. When the lowest measured severity is already below (S1 normally), the
    value is that severity (1.0). None when no measured severity falls below. NaN retentions are skipped.
    """
    points = sorted((int(s), float(r)) for s, r in curve.items() if int(s) > 0 and math.isfinite(float(r)))
    prev: tuple[int, float] | None = None
    for s, r in points:
        if r < level:
            if prev is None:
                return float(s)
            s0, r0 = prev
            return float(s0 + (r0 - level) / (r0 - r) * (s - s0))
        prev = (s, r)
    return None


def thresholds(summaries: Iterable[CellSummary]) -> dict[str, dict[str, float | None]]:
    """family -> {"s10": x|None, "s25": x|None} for every ladder family among the summaries."""
    curves: dict[str, dict[int, float]] = {}
    for s in summaries:
        if s.family not in DIAGNOSTIC_CELLS:
            curves.setdefault(s.family, {})[s.severity] = s.retention
    return {fam: {k: tolerance_threshold(c, lvl) for k, lvl in THRESHOLD_LEVELS.items()} for fam, c in curves.items()}


def _mean_or_none(values: Mapping[str, float], names: Sequence[str]) -> float | None:
    """Mean over `names`; None when any is missing or not finite (an axis over a subset is not that axis)."""
    got = [values.get(n) for n in names]
    if not names or any(v is None or not math.isfinite(v) for v in got):
        return None
    return math.fsum(got) / len(got)


def compute_axes(s5: Mapping[str, float], groups: FamilyGroups) -> dict[str, Any]:
    """The two axes from S5 retention per family: quality, removal, gap, mean, with dropout/occlusion beside.

    An axis whose families were not all run at S5 is None (``missing`` names them), never a guess.
    """
    quality = _mean_or_none(s5, groups.quality)
    removal = _mean_or_none(s5, (groups.removal,))
    beside = {n: _mean_or_none(s5, (n,)) for n in groups.beside}
    return {
        "quality": quality,
        "removal": removal,
        "gap": None if quality is None or removal is None else quality - removal,
        "mean": _mean_or_none(s5, groups.core),
        "dropout": beside.get("frame_dropout"),
        "occlusion": beside.get("occlusion"),
        "missing": sorted({n for n in (*groups.core, groups.removal, *groups.beside) if n not in s5}),
    }


def verdict(axes: Mapping[str, Any], flat: float = DEFAULT_FLAT) -> dict[str, Any]:
    """Label the planner from its axes (SPEC section 5) and say in plain words which case applies.

    quality >= flat and removal >= flat -> not-shown-to-use-cameras; quality >= flat > removal ->
    quality-insensitive; quality < flat -> camera-reliant (case "both-below" or "quality-only").
    "undetermined" when a missing axis leaves the label open. A negative gap is flagged.
    """
    # Compared at the certificate's precision (6 decimals), so a reader of the certificate reaches the same label.
    q, r, gap = (None if v is None else round(v, 6) for v in (axes.get(k) for k in ("quality", "removal", "gap")))
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
    nums = f"quality {fmt(q)}, removal {fmt(r)}, flat line {flat:.2f}"
    if q is not None and q < flat:
        label = "camera-reliant"
        case, tail = (("removal-not-measured", "removal was not measured.") if r is None else
                      ("both-below", "it also degrades when cameras are removed.") if r < flat else
                      ("quality-only", "removing cameras leaves it flat, so it relies on what the cameras left "
                                       "in view still show."))
        text = f"Camera-reliant: planning degrades when image quality degrades ({nums}); {tail}"
    elif q is not None and r is not None and r < flat:
        label, case = "quality-insensitive", "removal-only"
        text = (f"Quality-insensitive but camera-reliant: planning stays flat when image quality degrades "
                f"but falls when cameras are removed ({nums}).")
    elif q is not None and r is not None:
        label, case = "not-shown-to-use-cameras", "both-flat"
        text = (f"Not shown to use its cameras: planning stays within the flat line on both image quality and "
                f"camera removal ({nums}); this suite cannot tell it apart from a planner that ignores images.")
    else:
        label, case = "undetermined", "axis-missing"
        text = f"Undetermined: an axis could not be computed from the cells run ({nums}); run every family at S5."
    negative = gap is not None and gap < 0
    if negative:
        text += (f" Negative gap ({gap:.3f}): degraded images hurt more than removed cameras, which usually means "
                 "the planner is misled by corrupted pixels rather than helped by missing ones.")
    return {"label": label, "case": case, "flat": float(flat), "text": text, "negative_gap": bool(negative)}


def null_control(clean_plans: Any, null_plans: Any) -> dict[str, Any]:
    """Compare the null-control plans with clean: passed iff bit-identical; otherwise how far they wandered.

    ``max_l2_change`` is the largest waypoint displacement (m) over frames and steps; it is the wander that
    ``separable_from_null`` compares cells against.
    """
    a, b = np.asarray(clean_plans, dtype=np.float64), np.asarray(null_plans, dtype=np.float64)
    if a.shape != b.shape:
        raise InvalidInput(f"null-control plans have shape {b.shape}, clean plans {a.shape}")
    passed = a.tobytes() == b.tobytes()
    diff = np.abs(a - b)
    disp = np.linalg.norm(a - b, axis=-1) if a.size else np.zeros(0)
    return {
        "passed": bool(passed),
        "max_abs_diff": 0.0 if passed else float(np.nanmax(diff, initial=0.0)),
        "max_l2_change": 0.0 if passed else float(np.nanmax(disp, initial=0.0)),
        "frames_changed": int((diff.reshape(len(a), -1) > 0).any(axis=1).sum()) if a.size else 0,
    }


def separable_from_null(endpoint_shift: float, wander: float) -> bool:
    """A cell is separable only if its mean 3 s endpoint shift from clean exceeds the null's largest wander
    (a mean against a maximum: conservative). With a bit-identical null, any change at all is separable."""
    return bool(math.isfinite(endpoint_shift) and endpoint_shift > wander)


def floor_comparison(floor_l2: float | None, summaries: Sequence[CellSummary], removal: str = "blackout") -> dict:
    """Does the planner stay below the ego-only floor's clean L2 when blinded (blind) or at removal S5?"""
    by_cell = {s.cell: s.l2_avg for s in summaries}
    out: dict[str, Any] = {"l2_avg": floor_l2}
    for key, cell in (("blackout_s5", f"{removal}-s5"), ("blind", "blind")):
        value = by_cell.get(cell)
        out[f"{key}_l2_avg"] = value
        out[f"{key}_below_floor"] = None if value is None or floor_l2 is None else bool(value < floor_l2)
    return out


def _cell_order(summary: CellSummary, groups: FamilyGroups) -> tuple:
    """Report order: clean, null, blind, then families in registry order (unknown ones by name), S1..S5."""
    if summary.family in DIAGNOSTIC_CELLS:
        return (0, DIAGNOSTIC_CELLS.index(summary.family), "", 0)
    rank = groups.order.index(summary.family) if summary.family in groups.order else len(groups.order)
    return (1, rank, summary.family, summary.severity)


@dataclass
class RunAnalysis:
    """Everything the reports show, as plain builtins (summaries aside, which ``to_builtins`` flattens)."""

    summaries: list[CellSummary]
    thresholds: dict[str, dict[str, float | None]]
    axes: dict[str, Any]
    verdict: dict[str, Any]
    null_control: dict[str, Any] | None
    floor: dict[str, Any]
    settings: dict[str, Any]

    def to_builtins(self) -> dict[str, Any]:
        out = asdict(self)
        out["summaries"] = [s.flat() for s in self.summaries]
        return out

    def s5(self) -> dict[str, float]:
        """S5 retention per ladder family."""
        return {s.family: s.retention for s in self.summaries if s.severity == 5 and s.family not in DIAGNOSTIC_CELLS}


def analyse_run(records: Iterable[CellRecord | Mapping[str, Any]], *, groups: FamilyGroups | None = None,
                convention: str = "stp3", kind: str = "error", flat: float = DEFAULT_FLAT, seed: int = 0,
                n_resamples: int = DEFAULT_RESAMPLES, floor_l2: float | None = None) -> RunAnalysis:
    """Every figure of a run from its cell records (in any order; the result does not depend on it).

    Retention and its CI use the frames finite in both the cell and clean (a frame that failed conformance
    in a cell drops out of that cell's comparison only).

    Requires the clean cell. `groups` defaults to ``FamilyGroups.from_registry()``; `floor_l2` is the ego-only
    floor's clean l2_avg when it was run.
    """
    recs = [r if isinstance(r, CellRecord) else CellRecord.from_builtins(r) for r in records]
    by_cell = {r.cell: r for r in recs}
    if "clean" not in by_cell:
        raise InvalidInput("no clean cell among the results: retention needs it (was it deselected with -k?)")
    groups = groups or FamilyGroups.from_registry()
    clean = by_cell["clean"]
    summaries = [summarise_cell(r, clean, convention=convention, kind=kind, n_resamples=n_resamples, seed=seed)
                 for r in by_cell.values()]  # a cell recorded twice (a resumed run) counts once: the last
    summaries.sort(key=lambda s: _cell_order(s, groups))
    nc = null_control(clean.plans, by_cell["null"].plans) if "null" in by_cell else None
    wander = nc["max_l2_change"] if nc else 0.0
    for s in summaries:
        if s.cell not in ("clean", "null"):
            s.separable_from_null = separable_from_null(s.metrics["endpoint_shift"], wander)
    ax = compute_axes({s.family: s.retention for s in summaries if s.severity == 5}, groups)
    settings = {"seed": int(seed), "convention": convention, "metric": "l2_avg", "kind": kind, "flat": float(flat),
                "n_resamples": int(n_resamples), "confidence": 0.95, "threshold_levels": dict(THRESHOLD_LEVELS),
                "tolerance_default": DEFAULT_TOLERANCE}
    return RunAnalysis(summaries, thresholds(summaries), ax, verdict(ax, flat), nc,
                       floor_comparison(floor_l2, summaries, groups.removal), settings)


@dataclass(frozen=True)
class Regression:
    """One retention that fell more than the tolerance below its baseline."""

    name: str  # a cell id, or "axis:quality"
    baseline: float
    current: float

    @property
    def drop(self) -> float:
        return self.baseline - self.current

    def message(self) -> str:
        return f"{self.name}: retention {self.current:.3f} vs baseline {self.baseline:.3f} (drop {self.drop:.3f})"


def check_baseline_compatible(baseline: Mapping[str, Any], *, spec_version: str, dataset_fingerprint: str) -> None:
    """Raise ``BaselineError`` when the baseline was certified under another spec version or data set."""
    theirs = (baseline.get("spec_version"), (baseline.get("dataset") or {}).get("fingerprint"))
    for what, mine, other in (("spec version", spec_version, theirs[0]),
                              ("dataset fingerprint", dataset_fingerprint, theirs[1])):
        if mine != other:
            raise BaselineError(f"the baseline certificate has {what} {other!r} but this run has {mine!r}; "
                                "retentions are comparable only under the same ladder and data")


def cell_regression(cell: str, current: float, baseline: Mapping[str, Any], tolerance: float) -> Regression | None:
    """The regression of one cell against the baseline certificate, or None (also when the cell is new)."""
    base = {c.get("cell"): c.get("retention") for c in baseline.get("cells", [])}.get(cell)
    if base is None or current is None or not math.isfinite(current):
        return None
    return Regression(cell, float(base), float(current)) if float(base) - current > tolerance else None


def compare_to_baseline(current: Mapping[str, Any], baseline: Mapping[str, Any],
                        tolerance: float = DEFAULT_TOLERANCE) -> dict[str, list[Regression]]:
    """Cells and axes (quality, removal, mean) whose retention fell more than `tolerance` below the baseline.

    `current` and `baseline` are certificate-shaped mappings. Returns {"cells": [...], "axes": [...]}; an axis
    regression fails the session. Raises ``BaselineError`` on an incompatible baseline.
    """
    check_baseline_compatible(baseline, spec_version=current.get("spec_version"),
                              dataset_fingerprint=(current.get("dataset") or {}).get("fingerprint"))
    cells = [reg for c in current.get("cells", [])
             if (reg := cell_regression(c["cell"], c.get("retention"), baseline, tolerance))]
    axes = []
    for name in ("quality", "removal", "mean"):
        mine, theirs = (current.get("axes") or {}).get(name), (baseline.get("axes") or {}).get(name)
        if mine is not None and theirs is not None and theirs - mine > tolerance:
            axes.append(Regression(f"axis:{name}", float(theirs), float(mine)))
    return {"cells": cells, "axes": axes}

