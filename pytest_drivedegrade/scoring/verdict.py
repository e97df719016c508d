"""From cell summaries to the run's verdict: the two axes, the label and its prose, the null control, the floor
comparison and the failed cells, each as a typed figure of ``records``; ``analyse`` puts them together.

Pure functions over plain data (SPEC section 5); nothing here reads files, imports pytest or touches a planner.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np

from ..cells import CellRecord, cell_id, differing_frames, identical_plans, is_input, planned_in_both
from ..constants import DEFAULT_FLAT, EGO_BLIND, EGO_NOISE
from ..errors import InvalidInput
from .records import Axes, CellSummary, FailedCell, Floor, NullControl, Verdict, format_value, report_order

#: The run's labels; ``camera-sensitive`` (plans move, accuracy does not fall) comes from ``reliance.read_movement``.
VERDICT_LABELS: tuple[str, ...] = ("camera-reliant", "quality-insensitive", "not-shown-to-use-cameras",
                                   "camera-sensitive")


@dataclass(frozen=True)
class FamilyGroups:
    """Which families form each axis: read off the injector registry, or given (tests, custom ladders)."""

    quality: tuple[str, ...]
    core: tuple[str, ...]
    removal: str = "blackout"
    beside: tuple[str, ...] = ("frame_dropout", "occlusion")
    order: tuple[str, ...] = ()  # report order of every known family

    @classmethod
    def from_registry(cls, families: Mapping[str, Any] | None = None) -> FamilyGroups:
        """Groups from ``FAMILIES`` (imported only now): quality = axis "quality"; core = ``.core`` when the
        family objects carry it, else every family outside the contamination group."""
        if families is None:
            from ..corruptions.ladder import FAMILIES  # lazy, heavy import

            families = FAMILIES
        names = tuple(families)
        quality = tuple(n for n in names if getattr(families[n], "axis", None) == "quality")
        if all(hasattr(families[n], "core") for n in names):
            core = tuple(n for n in names if families[n].core)
        else:
            core = tuple(n for n in names if getattr(families[n], "group", None) != "contamination")
        return cls(quality=quality, core=core, order=names)


def _mean_or_none(values: Mapping[str, float], names: Sequence[str]) -> float | None:
    """Mean over `names`; None when any is missing or not finite (an axis over a subset is not that axis)."""
    got = [values.get(n) for n in names]
    if not names or any(v is None or not math.isfinite(v) for v in got):
        return None
    return math.fsum(cast("list[float]", got)) / len(got)  # no None left after the check above


def compute_axes(s5: Mapping[str, float], groups: FamilyGroups) -> Axes:
    """The two axes from S5 retention per family: quality, removal, gap, mean, with dropout/occlusion beside.

    An axis whose families were not all run at S5 is None (``missing`` names them), never a guess.
    """
    quality = _mean_or_none(s5, groups.quality)
    removal = _mean_or_none(s5, (groups.removal,))
    beside = {n: _mean_or_none(s5, (n,)) for n in groups.beside}
    return Axes(quality=quality, removal=removal,
                gap=None if quality is None or removal is None else quality - removal,
                mean=_mean_or_none(s5, groups.core), dropout=beside.get("frame_dropout"),
                occlusion=beside.get("occlusion"),
                missing=tuple(sorted({n for n in (*groups.core, groups.removal, *groups.beside) if n not in s5})))


def verdict(axes: Axes, flat: float = DEFAULT_FLAT) -> Verdict:
    """Label the planner from its axes (SPEC section 5) and say in plain words which case applies.

    quality >= flat and removal >= flat -> not-shown-to-use-cameras; quality >= flat > removal ->
    quality-insensitive; quality < flat -> camera-reliant (case "both-below" or "quality-only").
    "undetermined" when a missing axis leaves the label open. A negative gap is flagged (`negative_gap`).
    """
    # Compared at the certificate's precision (6 decimals), so a reader of the certificate reaches the same label.
    q, r, gap = (None if v is None else round(v, 6) for v in (axes.quality, axes.removal, axes.gap))
    nums = f"quality {format_value(q)}, removal {format_value(r)}, flat line {flat:.2f}"
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
    negative = negative_gap(gap, axes.interval("gap"))
    if negative:
        text += (f" Negative gap ({gap:.3f}): degraded images hurt more than removed cameras, which usually means "
                 "the planner is misled by corrupted pixels rather than helped by missing ones.")
    return Verdict(label=label, case=case, flat=float(flat), text=text, negative_gap=bool(negative),
                   computed_label=label)


def negative_gap(gap: float | None, interval: tuple[float | None, float | None] | None) -> bool:
    """A negative gap worth a sentence (issue 20): below 0 and, where the bootstrap gave the gap an interval, that
    interval below 0 too (a gap of -0.0008 whose interval holds 0 is noise, not a planner misled by pixels).
    Without an interval (no resamples, or axes on PDMS) the gap itself decides, as before."""
    if gap is None or gap >= 0:
        return False
    high = interval[1] if interval is not None else None
    return high is None or round(high, 6) < 0


#: The figures the verdict can be put on (--drivedegrade-metric): L2 retention (default), PDMS or EPDMS retention,
#: or the two-stage EPDMS retention (epdms2, --drivedegrade-two-stage).
VERDICT_METRICS: tuple[str, ...] = ("l2", "pdms", "epdms", "epdms2")
#: The score whose retention each metric but L2 is, by metric (a reward: M(cell) / M(clean)).
SCORE_METRICS: tuple[str, ...] = ("pdms", "epdms", "epdms2")
EGO_LABELS: tuple[str, ...] = ("ego-reliant", "ego-insensitive", "undetermined")


def retention_of(summary: CellSummary, metric: str = "l2") -> float:
    """A summary's retention on `metric`: L2 (``retention``), PDMS or EPDMS (``pdms_retention``,
    ``epdms_retention``; NaN when unscored)."""
    if metric in SCORE_METRICS:
        return float(summary.metrics.get(f"{metric}_retention", math.nan))
    return summary.retention


def camera_s5(summaries: Iterable[CellSummary], metric: str = "l2") -> dict[str, float]:
    """S5 retention per camera ladder family (the ego and command cells left out: they are not camera axes)."""
    return {s.family: retention_of(s, metric) for s in summaries if s.severity == 5 and not is_input(s.family)}


def ego_axes(summaries: Iterable[CellSummary], metric: str = "l2") -> tuple[float | None, float | None]:
    """The ego axis (SPEC section 10): (ego, ego_removal) = (ego_noise S5 retention, ego_blind retention), each
    None when that cell was not run or its retention is not finite."""
    by_cell = {s.cell: retention_of(s, metric) for s in summaries}
    got = [by_cell.get(cell) for cell in (cell_id(EGO_NOISE, 5), cell_id(EGO_BLIND, 0))]
    ego, removal = (v if v is not None and math.isfinite(v) else None for v in got)
    return ego, removal


def run_axes(summaries: Sequence[CellSummary], groups: FamilyGroups, metric: str = "l2") -> Axes:
    """The camera axes and the ego axis of a run on `metric` retention (no intervals, nothing partial)."""
    ego, removal = ego_axes(summaries, metric)
    return replace(compute_axes(camera_s5(summaries, metric), groups), ego=ego, ego_removal=removal)


def ego_label(ego_removal: float | None, flat: float = DEFAULT_FLAT) -> str:
    """``ego-reliant`` when ego_removal is below the flat line, else ``ego-insensitive``; ``undetermined`` when
    the ego_blind cell was not run. Compared at the certificate's precision, like the camera verdict."""
    if ego_removal is None:
        return "undetermined"
    return "ego-reliant" if round(ego_removal, 6) < flat else "ego-insensitive"


