"""The controller's end of a run (the controller process only, never an xdist worker): gather the cells, run the
floor, build the `FinishedRun` that `report.publish` writes (a shard writes its manifest instead), apply the
baseline gate, and return the terminal summary's lines. Never raises for a user mistake."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from ..cells import cell_id
from ..certificate.finished import FinishedRun, FloorFigures
from ..certificate.seal import Provenance, run_provenance
from ..errors import DriveDegradeError
from ..payload import CellPayload
from ..run import RunContext
from ..store import ResultStore
from .closed import ClosedInput, closed_run
from .egofloor import FloorAhead, floor_of_run
from .options import RunOptions

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from ..cells import CellRecord
    from ..certificate.closed import ClosedRun
    from ..scoring.sequential import UnitPlan


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


def reuse_lines(received: Mapping[str, CellPayload], run: Gathered, store: ResultStore) -> list[str]:
    """Which cells were reused from the store rather than computed, and which stored cells were recomputed
    because their record no longer hashed to its recorded digest (edited or corrupted on disk)."""
    reused = sorted(c for c, p in run.payloads.items() if c not in received or p.resumed)
    failed = {c: p.recomputed for c, p in received.items() if p.recomputed}
    failed.update({c: why for c, why in store.digest_failures.items() if c not in failed})
    lines = []
    if reused:
        lines.append(f"reused {len(reused)} stored cell(s) (same run key, digest verified): {', '.join(reused)}")
    if failed:
        lines.append(f"recomputed {len(failed)} stored cell(s) whose content digest failed (edited or corrupted "
                     f"on disk): {', '.join(sorted(failed))}")
    stale: dict[str, list[str]] = {}
    for c, p in received.items():
        if p.stale and not p.resumed:
            stale.setdefault(p.stale, []).append(c)
    for fields, cells in sorted(stale.items()):
        why = " (the scored frames' files changed)" if "dataset_fingerprint" in fields else \
            " (they took the clean plan on some frames; this run has --drivedegrade-no-reuse)" if fields == "reuse" \
            else ""
        lines.append(f"not reused: {len(cells)} stored cell(s) recomputed because their run key differs in "
                     f"{fields}{why}: {', '.join(sorted(cells))}")
    return lines


def planner_file(config: pytest.Config, path: Path) -> str:
    """The planner file (or conftest.py) as the certificate records it: relative to rootdir when inside it, so
    a moved checkout keeps it; else only its name (`shown_path`: no absolute path is published)."""
    from ..settings import shown_path

    return shown_path(path.resolve(), Path(config.rootpath))


def provenance(config: pytest.Config, options: RunOptions, context: RunContext, run: Gathered,
               planner_file: str = "") -> Provenance:
    """What makes the run traceable, for the certificate, cells.csv and a shard's manifest."""
    return run_provenance(options.settings, planner_name=run.planner, key=run.key, frames=len(context.frames),
                          frames_unscored=context.frames_unscored, command=_command(config),
                          planner_file=planner_file, root=Path(config.rootpath))


def coverage_lines(path: Path | None) -> list[str]:
    """Which modules besides the planner file its fingerprint covers (`planning.covered_modules`), when any: a
    change to them recomputes the stored cells; a change to anything else (installed packages, data) does not."""
    if path is None or not path.is_file():
        return []
    from ..planning import covered_modules

    extra = covered_modules(path)[1:]
    return [f"planner fingerprint covers {path.name} and {len(extra)} module(s) it imports from outside "
            f"site-packages: {', '.join(p.name for p in extra)}"] if extra else []


