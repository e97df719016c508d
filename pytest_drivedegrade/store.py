"""Cell results on disk: `<report>/<planner>/cells/<cell>.json`, written atomically as each cell finishes.

A stored result carries the run key (spec version, planner and dataset fingerprints, scored frames, seed);
a rerun reuses exactly the results whose key matches, so an interrupted run resumes and a changed planner,
data set or ladder recomputes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .report.io import atomic_write_text


class ResultStore:
    def __init__(self, report_dir: Path) -> None:
        self.report_dir = Path(report_dir)

    def path(self, planner: str, cell: str) -> Path:
        return self.report_dir / planner / "cells" / f"{cell}.json"

    def write(self, payload: dict[str, Any]) -> Path:
        record = payload["record"]
        return atomic_write_text(self.path(payload["planner"], record["cell"]), json.dumps(payload, allow_nan=True))

    def read(self, planner: str, cell: str, key: dict[str, Any]) -> dict[str, Any] | None:
        """The stored payload of `cell` when its run key equals `key`; None when absent, stale or unreadable."""
        path = self.path(planner, cell)
        try:
            payload = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(payload, dict) or payload.get("key") != key or "record" not in payload:
            return None
        return payload

    def read_all(self, planner: str, key: dict[str, Any], cells: list[str]) -> dict[str, dict[str, Any]]:
        return {c: p for c in cells if (p := self.read(planner, c, key)) is not None}
