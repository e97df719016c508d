"""The terminal summary: verdict, axes, controls, floor, the family x severity retention table, missing cells."""

from __future__ import annotations

from collections.abc import Sequence

from ..scoring.records import RunAnalysis, format_value


def format_interval(ci: Sequence[float | None] | None, digits: int = 3, never: str = "never") -> str:
    """[low, high] for people; an open (null) bound reads `never` (a threshold not reached in those resamples)."""
    if not ci:
        return "n/a"
    low, high = (never if v is None else f"{v:.{digits}f}" for v in ci)
    return f"[{low}, {high}]"


def interval_lines(analysis: RunAnalysis) -> list[str]:
    """The intervals of the axes, the verdict's confidence and the thresholds' intervals (issue 15)."""
    ax, verdict = analysis.axes, analysis.verdict
    if verdict.get("confidence") is None and all(ax.get(f"{k}_ci") is None for k in ("quality", "removal")):
        return []
    n = analysis.settings.get("n_resamples")
    seeds = analysis.settings.get("seeds", 1)
    how = f"{n} paired resamples" + (f" over frames and {seeds} seeds" if seeds and seeds > 1 else " of frames")
    lines = ["axes 95% intervals: " + "  ".join(f"{k} {format_interval(ax.get(f'{k}_ci'))}"
                                                  for k in ("quality", "removal", "gap", "mean"))]
    if verdict.get("confidence") is not None:
        state = "BORDERLINE" if verdict.get("borderline") else "stable"
        lines.append(f"verdict confidence: {verdict['confidence']:.3f} ({state}; share of {how} giving this label)")
    rows = [(fam, t) for fam, t in analysis.thresholds.items() if t.get("s10_ci") is not None or
            t.get("s25_ci") is not None]
    if rows:
        lines.append(f"{'thresholds 95%':15s}{'s*10':>16s}{'never':>7s}{'s*25':>16s}{'never':>7s}")
        for fam, t in rows:
            lines.append(f"{fam:15s}" + "".join(
                f"{format_interval(t.get(k + '_ci'), 2):>16s}{format_value(t.get(k + '_never'), 2):>7s}"
                for k in ("s10", "s25")))
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
    head = f"{'retention':15s}" + "".join(f"{'S' + str(s):>7s}" for s in severities) + f"{'s*10':>7s}{'s*25':>7s}"
    lines = [head]
    for family, row in by_family.items():
        t = analysis.thresholds.get(family, {})
        cells = "".join(f"{format_value(row.get(s)):>7s}" for s in severities)
        marks = "".join(f"{('-' if t.get(k) is None else format(t[k], '.2f')):>7s}" for k in ("s10", "s25"))
        lines.append(f"{family:15s}{cells}{marks}")
    return lines


def pdms_ego_lines(analysis: RunAnalysis) -> list[str]:
    """The axes on PDMS retention (spec 3) and the ego axis with its label (SPEC section 10)."""
    ap, ax = analysis.axes_pdms or {}, analysis.axes
    lines = []
    if ap:
        lines.append(f"axes (PDMS): quality {format_value(ap.get('quality'))}  removal "
                     f"{format_value(ap.get('removal'))}  gap {format_value(ap.get('gap'))}  mean "
                     f"{format_value(ap.get('mean'))}")
    if ax.get("ego") is not None or ax.get("ego_removal") is not None:
        lines.append(f"ego: ego_noise S5 {format_value(ax.get('ego'))}  ego_blind "
                     f"{format_value(ax.get('ego_removal'))} -> {analysis.verdict.get('ego_label', 'undetermined')}")
    return lines


def summary_lines(analysis: RunAnalysis, missing: Sequence[str]) -> list[str]:
    """The terminal summary's head: verdict, axes, controls, floor, the retention table, missing cells."""
    ax, verdict = analysis.axes, analysis.verdict
    lines = [f"verdict: {verdict['label']} - {verdict['text']}",
             f"axes: quality {format_value(ax.get('quality'))}  removal {format_value(ax.get('removal'))}  "
             f"gap {format_value(ax.get('gap'))}  mean {format_value(ax.get('mean'))}"]
    lines += pdms_ego_lines(analysis)
    if verdict.get("reason"):
        lines.append(f"UNDETERMINED by failed frames: {verdict['reason']}")
    nc = analysis.null_control
    if nc is not None and nc.get("passed") is None:
        lines.append("null control: not run (no frame produced a plan in both clean and null)")
    elif nc is not None:
        state = "passed" if nc["passed"] else "FAILED"
        lines.append(f"null control: {state} (max abs diff {nc['max_abs_diff']:.3g} m)")
    clean = next((s for s in analysis.summaries if s.cell == "clean"), None)
    floor = (analysis.floor or {}).get("l2_avg")
    if clean is not None:
        lines.append(f"clean l2_avg {format_value(clean.l2_avg)} m; ego-only floor l2_avg {format_value(floor)} m")
    lines += retention_table(analysis)
    lines += interval_lines(analysis)
    if missing:
        lines.append(f"missing cells ({len(missing)}): {', '.join(missing)}; rerun the same command to "
                     "compute only these (finished cells are reused)")
    return lines