def finish_run(config: pytest.Config, options: RunOptions, context: RunContext | None,
               received: Mapping[str, CellPayload], expected: Sequence[tuple[str, int]],
               baseline: Mapping[str, object] | None, store: ResultStore | None = None, planner_file: str = "",
               signing_key: Ed25519PrivateKey | None = None, closed: ClosedInput | None = None, *,
               floor: FloorAhead | None = None) -> Outcome | None:
    """Analyse and write everything the run has (a shard writes its manifest for the merge instead); None when
    the run never opened its data. `planner_file` goes into the certificate, signed with `signing_key` when
    given; `closed`: the closed-loop cells received and expected (SPEC 13); `floor`: `egofloor.start_floor`'s."""
    if context is None:
        return None
    out = Outcome()
    store = store or ResultStore(options.report_dir, resume=options.resume)
    run = gather(received, expected, store)
    closed_cells = closed_run(options.settings, store, closed)
    if run is None and closed_cells is not None:  # --drivedegrade-loop closed: the closed cells alone
        first = next(iter(closed_cells.payloads.values()))
        run = Gathered(first.planner, first.key, {}, [])
    if run is None:
        out.lines.append("no cell finished: nothing to analyse")
        return out
    out.lines += reuse_lines(received, run, store) + coverage_lines(options.planner_path)
    if options.settings.shard is not None:
        return finish_shard(config, options, context, run, store, out, expected, planner_file, closed, floor)
    if closed_cells is not None and not run.payloads:
        finished = finished_run(config, options, context, run, out.lines, planner_file, closed_cells, floor)
        from ..report.publish import publish

        out.lines = publish(finished, options.report_dir, signing_key=signing_key).lines
        return out
    if "clean" not in run.payloads:  # not a failure: the cells that ran are stored, and a later run completes them
        out.lines.append("no clean cell result, so no report written: retention is relative to clean (was it "
                         "deselected with -k?); the cells that ran are stored and reused by a run that includes "
                         "clean")
        return out
    from ..report.publish import publish

    finished = finished_run(config, options, context, run, out.lines, planner_file, closed_cells, floor)
    published = publish(finished, options.report_dir, signing_key=signing_key)
    from .compat import junit_xml

    xml = junit_xml(config)
    if xml is not None:
        from ..report.junit import suite_properties

        for prop, value in suite_properties(published.analysis) if published.analysis else ():
            xml.add_global_property(prop, value)
    if options.settings.adaptive and baseline is not None:
        gate_lines, out.failed = sequential_gate(options, context, run, published.certificate, baseline)
    elif baseline is not None and isinstance(baseline.get("adaptive"), Mapping):  # its intervals, not its points
        from ..scoring.seqgate import interval_gate, interval_lines

        why = incompatible(published.certificate, baseline)
        result = interval_gate(published.certificate, baseline, options.tolerance)
        gate_lines, out.failed = ([f"baseline: {why}"], True) if why else \
            (interval_lines(result, options.tolerance, baseline), result.failed)
    else:
        gate_lines, out.failed = gate(published.certificate, baseline, options.tolerance,
                                      partial=options.baseline_partial, any_planner=options.baseline_any_planner)
    out.lines = published.lines + gate_lines
    return out


def finished_run(config: pytest.Config, options: RunOptions, context: RunContext, run: Gathered,
                 notes: list[str], planner_file: str = "", closed: ClosedRun | None = None,
                 ahead: FloorAhead | None = None) -> FinishedRun:
    """This session's run as `report.publish` takes it (the floor is run here, or taken from `ahead`, for open
    cells; its notes join `notes`); with its closed-loop cells."""
    floor = floor_of_run(config, options, context, notes, ahead) if run.payloads else None
    adaptive = adaptive_section(options, context, run, notes)
    return FinishedRun(records={c: p.record for c, p in run.payloads.items()},
                       provenance=provenance(config, options, context, run, planner_file),
                       settings=options.settings, floor=FloorFigures() if floor is None else floor.figures(),
                       gt={f.token: f.gt_future for f in context.frames}, front=front_image(context),
                       scenes={f.token: f.scene_token for f in context.frames},
                       missing_cells=tuple(run.missing),
                       resumed_cells=tuple(c for c, p in run.payloads.items() if p.resumed), notes=tuple(notes),
                       closed=closed, adaptive=adaptive,
                       digests={c: p.digest for c, p in run.payloads.items() if p.digest})



def adaptive_section(options: RunOptions, context: RunContext, run: Gathered,
                     notes: list[str]) -> dict[str, object] | None:
    """--drivedegrade-adaptive: the certificate's ``adaptive`` section from the run's records, and a line saying
    what the run spent against a full run (None for a full run)."""
    if not options.settings.adaptive or "clean" not in run.payloads:
        return None
    from ..cells import run_order
    from ..scoring import sequential
    from ..scoring.verdict import FamilyGroups

    groups = FamilyGroups.from_registry()
    records = {c: p.record for c, p in run.payloads.items()}
    plan = run_plan(options, context, run)
    cells = run_order(options.families, options.severities, ego=options.ego)
    section = sequential.adaptive_section(
        records, plan, cells, alpha=options.settings.alpha, flat=options.settings.flat, quality=groups.quality,
        removal=groups.removal, rule="certify" if options.baseline_path is None else "gate")
    if options.baseline_path is not None:  # what verify needs to recompute the gate's stops (`seqgate.gate_record`)
        section["gate"] = gate_part(options, records, plan, 2 * sequential.alpha_side(options.settings.alpha, cells))
    notes.append(sequential.summary_line(section))
    return section


