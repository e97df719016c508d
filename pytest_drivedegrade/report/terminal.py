"""The terminal summary: verdict, axes, controls, floor, the family x severity retention table, missing cells."""

from __future__ import annotations

import math
from collections.abc import Sequence

from ..constants import WORSE_FACTOR, WORSE_MARGIN
from ..scoring.records import AXES, Axes, FamilyThresholds, RunAnalysis, format_value
from ..scoring.retention import THRESHOLD_LEVELS


def format_interval(ci: Sequence[float | None] | None, digits: int = 3, never: str = "never") -> str:
    """[low, high] for people; an open (null) bound reads `never` (a threshold not reached in those resamples)."""
    if not ci:
        return "n/a"
    low, high = (never if v is None else f"{v:.{digits}f}" for v in ci)
    return f"[{low}, {high}]"


def interval_lines(analysis: RunAnalysis) -> list[str]:
    """The intervals of the axes, the verdict's confidence and the thresholds' intervals (issue 15)."""
    ax, verdict = analysis.axes, analysis.verdict
    if verdict.confidence is None and ax.interval("quality") is None and ax.interval("removal") is None:
        return []
    n = analysis.settings.get("n_resamples")
    seeds = analysis.settings.get("seeds", 1)
    basis = analysis.settings.get("intervals", {}).get("basis")
    unit = "scenes" if str(basis).startswith("scene") else "frames"
    how = f"{n} paired resamples" + (f" over {unit} and {seeds} seeds" if seeds and seeds > 1 else f" of {unit}")
    lines = ["axes 95% intervals: " + "  ".join(f"{k} {format_interval(ax.interval(k))}" for k in AXES),
             f"interval basis: {basis or 'frame bootstrap'}"]
    reason = analysis.settings.get("intervals", {}).get("confidence_reason")
    if verdict.confidence is None and reason:
        lines.append(f"verdict confidence: not stated ({reason})")
    if verdict.confidence is not None:
        state = "BORDERLINE" if verdict.borderline else "stable"
        lines.append(f"verdict confidence: {verdict.confidence:.3f} ({state}; share of {how} giving this label)")
    rows = [(fam, t) for fam, t in analysis.thresholds.items() if any(x.ci is not None for x in t.levels.values())]
    if rows:
        lines.append(f"{'thresholds 95%':15s}" + "".join(f"{'s*' + k[1:]:>16s}{'never':>7s}" for k in THRESHOLD_LEVELS))
        for fam, t in rows:
            lines.append(f"{fam:15s}" + "".join(f"{format_interval(x.ci, 2):>16s}{format_value(x.never, 2):>7s}"
                                                for x in t.levels.values()))
    return lines


def retention_table(analysis: RunAnalysis) -> list[str]:
    """Family x severity retention, with s*10 / s*25, as fixed-width lines."""
    by_family: dict[str, dict[int, float]] = {}
    for summary in analysis.summaries:
        if summary.severity > 0:
            by_family.setdefault(summary.family, {})[summary.severity] = summary.retention
    if not by_family:
        return []
    severities = sorted({s for row in by_family.values() for s in row})
    head = f"{'retention':15s}" + "".join(f"{'S' + str(s):>7s}" for s in severities) + \
        "".join(f"{'s*' + k[1:]:>7s}" for k in THRESHOLD_LEVELS)
    lines = [head]
    for family, row in by_family.items():
        t = analysis.thresholds.get(family)
        cells = "".join(f"{format_value(row.get(s)):>7s}" for s in severities)
        # a family without thresholds (the ego cells, a ladder cut short) reads n/a; a threshold never crossed
        # on the ladder reads never, as in the thresholds table: one mark, one meaning
        marks = "".join(f"{_threshold_mark(t, k):>7s}" for k in THRESHOLD_LEVELS)
        lines.append(f"{family:15s}{cells}{marks}")
    return lines


def _threshold_mark(thresholds: FamilyThresholds | None, level: str) -> str:
    """A family's s* at `level`: its severity, `never` where the ladder never crosses it, `n/a` without one."""
    if thresholds is None:
        return "n/a"
    value = thresholds.levels[level].value
    return "never" if value is None else format(value, ".2f")


def _axes_line(axes: Axes) -> str:
    return "  ".join(f"{k} {format_value(axes.value(k))}" for k in AXES)


