"""The controller's end of a run (the controller process only, never an xdist worker): gather the cells, compute
the analysis and the floor, write the outputs, apply the baseline gate, and return the terminal summary's lines.
Never raises for a user mistake."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import pytest

from ..cells import CellPayload, CellRecord, cell_id
from ..errors import DriveDegradeError
from ..report.certificate import Provenance
from ..run import RunContext
from ..store import ResultStore
from .context import cache_root
from .options import RunOptions


@dataclass
class Outcome:
    """What the end of a run says (`lines`, for the terminal summary) and whether it fails the session."""

    lines: list[str] = field(default_factory=list)
    failed: bool = False


@dataclass(frozen=True)
class Gathered:
    """This session's cells plus the stored ones of the same run (same planner and run key)."""

    planner: str
    key: Mapping[str, Any]
    payloads: dict[str, CellPayload]
    missing: list[str]


def gather(received: Mapping[str, CellPayload], expected: Sequence[tuple[str, int]],
           store: ResultStore) -> Gathered | None:
    """The run's payloads: those received this session (keyed like clean's, or the first one's) plus stored
    results of the same run for the expected cells not received; and the expected cells neither has. None when
    no cell finished."""
    if not received:
        return None
    first = received.get("clean") or next(iter(received.values()))
    payloads = {c: p for c, p in received.items() if dict(p.key) == dict(first.key)}
    ids = [cell_id(f, s) for f, s in expected]
    stored = store.read_all(first.planner, first.key, [c for c in ids if c not in payloads])
    payloads = {**stored, **payloads}
    return Gathered(first.planner, first.key, payloads, [c for c in ids if c not in payloads])


def floor_l2(config: pytest.Config, context: RunContext, split: str, lines: list[str],
             ego: dict[str, float] | None = None) -> float | None:
    """The ego-only floor's clean l2_avg on the scored frames (trained on the train split once, cached); with
    `ego`, also its ego_blind retention there (``ego["ego_removal"]``, for the reliance chart)."""
    from ..scoring.floor import load_or_train_floor, train_split_for
    from ..scoring.records import finite_mean

    try:
        train = context.reader.with_split(train_split_for(split))
        if not any(f.scorable for f in train.frames()):  # lazily: stops at the first scorable frame
            lines.append(f"ego-only floor: skipped, split {train.split!r} has no scorable frames")
            return None
        model = load_or_train_floor(train, cache_root(config) / "floor")
    except DriveDegradeError as exc:
        lines.append(f"ego-only floor: skipped ({exc})")
        return None
    clean = finite_mean(context.run_cell(model, "clean", 0).l2_avg_per_frame())
    if ego is not None:
        from ..scoring.retention import retention

        blind = finite_mean(context.run_cell(model, "ego_blind", 0).l2_avg_per_frame())
        ego["ego_removal"] = float(retention(clean, blind))
    return clean


def provenance(options: RunOptions, context: RunContext, name: str, key: Mapping[str, Any],
               command: str) -> Provenance:
    """What makes the run traceable, for the certificate and cells.csv."""
    from .. import __version__
    from ..corruptions.ladder import SPEC_VERSION

    source = "embedded world" if options.data is None else str(options.data)
    return Provenance(planner_name=name, planner_fingerprint=str(key["planner_fingerprint"]),
                      dataset_fingerprint=str(key["dataset_fingerprint"]), split=options.split,
                      spec_version=SPEC_VERSION, seed=options.seed, frames=len(context.frames),
                      frames_unscored=context.frames_unscored, data_source=source, command=command,
                      tool_version=__version__)


def finish_run(config: pytest.Config, options: RunOptions, context: RunContext | None,
               received: Mapping[str, CellPayload], expected: Sequence[tuple[str, int]],
               baseline: Mapping[str, Any] | None) -> Outcome | None:
    """Analyse and write everything the run has; None when the run never opened its data."""
    if context is None:
        return None
    out = Outcome()
    run = gather(received, expected, ResultStore(options.report_dir))
    if run is None:
        out.lines.append("no cell finished: nothing to analyse")
        return out
    if "clean" not in run.payloads:  # not a failure: the cells that ran are stored, and a later run completes them
        out.lines.append("no clean cell result, so no report written: retention is relative to clean (was it "
                         "deselected with -k?); the cells that ran are stored and reused by a run that includes "
                         "clean")
        return out
    from ..report.outputs import write_outputs
    from ..report.terminal import summary_lines
    from ..scoring.verdict import analyse_run

    floor_ego: dict[str, float] = {}
    floor = floor_l2(config, context, options.split, out.lines, floor_ego if options.ego else None)
    records: dict[str, CellRecord] = {c: p.record for c, p in run.payloads.items()}
    analysis = analyse_run(records.values(), flat=options.flat, seed=options.seed, floor_l2=floor,
                           metric=options.metric)
    analysis.floor.update(floor_ego)
    command = "pytest " + " ".join(str(a) for a in config.invocation_params.args)
    prov = provenance(options, context, run.planner, run.key, command)
    cert, written = write_outputs(options.report_dir, prov, context, records, analysis, run.missing)
    out.lines.append(written)
    from .compat import junit_xml

    xml = junit_xml(config)
    if xml is not None:
        from ..report.junit import suite_properties

        for prop, value in suite_properties(analysis):
            xml.add_global_property(prop, value)
    gate_lines, out.failed = gate(cert, baseline, options.tolerance)
    out.lines = summary_lines(analysis, run.missing) + out.lines + gate_lines
    return out


def gate(cert: Mapping[str, Any], baseline: Mapping[str, Any] | None, tolerance: float) -> tuple[list[str], bool]:
    """--drivedegrade-baseline: (lines, failed); an axis that regressed fails the session (cells fail in their
    own items)."""
    if baseline is None:
        return [], False
    from ..scoring.baseline import BaselineError, compare_to_baseline

    try:
        result = compare_to_baseline(cert, baseline, tolerance)
    except BaselineError as exc:
        return [f"baseline: {exc}"], True
    lines = [f"REGRESSION {reg.message()}" for reg in result["axes"]]
    lines.append(f"baseline: {len(result['cells'])} cell and {len(result['axes'])} axis regression(s) beyond "
                 f"tolerance {tolerance:g}")
    return lines, bool(result["axes"])
