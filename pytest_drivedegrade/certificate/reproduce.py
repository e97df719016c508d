"""`drivedegrade reproduce CERT PLANNER`: check a certificate by rerunning some of its cells bit for bit.

The suite is deterministic (same command, same bits on any worker layout), so the strongest check a stranger can
make is to rerun cells and compare plans. The certificate is verified first, and refused when its thresholds, axes
or verdict contradict its cells (verify's arithmetic); then clean, the null control and N other cells, sampled
from the certificate's digest and a seed (fresh randomness unless ``--seed`` repeats one; the output names it), are
rerun by the real pipeline: a ``python -m pytest --drivedegrade PLANNER -k CELLS`` subprocess into a fresh report
folder, with the settings the certificate records (`RunSettings.from_certificate`, `RunSettings.rerun_argv`) and no
pytest cache (``-p no:cacheprovider``: no stored cell and no last-failed state can leak in). Each cell's
``plans_digest`` is compared as it finishes, then every certified figure of the sampled cells.

A certificate with closed-loop cells (``--drivedegrade-loop closed|both``) has ``closed-clean`` and
``--closed-cells`` N (default 1) sampled closed cells rerun in the same subprocess (`reproduce_closed` says which
and why so few, and compares each with the ``closed_loop`` section run by run); ``--loop open|closed`` reruns one
loop only.
"""

from __future__ import annotations

import hashlib
import json
import math
import secrets
import shlex
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..cells import DIAGNOSTIC, CellRecord, differing_frames
from ..closedloop.cells import ClosedPayload
from ..errors import DriveDegradeError, InvalidInput
from ..payload import CellPayload
from ..progress import Progress, Sink
from ..settings import RunSettings
from . import reproduce_closed as rc
from .rerun_watch import Watch, run_watched, tail

#: Cells every reproduction reruns (when the certificate has them), before the sampled ones.
ALWAYS: tuple[str, ...] = ("clean", "null")
DEFAULT_SAMPLED = 3
#: Settings reproduce sets itself (which loops and closed cells the rerun drives), not repeated from the
#: certificate: never a reason to note that the rerun's figures are of another run.
RERUN_CHOSEN = ("loop", "closed_cells")
#: Library names of `runtime_versions` as people know them.
LIBRARIES = {"python": "Python", "numpy": "numpy", "opencv": "OpenCV", "torch": "torch"}


def sample_cells(cells: Sequence[str], digest: str, n: int, salt: str = "",
                 always: Sequence[str] = ALWAYS) -> list[str]:
    """Clean, null (`always`) and `n` other cells of `cells` (all of them when fewer), in `cells`' order.

    The others are ranked by ``sha256(digest|salt|cell)``: deterministic, independent of numpy and of the order
    of `cells`, and a different `salt` draws another sample from the same certificate.
    """
    if n < 0:
        raise InvalidInput(f"--cells must be 0 or more, got {n}")
    others = sorted((c for c in cells if c not in always),
                    key=lambda c: hashlib.sha256(f"{digest}|{salt}|{c}".encode()).hexdigest())
    chosen = {*always, *others[:n]}
    return [c for c in cells if c in chosen]


def version_notes(cert: Mapping[str, Any], here: Mapping[str, str | None], tool_version: str,
                  spec_version: str) -> list[str]:
    """What differs between the certificate's software and this machine's, as lines (empty: nothing known)."""
    tool: Mapping[str, Any] = cert["tool"] if isinstance(cert.get("tool"), dict) else {}
    notes = []
    recorded = tool.get("versions") if isinstance(tool.get("versions"), dict) else None
    if recorded is None:
        notes.append("the certificate does not record its OpenCV / numpy / torch versions (written before they "
                     "were recorded): a difference cannot be put down to them")
    else:
        diff = [f"{LIBRARIES.get(k, k)} {here.get(k)} here, {recorded.get(k)} in the certificate"
                for k in LIBRARIES if k in recorded and recorded.get(k) != here.get(k)]
        if diff:
            notes.append("library versions differ (" + "; ".join(diff) + "): differences are then expected, "
                         "and are named as such below")
    if tool.get("version") and tool.get("version") != tool_version:
        notes.append(f"pytest-drivedegrade {tool_version} here, {tool.get('version')} in the certificate")
    if cert.get("spec_version") != spec_version:
        notes.append(f"ladder spec {spec_version} here, {cert.get('spec_version')} in the certificate: the "
                     "corruptions differ, so the cells will")
    return notes