def run_plan(options: RunOptions, context: RunContext, run: Gathered) -> UnitPlan:
    """The unit plan the run's cells used: the kind read off clean's unit count, the draw seed from the planner's
    fingerprint (the run key's) and, in a gate run, the baseline's digest (`sequential.draw_seed`)."""
    from ..scoring.sequential import UnitPlan
    from .adaptive import baseline_digest

    units = int(run.payloads["clean"].record.units or 0)
    base = None if options.baseline_path is None else baseline_digest(options.baseline_path)
    return UnitPlan.matching(context.frames, context.seed, units, str(run.key.get("planner_fingerprint", "")), base)


def gate_part(options: RunOptions, records: Mapping[str, CellRecord], plan: UnitPlan,
              alpha: float) -> dict[str, object]:
    """A gate run's ``adaptive.gate``: the baseline's digest, the tolerance, the level each cell's test ran at and
    per cell its test's parts (`seqgate.gate_record`, from the baseline's cells/ beside its certificate)."""
    from ..certificate.adaptive_check import load_records
    from ..scoring.seqgate import gate_record

    assert options.baseline_path is not None
    base, _ = load_records(options.baseline_path.parent / "cells", sorted(records), {})
    try:
        digest = json.loads(options.baseline_path.read_text()).get("digest")
    except (OSError, ValueError, AttributeError):
        digest = None
    return {"baseline_digest": digest, "tolerance": options.tolerance, "alpha": alpha,
            "cells": gate_record(records, base, plan, tolerance=options.tolerance, alpha=alpha)}


def _command(config: pytest.Config) -> str:
    """The command line as recorded: a signing key option's value redacted (`keys.recorded_args`), absolute paths
    relative to rootdir (`shown_arg`)."""
    from ..settings import shown_arg
    from .keys import recorded_args

    here, root = Path(config.invocation_params.dir), Path(config.rootpath)
    return "pytest " + " ".join(shown_arg(a, root) for a in recorded_args(config.invocation_params.args, here))


def front_image(context: RunContext) -> tuple[str, np.ndarray] | None:
    """(token, image) of the first scored frame's front camera, the report's figure (None when that image
    cannot be read; the cells already reported it)."""
    frame = context.frames[0]
    try:
        return frame.token, context.decode(frame, "CAM_FRONT")
    except DriveDegradeError:
        return None


def finish_shard(config: pytest.Config, options: RunOptions, context: RunContext, run: Gathered,
                 store: ResultStore, out: Outcome, expected: Sequence[tuple[str, int]],
                 planner_file: str = "", closed: ClosedInput | None = None,
                 ahead: FloorAhead | None = None) -> Outcome:
    """A shard's end: its manifest beside its cells, for `drivedegrade merge`; no certificate of its own."""
    from ..atomic import atomic_write_text
    from ..certificate.merge import MANIFEST, shard_manifest

    shard = options.settings.shard
    assert shard is not None
    floor = floor_of_run(config, options, context, out.lines, ahead) if expected else None
    manifest = shard_manifest(index=shard.index, count=shard.count, planner=run.planner, key=run.key,
                              provenance=provenance(config, options, context, run, planner_file),
                              settings=options.settings, frames_total=context.frames_total,
                              cells=[cell_id(f, s) for f, s in expected],
                              missing=run.missing, floor_l2=None if floor is None else list(floor.clean),
                              floor_ego_blind_l2=None if floor is None else floor.blind_list(),
                              gt={f.token: f.gt_future for f in context.frames}, data_root=str(context.reader.root),
                              front=(context.frames[0].token, context.frames[0].cameras["CAM_FRONT"].path),
                              scenes={f.token: f.scene_token for f in context.frames})
    if closed is not None and closed[1]:  # the closed cells this shard drove its share of runs of (SPEC 13)
        manifest["closed_cells"] = list(closed[1])
    if options.settings.adaptive:  # the shard owns whole families' cells, on every frame (`adaptive_merge`)
        from ..certificate.adaptive_merge import adaptive_manifest

        manifest["adaptive"] = adaptive_manifest(expected, shard, context.frames, context.seed,
                                                 str(run.key.get("planner_fingerprint", "")))
        owned = set(manifest["adaptive"]["owned"])
        run = replace(run, missing=[c for c in run.missing if c in owned])
        manifest["missing_cells"] = run.missing
    path = atomic_write_text(store.folder(run.planner) / MANIFEST, json.dumps(manifest, indent=1) + "\n")
    scenes = len({f.scene_token for f in context.frames})
    out.lines.append(f"shard {shard}: {len(context.frames)} of {context.frames_total} frames ({scenes} scene(s)), "
                     f"{len(run.payloads)} cell(s) finished; wrote {path}")
    if run.missing:
        out.lines.append(f"missing cells ({len(run.missing)}): {', '.join(run.missing)}; rerun the same command")
    out.lines.append("merge the shards with: drivedegrade merge <report>/<planner>/shard-*-of-"
                     f"{shard.count} --out <folder>")
    return out


