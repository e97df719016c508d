"""The reliance certificate: build it from an analysis, seal it with SHA-256, verify it, load it as a baseline.

The digest covers the canonical JSON of everything but the digest itself: keys sorted, separators ``(",", ":")``,
ASCII only, floats rounded to ``DIGITS`` decimals *before* sealing (so what is stored is exactly what was hashed)
and non-finite floats stored as null. ``section_digests`` hashes each top-level section on its own, so a
verification failure can name the section that was edited, and two runs can be compared section by section
(``cells`` is identical under ``-n 0`` and ``-n 2``; only ``created`` differs).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, cast

import numpy as np

from ..atomic import atomic_write_text
from ..cells import CellRecord
from ..errors import DriveDegradeError
from ..payload import record_digests
from ..scoring.records import RunAnalysis, null_control_section
from ..scoring.verdict import VERDICT_LABELS
from ..settings import RunSettings
from .fields import CERTIFICATE_CELL

SCHEMA = "drivedegrade-certificate/1"
DIGITS = 6
#: Top-level keys every certificate has (SPEC section 6 stable names, plus this tool's additions).
REQUIRED_KEYS = ("schema", "spec_version", "planner", "dataset", "cells", "thresholds", "axes", "floor",
                 "null_control", "verdict", "settings", "created", "section_digests", "digest")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


class CertificateError(DriveDegradeError):
    """A certificate that cannot be read or is not a sealed certificate at all (CLI exit 2)."""


class CertificateMismatch(CertificateError):
    """A readable certificate whose content no longer matches its digest: it was edited (CLI exit 1)."""

    def __init__(self, message: str, *, recorded: str, computed: str, sections: list[str], problems: list[str]):
        super().__init__(message)
        self.recorded, self.computed, self.sections, self.problems = recorded, computed, sections, problems


@dataclass(frozen=True)
class Provenance:
    """What makes a run traceable: who was certified, on what data, under which ladder and how it was run."""

    planner_name: str
    planner_fingerprint: str
    dataset_fingerprint: str
    split: str
    spec_version: str
    seed: int = 0
    frames: int = 0
    frames_unscored: int | None = None
    data_source: str = "embedded world"
    command: str = ""
    tool_version: str = ""
    #: --drivedegrade-frames (None: every scorable frame) and --drivedegrade-timeout: what a rerun needs
    frames_requested: int | None = None
    timeout: float | None = None
    #: The libraries the cells were computed with (`runtime_versions`): a rerun elsewhere says when they differ.
    versions: Mapping[str, str | None] = field(default_factory=dict)
    planner_file: str = ""  #: the planner file (or conftest.py), relative to rootdir when inside it


def runtime_versions() -> dict[str, str | None]:
    """The versions that can change a cell's bits: Python, numpy, OpenCV, torch (None when not installed)."""
    import platform
    from importlib import metadata

    import cv2

    try:
        torch: str | None = metadata.version("torch")
    except metadata.PackageNotFoundError:
        torch = None
    return {"python": platform.python_version(), "numpy": np.__version__, "opencv": str(cv2.__version__),
            "torch": torch}


def run_provenance(settings: RunSettings, *, planner_name: str, key: Mapping[str, object], frames: int,
                   frames_unscored: int | None, command: str, planner_file: str = "",
                   recorded: Mapping[str, Any] | None = None, root: Path | None = None) -> Provenance:
    """The one way a run's `Provenance` is built: from its settings (split, seed, data source, frames asked
    for, timeout), its run key (the planner's and the data's fingerprints) and
    the frames it scored. The ladder's, the tool's and the libraries' versions are this process's, or, with
    `recorded` (a shard manifest), those the cells were computed with. With `root`, the data set's path is
    recorded relative to it (`RunSettings.shown_source`)."""
    if recorded is None:
        from .. import __version__
        from ..corruptions.ladder import SPEC_VERSION

        recorded = {"spec_version": SPEC_VERSION, "tool_version": __version__, "versions": runtime_versions()}
    return Provenance(planner_name=planner_name, planner_fingerprint=str(key["planner_fingerprint"]),
                      dataset_fingerprint=str(key["dataset_fingerprint"]), split=settings.split,
                      spec_version=str(recorded["spec_version"]), seed=settings.seed, frames=frames,
                      frames_unscored=frames_unscored, data_source=settings.shown_source(root),
                      command=command, tool_version=str(recorded.get("tool_version", "")),
                      frames_requested=settings.frames, timeout=settings.timeout,
                      versions=recorded.get("versions") or {}, planner_file=planner_file)


