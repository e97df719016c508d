"""`drivedegrade reproduce` for closed-loop cells (SPEC section 13): which of a certificate's closed cells a rerun
drives, and how a rerun cell is compared with the certificate's ``closed_loop`` section, bit for bit.

Which: ``closed-clean`` always (the reference every retention and the null control divide by) and N others
(``--closed-cells``, default 1) drawn like the open cells (`reproduce.sample_cells`: the certificate's digest and
the sample seed). One closed cell drives every route under every seed (on the default slice 12 runs, about
20 s of one core for camera_cnn), far more than an open cell, so the default reruns two; ``--closed-cells N``
more, ``--loop open`` none.

How: the rerun record's content digest against the section's ``record_digests`` (every run's trace, DS, ends,
infractions with their steps); when it differs, run by run against the section's run rows (DS, completion, end,
trace digest, infraction counts), naming the first route and seed that differs and, when the certified cell
file lies beside the certificate (``cells/closed-<cell>.json``), the planner step at which the paths part.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from ..closedloop.analysis import NULL, RunRow, parting_step
from ..closedloop.cells import ClosedPayload, ClosedRecord, as_list, as_map, closed_id
from ..closedloop.results import RunResult
from ..errors import DriveDegradeError
from ..settings import RunSettings

#: The closed cell every reproduction of a certificate with closed cells reruns.
CLOSED_ALWAYS: tuple[str, ...] = (closed_id("clean", 0),)
DEFAULT_CLOSED = 1
#: A cell's figures that follow from its own runs alone (retention and separability need other cells, which the
#: rerun may not have driven).
ROW_FIGURES = ("runs", "unscored", "ds_mean", "ds_std", "ds_low", "ds_high", "completion", "infractions")
#: 10 Hz simulation steps.
SIM_HZ = 10


def section_of(cert: Mapping[str, object]) -> Mapping[str, object] | None:
    """The certificate's ``closed_loop`` section, None when it has none."""
    section = cert.get("closed_loop")
    return section if isinstance(section, Mapping) and isinstance(section.get("cells"), list) else None


def _cells(section: Mapping[str, object]) -> dict[str, Mapping[str, object]]:
    """A closed_loop section's cells by id."""
    return {str(c["cell"]): c for c in (as_map(x, "closed_loop cell") for x in as_list(section["cells"]))}


def closed_cells(cert: Mapping[str, object]) -> list[str]:
    """The certificate's closed cell ids, in its order (empty when it has no closed_loop section)."""
    section = section_of(cert)
    return list(_cells(section)) if section is not None else []


def loops(cert: Mapping[str, object], asked: str | None) -> tuple[bool, bool]:
    """(rerun open cells, rerun closed cells): the certificate's loops, or the `asked` ones (``--loop``) of
    them; DriveDegradeError when asked for a loop the certificate has no cell of."""
    has_open, has_closed = bool(cert.get("cells")), bool(closed_cells(cert))
    if asked is None:
        return has_open, has_closed
    if asked not in ("open", "closed", "both"):
        raise DriveDegradeError(f"--loop {asked!r}: expected open, closed or both")
    want_open, want_closed = asked in ("open", "both"), asked in ("closed", "both")
    for wanted, has, what in ((want_open, has_open, "open-loop"), (want_closed, has_closed, "closed-loop")):
        if wanted and not has:
            raise DriveDegradeError(f"--loop {asked}: the certificate has no {what} cell to rerun (it was made "
                                    f"with --drivedegrade-loop {RunSettings.from_certificate(cert).loop})")
    return want_open, want_closed


def closed_argv(cells: Sequence[str], with_open: bool) -> list[str]:
    """The options that drive exactly `cells` (closed ids) in the rerun, beside the open cells or alone."""
    names = [c[len("closed-"):] for c in cells]
    return ["--drivedegrade-loop", "both" if with_open else "closed", "--drivedegrade-closed-cells", ",".join(names)]


def plan_every(cert: Mapping[str, object]) -> int:
    """Simulation steps per planner call of the certificate's closed loop."""
    return SIM_HZ // RunSettings.from_certificate(cert).closed_hz