def find_default_world(cwd: Path) -> Path | None:
    """The embedded world an earlier run rendered under `cwd` (pytest's cache, or the no-cacheprovider folder),
    so a rerun reads it rather than render it again; None when there is none (the rerun renders it)."""
    from ..data.world.build import MANIFEST, default_world_dir

    for cache in (cwd / ".pytest_cache" / "d" / "drivedegrade", cwd / ".drivedegrade-cache"):
        if (default_world_dir(cache) / MANIFEST).is_file():
            return default_world_dir(cache)
    return None


def data_root(cert: Mapping[str, Any], data: str | None, cwd: Path) -> Path | None:
    """The data set to rerun on: `data`, else the certificate's nuScenes root, else the embedded world."""
    if data is not None:
        if not Path(data).is_dir():
            raise DriveDegradeError(f"--data {data}: no such folder")
        return Path(data).resolve()
    source = str(cert["dataset"].get("source") or "embedded world")
    if source == "embedded world":
        return find_default_world(cwd)
    # recorded relative to the run's rootdir (or by name only, outside it): this folder or one above it
    found = next((d / source for d in (Path(cwd), *Path(cwd).parents) if (d / source).is_dir()), Path(source))
    if not found.is_dir():
        raise DriveDegradeError(f"the certificate was made on the data set {source} (recorded relative to its run's "
                                "rootdir), which is not on this machine: pass its root with --data PATH")
    return found.resolve()


def rerun_argv(cert: Mapping[str, Any], planner: Path, cells: Sequence[str], report_dir: Path,
               data: Path | None, closed: Sequence[str] = ()) -> list[str]:
    """The pytest command that reruns `cells` (open) and `closed` (closed-loop ids) with the certificate's
    settings (`RunSettings.rerun_argv`) into `report_dir`, on the data at `data`."""
    by_id = {c["cell"]: c for c in cert["cells"]}
    argv = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "--drivedegrade", str(planner),
            "--drivedegrade-report", str(report_dir), *RunSettings.from_certificate(cert).rerun_argv()]
    if data is not None:
        argv += ["--drivedegrade-data", str(data)]
    # collect only the sampled cells' families and severities, then select the cells themselves with -k; an
    # adaptive run collects all of them (a cell's stop depends on the run's cells: the union bound, the schedule)
    collected = list(by_id) if isinstance(cert.get("adaptive"), Mapping) else cells
    families = [by_id[c]["family"] for c in collected if by_id[c]["family"] not in DIAGNOSTIC]
    severities = sorted({int(by_id[c]["severity"]) for c in collected if by_id[c]["family"] not in DIAGNOSTIC} - {0})
    if families:
        argv += ["--drivedegrade-families", ",".join(dict.fromkeys(families))]
    if severities:
        argv += ["--drivedegrade-severities", ",".join(map(str, severities))]
    if closed:  # exactly the sampled closed cells are collected (-k clean also matches closed-clean)
        argv += rc.closed_argv(closed, bool(cells))
    elif RunSettings.from_certificate(cert).loop != "open":  # no closed cell to rerun: none is collected
        argv += ["--drivedegrade-loop", "open"]
    return [*argv, "-k", " or ".join([*cells, *closed])]