def canonicalize(obj: object, digits: int = DIGITS) -> Any:
    """Plain JSON builtins with floats rounded to `digits` decimals and NaN / inf as None (numpy accepted)."""
    if isinstance(obj, Mapping):
        return {str(k): canonicalize(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [canonicalize(v, digits) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
    if obj is None or isinstance(obj, (bool, np.bool_)):
        return None if obj is None else bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        value = float(obj)
        return round(value, digits) + 0.0 if math.isfinite(value) else None
    if isinstance(obj, (str, os.PathLike)):
        return os.fspath(obj)
    raise TypeError(f"cannot put a {type(obj).__name__} into a certificate")


def canonical_json(obj: object) -> bytes:
    """The exact bytes the digest is taken over."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode()


def _sha256(obj: object) -> str:
    return hashlib.sha256(canonical_json(obj)).hexdigest()


def compute_digest(cert: Mapping[str, object]) -> str:
    """SHA-256 hex over the canonical JSON of every key but ``digest``."""
    return _sha256({k: v for k, v in cert.items() if k != "digest"})


#: Why an EPDMS term may go unscored, as the certificate says it (`epdms_unscored`).
EPDMS_UNSCORED_REASONS: dict[str, str] = {
    "tlc": "the data have no traffic lights", "ddc": "the map has no lane layers", "lk": "the map has no lane layers",
    "ec": "no frame has its scene's previous keyframe in the run"}


def epdms_unscored(analysis: RunAnalysis) -> dict[str, str]:
    """The EPDMS terms the clean cell scored on no frame, each with the reason: they are left out of the score
    (a multiplier of 1 is not claimed, the weights renormalised), not counted as met."""
    clean = next((s for s in analysis.summaries if s.cell == "clean"), None)
    metrics = clean.metrics if clean is not None else {}
    return {k: why for k, why in EPDMS_UNSCORED_REASONS.items()
            if not math.isfinite(float(metrics.get(k, math.nan)))}


def build_certificate(analysis: RunAnalysis, provenance: Provenance, *, created: str | None = None,
                      records: Mapping[str, CellRecord] | None = None,
                      digests: Mapping[str, str] | None = None) -> dict:
    """The unsealed certificate of a run (``seal`` it before writing). `created` defaults to now, UTC. With the
    run's `records`, each cell carries ``plans_digest`` (`CellRecord.plans_digest`), what `drivedegrade
    reproduce` compares a rerun with, and ``record_digests`` maps each cell to `payload.record_digest` of its record,
    what its stored cell file (``cells/<cell>.json``) must hash to. That digest covers the record's timings too,
    so it sits beside the cells, not in them: the cells section stays the same on any layout and rerun.
    `digests`: those already known (checked when each record was read), taken as they are."""
    cells = [{k: row[k] for k in CERTIFICATE_CELL if k in row} for row in (s.flat() for s in analysis.summaries)]
    for cell in cells:
        if records is not None and cell["cell"] in records:
            cell["plans_digest"] = records[cell["cell"]].plans_digest()
    return {
        "schema": SCHEMA,
        "spec_version": provenance.spec_version,
        "planner": {"name": provenance.planner_name, "fingerprint": provenance.planner_fingerprint,
                    **({"file": provenance.planner_file} if provenance.planner_file else {})},
        "dataset": {"fingerprint": provenance.dataset_fingerprint, "split": provenance.split,
                    "frames": provenance.frames, "frames_unscored": provenance.frames_unscored,
                    "frames_requested": provenance.frames_requested, "source": provenance.data_source},
        "cells": cells,
        "thresholds": {fam: t.to_builtins() for fam, t in analysis.thresholds.items()},
        "axes": analysis.axes.to_builtins(),
        "axes_pdms": analysis.axes_pdms.to_builtins(),
        **({} if analysis.axes_epdms is None else {"axes_epdms": analysis.axes_epdms.to_builtins(),
                                                   "epdms_unscored": epdms_unscored(analysis)}),
        **analysis.two_stage_sections(),
        "floor": analysis.floor.to_builtins(),
        **({} if analysis.reliance is None else {"reliance": analysis.reliance.to_builtins()}),
        **({} if analysis.command is None else {"command": analysis.command.to_builtins()}),
        "null_control": null_control_section(analysis.null_control),
        "verdict": analysis.verdict.to_builtins(),
        "settings": {**analysis.settings, "seed": provenance.seed, "timeout": provenance.timeout},
        "tool": {"name": "pytest-drivedegrade", "version": provenance.tool_version, "command": provenance.command,
                 "versions": dict(provenance.versions)},
        "created": created or datetime.now(timezone.utc).replace(microsecond=0).isoformat(),
        **({"record_digests": record_digests(records, [c["cell"] for c in cells], digests)}
           if records is not None else {}),
    }


def seal(cert: Mapping[str, object]) -> dict[str, Any]:
    """Canonicalise, add per-section digests and the overall digest. Idempotent on a sealed certificate."""
    body = canonicalize({k: v for k, v in cert.items() if k not in ("digest", "section_digests")})
    body["section_digests"] = {k: _sha256(v) for k, v in body.items()}
    body["digest"] = compute_digest(body)
    return body


def certificate_text(cert: Mapping[str, object]) -> str:
    """The file's text: indented for people; the digest does not depend on the layout."""
    return json.dumps(cert, indent=2, sort_keys=True, ensure_ascii=True, allow_nan=False) + "\n"


def write_certificate(path: str | os.PathLike[str], cert: Mapping[str, object]) -> Path:
    """Seal (if needed) and write atomically."""
    return atomic_write_text(path, certificate_text(seal(cert)))


#: The deepest nesting of arrays and objects a certificate may have (a sealed one is about 5 deep): deeper input
#: is refused before parsing, so a crafted file cannot exhaust Python's recursion limit.
MAX_DEPTH = 64
_TOKENS = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]')


class _Constant:
    """Stands in for a NaN / Infinity literal, or a number literal no double can hold (1e999), while parsing,
    so the check can name where it was."""

    def __init__(self, literal: str, what: str = "JSON has no such number") -> None:
        self.literal, self.what = literal, what


#: The longest integer literal read (Python refuses to convert past 4300 digits; no figure needs 100).
MAX_INT_DIGITS = 1000


def _float(literal: str) -> float | _Constant:
    """A number literal as a double; one that overflows (1e999 reads as infinity) stands in as a `_Constant`."""
    value = float(literal)
    return value if math.isfinite(value) else _Constant(literal[:40], "it overflows a double")


def _int(literal: str) -> int | _Constant:
    return int(literal) if len(literal) <= MAX_INT_DIGITS else _Constant(literal[:40] + "...", "too long a number")


class _Object(dict):
    """A parsed JSON object that remembers the keys it held more than once."""

    duplicates: tuple[str, ...] = ()


def _pairs(pairs: list[tuple[str, object]]) -> _Object:
    obj = _Object(pairs)
    if len(obj) != len(pairs):
        counts = Counter(k for k, _ in pairs)
        obj.duplicates = tuple(k for k, n in counts.items() if n > 1)
    return obj


def _line_col(text: str, offset: int) -> str:
    line = text.count("\n", 0, offset) + 1
    return f"line {line}, column {offset - (text.rfind(chr(10), 0, offset) + 1) + 1}"


def _too_deep(text: str) -> str | None:
    """Where the nesting first goes deeper than MAX_DEPTH (brackets inside strings do not count), or None."""
    depth = 0
    for match in _TOKENS.finditer(text):
        token = match.group()
        if token in "[{":
            depth += 1
            if depth > MAX_DEPTH:
                return _line_col(text, match.start())
        elif token in "]}":
            depth -= 1
    return None


def _strict_problem(obj: object, where: str = "") -> str | None:
    """The first NaN / Infinity literal or duplicate key in the parsed tree, as 'what at path', or None."""
    if isinstance(obj, _Constant):
        return f"a {obj.literal} literal at {where or 'the top level'} ({obj.what})"
    if isinstance(obj, dict):
        if isinstance(obj, _Object) and obj.duplicates:
            return f"duplicate key {obj.duplicates[0]!r} in {where or 'the top-level object'}"
        items: Iterable[tuple[object, object]] = obj.items()
    elif isinstance(obj, list):
        items = enumerate(obj)
    else:
        return None
    for k, v in items:
        found = _strict_problem(v, f"{where}[{k}]" if isinstance(k, int) else f"{where}.{k}" if where else str(k))
        if found:
            return found
    return None


def parse_certificate_text(text: str, where: str) -> dict[str, Any]:
    """Parse a certificate's text strictly: NaN / Infinity literals, a number that overflows a double (1e999),
    duplicate keys (JSON's parser keeps the last silently, so what is shown and what is hashed could differ) and
    nesting deeper than MAX_DEPTH are refused with a ``CertificateError`` naming the file, the problem and where
    it is."""
    data = parse_strict_json(text, where)
    if not isinstance(data, dict):
        raise CertificateError(f"{where}: a certificate is a JSON object, found {type(data).__name__}")
    return cast("dict[str, Any]", data)


def read_strict_json(path: str | os.PathLike[str], *, constants: bool = False) -> object:
    """A JSON file of the suite (a cell file, a shard manifest) read as strictly as a certificate
    (`parse_strict_json`; with `constants`, NaN / Infinity literals are read, as a cell file holds them); a
    ``CertificateError`` naming the file and the problem otherwise."""
    return parse_strict_json(_read_text(path), os.fspath(path), constants=constants)


def _read_text(path: str | os.PathLike[str]) -> str:
    """A suite file's UTF-8 text; a ``CertificateError`` naming the file when it is missing or unreadable."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CertificateError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CertificateError(f"{path}: cannot read it ({exc})") from None


def parse_strict_json(text: str, where: str, *, constants: bool = False) -> object:
    """`parse_certificate_text` for any JSON value (plain dicts and lists); with `constants`, NaN / Infinity
    literals are numbers (a number literal that overflows still is not: no writer of the suite writes one)."""
    deep = _too_deep(text)
    if deep is not None:
        raise CertificateError(f"{where}: malformed: nested deeper than {MAX_DEPTH} levels at {deep}; a "
                               "certificate is a few levels deep")
    try:
        data = json.loads(text, object_pairs_hook=_pairs, parse_constant=float if constants else _Constant,
                          parse_float=_float, parse_int=_int)
    except json.JSONDecodeError as exc:
        raise CertificateError(f"{where}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})") \
            from None
    except RecursionError:  # MAX_DEPTH is far below the limit; a safety net, never a traceback
        raise CertificateError(f"{where}: malformed: nested too deeply to read") from None
    problem = _strict_problem(data)
    if problem is not None:
        raise CertificateError(f"{where}: malformed: {problem}; certificates are written as strict JSON, so "
                               "this file was not written by drivedegrade or was edited")
    return _plain(data)


def _plain(obj: object) -> Any:
    """The parsed tree with plain dicts (the duplicate-key bookkeeping class dropped)."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_plain(v) for v in obj]
    return obj


def load_certificate(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read and parse a certificate file strictly (see ``parse_certificate_text``); ``CertificateError`` naming
    the file and the problem otherwise."""
    return parse_certificate_text(_read_text(path), os.fspath(path))


def _num(v: object) -> bool:
    return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))


def check_schema(cert: Mapping[str, Any]) -> list[str]:
    """Every malformed field as 'where: what', e.g. ``cells[3].retention: expected a number, found str``."""
    problems = [f"{k}: missing" for k in REQUIRED_KEYS if k not in cert]

    def expect(where: str, value: object, ok: bool, what: str) -> None:
        if not ok:
            problems.append(f"{where}: expected {what}, found {type(value).__name__} {value!r:.40}")

    for sect in ("planner", "dataset", "axes", "floor", "null_control", "verdict", "thresholds", "settings"):
        expect(sect, cert.get(sect), isinstance(cert.get(sect, {}), dict), "an object")
    cells = cert.get("cells", [])
    expect("cells", cells, isinstance(cells, list), "a list")
    for i, c in enumerate(cells if isinstance(cells, list) else []):
        if not isinstance(c, dict):
            expect(f"cells[{i}]", c, False, "an object")
            continue
        for k in ("cell", "family"):
            expect(f"cells[{i}].{k}", c.get(k), isinstance(c.get(k), str), "a string")
        expect(f"cells[{i}].severity", c.get("severity"), type(c.get("severity")) is int, "an integer")
        for k in ("l2_avg", "retention", "retention_ci_low", "retention_ci_high"):
            expect(f"cells[{i}].{k}", c.get(k), _num(c.get(k)), "a number or null")
        if "plans_digest" in c:  # absent from certificates written before digests of the plans existed
            got = c["plans_digest"]
            expect(f"cells[{i}].plans_digest", got, isinstance(got, str) and bool(_HEX64.match(got)),
                   "64 lowercase hex digits")
        for k in ("conformance_errors", "data_errors"):  # failed-frame counts (data_errors: spec 3, may be absent)
            if k in c:
                expect(f"cells[{i}].{k}", c.get(k), type(c.get(k)) is int and c[k] >= 0, "a count")
    digests = cert.get("record_digests", {})  # absent from certificates written before it
    expect("record_digests", digests, isinstance(digests, dict), "an object")
    for cell, got in digests.items() if isinstance(digests, dict) else ():
        expect(f"record_digests.{cell}", got, isinstance(got, str) and bool(_HEX64.match(got)),
               "64 lowercase hex digits")
    for fam, t in (cert.get("thresholds") or {}).items() if isinstance(cert.get("thresholds"), dict) else ():
        for k in ("s10", "s25"):
            v = t.get(k) if isinstance(t, dict) else t
            expect(f"thresholds.{fam}.{k}", v, isinstance(t, dict) and _num(v), "a number or null")
    axes = cast("dict[str, Any]", cert.get("axes") if isinstance(cert.get("axes"), dict) else {})
    for k in ("quality", "removal", "gap", "mean"):
        expect(f"axes.{k}", axes.get(k), _num(axes.get(k)), "a number or null")
    verdict = cast("dict[str, Any]", cert.get("verdict") if isinstance(cert.get("verdict"), dict) else {})
    label = verdict.get("label")
    expect("verdict.label", label, label in (*VERDICT_LABELS, "undetermined"), "a verdict label")
    if "reason" in verdict:  # why the verdict is undetermined by failed frames (SPEC section 11), else null
        expect("verdict.reason", verdict["reason"], verdict["reason"] is None or isinstance(verdict["reason"], str),
               "a string or null")
    if "failed_cells" in verdict:
        expect("verdict.failed_cells", verdict["failed_cells"], isinstance(verdict["failed_cells"], dict),
               "an object")
    expect("digest", cert.get("digest"), isinstance(cert.get("digest"), str) and bool(_HEX64.match(cert["digest"])),
           "64 lowercase hex digits")
    return problems


def verify_data(cert: Mapping[str, object], where: str = "certificate") -> dict[str, Any]:
    """Return `cert` when its digest verifies; raise ``CertificateMismatch`` (edited) or ``CertificateError``."""
    recorded = cert.get("digest")
    if not isinstance(recorded, str):
        raise CertificateError(f"{where}: no digest: this is not a sealed drivedegrade certificate")
    computed = compute_digest(cert)
    problems = check_schema(cert)
    if computed == recorded:
        if problems:  # sealed as is: written by something else, not edited afterwards
            raise CertificateError(f"{where}: digest verifies but the content is malformed: {'; '.join(problems)}")
        return dict(cert)
    recorded_sections = cast("dict[str, Any]",
                             cert.get("section_digests") if isinstance(cert.get("section_digests"), dict) else {})
    sections = sorted(k for k, v in cert.items() if k not in ("digest", "section_digests")
                      and recorded_sections.get(k) != _sha256(v))
    msg = f"{where}: digest mismatch: recorded {recorded}, content hashes to {computed}"
    if sections:
        msg += f"; edited section(s): {', '.join(sections)}"
    if problems:
        msg += f"; malformed: {'; '.join(problems)}"
    raise CertificateMismatch(msg, recorded=recorded, computed=computed, sections=sections, problems=problems)


def verify(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Load and verify a certificate file; returns it when intact (see ``verify_data`` for the errors)."""
    return verify_data(load_certificate(path), where=os.fspath(path))
