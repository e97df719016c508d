"""The controller's end of a run (the controller process only, never an xdist worker): gather the cells, compute
the analysis and the floor, write the outputs, apply the baseline gate, and return the terminal summary's lines.
Never raises for a user mistake."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ..cells import CellPayload, CellRecord, cell_id
from ..certificate.seal import Provenance
from ..errors import DriveDegradeError
from ..run import RunContext
from ..scoring.records import cost_ledger, finite_mean
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
        why = " (the scored frames' files changed)" if "dataset_fingerprint" in fields else ""
        lines.append(f"not reused: {len(cells)} stored cell(s) recomputed because their run key differs in "
                     f"{fields}{why}: {', '.join(sorted(cells))}")
    return lines


def floor_per_frame(config: pytest.Config, context: RunContext, split: str, lines: list[str],
                    ego: dict[str, Any] | None = None) -> np.ndarray | None:
    """The ego-only floor's clean l2_avg per scored frame (trained on the train split once, cached); None with a
    line saying why when there is no floor. With `ego`, also its ego_blind retention there
    (``ego["ego_removal"]``, for the reliance chart)."""
    from ..floor import load_or_train_floor, train_split_for

    try:
        train = context.reader.with_split(train_split_for(split))
        if not any(f.scorable for f in train.frames()):  # lazily: stops at the first scorable frame
            lines.append(f"ego-only floor: skipped, split {train.split!r} has no scorable frames")
            return None
        model = load_or_train_floor(train, cache_root(config) / "floor")
    except DriveDegradeError as exc:
        lines.append(f"ego-only floor: skipped ({exc})")
        return None
    clean = context.run_cell(model, "clean", 0).l2_avg_per_frame()
    if ego is not None:
        from ..scoring.retention import retention

        blind_frames = context.run_cell(model, "ego_blind", 0).l2_avg_per_frame()
        ego["ego_removal"] = float(retention(finite_mean(clean), finite_mean(blind_frames)))
        ego["per_frame"] = blind_frames
    return clean


def planner_file(config: pytest.Config, path: Path) -> str:
    """The planner file (or conftest.py) as the certificate records it: relative to rootdir when inside it, so
    a moved checkout keeps it."""
    try:
        return path.resolve().relative_to(Path(config.rootpath).resolve()).as_posix()
    except ValueError:
        return path.resolve().as_posix()



def provenance(options: RunOptions, context: RunContext, name: str, key: Mapping[str, Any],
               command: str, planner_file: str = "") -> Provenance:
    """What makes the run traceable, for the certificate and cells.csv."""
    from .. import __version__
    from ..certificate.seal import runtime_versions
    from ..corruptions.ladder import SPEC_VERSION

    source = "embedded world" if options.data is None else str(options.data)
    return Provenance(planner_name=name, planner_fingerprint=str(key["planner_fingerprint"]),
                      dataset_fingerprint=str(key["dataset_fingerprint"]), split=options.split,
                      spec_version=SPEC_VERSION, seed=options.seed, frames=len(context.frames),
                      frames_unscored=context.frames_unscored, data_source=source, command=command,
                      tool_version=__version__, frames_requested=options.frames, timeout=options.timeout,
                      versions=runtime_versions(), planner_file=planner_file)


def finish_run(config: pytest.Config, options: RunOptions, context: RunContext | None,
               received: Mapping[str, CellPayload], expected: Sequence[tuple[str, int]],
               baseline: Mapping[str, Any] | None, store: ResultStore | None = None,
               planner_file: str = "") -> Outcome | None:
    """Analyse and write everything the run has (a shard writes its manifest for the merge instead); None when
    the run never opened its data. `planner_file` goes into the certificate (see `planner_file`)."""
    if context is None:
        return None
    out = Outcome()
    store = store or ResultStore(options.report_dir)
    run = gather(received, expected, store)
    if run is None:
        out.lines.append("no cell finished: nothing to analyse")
        return out
    out.lines += reuse_lines(received, run, store)
    if options.shard is not None:
        return finish_shard(config, options, context, run, store, out, expected, planner_file)
    if "clean" not in run.payloads:  # not a failure: the cells that ran are stored, and a later run completes them
        out.lines.append("no clean cell result, so no report written: retention is relative to clean (was it "
                         "deselected with -k?); the cells that ran are stored and reused by a run that includes "
                         "clean")
        return out
    from ..report.outputs import write_outputs
    from ..report.terminal import summary_lines
    from ..scoring.verdict import analyse_run

    floor_ego: dict[str, Any] = {}
    per_frame = floor_per_frame(config, context, options.split, out.lines, floor_ego if options.ego else None)
    floor_ego.pop("per_frame", None)
    floor = None if per_frame is None else finite_mean(per_frame)
    records: dict[str, CellRecord] = {c: p.record for c, p in run.payloads.items()}
    analysis = analyse_run(records.values(), flat=options.flat, seed=options.seed, floor_l2=floor,
                           seeds=options.seeds, metric=options.metric)
    analysis.floor.update(floor_ego)
    analysis.settings.update(batch=options.batch, reuse=options.reuse, device=options.device)
    prov = provenance(options, context, run.planner, run.key, _command(config), planner_file)
    cost = cost_ledger(records.values())
    # the stored cells this run took instead of computing them (resume): said in the certificate, not only here
    cost["resumed_cells"] = sorted(c for c, p in run.payloads.items() if p.resumed)
    cert, written = write_outputs(options.report_dir, prov, records, analysis, run.missing,
                                  gt={f.token: f.gt_future for f in context.frames},
                                  montage=front_montage(context, options.seed), cost=cost,
                                  signing_key=signing_key(options))
    out.lines.append(cost_line(cost))
    out.lines.append(written)
    from .compat import junit_xml

    xml = junit_xml(config)
    if xml is not None:
        from ..report.junit import suite_properties

        for prop, value in suite_properties(analysis):
            xml.add_global_property(prop, value)
    gate_lines, out.failed = gate(cert, baseline, options.tolerance, partial=options.baseline_partial,
                                  any_planner=options.baseline_any_planner)
    out.lines = summary_lines(analysis, run.missing) + out.lines + gate_lines
    return out


def cost_line(cost: Mapping[str, Any]) -> str:
    """The cost ledger in one line of the terminal summary."""
    sec = cost["seconds"]
    fps = cost.get("planner_frames_per_second")
    return (f"cost: {cost['predictions']} predictions, {cost['reused']} frames reused the clean plan; seconds in "
            f"cells: planner "
            f"{sec['planner']:.1f}" + (f" ({fps:.1f} frames/s)" if fps else "") + f", decode {sec['decode']:.1f}, "
            f"inject {sec['inject']:.1f}, scoring {sec['metrics'] + sec['pdms']:.1f}, input check {sec['check']:.1f}")


def signing_key(options: RunOptions) -> Any:
    """The run's Ed25519 private key (checked at start-up by `options.parse`), or None for an unsigned run."""
    if options.sign_key_pem is None:
        return None
    from ..certificate.signing import load_private_key

    return load_private_key(options.sign_key_pem, "--drivedegrade-sign-key")