def compare_plans(expected: str, got: CellRecord, original: CellRecord | None) -> str:
    """``identical``, or ``DIFFERENT (...)`` with the first differing frame token and the largest plan
    difference when the certified plans are at hand (`original`)."""
    digest = got.plans_digest()
    if digest == expected:
        return "identical"
    if original is None:
        return (f"DIFFERENT (plans digest {digest[:12]}..., certified {expected[:12]}...; which frame differs is "
                "unknown: the certified cell records are not beside the certificate)")
    if original.frames != got.frames:
        return "DIFFERENT (the rerun scored other frames than the certified run)"
    for i, (a, b) in enumerate(zip(original.runs(), got.runs())):
        bad = differing_frames(a.plans, b.plans)
        if len(bad):
            delta = np.abs(a.plans[bad] - b.plans[bad])
            size = f"{np.nanmax(delta):.3g} m" if np.isfinite(delta).any() else "a NaN against a number"
            seed = f", seed run {i + 1}" if len(got.runs()) > 1 else ""
            return (f"DIFFERENT (first differing frame {got.frames[int(bad[0])]}{seed}, {len(bad)} frame(s) differ, "
                    f"max plan difference {size})")
    return "DIFFERENT (another number of seed runs than certified)"


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return bool(a == b)


def metric_differences(certified: Mapping[str, Any], rerun: Mapping[str, Any]) -> list[str]:
    """Every certified figure of a cell the rerun's certificate gives differently, as ``name a (certified b)``."""
    return [f"{k} {rerun.get(k)!r} (certified {v!r})" for k, v in certified.items()
            if k != "plans_digest" and not _same(v, rerun.get(k))]


def certified_record(cert_path: Path, cell: str, digest: str) -> CellRecord | None:
    """The certified run's record of `cell` when it lies beside the certificate (``cells/<cell>.json``) and its
    plans hash to the certified digest; None otherwise."""
    try:
        record = CellPayload.from_builtins(json.loads((cert_path.parent / "cells" / f"{cell}.json").read_text())).record
    except (OSError, ValueError, DriveDegradeError):
        return None
    return record if record.plans_digest() == digest else None


def verified(path: Path, public_key: str | None) -> tuple[dict[str, Any], str]:
    """The certificate when its digest (and, with `public_key`, its signature) verifies, and what was proven;
    ``CertificateError`` otherwise (edited, unreadable, badly signed: a usage error for reproduce)."""
    from .seal import verify
    from .signing import UNSIGNED_TEXT, load_public_key, verify_signature

    key = load_public_key(public_key) if public_key else None
    cert = verify(path)
    if key is not None:
        return cert, f"signature verifies (key fingerprint {verify_signature(cert, key, where=str(path))})"
    return cert, "digest verifies" + ("" if isinstance(cert.get("signature"), dict) else f" ({UNSIGNED_TEXT})")


def usable(cert: Mapping[str, Any], path: Path) -> list[str]:
    """The certificate's open cell ids, when it carries what a rerun compares (none for a closed-loop-only
    certificate); DriveDegradeError otherwise."""
    cells = [c["cell"] for c in cert["cells"]]
    if not cells and rc.closed_cells(cert):
        return []
    lacking = [c["cell"] for c in cert["cells"] if "plans_digest" not in c]
    if lacking:
        raise DriveDegradeError(f"{path}: cells without plans_digest ({', '.join(lacking[:5])}"
                                f"{', ...' if len(lacking) > 5 else ''}): the certificate was written before "
                                "reproduction was possible; certify again with this version")
    if "clean" not in cells:
        raise DriveDegradeError(f"{path}: no clean cell: nothing to reproduce against")
    return cells


def refuse_imported(cert: Mapping[str, object], path: Path) -> None:
    """DriveDegradeError for a certificate made from a per-cell table (`drivedegrade analyse`): its figures were
    computed by another evaluator, so there are no plans to rerun against."""
    from .fields import IMPORTED_TEXT, imported_source, is_imported

    if is_imported(dict(cert)):
        raise DriveDegradeError(f"{path}: cannot be reproduced: {IMPORTED_TEXT} (from "
                                f"{imported_source(dict(cert))}); `drivedegrade verify` checks its arithmetic, "
                                "and reproducing it means rerunning the evaluator that made the table")


