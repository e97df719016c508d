"""`analyse_run`: every figure of a run from its cell records, in named steps (the records checked, the joint
bootstrap, the cell summaries, the null control, the thresholds, the axes, the verdict, the floor, the settings).

Pure functions over plain data (SPEC section 5); nothing here reads files, imports pytest or touches a planner.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import Any

from ..cells import DIAGNOSTIC, CellRecord, is_camera_ladder
from ..constants import COMMAND_SWAP, DEFAULT_FLAT, DEFAULT_TOLERANCE
from ..errors import InvalidInput
from . import intervals as iv
from .command import CommandProbe, swap_probe
from .records import Axes, CellSummary, FamilyThresholds, NullControl, RunAnalysis, Threshold, Verdict, report_order
from .reliance import Reliance, read_movement, run_movement
from .retention import DEFAULT_RESAMPLES, THRESHOLD_LEVELS, summarise_cell, thresholds
from .verdict import (
    VERDICT_METRICS,
    FamilyGroups,
    blind_equals_clean,
    ego_label,
    failed_cells,
    floor_comparison,
    null_control,
    run_axes,
    separable_from_null,
    undetermined_by_failures,
    undetermined_by_memo,
    undetermined_by_null_control,
    verdict,
)


def analyse_run(records: Iterable[CellRecord | Mapping[str, Any]], *, groups: FamilyGroups | None = None,
                convention: str = "stp3", kind: str = "error", flat: float = DEFAULT_FLAT, seed: int = 0,
                n_resamples: int = DEFAULT_RESAMPLES, floor_l2: float | None = None, seeds: int = 1,
                intervals: bool = True, metric: str = "l2", floor_ego_removal: float | None = None,
                floor_frames: Sequence[float] | None = None,
                scenes: Mapping[str, str] | None = None) -> RunAnalysis:
    """Every figure of a run from its cell records (in any order; the result does not depend on it).

    Retention and its CI use the frames finite in both the cell and clean (a frame that failed conformance
    in a cell drops out of that cell's comparison only). A cell run under several seeds has the mean of its
    per-seed retentions and the two-level bootstrap's CI.

    A cell with failed frames (planner contract or data) makes the verdict ``undetermined`` with the reason
    (`undetermined_by_failures`); the axes and thresholds are still computed, flagged by ``partial``. So does a
    failed null control (`undetermined_by_null_control`).

    Requires the clean cell. `groups` defaults to ``FamilyGroups.from_registry()``; `floor_l2` is the ego-only
    floor's clean l2_avg when it was run (`floor_ego_removal` its ego_blind retention); `seeds` the run's
    ``--drivedegrade-seeds`` (recorded in the settings). With `intervals` (the default) the thresholds, axes and
    verdict get their intervals from one joint bootstrap of every ladder cell (``scoring.intervals``); without,
    those fields are None. The axes are computed on L2 retention (``axes``, with the ego axis) and on PDMS
    retention (``axes_pdms``); `metric` ("l2" or "pdms") says which one the verdict is put on.

    `scenes` maps each frame token to its scene: every interval is then a scene-cluster bootstrap (SPEC section
    17; ``settings.intervals.basis`` says which basis was used, and the verdict states a confidence only on
    `intervals.MIN_SCENES_FOR_CONFIDENCE` scenes or more). Without it, frames are treated as independent.
    """
    if metric not in VERDICT_METRICS:
        raise InvalidInput(f"metric must be one of {', '.join(VERDICT_METRICS)}, got {metric!r}")
    by_cell = cells_by_id(records)
    groups = groups or FamilyGroups.from_registry()
    clean = by_cell["clean"]
    frame_scenes = scene_labels(clean.frames, scenes)
    _, basis = iv.scene_clusters(frame_scenes, len(clean.frames))
    res = resample(by_cell, convention=convention, kind=kind, n_resamples=n_resamples, seed=seed,
                   scenes=frame_scenes) if intervals and n_resamples > 0 else None
    summaries = summarise(by_cell, res, groups, convention=convention, kind=kind, n_resamples=n_resamples,
                          seed=seed, scenes=frame_scenes)
    nc = null_control(clean.plans, by_cell["null"].plans) if "null" in by_cell else None
    separate_from_null(summaries, nc)
    failed = failed_cells(by_cell.values(), groups.order)
    partial = tuple(failed)  # the figures are still computed, and flagged as resting on partial cells
    partial_families = {by_cell[c].family for c in partial}
    per = axis_resamples(summaries, res, groups)
    ax = replace(run_axes(summaries, groups), intervals=iv.axis_intervals(per), partial=partial)
    ax_pdms, ax_epdms, ax_epdms2 = score_axes(summaries, groups, partial)
    moved = run_movement(summaries, nc.max_l2_change if nc is not None else None, groups.quality, groups.removal)
    on = {"pdms": ax_pdms, "epdms": ax_epdms, "epdms2": ax_epdms2}.get(metric) or ax
    v = run_verdict(on, per, metric=metric, flat=flat, basis=basis, reliance=moved)
    memo = blind_equals_clean(clean, by_cell.get("blind"), floor_frames, convention=convention, seed=seed,
                              n_resamples=n_resamples if intervals else 0)
    v = undetermined_by_memo(undetermined_by_null_control(undetermined_by_failures(v, failed), nc), memo)
    probe = command_probe(by_cell, seed=seed, n_resamples=n_resamples if intervals else 0, scenes=frame_scenes)
    v = v if probe is None else replace(v, text=f"{v.text} {probe.following.text()}")
    return RunAnalysis(summaries, run_thresholds(summaries, res, partial_families), ax, v, nc,
                       floor_comparison(floor_l2, summaries, groups.removal, floor_ego_removal),
                       analysis_settings(convention=convention, kind=kind, flat=flat, seed=seed, seeds=seeds,
                                         n_resamples=n_resamples, metric=metric, res=res, basis=basis),
                       axes_pdms=ax_pdms, axes_epdms=ax_epdms, axes_epdms2=ax_epdms2, reliance=moved, command=probe)


def score_axes(summaries: list[CellSummary], groups: FamilyGroups, partial: tuple[str, ...]
               ) -> tuple[Axes, Axes, Axes | None]:
    """The axes on PDMS, EPDMS and two-stage EPDMS retention (None: not a two-stage run), flagged `partial`."""
    two_stage = any("epdms2_retention" in s.metrics for s in summaries)  # --drivedegrade-two-stage
    ax_pdms, ax_epdms, *rest = (replace(run_axes(summaries, groups, m), partial=partial)
                                for m in ("pdms", "epdms", *(("epdms2",) if two_stage else ())))
    return ax_pdms, ax_epdms, rest[0] if rest else None


def command_probe(by_cell: Mapping[str, CellRecord], *, seed: int, n_resamples: int,
                  scenes: Sequence[str] | None = None) -> CommandProbe | None:
    """The command_swap cell's following figure against clean (`scoring.command.swap_probe`; its interval a
    scene-cluster bootstrap with `scenes`, each clean frame's scene); None when the cell did not run. Frames away
    from junctions are not scored."""
    swap = by_cell.get(COMMAND_SWAP)
    if swap is None:
        return None
    return swap_probe(by_cell["clean"].plans, swap.plans, swap.command_target, n_resamples=n_resamples, seed=seed,
                      scenes=scenes)


def cells_by_id(records: Iterable[CellRecord | Mapping[str, Any]]) -> dict[str, CellRecord]:
    """The records by cell id (builtins read back; a resumed duplicate counts once); clean is required."""
    recs = [r if isinstance(r, CellRecord) else CellRecord.from_builtins(r) for r in records]
    by_cell = {r.cell: r for r in recs}
    if "clean" not in by_cell:
        raise InvalidInput("no clean cell among the results: retention needs it (was it deselected with -k?)")
    return by_cell


def scene_labels(frames: Sequence[str], scenes: Mapping[str, str] | None) -> list[str] | None:
    """Each frame's scene from `scenes` (token -> scene); None when not given. A frame the map lacks is an
    error naming it: the intervals' basis must cover every frame."""
    if scenes is None:
        return None
    missing = [f for f in frames if f not in scenes]
    if missing:
        raise InvalidInput(f"no scene for {len(missing)} scored frame(s) (first {missing[0]!r}): the scene-cluster "
                           "intervals need every frame's scene")
    return [str(scenes[f]) for f in frames]


def resample(by_cell: Mapping[str, CellRecord], *, convention: str, kind: str, n_resamples: int,
             seed: int, scenes: Sequence[str] | None = None) -> iv.Resamples | None:
    """The joint bootstrap of every ladder cell against clean (None when there is no ladder cell)."""
    clean = by_cell["clean"]
    ladder = [r for r in by_cell.values() if r.family not in DIAGNOSTIC]
    if not ladder:
        return None
    return iv.resample_cells(clean.l2_avg_per_frame(convention),
                             {r.cell: [run.l2_avg_per_frame(convention) for run in r.runs()] for r in ladder},
                             kind=kind, n_resamples=n_resamples, seed=seed, scenes=scenes)


def summarise(by_cell: Mapping[str, CellRecord], res: iv.Resamples | None, groups: FamilyGroups, *,
              convention: str, kind: str, n_resamples: int, seed: int,
              scenes: Sequence[str] | None = None) -> list[CellSummary]:
    """Every cell's summary against clean, in report order (one-run CIs over `scenes` when given)."""
    clean = by_cell["clean"]
    summaries = [summarise_cell(r, clean, convention=convention, kind=kind, n_resamples=n_resamples, seed=seed,
                                ci=_seed_ci(res, r), scenes=scenes) for r in by_cell.values()]
    summaries.sort(key=lambda s: report_order(s.family, s.severity, groups.order))
    return summaries


def separate_from_null(summaries: Sequence[CellSummary], nc: NullControl | None) -> None:
    """Mark each cell but clean and null separable (or not) from the null control's wander."""
    wander = (nc.max_l2_change if nc is not None else None) or 0.0
    for s in summaries:
        if s.cell not in ("clean", "null"):
            s.separable_from_null = separable_from_null(s.metrics["endpoint_shift"], wander)


def _curves(summaries: Sequence[CellSummary]) -> dict[str, dict[int, str]]:
    """family -> severity -> cell id, for every camera ladder family."""
    curves: dict[str, dict[int, str]] = {}
    for s in summaries:
        if is_camera_ladder(s.family):
            curves.setdefault(s.family, {})[s.severity] = s.cell
    return curves


def run_thresholds(summaries: Sequence[CellSummary], res: iv.Resamples | None,
                   partial_families: set[str]) -> dict[str, FamilyThresholds]:
    """Each camera ladder family's s*10 / s*25 with their intervals (None without resamples) and whether the
    family has a cell with failed frames."""
    found = iv.threshold_intervals(res, _curves(summaries)) if res is not None else {}
    out = {}
    for fam, values in thresholds(summaries).items():
        spread = found.get(fam, {})
        levels = {key: Threshold(values[key], *spread.get(key, (None, None))) for key in THRESHOLD_LEVELS}
        out[fam] = FamilyThresholds(levels, partial=fam in partial_families)
    return out


def axis_resamples(summaries: Sequence[CellSummary], res: iv.Resamples | None,
                   groups: FamilyGroups) -> iv.AxisResamples:
    """The axes in every resample (all None without resamples)."""
    if res is None:
        return iv.AxisResamples()
    s5 = {fam: cells[5] for fam, cells in _curves(summaries).items() if 5 in cells}
    return iv.axes_per_resample(res, s5, groups.quality, groups.removal, groups.core)


def run_verdict(on: Axes, per: iv.AxisResamples, *, metric: str, flat: float,
                basis: iv.Basis | None = None, reliance: Reliance | None = None) -> Verdict:
    """The label from the axes the verdict is put on (`on`), read beside the plans' movement (`reliance`:
    ``reliance.read_movement``), with the ego label and, on L2, its confidence (the resamples are of L2
    retention; the share of them giving the axes' label) and a borderline flag; no confidence where the `basis`
    cannot support one (too few scenes: `Basis.confidence_reason`, said in the text)."""
    by_axes = verdict(on, flat)
    v = read_movement(by_axes, on, reliance)
    text = {"pdms": "On PDMS retention: ", "epdms": "On EPDMS retention: ",
            "epdms2": "On two-stage EPDMS retention: "}.get(metric, "") + v.text
    confidence = iv.verdict_confidence(by_axes.label, per.quality, per.removal, flat) \
        if per.quality is not None and metric == "l2" else None
    withheld = None if basis is None or confidence is None else basis.confidence_reason
    if withheld is not None:
        confidence = None
        text += f" No confidence is stated: {withheld}."
    borderline = confidence is not None and confidence < iv.BORDERLINE
    if borderline and confidence is not None:
        text += iv.borderline_text(confidence)
    return replace(v, text=text, metric=metric, ego_label=ego_label(on.ego_removal, flat), confidence=confidence,
                   borderline=borderline)


def analysis_settings(*, convention: str, kind: str, flat: float, seed: int, seeds: int, n_resamples: int,
                      metric: str, res: iv.Resamples | None, basis: iv.Basis | None = None) -> dict[str, Any]:
    """The settings the figures were computed under, as the certificate records them."""
    return {"seed": int(seed), "convention": convention, "metric": "l2_avg", "kind": kind, "flat": float(flat),
            "n_resamples": int(n_resamples), "confidence": 0.95, "threshold_levels": dict(THRESHOLD_LEVELS),
            "tolerance_default": DEFAULT_TOLERANCE, "verdict_metric": metric, "seeds": int(seeds),
            "seed_values": [int(seed) + k for k in range(int(seeds))],
            "intervals": {"computed": res is not None, "scheme": _scheme(res, basis),
                          "percentile": "linear" if basis is None or basis.clusters is None else
                          "linear, expanded levels (Hesterberg 2015) for the scene count",
                          "never": "+inf (null bound)", **({} if basis is None else basis.to_builtins())}}


def _scheme(res: iv.Resamples | None, basis: iv.Basis | None) -> str:
    """How a resample is drawn, in words: the seeds level (several seeds) then scenes or frames."""
    unit = "scenes (frames whole)" if basis is not None and basis.units == "scenes" else "paired frames"
    if res is not None and res.n_seeds > 1:
        return "seeds then " + ("scenes (frames whole)" if unit.startswith("scenes") else "frames")
    return unit


def _seed_ci(res: iv.Resamples | None, record: CellRecord) -> tuple[float, float] | None:
    """A multi-seed cell's CI from the two-level bootstrap (None for a one-run cell: it keeps its own)."""
    if not record.seed_runs or res is None or record.cell not in res.retention:
        return None
    got = iv.percentile_interval(res.retention[record.cell], clusters=res.clusters)
    if got is None:
        return math.nan, math.nan
    return (math.nan if got[0] is None else got[0]), (math.inf if got[1] is None else got[1])