def _command(config: pytest.Config) -> str:
    """The command line as recorded: a signing key option's value redacted (`keys.recorded_args`)."""
    from .keys import recorded_args

    return "pytest " + " ".join(recorded_args(config.invocation_params.args, Path(config.invocation_params.dir)))


def front_montage(context: RunContext, seed: int) -> np.ndarray | None:
    """The report's figure: the first scored frame's front camera under every family at S4 (None when that
    image cannot be read; the cells already reported it)."""
    from ..report.outputs import montage_of

    frame = context.frames[0]
    try:
        image = context.decode(frame, "CAM_FRONT")
    except DriveDegradeError:
        return None
    return montage_of(image, frame.token, seed)


def finish_shard(config: pytest.Config, options: RunOptions, context: RunContext, run: Gathered,
                 store: ResultStore, out: Outcome, expected: Sequence[tuple[str, int]],
                 planner_file: str = "") -> Outcome:
    """A shard's end: its manifest beside its cells, for `drivedegrade merge`; no certificate of its own."""
    from ..atomic import atomic_write_text
    from ..certificate.merge import MANIFEST, shard_manifest

    shard = options.shard
    assert shard is not None
    floor_ego: dict[str, Any] = {}
    per_frame = floor_per_frame(config, context, options.split, out.lines, floor_ego if options.ego else None)
    prov = provenance(options, context, run.planner, run.key, _command(config), planner_file)
    manifest = shard_manifest(index=shard.index, count=shard.count, planner=run.planner, key=run.key,
                              provenance=prov, flat=options.flat, seeds=options.seeds, metric=options.metric,
                              batch=options.batch, reuse=options.reuse, device=options.device,
                              frames_total=context.frames_total,
                              cells=[cell_id(f, s) for f, s in expected],
                              missing=run.missing, floor_l2=None if per_frame is None else list(per_frame),
                              floor_ego_blind_l2=floor_ego.get("per_frame"),
                              gt={f.token: f.gt_future for f in context.frames}, data_root=str(context.reader.root),
                              front=(context.frames[0].token, context.frames[0].cameras["CAM_FRONT"].path))
    path = atomic_write_text(store.folder(run.planner) / MANIFEST, json.dumps(manifest, indent=1) + "\n")
    scenes = len({f.scene_token for f in context.frames})
    out.lines.append(f"shard {shard}: {len(context.frames)} of {context.frames_total} frames ({scenes} scene(s)), "
                     f"{len(run.payloads)} cell(s) finished; wrote {path}")
    if run.missing:
        out.lines.append(f"missing cells ({len(run.missing)}): {', '.join(run.missing)}; rerun the same command")
    out.lines.append("merge the shards with: drivedegrade merge <report>/<planner>/shard-*-of-"
                     f"{shard.count} --out <folder>")
    return out


def gate(cert: Mapping[str, Any], baseline: Mapping[str, Any] | None, tolerance: float, *, partial: bool = False,
         any_planner: bool = False) -> tuple[list[str], bool]:
    """--drivedegrade-baseline: (lines, failed); an axis that regressed fails the session (cells fail in their
    own items), and so does a baseline that leaves part of the run uncompared (unless `partial`) or is another
    planner's (unless `any_planner`), with a line saying what was not compared."""
    if baseline is None:
        return [], False
    from ..scoring.baseline import BaselineError, compare_to_baseline, not_compared, planner_mismatch

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
    gaps = not_compared(baseline, [c["cell"] for c in cert.get("cells", []) if c.get("retention") is not None],
                        cert.get("axes"))
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