def null_control(clean_plans: np.ndarray, null_plans: np.ndarray) -> NullControl:
    """Compare the null-control plans with clean: passed iff bit-identical (`cells.identical_plans`); otherwise
    how far they wandered. Only the frames with a plan in both are compared (`cells.planned_in_both`), as in the
    null-control item: a frame that failed in either cell is that cell's failure, not a wander.

    ``max_l2_change`` is the largest waypoint displacement (m) over frames and steps; it is the wander that
    ``separable_from_null`` compares cells against. ``frames_compared`` counts the frames with a plan in both;
    with none, nothing was compared: ``passed`` is None (not run), never a pass over failed frames.
    """
    a, b = np.asarray(clean_plans, dtype=np.float64), np.asarray(null_plans, dtype=np.float64)
    if a.shape != b.shape:
        raise InvalidInput(f"null-control plans have shape {b.shape}, clean plans {a.shape}")
    both = planned_in_both(a, b)
    compared = int(both.sum())
    if compared == 0:
        return NullControl(passed=None, max_abs_diff=None, max_l2_change=None, frames_changed=0, frames_compared=0)
    a, b = a[both], b[both]
    passed = identical_plans(a, b)
    diff = np.abs(a - b)
    disp = np.linalg.norm(a - b, axis=-1) if a.size else np.zeros(0)
    return NullControl(passed=bool(passed), max_abs_diff=0.0 if passed else float(np.nanmax(diff, initial=0.0)),
                       max_l2_change=0.0 if passed else float(np.nanmax(disp, initial=0.0)),
                       frames_changed=int(len(differing_frames(a, b))) if a.size else 0, frames_compared=compared)