def consistent(cert: Mapping[str, object], path: Path) -> None:
    """DriveDegradeError when the certificate's thresholds, axes or verdict contradict its cells (verify's
    arithmetic, `consistency.check_consistency`): a resealed certificate is not worth a rerun."""
    from .consistency import check_consistency

    problems = check_consistency(cert)
    if problems:
        raise DriveDegradeError(f"{path}: its thresholds, axes or verdict contradict its own cells ("
                                f"{'; '.join(problems[:3])}{'; ...' if len(problems) > 3 else ''}): `drivedegrade "
                                "verify` rejects it; nothing was rerun")


def fresh_seed() -> str:
    """A sample seed no one can predict from the certificate (the OS's randomness), as ``--seed`` takes it."""
    return str(secrets.randbelow(2**31))


def choose(cert: Mapping[str, Any], path: Path, n: int, closed_n: int, salt: str, loop: str | None) \
        -> tuple[list[str], list[str]]:
    """The open cells (clean, null and `n` sampled) and the closed cells (``closed-clean`` and `closed_n`
    sampled, `reproduce_closed`) to rerun, of the loops `loop` names (None: the certificate's)."""
    want_open, want_closed = rc.loops(cert, loop)
    cells = sample_cells(usable(cert, path), cert["digest"], n, salt) if want_open else []
    if closed_n < 0:
        raise InvalidInput(f"--closed-cells must be 0 or more, got {closed_n}")
    closed = sample_cells(rc.closed_cells(cert), cert["digest"], closed_n, salt, rc.CLOSED_ALWAYS) \
        if want_closed else []
    return cells, closed


def reproduce(cert_path: Path, planner: Path, *, n: int = DEFAULT_SAMPLED, data: str | None = None,
              salt: str | None = None, public_key: str | None = None, keep: bool = False,
              any_planner: bool = False, closed_n: int = rc.DEFAULT_CLOSED, loop: str | None = None,
              say: Callable[[str], None] = print, progress: Callable[[str], None] | None = None,
              bar_sink: Sink | None = None) -> int:
    """Rerun clean, null and `n` sampled cells (and closed-clean and `closed_n` sampled closed cells, of the
    loops `loop` names); 0 when every one is identical to the certificate, 1 otherwise.
    Usage errors (a missing planner or certificate, one that does not verify or contradicts its cells, a rerun
    by another planner unless `any_planner`) raise DriveDegradeError. Without `salt` (``--seed``) the sample is
    drawn from fresh randomness (`fresh_seed`), said in the output so the same cells can be drawn again."""
    from .. import __version__
    from ..corruptions.ladder import SPEC_VERSION
    from .seal import runtime_versions

    note = progress or (lambda s: print(s, file=sys.stderr, flush=True))
    if not planner.is_file() or planner.suffix != ".py":
        raise DriveDegradeError(f"planner file {planner} does not exist or is not a .py file: give the file the "
                                "certificate was made with")
    cert, proof = verified(cert_path, public_key)
    refuse_imported(cert, cert_path)
    consistent(cert, cert_path)
    drawn = "given" if salt is not None else "fresh randomness"  # (the rerun: one progress line on `bar_sink`)
    salt = fresh_seed() if salt is None else salt
    open_cells, closed = choose(cert, cert_path, n, closed_n, salt, loop)
    cells = [*open_cells, *closed]
    root = data_root(cert, data, Path.cwd())
    note(f"reproduce: {cert_path}: {proof}; planner {cert['planner'].get('name')!r}, {len(cert['cells'])} cells"
         + (f", {len(rc.closed_cells(cert))} closed-loop cells" if rc.closed_cells(cert) else ""))
    notes = version_notes(cert, runtime_versions(), __version__, SPEC_VERSION)
    for line in notes:
        note(f"reproduce: NOTE: {line}")
    report_dir = Path(tempfile.mkdtemp(prefix="drivedegrade-reproduce-"))
    argv = rerun_argv(cert, planner.resolve(), open_cells, report_dir, root, closed)
    note(f"reproduce: rerunning {len(cells)} cell(s): {', '.join(cells)}\n  {shlex.join(['python', *argv[1:]])}")
    say(f"reproduce: sample seed {salt} ({drawn}; --seed {salt} draws these cells again): {', '.join(cells)}")
    judge = _judged_rerun(lambda s, n: Judge(cert, cert_path, cells, s, n, ["other software"] if notes else [],
                                             any_planner), say, note, cells, argv, report_dir, bar_sink)
    rerun = _rerun_certificate(report_dir)
    for line in settings_notes(cert, rerun):
        note(f"reproduce: NOTE: {line}")
    different = judge.finish(rerun)
    checked = "" if rerun is not None else " (the rerun wrote no certificate: figures not compared)"
    if different:
        say(f"reproduce: {len(different)} of {len(cells)} cell(s) DIFFERENT from the certificate: "
            f"{', '.join(different)}{checked}; the rerun is kept in {report_dir} (pytest.log, cells/)")
        return 1
    what = "plans bit for bit" + (", closed-loop runs bit for bit" if closed else "")
    say(f"reproduce: all {len(cells)} cell(s) identical to the certificate, {what} and every certified "
        f"figure{checked}")
    if not keep:
        shutil.rmtree(report_dir, ignore_errors=True)
    return 0