def certified_closed(cert_path: Path, cell: str, digest: str) -> ClosedRecord | None:
    """The certified closed cell when its file lies beside the certificate (``cells/<cell>.json``) and its record
    hashes to the certified digest (then its traces say where a rerun's path parts); None otherwise."""
    try:
        payload = ClosedPayload.from_builtins(json.loads((cert_path.parent / "cells" / f"{cell}.json").read_text()))
    except (OSError, ValueError, DriveDegradeError):
        return None
    return payload.record if payload.record.digest() == digest else None


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return bool(a == b)


def _rows(value: object) -> list[RunRow]:
    return [RunRow.from_list(as_list(r, "run row")) for r in as_list(value or [], "run_rows")]


def run_difference(want: RunRow, got: RunResult, original: RunResult | None, every: int) -> str | None:
    """What differs between a certified run row and a rerun run (None: nothing the row holds), with the step
    where the paths part when the certified run's trace is at hand."""
    mine = RunRow.of(got)
    parts = [f"{name} {b!r} (certified {a!r})" for name, a, b in (
        ("DS", want.ds, mine.ds), ("completion", want.completion, mine.completion), ("end", want.end, mine.end),
        ("infractions", dict(want.infractions), dict(mine.infractions))) if not _same(a, b)]
    if (want.route, want.seed) != (mine.route, mine.seed):
        return f"run {mine.route} seed {mine.seed} where the certificate has {want.route} seed {want.seed}"
    if want.trace != mine.trace:
        where = (f"the path parts at step {parting_step(original, got, every)}" if original is not None else
                 "the path differs (trace digest "
                 f"{mine.trace} here, {want.trace} certified; the step is unknown: the certified cell file is "
                 "not beside the certificate)")
        parts.insert(0, where)
    return f"route {mine.route} seed {mine.seed}: {', '.join(parts)}" if parts else None


def first_run_difference(rows: Sequence[RunRow], runs: Sequence[RunResult], original: Sequence[RunResult] | None,
                         every: int, what: str = "") -> str | None:
    """The first run (of `runs`, in run order) that differs from the certified `rows`, described; None when
    every run is as certified."""
    for i, (want, got) in enumerate(zip(rows, runs)):
        before = original[i] if original is not None and i < len(original) else None
        found = run_difference(want, got, before, every)
        if found is not None:
            return f"{what}{found}"
    if len(rows) != len(runs):
        return f"{what}the rerun drove {len(runs)} run(s), the certificate has {len(rows)}"
    return None


def compare_closed(cert: Mapping[str, object], cert_path: Path, got: ClosedRecord) -> str:
    """``identical`` when the rerun record hashes to the certified digest, else ``DIFFERENT (...)`` naming the
    first route and seed that differs, what differs and (certified traces at hand) the step where paths part."""
    section = section_of(cert) or {"cells": []}
    digest = str(as_map(section.get("record_digests") or {}).get(got.cell, ""))
    if got.digest() == digest:
        return "identical"
    original = certified_closed(cert_path, got.cell, digest)
    every = plan_every(cert)
    found = first_run_difference(_rows(_cells(section)[got.cell].get("run_rows")), got.runs,
                                 original.runs if original else None, every)
    null = as_map(section.get("null_control") or {})
    if found is None and got.cell == NULL and null.get("mode") == "wander":
        found = first_run_difference(_rows(null.get("run_rows")), got.null_runs,
                                     original.null_runs if original else None, every, "the null's clean rerun, ")
    if found is None:
        found = ("every run's DS, completion, end, trace and infraction counts are as certified, but the record "
                 f"is not (digest {got.digest()[:12]}..., certified {digest[:12]}...): an infraction's step, a run's "
                 "error text or its step count differs")
    return f"DIFFERENT ({found})"


def closed_figure_differences(cert: Mapping[str, object], rerun: Mapping[str, object] | None, cell: str) -> list[str]:
    """The figures of closed `cell` that follow from its runs alone and that the rerun's certificate gives
    differently, as ``name a (certified b)``."""
    mine, theirs = section_of(cert), section_of(rerun) if rerun is not None else None
    want = _cells(mine).get(cell) if mine is not None else None
    got = _cells(theirs).get(cell) if theirs is not None else None
    if want is None or got is None:
        return []
    return [f"{k} {got.get(k)!r} (certified {want.get(k)!r})" for k in ROW_FIGURES
            if not _same(want.get(k), got.get(k))]