def pdms_ego_lines(analysis: RunAnalysis) -> list[str]:
    """The axes on PDMS retention (spec 3) and the ego axis with its label (SPEC section 10)."""
    ax = analysis.axes
    lines = [f"axes (PDMS): {_axes_line(analysis.axes_pdms)}"]
    if analysis.axes_epdms is not None:
        lines.append(f"axes (EPDMS): {_axes_line(analysis.axes_epdms)}")
    if analysis.axes_epdms2 is not None:
        lines.append(f"axes (two-stage EPDMS): {_axes_line(analysis.axes_epdms2)}")
    if ax.ego is not None or ax.ego_removal is not None:
        lines.append(f"ego: ego_noise S5 {format_value(ax.ego)}  ego_blind "
                     f"{format_value(ax.ego_removal)} -> {analysis.verdict.ego_label}")
    if analysis.reliance is not None:
        from .profile import command_retention, profile_lines

        lines += ["reliance profile (plan movement against the null's wander, and accuracy):",
                  *profile_lines(analysis.reliance, ax, analysis.verdict.flat, command_retention(analysis.summaries),
                                None if analysis.command is None else analysis.command.following)]
    return lines




def floor_warning(analysis: RunAnalysis) -> str | None:
    """The loud warning for a planner far worse than the ego-only floor on clean frames (issue 20, new user:
    3.30 m against the floor's 0.34 m), or None. Not a verdict: the figures stay as measured."""
    clean = next((s.l2_avg for s in analysis.summaries if s.cell == "clean"), None)
    floor = analysis.floor.l2_avg
    if clean is None or floor is None or not (math.isfinite(clean) and math.isfinite(floor)) or floor <= 0:
        return None
    if clean <= WORSE_FACTOR * floor or clean - floor <= WORSE_MARGIN:
        return None
    return (f"WARNING: the planner is far worse than the ego-only floor on clean frames (clean L2 {clean:.3f} m, "
            f"floor {floor:.3f} m, {clean / floor:.1f}x): a planner of ego status and command alone, no camera, "
            "plans closer to the logged path on these frames. That is all this figure knows. Causes include a "
            "miswired adapter (camera order, RGB/BGR colour order, units in metres or pixels, the ego frame's axes, "
            "the trajectory's time steps), weights trained on other data or too briefly, or a planner that is "
            "simply weaker than ego status on open-loop L2 (perception-free planners often are). Retention then "
            "measures how a weak planner's error changes: read it beside how far its plans move (the reliance "
            "profile).")


def summary_lines(analysis: RunAnalysis, missing: Sequence[str], advice: str = "") -> list[str]:
    """The terminal summary's head: verdict, axes, controls, floor, the retention table, missing cells (with
    `advice`, what to do about them; by default rerunning the same command)."""
    verdict = analysis.verdict
    lines = [f"verdict: {verdict.label} - {verdict.text}", f"axes: {_axes_line(analysis.axes)}"]
    lines += pdms_ego_lines(analysis)
    if verdict.reason:
        by = {"null-control-failed": "the null control", "blind-equals-clean": "the memo check (blind equals clean)"}
        lines.append(f"UNDETERMINED by {by.get(verdict.case, 'failed frames')}: {verdict.reason}")
    nc = analysis.null_control
    if nc is not None and nc.passed is None:
        lines.append("null control: not run (no frame produced a plan in both clean and null)")
    elif nc is not None:
        state = "passed" if nc.passed else "FAILED"
        lines.append(f"null control: {state} (max abs diff {nc.max_abs_diff:.3g} m)")
    clean = next((s for s in analysis.summaries if s.cell == "clean"), None)
    if clean is not None:
        lines.append(f"clean l2_avg {format_value(clean.l2_avg)} m; ego-only floor l2_avg "
                     f"{format_value(analysis.floor.l2_avg)} m")
    warning = floor_warning(analysis)
    if warning:
        lines.insert(1, warning)  # beside the verdict, not lost below the table
    lines += retention_table(analysis)
    lines += interval_lines(analysis)
    if missing:
        lines.append(f"missing cells ({len(missing)}): {', '.join(missing)}; " + (advice or "rerun the same "
                     "command to compute only these (finished cells are reused)"))
    return lines