def _judged_rerun(judge_for: Callable[[Callable[[str], None], Callable[[str], None]], Judge],
                  say: Callable[[str], None], note: Callable[[str], None], cells: Sequence[str], argv: Sequence[str],
                  report_dir: Path, bar_sink: Sink | None) -> Judge:
    """Run the rerun, a judge (`judge_for(say, note)`) saying each cell's verdict as it finishes; between verdicts
    one progress line on `bar_sink` counts cells and seconds (verdict lines print above it; once the line is
    closed they print plainly)."""
    with Progress("drivedegrade reproduce", len(cells), unit="cells", milestones=1,
                  sink=bar_sink or Sink.silent()) as bar:
        judge = judge_for(lambda s: bar.interject(say, s), lambda s: bar.interject(note, s))

        def finished(payload: CellPayload | ClosedPayload) -> None:
            judge.on_cell(payload)
            bar.advance(note=payload.cell)

        code = run_watched(argv, report_dir / "pytest.log", Watch(report_dir, cells), finished, tick=bar.tick)
    if code in (2, 3, 4) and not judge.results:
        raise DriveDegradeError(f"the rerun stopped before any cell finished (pytest exit {code}); its output:\n"
                                f"{tail(report_dir / 'pytest.log')}")
    return judge


@dataclass
class Judge:
    """Compares each rerun cell with the certificate as it finishes, and says so; `expected` names why a
    difference is to be expected (other software, another planner or data set), appended to DIFFERENT lines."""

    cert: Mapping[str, Any]
    cert_path: Path
    cells: Sequence[str]
    say: Callable[[str], None]
    note: Callable[[str], None]
    expected: list[str]
    any_planner: bool = False
    results: dict[str, str] = field(default_factory=dict)
    started: float = field(default_factory=time.perf_counter)

    def _line(self, cell: str, verdict: str, prefix: str = "") -> None:
        because = f" [expected: {', '.join(self.expected)}]" if self.expected and verdict != "identical" else ""
        self.results[cell] = verdict
        self.say(f"{prefix}{cell}: {verdict}{because}")

    def other_planner(self, payload: CellPayload | ClosedPayload) -> None:
        """DriveDegradeError (the rerun is stopped) when the rerun's planner is not the certificate's, by name or
        fingerprint, unless `any_planner`."""
        theirs = self.cert["planner"]
        differ = []
        if payload.planner != theirs.get("name"):
            differ.append(f"name {payload.planner!r} here, {theirs.get('name')!r} in the certificate")
        here = str(payload.key.get("planner_fingerprint"))
        if here != str(theirs.get("fingerprint")):
            differ.append(f"fingerprint {here[:16]}... here, {str(theirs.get('fingerprint'))[:16]}... in the "
                          "certificate")
        if differ and not self.any_planner:
            raise DriveDegradeError(f"the planner is not the certificate's ({'; '.join(differ)}): reproduce checks "
                                    "a certificate with the planner it was made with; pass --any-planner to compare "
                                    "another planner's plans with it")

    def on_cell(self, payload: CellPayload | ClosedPayload) -> None:
        if not self.results:  # the first cell says which planner and data the rerun had
            self.other_planner(payload)
            for name, section, what in (("planner_fingerprint", "planner", "planner"),
                                        ("dataset_fingerprint", "dataset", "data set")):
                here, there = str(payload.key.get(name)), str(self.cert[section].get("fingerprint"))
                if here != there:
                    self.note(f"reproduce: NOTE: the {what} fingerprint differs from the certificate's "
                              f"({here[:16]}... here, {there[:16]}...): a different {what}")
                    self.expected.append(f"a different {what}")
        if isinstance(payload, ClosedPayload):
            verdict = rc.compare_closed(self.cert, self.cert_path, payload.record)
        else:
            digest = {c["cell"]: c for c in self.cert["cells"]}[payload.cell]["plans_digest"]
            verdict = compare_plans(digest, payload.record, certified_record(self.cert_path, payload.cell, digest))
        self._line(payload.cell, verdict,
                   f"[{len(self.results) + 1}/{len(self.cells)} {time.perf_counter() - self.started:.0f} s] ")

    def finish(self, rerun: Mapping[str, Any] | None) -> list[str]:
        """Cells the rerun did not give, and identical plans (runs) whose other figures in the rerun's
        certificate differ; the different cells."""
        by_id = {c["cell"]: c for c in self.cert["cells"]}
        figures = {c["cell"]: c for c in rerun["cells"]} if rerun is not None else {}
        for cell in self.cells:
            if cell not in self.results:
                self._line(cell, "DIFFERENT (not rerun: the rerun gave no result for it; see its pytest.log)")
                continue
            if self.results[cell] != "identical":
                continue
            closed = cell.startswith("closed-")
            diff = rc.closed_figure_differences(self.cert, rerun, cell) if closed else \
                metric_differences(by_id[cell], figures[cell]) if cell in figures else []
            if diff:
                self._line(cell, f"DIFFERENT ({'runs' if closed else 'plans'} identical, figures not: "
                                 f"{'; '.join(diff[:4])}{'; ...' if len(diff) > 4 else ''})")
        return [c for c in self.cells if self.results.get(c) != "identical"]


def _rerun_certificate(report_dir: Path) -> dict[str, Any] | None:
    """The rerun's certificate (None when it wrote none, or one without a list of cells)."""
    found = sorted(report_dir.glob("*/certificate.json"))
    if not found:
        return None
    try:
        cert = json.loads(found[0].read_text())
        return cert if isinstance(cert, dict) and all(isinstance(c, dict) and "cell" in c for c in cert["cells"]) \
            else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def settings_notes(cert: Mapping[str, Any], rerun: Mapping[str, Any] | None) -> list[str]:
    """The settings the rerun's certificate records differently from the certificate's (the rerun's command line
    should repeat them all: `RunSettings.rerun_argv`), as lines; where the data lies may differ."""
    if rerun is None:
        return []
    differ = [d for d in RunSettings.from_certificate(cert).same_run(RunSettings.from_certificate(rerun))
              if d.setting.name not in RERUN_CHOSEN]
    return [f"the rerun ran with {d.setting.label} {d.theirs!r} where the certificate has {d.mine!r} "
            f"({d.setting.flag}): its figures are of another run" for d in differ]

