"""The session's start-up policies, checked before any cell computes: the baseline (loaded, verified, not this
run's own output, compatible with this run), the report folder (creatable, swept of interrupted writes, not
another planner's), the planner's name, the device, and the signing key.

Each raises ``pytest.UsageError`` (or returns the reason) for a user mistake; `session` calls them from its
hooks and keeps only the hooks.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest

from ..cells import cell_id
from ..run import RunContext
from .options import RunOptions

#: The files the controller writes in a planner's (or a shard's) folder; cells/ holds one <cell>.json each.
OUTPUT_FILES = ("certificate.json", "cells.csv", "report.html", "shard.json")


# --- the baseline ------------------------------------------------------------------------------------------------

def load_baseline(options: RunOptions) -> dict[str, Any] | None:
    """--drivedegrade-baseline, verified as `drivedegrade verify` verifies (None without one): a missing, edited
    or unreadable file, one whose arithmetic does not add up, one not signed by --drivedegrade-baseline-public-key
    (when given), or this run's own output, is a usage error naming why."""
    if options.baseline_path is None:
        return None
    from ..certificate.consistency import check_consistency
    from ..certificate.seal import CertificateError, verify
    from ..certificate.signing import load_public_key, verify_signature

    where = f"--drivedegrade-baseline: {options.baseline_path}"
    if not options.baseline_path.is_file():
        raise pytest.UsageError(f"{where} does not exist")
    refuse_own_output(options)
    try:
        cert = verify(options.baseline_path)
        if options.baseline_public_key is not None:
            verify_signature(cert, load_public_key(options.baseline_public_key), where=str(options.baseline_path))
    except CertificateError as exc:  # SignatureFailure included: unsigned, another key, edited after signing
        flag = " (--drivedegrade-baseline-public-key)" if options.baseline_public_key is not None else ""
        raise pytest.UsageError(f"--drivedegrade-baseline{flag}: {exc}") from None
    problems = check_consistency(cert)
    if problems:
        raise pytest.UsageError(f"{where}: refused: the digest verifies but the arithmetic does not add up "
                                f"({'; '.join(problems[:3])}{'; ...' if len(problems) > 3 else ''}): `drivedegrade "
                                "verify` rejects it, so it cannot be trusted as a baseline")
    if options.settings.adaptive:  # the sequential gate reads the baseline's per-frame results beside it
        check_baseline_cells(cert, options.baseline_path.parent / "cells")
    return cert


def sealed_digests(cert: Mapping[str, object] | None) -> dict[str, object]:
    """The baseline certificate's ``record_digests`` (its open-loop cells' sealed records), {} without any."""
    got = (cert or {}).get("record_digests")
    return dict(got) if isinstance(got, Mapping) else {}


def check_baseline_cells(cert: Mapping[str, object], folder: Path) -> None:
    """Every file of the baseline's ``cells/`` checked against the record the baseline certificate sealed
    (issue 37 H2), before any cell runs: one whose record hashes to another digest (a cell file of another run
    copied over it), or one the certificate sealed no record for, is a usage error naming the file. Files of
    the closed loop's cells (sealed in its own section, never read by the gate) are left alone."""
    from ..certificate.adaptive_check import load_records

    if not folder.is_dir():
        return
    digests = sealed_digests(cert)
    closed = cert.get("closed_loop")
    closed_cells = closed.get("record_digests") if isinstance(closed, Mapping) else None
    for path in sorted(folder.glob("*.json")):
        cell = path.stem
        if cell not in digests:
            if isinstance(closed_cells, Mapping) and cell in closed_cells:
                continue
            raise pytest.UsageError(f"--drivedegrade-baseline: {path}: the baseline certificate sealed no record of "
                                    f"cell {cell!r} (record_digests), so the sequential gate cannot trust it; "
                                    "remove it, or use the baseline's own cells/ folder as its run wrote it")
        _, problems = load_records(folder, [cell], digests)
        if problems:
            raise pytest.UsageError(f"--drivedegrade-baseline: refused before any cell ran: {problems[0]}; the "
                                    "gate would compare this run with results the baseline never certified. Restore "
                                    "the baseline's cells/ as its run wrote them (or rerun the baseline)")