def failed_cells(records: Iterable[CellRecord], order: Sequence[str] = ()) -> dict[str, FailedCell]:
    """The cells with failed frames, in report order: cell -> frames run (every seed run counted), the planner's
    contract failures (``conformance_errors``) and the data faults (``data_errors``)."""
    out = {}
    for r in sorted(records, key=lambda r: report_order(r.family, r.severity, order)):
        planner, data = r.failed_frames()
        if planner or data:
            out[r.cell] = FailedCell(sum(len(run.frames) for run in r.runs()), planner, data)
    return out


def failure_reason(failed: Mapping[str, FailedCell], shown: int = 8) -> str:
    """One sentence naming the cells with failed frames and their counts, e.g. ``2 cells have failed frames:
    clean (1 of 8 frames: 1 data error), jpeg-s5 (2 of 8 frames: 2 planner contract failures)``."""
    def counts(c: FailedCell) -> str:
        parts = [f"{n} {what}{'s' if n != 1 else ''}" for n, what in
                 ((c.conformance_errors, "planner contract failure"), (c.data_errors, "data error")) if n]
        return f"{c.conformance_errors + c.data_errors} of {c.frames} frames: {', '.join(parts)}"

    items = [f"{cell} ({counts(c)})" for cell, c in list(failed.items())[:shown]]
    more = f", and {len(failed) - shown} more" if len(failed) > shown else ""
    return f"{len(failed)} cell{'s' if len(failed) != 1 else ''} with failed frames: {', '.join(items)}{more}"


def undetermined_by_failures(v: Verdict, failed: Mapping[str, FailedCell]) -> Verdict:
    """The verdict of a run with failed frames (SPEC section 11): ``undetermined`` with the `reason`, the label
    the axes give over the frames that did produce a plan kept as ``computed_label`` (flagged, not claimed).
    Without failures: the verdict as is, with ``reason`` None and no failed cells."""
    if not failed:
        return replace(v, reason=None, failed_cells={}, computed_label=v.label)
    reason = failure_reason(failed)
    would = f"would give {v.label}" if v.label != "undetermined" else "leave it open too"
    text = (f"Undetermined: {reason}. Retention, thresholds and axes are computed over the frames that did produce "
            f"a plan and {would}, but a verdict is not sealed on partial results: fix the failures named in the "
            "cells' messages (planner contract or data set) and rerun.")
    return replace(v, label="undetermined", case="failed-frames", text=text, reason=reason,
                   failed_cells=dict(failed), computed_label=v.label, ego_label="undetermined", borderline=False)


def undetermined_by_null_control(v: Verdict, nc: NullControl | None) -> Verdict:
    """The verdict of a run whose null control failed (M4): ``undetermined``, since plans that move with no
    corruption cannot tell a camera's effect from the planner's own; the label the axes give is kept as
    ``computed_label`` (after `undetermined_by_failures`, whose reason it extends). Otherwise `v` as is."""
    if nc is None or nc.passed is not False:
        return v
    reason = (f"the null control failed (plans moved by up to {float(nc.max_l2_change or 0.0):.6g} m with no "
              "corruption applied)")
    text = (f"Undetermined: {reason}. Plans that change when nothing changed cannot be told from a camera's "
            f"effect: the axes give {v.computed_label}, but a verdict is not sealed on them; make predict() "
            "deterministic (or declare the cameras it reads) and rerun.")
    failed_frames = v.label == "undetermined" and v.case == "failed-frames"
    if failed_frames:
        text = f"{v.text} Also {reason}."
    return replace(v, label="undetermined", case="failed-frames" if failed_frames else "null-control-failed",
                   text=text, ego_label="undetermined", borderline=False,
                   reason=reason if not v.reason else f"{v.reason}; {reason}")


def separable_from_null(endpoint_shift: float, wander: float) -> bool:
    """A cell is separable only if its mean 3 s endpoint shift from clean exceeds the null's largest wander
    (a mean against a maximum: conservative). With a bit-identical null, any change at all is separable."""
    return bool(math.isfinite(endpoint_shift) and endpoint_shift > wander)


def floor_comparison(floor_l2: float | None, summaries: Sequence[CellSummary], removal: str = "blackout",
                     ego_removal: float | None = None) -> Floor:
    """Does the planner stay below the ego-only floor's clean L2 when blinded (blind) or at removal S5? With the
    floor's own ego_blind retention (`ego_removal`) when the ego cells ran."""
    by_cell = {s.cell: s.l2_avg for s in summaries}
    at_removal, blind = by_cell.get(cell_id(removal, 5)), by_cell.get(cell_id("blind", 0))

    def below(value: float | None) -> bool | None:
        return None if value is None or floor_l2 is None else bool(value < floor_l2)

    return Floor(l2_avg=floor_l2, blackout_s5_l2_avg=at_removal, blackout_s5_below_floor=below(at_removal),
                 blind_l2_avg=blind, blind_below_floor=below(blind), ego_removal=ego_removal)