def gate(cert: Mapping[str, Any], baseline: Mapping[str, object] | None, tolerance: float, *, partial: bool = False,
         any_planner: bool = False) -> tuple[list[str], bool]:
    """--drivedegrade-baseline: (lines, failed); an axis that regressed fails the session (cells fail in their
    own items), and so does a baseline that leaves part of the run uncompared, or a run that leaves part of the
    baseline uncomputed (`-k`, fewer families: unless `partial`), or a baseline that is another
    planner's (unless `any_planner`), with a line saying what was not compared."""
    if baseline is None:
        return [], False
    from ..scoring.baseline import (
        METRIC_FIELDS,
        BaselineError,
        compare_to_baseline,
        gate_metric,
        not_compared,
        planner_mismatch,
    )

    try:
        result = compare_to_baseline(cert, baseline, tolerance)
    except BaselineError as exc:
        return [f"baseline: {exc}"], True
    lines = [f"REGRESSION {reg.message()}" for reg in result["axes"]]
    failed = bool(result["axes"])
    planner = cert.get("planner")
    planner = planner if isinstance(planner, Mapping) else {}
    foreign = None if any_planner else planner_mismatch(baseline, planner.get("name"))
    if foreign:
        lines.append(f"baseline: FAILED: {foreign}")
        failed = True
    metric = gate_metric(cert)  # the gate compares the verdict's metric (M13)
    key, axes_key = METRIC_FIELDS[metric]
    gaps = not_compared(baseline, [c["cell"] for c in cert.get("cells", []) if c.get(key) is not None],
                        cert.get(axes_key) or {}, metric)
    if gaps and partial:
        lines.append(f"baseline (--drivedegrade-baseline-partial): not compared: {'; '.join(gaps)}")
    elif gaps:
        lines.append(f"baseline: FAILED: not compared: {'; '.join(gaps)}; certify a complete baseline with this "
                     "run's families and severities, or pass --drivedegrade-baseline-partial to gate on what both "
                     "have")
        failed = True
    lines.append(f"baseline: {len(result['cells'])} cell and {len(result['axes'])} axis regression(s) beyond "
                 f"tolerance {tolerance:g}")
    return lines, failed


def incompatible(cert: Mapping[str, object], baseline: Mapping[str, object]) -> str:
    """Why `baseline` cannot gate the run of `cert` (another spec, data set, settings or frame count); "" when it
    can (`scoring.baseline.check_baseline_compatible`)."""
    from ..scoring.baseline import BaselineError, check_baseline_compatible
    from ..settings import RunSettings

    got = cert.get("dataset")
    dataset: Mapping[str, object] = got if isinstance(got, Mapping) else {}
    spec, fingerprint, frames = cert.get("spec_version"), dataset.get("fingerprint"), dataset.get("frames")
    try:
        check_baseline_compatible(baseline, spec_version=spec if isinstance(spec, str) else None,
                                  dataset_fingerprint=fingerprint if isinstance(fingerprint, str) else None,
                                  settings=RunSettings.from_certificate(cert),
                                  frames_scored=frames if isinstance(frames, int) else None)
    except BaselineError as exc:
        return str(exc)
    return ""


def sequential_gate(options: RunOptions, context: RunContext, run: Gathered, cert: Mapping[str, object],
                    baseline: Mapping[str, object]) -> tuple[list[str], bool]:
    """--drivedegrade-baseline with --drivedegrade-adaptive: each cell's sequential test against the baseline's
    per-frame results (`scoring.seqgate`), read from the cells/ folder beside the baseline; (lines, failed)."""
    from ..certificate.adaptive_check import load_records
    from ..scoring.seqgate import gate_lines, sequential_gate

    why = incompatible(cert, baseline)
    if why:
        return [f"baseline: {why}"], True
    assert options.baseline_path is not None
    folder = options.baseline_path.parent / "cells"
    records = {c: p.record for c, p in run.payloads.items()}
    base, problems = load_records(folder, sorted(records), {})
    if "clean" not in base:
        return [f"baseline: FAILED: the sequential gate pairs with the baseline's per-frame results, and {folder} "
                "has no clean cell of it; gate against a report folder with its cells/"], True
    plan = run_plan(options, context, run)
    result = sequential_gate(records, base, plan, tolerance=options.tolerance, alpha=options.settings.alpha)
    return gate_lines(result, options.tolerance, options.settings.alpha), result.failed
