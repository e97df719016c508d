"""Watching `reproduce`'s rerun: the pytest subprocess run with its output into a log, and each sampled cell,
open or closed-loop, handed on as soon as the rerun's store holds it (so a verdict line, and the progress line's
count, come as cells finish, not at the end)."""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..closedloop.cells import ClosedPayload
from ..errors import DriveDegradeError
from ..payload import CellPayload


@dataclass
class Watch:
    """The rerun's finished cells, read from its store as each one is written."""

    report_dir: Path
    wanted: Sequence[str]
    seen: dict[str, CellPayload | ClosedPayload] = field(default_factory=dict)

    def poll(self) -> list[CellPayload | ClosedPayload]:
        new: list[CellPayload | ClosedPayload] = []
        for path in sorted(self.report_dir.glob("*/cells/*.json")):
            if path.stem in self.wanted and path.stem not in self.seen:
                kind = ClosedPayload if path.stem.startswith("closed-") else CellPayload
                try:
                    payload = kind.from_builtins(json.loads(path.read_text()))
                except (OSError, ValueError, DriveDegradeError):
                    continue  # written atomically, so only a file of another kind: read again next time
                self.seen[path.stem] = payload
                new.append(payload)
        return new


def run_watched(argv: Sequence[str], log: Path, watch: Watch, on_cell: Callable[[CellPayload | ClosedPayload], None],
                interval: float = 0.25, tick: Callable[[], None] | None = None) -> int:
    """Run the rerun, its output into `log`, calling `on_cell` for each sampled cell as it finishes (and `tick`
    at every look, for a progress line's clock)."""
    with open(log, "w") as out:
        proc = subprocess.Popen(list(argv), stdout=out, stderr=subprocess.STDOUT)
        try:
            while True:
                done = proc.poll() is not None
                for payload in watch.poll():
                    on_cell(payload)
                if tick is not None:
                    tick()
                if done:
                    return int(proc.returncode)
                time.sleep(interval)
        except BaseException:
            proc.kill()
            proc.wait()
            raise


def tail(path: Path, lines: int = 15) -> str:
    text = path.read_text(errors="replace").splitlines() if path.is_file() else []
    return "\n".join(f"    {line}" for line in text[-lines:])