#: The verdict's case when blind equals clean while beating the ego-only floor (M12): a memo, not the cameras.
BLIND_EQUALS_CLEAN = "blind-equals-clean"


@dataclass(frozen=True)
class BlindEqualsClean:
    """M12's finding: blind's plans (every camera off) are clean's bit for bit over `frames` frames, while blind's
    L2 beats the ego-only floor's by `gap` m (floor minus blind, mean over the frames) with the paired bootstrap's
    95 % interval (`low`, `high`; None without resamples, when the point gap decides alone)."""

    frames: int
    gap: float
    low: float | None
    high: float | None

    @property
    def settled(self) -> bool:
        """Whether the gap is beyond the bootstrap's interval (or no interval was drawn). Unsettled (issue 37: at
        24 and 48 frames a memoising planner's gap was not significant and it was certified camera-free) the
        finding still stands: a memo is not ruled out, so no camera-free label is sealed on these frames."""
        return self.low is None or self.low > 0

    def reason(self) -> str:
        spread = "" if self.low is None else f", 95 % interval {self.low:.3g} .. {self.high:.3g} m"
        text = (f"with every camera off (blind) the plans equal clean's bit for bit on {self.frames} frames, while "
                f"they beat the ego-only floor by {self.gap:.3g} m L2{spread}")
        if not self.settled:
            text += (" (not significant on this many frames, so a per-frame memo cannot be ruled out either; more "
                     "frames tell the two apart)")
        return text


def blind_equals_clean(clean: CellRecord, blind: CellRecord | None, floor_frames: Sequence[float] | None, *,
                       convention: str = "stp3", n_resamples: int = 0, seed: int = 0) -> BlindEqualsClean | None:
    """M12: a planner that memoises its plan per frame (keyed by ego status or the frame's token) returns clean's
    plans in every later cell, so all its axes read 1.000. Blind is where that cannot be the cameras' doing: with
    no image at all it plans exactly as with clean images, yet better than a planner of ego status alone (the
    ego-only floor, per frame in `floor_frames`) on the mean gap; the paired bootstrap's interval says whether
    that is settled (`BlindEqualsClean.settled`), but an unsettled gap is a finding too (issue 37: the memo check
    decided only when the gap was significant, so at 24 and 48 frames a memo was certified camera-free). The
    finding, or None when blind's plans differ from clean's, blind does not beat the floor on average, blind did
    not run, or the floor's frames do not line up with clean's."""
    if blind is None or floor_frames is None or len(floor_frames) != len(clean.frames):
        return None
    both = planned_in_both(clean.plans, blind.plans)
    if not both.any() or not identical_plans(clean.plans[both], blind.plans[both]):
        return None
    gap = np.asarray(floor_frames, dtype=np.float64) - blind.l2_avg_per_frame(convention)
    gap = gap[both & np.isfinite(gap)]
    if not gap.size or not float(gap.mean()) > 0:
        return None
    if n_resamples <= 0:
        return BlindEqualsClean(int(both.sum()), float(gap.mean()), None, None)
    rng = np.random.default_rng(seed)
    means = gap[rng.integers(0, gap.size, size=(n_resamples, gap.size))].mean(axis=1)
    low, high = (float(v) for v in np.percentile(means, [2.5, 97.5]))
    return BlindEqualsClean(int(both.sum()), float(gap.mean()), low, high)  # unsettled too (`settled`)


def undetermined_by_memo(v: Verdict, found: BlindEqualsClean | None) -> Verdict:
    """The verdict of a run whose blind cell planned as clean while beating the ego-only floor (M12):
    ``undetermined`` (case `BLIND_EQUALS_CLEAN`), since flat axes then say nothing of the cameras: the planner
    plans without images better than ego status allows, so its plans come from elsewhere (a plan memoised per frame
    on first sight, kept across cells). The label the axes give stays as ``computed_label``. Otherwise `v`."""
    if found is None:
        return v
    reason = found.reason()
    if v.label == "undetermined" and v.case in ("failed-frames", "null-control-failed"):
        return replace(v, text=f"{v.text} Also {reason}.", reason=f"{v.reason}; {reason}" if v.reason else reason)
    text = (f"Undetermined: {reason}. Plans that do not move when every camera is removed yet beat a planner of "
            f"ego status alone did not come from the images of the cell: the planner may remember plans across "
            f"calls (memoised per frame), which hides any effect of the cameras; the axes give {v.computed_label}, "
            "but a verdict is not sealed on them. Plan each call from its inputs (state only within a scene, "
            "cleared by reset()) and rerun; a planner that truly plans from ego status better than the floor gets "
            "this too.")
    return replace(v, label="undetermined", case=BLIND_EQUALS_CLEAN, text=text, reason=reason,
                   ego_label="undetermined", borderline=False)
