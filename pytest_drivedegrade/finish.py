"""The controller's end of a run: gather the cells, compute the analysis and the floor, write the outputs,
apply the baseline gate, and say it all in a short terminal summary. Never raises for a user mistake."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from .options import RunOptions


@dataclass
class Outcome:
    lines: list[str] = field(default_factory=list)
    failed: bool = False


def cache_root(config: pytest.Config) -> Path:
    """pytest's cache folder for the world and the floor, or a folder under rootdir with -p no:cacheprovider."""
    cache = getattr(config, "cache", None)
    return Path(cache.mkdir("drivedegrade")) if cache is not None else Path(config.rootpath) / ".drivedegrade-cache"


def open_run_context(config: pytest.Config, options: RunOptions):
    """The data (the embedded world unless --drivedegrade-data) indexed, and the frames to score chosen."""
    from .run import open_context

    root = options.data
    if root is None:
        from .data.world import ensure_default_world

        root = ensure_default_world(cache_root(config),
                                    progress=lambda s: print(f"drivedegrade: {s}", file=sys.stderr, flush=True))
    return open_context(data_root=root, split=options.split, frames=options.frames, seed=options.seed,
                        timeout=options.timeout, planner_path=options.planner_path)


def _floor_l2(config: pytest.Config, context: Any, split: str, lines: list[str]) -> float | None:
    """The ego-only floor's clean l2_avg on the scored frames (trained on the train split once, cached)."""
    from .analysis import _finite_mean
    from .errors import DriveDegradeError
    from .floor import load_or_train_floor, train_split_for

    try:
        train = context.reader.with_split(train_split_for(split))
        if not any(f.scorable for f in train.frames()):  # lazily: stops at the first scorable frame
            lines.append(f"ego-only floor: skipped, split {train.split!r} has no scorable frames")
            return None
        model = load_or_train_floor(train, cache_root(config) / "floor")
    except DriveDegradeError as exc:
        lines.append(f"ego-only floor: skipped ({exc})")
        return None
    return _finite_mean(context.run_cell(model, "clean", 0).l2_avg_per_frame())


def _gather(plugin: Any) -> tuple[str | None, dict[str, Any], dict[str, dict[str, Any]], list[str]]:
    """(planner name, run key, cell -> payload, missing cells): this session's cells plus stored ones of the
    same run, and the expected cells that neither has."""
    from .loader import cell_id
    from .store import ResultStore

    payloads = dict(plugin.records)
    if not payloads:
        return None, {}, {}, []
    first = payloads.get("clean") or next(iter(payloads.values()))
    name, key = first["planner"], first["key"]
    payloads = {c: p for c, p in payloads.items() if p["key"] == key}
    expected = [cell_id(f, s) for f, s in plugin.cells()]
    stored = ResultStore(plugin.options.report_dir).read_all(name, key, [c for c in expected if c not in payloads])
    payloads = {**stored, **payloads}
    return name, key, payloads, [c for c in expected if c not in payloads]


def finish_run(plugin: Any, session: pytest.Session) -> Outcome | None:
    """Analyse and write everything the run has; an Outcome whose lines go into the terminal summary."""
    out = Outcome()
    context = plugin.context
    if context is None:
        return None
    name, key, payloads, missing = _gather(plugin)
    if name is None:
        out.lines.append("no cell finished: nothing to analyse")
        return out
    if "clean" not in payloads:  # not a failure: the cells that ran are stored, and a later run completes them
        out.lines.append("no clean cell result, so no report written: retention is relative to clean (was it "
                         "deselected with -k?); the cells that ran are stored and reused by a run that includes "
                         "clean")
        return out
    from .analysis import CellRecord, analyse_run
    from .outputs import write_outputs

    floor_l2 = _floor_l2(plugin.config, context, plugin.options.split, out.lines)
    records = {c: CellRecord.from_builtins(p["record"]) for c, p in payloads.items()}
    analysis = analyse_run(records.values(), flat=plugin.options.flat, seed=plugin.options.seed,
                           floor_l2=floor_l2)
    cert = write_outputs(plugin, session, context, name, key, records, analysis, out, missing)
    _gate(plugin, cert, out)
    out.lines = _summary(analysis, missing) + out.lines
    return out


def _gate(plugin: Any, cert: dict[str, Any], out: Outcome) -> None:
    """--drivedegrade-baseline: an axis that regressed fails the session (cells fail in their own items)."""
    if plugin.baseline is None:
        return
    from .analysis import BaselineError, compare_to_baseline

    try:
        result = compare_to_baseline(cert, plugin.baseline, plugin.options.tolerance)
    except BaselineError as exc:
        out.lines.append(f"baseline: {exc}")
        out.failed = True
        return
    for reg in result["axes"]:
        out.lines.append(f"REGRESSION {reg.message()}")
        out.failed = True
    out.lines.append(f"baseline: {len(result['cells'])} cell and {len(result['axes'])} axis regression(s) beyond "
                     f"tolerance {plugin.options.tolerance:g}")


def _fmt(value: Any) -> str:
    return "n/a" if value is None or (isinstance(value, float) and not math.isfinite(value)) else f"{value:.3f}"


def _retention_table(analysis: Any) -> list[str]:
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
        cells = "".join(f"{_fmt(row.get(s)):>7s}" for s in severities)
        marks = "".join(f"{('-' if t.get(k) is None else format(t[k], '.2f')):>7s}" for k in ("s10", "s25"))
        lines.append(f"{family:15s}{cells}{marks}")
    return lines


def _summary(analysis: Any, missing: list[str]) -> list[str]:
    """The terminal summary's head: verdict, axes, controls, floor, the retention table, missing cells."""
    ax, verdict = analysis.axes, analysis.verdict
    lines = [f"verdict: {verdict['label']} - {verdict['text']}",
             f"axes: quality {_fmt(ax.get('quality'))}  removal {_fmt(ax.get('removal'))}  "
             f"gap {_fmt(ax.get('gap'))}  mean {_fmt(ax.get('mean'))}"]
    nc = analysis.null_control
    if nc is not None:
        lines.append(f"null control: {'passed' if nc['passed'] else 'FAILED'} (max abs diff {nc['max_abs_diff']:.3g} m)")
    clean = next((s for s in analysis.summaries if s.cell == "clean"), None)
    floor = (analysis.floor or {}).get("l2_avg")
    if clean is not None:
        lines.append(f"clean l2_avg {_fmt(clean.l2_avg)} m; ego-only floor l2_avg {_fmt(floor)} m")
    lines += _retention_table(analysis)
    if missing:
        lines.append(f"missing cells ({len(missing)}): {', '.join(missing)}; rerun the same command to "
                     "compute only these (finished cells are reused)")
    return lines