def refuse_own_output(options: RunOptions) -> None:
    """A baseline that is (or resolves to, through symlinks) a certificate this run writes, some
    `<report>/<planner>/certificate.json`, would be replaced by the run it gates, so the next run compares the
    planner with itself and passes: a usage error before anything runs."""
    assert options.baseline_path is not None
    real = options.baseline_path.resolve()
    if real.name == "certificate.json" and real.parent.parent == options.report_dir.resolve():
        shown = "" if real == options.baseline_path else f" (it resolves to {real})"
        raise pytest.UsageError(
            f"--drivedegrade-baseline: {options.baseline_path}{shown} lies in this run's report folder "
            f"{options.report_dir}, where the run writes its own certificate: a failing run would replace the "
            "baseline and the next run would pass against itself; copy it elsewhere first (e.g. cp "
            f"{real} baseline.json) and pass the copy, or pass another --drivedegrade-report")


def check_baseline(baseline: Mapping[str, object] | None, options: RunOptions, context: RunContext,
                   cells: Sequence[tuple[str, int]]) -> None:
    """A baseline from another ladder, data set or settings, or one that does not cover this run's cells
    (unless --drivedegrade-baseline-partial), is a usage error now, not a failure after the whole run."""
    if baseline is None:
        return
    from ..corruptions.ladder import SPEC_VERSION
    from ..scoring.baseline import BaselineError, check_baseline_compatible, not_compared

    where = f"--drivedegrade-baseline: {options.baseline_path}"
    try:
        check_baseline_compatible(baseline, spec_version=SPEC_VERSION,
                                  dataset_fingerprint=context.dataset_fingerprint,
                                  frames_scored=context.frames_total, settings=options.settings)
    except BaselineError as exc:
        raise pytest.UsageError(f"{where}: {exc}") from None
    section = baseline.get("adaptive")
    if isinstance(section, Mapping) and options.settings.adaptive:
        raise pytest.UsageError(f"{where}: an adaptive baseline cannot gate an adaptive run: the sequential gate "
                                "pairs each unit with the baseline's result on it and needs the baseline's mean "
                                "over every unit, and an adaptive baseline ran only some units; gate against a full "
                                "baseline, or gate a full run against this one (on its intervals)")
    if isinstance(section, Mapping):  # a full run, gated on the adaptive baseline's intervals (`interval_gate`)
        if options.settings.metric != "l2":
            raise pytest.UsageError(f"{where}: an adaptive baseline holds anytime-valid intervals of L2 retention "
                                    f"only; gate a --drivedegrade-metric {options.settings.metric} run against a "
                                    "full baseline")
        theirs = section.get("cells")
        lacking = [cell_id(f, s) for f, s in cells if not isinstance(theirs, Mapping) or cell_id(f, s) not in theirs]
        gaps = [f"{len(lacking)} cell(s) of this run are not in the adaptive baseline: {', '.join(lacking[:8])}"] \
            if lacking else []
    else:
        gaps = not_compared(baseline, [cell_id(f, s) for f, s in cells], metric=options.settings.metric)
    if gaps and not options.baseline_partial:
        raise pytest.UsageError(f"{where}: the baseline does not cover this run, so part of it would not be "
                                f"compared: {'; '.join(gaps)}; certify a complete baseline with this run's "
                                "families and severities, or pass --drivedegrade-baseline-partial to gate on "
                                "what both have")


# --- the report folder -------------------------------------------------------------------------------------------

