"""Cell results on disk: `<report>/<planner>/cells/<cell>.json`, written atomically as each cell finishes.

A stored result is a `CellPayload` with its run key (spec and tool versions, planner and dataset fingerprints,
scored frames, seed) and its record's content digest; a rerun reuses exactly the results whose key matches and
whose record still hashes to its digest, so an interrupted run resumes, a changed planner, data set, ladder or
tool recomputes, and a stored file edited by hand, or without a digest, is recomputed (and reported in
`digest_failures`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .atomic import atomic_write_text
from .errors import InvalidInput
from .payload import CellPayload, RecordDigestMismatch


class ResultStore:
    """`<report>/<planner>/cells/`, or `<report>/<planner>/<shard label>/cells/` for one shard of a run."""

    def __init__(self, report_dir: Path, shard: str | None = None, *, resume: bool = True,
                 reuse: bool = True) -> None:
        self.report_dir, self.shard = Path(report_dir), shard
        #: False (--drivedegrade-no-resume): every read finds nothing, so every cell is computed again
        self.resume = resume
        #: False (--drivedegrade-no-reuse): a stored cell that took the clean plan on a frame is computed again,
        #: so the certificate's settings.reuse false and cost.reused agree (issue 20)
        self.reuse = reuse
        #: cell -> why its stored record was not reused although present: its content digest failed
        self.digest_failures: dict[str, str] = {}
        #: cell -> the run-key fields in which its stored result differed (so it was not reused), comma-separated
        self.stale: dict[str, str] = {}

    def folder(self, planner: str) -> Path:
        """The planner's folder of this run (a shard's own subfolder for a shard)."""
        return self.report_dir / planner / self.shard if self.shard else self.report_dir / planner

    def path(self, planner: str, cell: str) -> Path:
        return self.folder(planner) / "cells" / f"{cell}.json"

    def write(self, payload: CellPayload, text: str | None = None) -> Path:
        """Store `payload`; `text`: its `CellPayload.to_json` already made (the text it was read from), written
        as it is."""
        return atomic_write_text(self.path(payload.planner, payload.cell), payload.to_json() if text is None else text)

    def read(self, planner: str, cell: str, key: Mapping[str, Any]) -> CellPayload | None:
        """The stored payload of `cell` when its run key equals `key`; None when absent, stale, unreadable or
        edited (its record no longer hashes to its digest: noted in `digest_failures`); always None without
        `resume`."""
        if not self.resume:
            return None
        try:
            data = json.loads(self.path(planner, cell).read_text())
            payload = CellPayload.from_builtins(data)
        except RecordDigestMismatch as exc:
            if isinstance(data, dict) and dict(data.get("key") or {}) == dict(key):
                self.digest_failures[cell] = str(exc)
            return None
        except (OSError, ValueError, InvalidInput):
            return None
        if payload.cell != cell:
            return None
        if dict(payload.key) != dict(key):
            self.stale[cell] = ", ".join(sorted(k for k in {*payload.key, *key} if payload.key.get(k) != key.get(k)))
            return None
        if not self.reuse and any(int(getattr(r, "reused", 0)) for r in payload.record.runs()):
            self.stale[cell] = "reuse"
            return None
        return payload

    def read_all(self, planner: str, key: Mapping[str, Any], cells: Iterable[str]) -> dict[str, CellPayload]:
        return {c: p for c in cells if (p := self.read(planner, c, key)) is not None}
