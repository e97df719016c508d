"""Atomic file writes: write a temporary file beside the target, then rename over it."""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Collection, Mapping
from pathlib import Path

#: The name of the temporary file `atomic_write_bytes` writes beside `target`: ".<target>.<8 mkstemp characters>.tmp"
#: (what a kill -9 between write and rename leaves behind).
TEMP_NAME = re.compile(r"^\.(?P<target>.+)\.[a-z0-9_]{8}\.tmp$")


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write `data` to `path` so that a reader sees the old file or the new one, never half of one."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)  # TEMP_NAME
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; outputs are meant to be shared and archived
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


def atomic_write_set(files: Mapping[Path, bytes]) -> list[Path]:
    """Write several files as one set: every file to its temporary first (each synced), then each renamed over
    its target in the given order. A failure or a crash while the temporaries are written leaves every target
    as it was; only the renames, a few microseconds, can be cut between (put the file that vouches for the
    others last)."""
    written: list[tuple[str, Path]] = []
    try:
        for target, data in files.items():
            target.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)  # TEMP_NAME
            written.append((tmp, target))
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp, 0o644)
        for tmp, target in written:
            os.replace(tmp, target)
    except BaseException:
        for tmp, _ in written:
            Path(tmp).unlink(missing_ok=True)
        raise
    return [target for _, target in written]


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def stray_temporaries(folder: Path, targets: Collection[str] | None, older_than: float) -> list[Path]:
    """The temporary files of interrupted atomic writes in `folder`: named exactly like ours (`TEMP_NAME`), for
    a target in `targets` (None: any ``*.json`` target), last modified before `older_than` (a POSIX time), so
    a write in flight now is never taken."""
    found = []
    try:
        entries = list(folder.iterdir())
    except OSError:
        return []
    for path in entries:
        match = TEMP_NAME.match(path.name)
        if match is None or not path.is_file() or path.is_symlink():
            continue
        target = match.group("target")
        if (target not in targets) if targets is not None else not target.endswith(".json"):
            continue
        try:
            if path.stat().st_mtime < older_than:
                found.append(path)
        except OSError:
            continue
    return sorted(found)


def neutralise(value: object) -> object:
    """A text cell that a spreadsheet would run as a formula (it starts with = + - @, a tab or a carriage
    return) with a leading apostrophe, as OWASP's CSV-injection advice says; anything else unchanged."""
    return "'" + value if isinstance(value, str) and value[:1] in ("=", "+", "-", "@", "\t", "\r") else value