def prepare_report_dir(folder: Path, started: float) -> str | None:
    """Results are written as each cell finishes: a report folder that cannot be created fails now. The temporary
    files of writes a kill -9 interrupted are swept; the line saying so (None when there were none)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise pytest.UsageError(f"--drivedegrade-report: cannot create the report folder {folder}: "
                                f"{exc.strerror or exc}") from None
    removed = sweep_temporaries(folder, started)
    if not removed:
        return None
    shown = ", ".join(str(p.relative_to(folder)) for p in removed[:5])
    more = f" and {len(removed) - 5} more" if len(removed) > 5 else ""
    return (f"drivedegrade: removed {len(removed)} temporary file(s) left in {folder} by an interrupted write: "
            f"{shown}{more}")


def sweep_temporaries(report_dir: Path, started: float) -> list[Path]:
    """Remove the temporary files of our atomic writes that an interrupted run left (named exactly as the atomic
    writer names them, older than this run's start) in each planner folder, its shard folders and their cells/;
    return what was removed."""
    from ..atomic import stray_temporaries

    removed = []
    for planner in sorted(p for p in report_dir.iterdir() if p.is_dir() and not p.is_symlink()):
        for folder in (planner, *sorted(p for p in planner.iterdir() if p.is_dir() and p.name != "cells")):
            for path in [*stray_temporaries(folder, OUTPUT_FILES, started),
                         *stray_temporaries(folder / "cells", None, started)]:
                try:
                    path.unlink()
                    removed.append(path)
                except OSError:
                    pass
    return removed


def folder_owner_problem(options: RunOptions, name: str, mine: str) -> str:
    """A report folder whose certificate records another planner file than `mine` (a planner of the same name)
    is not overwritten silently; "" when it is free, ours, or --drivedegrade-report-overwrite."""
    if options.report_overwrite:
        return ""
    folder = options.report_dir / name
    try:
        planner = json.loads((folder / "certificate.json").read_text()).get("planner", {})
        theirs = planner.get("file") if isinstance(planner, dict) else None
    except (OSError, ValueError, AttributeError):
        return ""  # none, or unreadable: nothing recorded to protect
    if not isinstance(theirs, str) or theirs == mine:
        return ""
    return (f"--drivedegrade-report: {folder} holds the certificate of another planner named {name!r} "
            f"(planner file {theirs}; this run's is {mine}); pass another --drivedegrade-report, or "
            "--drivedegrade-report-overwrite to replace its outputs")


# --- the planner, the device, the key ----------------------------------------------------------------------------

def name_problem(planner: object, options: RunOptions, baseline: Mapping[str, object] | None, mine: str) -> str:
    """Why this planner cannot be certified under its name ("" when it can): a malformed name, another planner
    than the baseline's (unless --drivedegrade-baseline-any-planner), a report folder another planner file
    holds. `mine`: this run's planner file as the certificate records it."""
    from ..errors import InvalidInput
    from ..planning import planner_name

    default = options.planner_path.stem if options.planner_path else "planner"
    try:
        name = planner_name(planner, default)
    except InvalidInput as exc:
        return f"--drivedegrade: unusable planner name: {exc}"
    if baseline is not None and not options.baseline_any_planner:
        from ..scoring.baseline import planner_mismatch

        foreign = planner_mismatch(baseline, name)
        if foreign:
            return f"--drivedegrade-baseline: {options.baseline_path}: {foreign}"
    return folder_owner_problem(options, name, mine)


def use_device(device: str) -> str | None:
    """--drivedegrade-device for every planner of the run: ``$DRIVEDEGRADE_DEVICE`` set for this process and the
    workers and actors it starts; on CUDA, cuDNN made deterministic (no autotuned kernel choice, no TF32
    convolutions) so a GPU run is bit-reproducible. Returns the variable's previous value, for `restore_device`."""
    from ..planning import DEVICE_ENV, deterministic_cuda

    previous = os.environ.get(DEVICE_ENV)
    os.environ[DEVICE_ENV] = device
    if device != "cpu":
        deterministic_cuda()
    return previous


def restore_device(previous: str | None) -> None:
    """``$DRIVEDEGRADE_DEVICE`` as it was before `use_device`."""
    from ..planning import DEVICE_ENV

    if previous is None:
        os.environ.pop(DEVICE_ENV, None)
    else:
        os.environ[DEVICE_ENV] = previous

