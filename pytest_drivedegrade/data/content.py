"""The content fingerprint of a run's data: what the scored frames are actually read from, not what a manifest says.

`content_fingerprint` hashes the reader's identity (`NuScenesReader.fingerprint`: the split and the world's
manifest, or the scene list) together with the size and content digest of every file a run's scores depend on:
the tables of the version folder (calibration and ego poses included), each scored frame's six camera images and
its LIDAR_TOP sweep (`FrameContext.lidar_file`, issue 37 H4), and the CAN bus and map expansion files of the
scored scenes: every file the frame context hands a planner. A swapped image or sweep therefore changes the run
key and its cells are recomputed.

Digests are cached per data root in a small JSON file keyed by (path, size, mtime_ns), written atomically, so a
rerun stats the files instead of reading them. A file replaced with the same size and the same nanosecond
mtime (a deliberate `touch -r`) is not noticed; anything else is.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

from ..atomic import atomic_write_text
from ..constants import CAMERAS
from .frame import Frame
from .nuscenes import NuScenesReader

#: The cache file's layout version: another version is ignored (recomputed), never misread.
CACHE_VERSION = 1
_CHUNK = 1 << 20


def file_digest(path: str | os.PathLike[str]) -> str:
    """BLAKE2b-128 hex of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def scored_files(reader: NuScenesReader, frames: Sequence[Frame]) -> Iterator[Path]:
    """Every file the scores of `frames` are read from, in a fixed order, each once: the tables, then per frame
    its camera images (camera order) and its LIDAR_TOP sweep (when the data set has one), then the CAN bus and
    map files of the scenes and locations (when present)."""
    yield from sorted(reader.table_dir.glob("*.json"))
    seen_scenes: dict[str, None] = {}
    seen_locations: dict[str, None] = {}
    for frame in frames:
        for camera in CAMERAS:
            if camera in frame.cameras:
                yield Path(frame.cameras[camera].path)
        if frame.lidar_file:
            yield Path(frame.lidar_file)
        seen_scenes.setdefault(frame.scene_name, None)
        if frame.location:
            seen_locations.setdefault(frame.location, None)
    for scene in seen_scenes:
        can = reader.root / "can_bus" / f"{scene}_pose.json"
        if can.is_file():
            yield can
    for location in seen_locations:
        area = reader.root / "maps" / "expansion" / f"{location}.json"
        if area.is_file():
            yield area


class DigestCache:
    """File digests by absolute path, valid while the file's (size, mtime_ns) is unchanged."""

    def __init__(self, path: Path | None) -> None:
        self.path, self.entries, self.changed = path, {}, False
        self.hits = self.misses = 0
        if path is not None and path.is_file():
            try:
                data = json.loads(path.read_text())
            except (OSError, ValueError):
                data = None  # unreadable: start afresh, it is only a cache
            if isinstance(data, dict) and data.get("version") == CACHE_VERSION and isinstance(data.get("files"), dict):
                self.entries = data["files"]

    def digest(self, path: Path) -> tuple[int, str]:
        """(size, digest) of `path`; (-1, "missing") when it cannot be read (the cell that reads it says why)."""
        try:
            st = path.stat()
        except OSError:
            return -1, "missing"
        key = str(path.absolute())
        cached = self.entries.get(key)
        if isinstance(cached, list) and len(cached) == 3 and cached[:2] == [st.st_size, st.st_mtime_ns]:
            self.hits += 1
            return st.st_size, str(cached[2])
        try:
            digest = file_digest(path)
        except OSError:
            return -1, "unreadable"
        self.misses += 1
        self.entries[key] = [st.st_size, st.st_mtime_ns, digest]
        self.changed = True
        return st.st_size, digest

    def save(self) -> None:
        if self.path is not None and self.changed:
            try:
                atomic_write_text(self.path, json.dumps({"version": CACHE_VERSION, "files": self.entries}))
            except OSError:
                pass  # a read-only cache folder costs speed, not correctness
            self.changed = False


def cache_file(cache_dir: Path, root: Path) -> Path:
    """The digest cache of one data root inside `cache_dir`."""
    name = hashlib.blake2b(str(root.absolute()).encode(), digest_size=8).hexdigest()
    return cache_dir / f"digests-{name}.json"


def content_fingerprint(reader: NuScenesReader, frames: Sequence[Frame], cache_dir: Path | None = None) -> str:
    """A stable hex id of the data a run scores (see the module docstring); digests cached under `cache_dir`."""
    cache = DigestCache(None if cache_dir is None else cache_file(cache_dir, reader.root))
    h = hashlib.blake2b(digest_size=16)
    h.update(f"content-v1|{reader.fingerprint()}".encode())
    for path in scored_files(reader, frames):
        size, digest = cache.digest(path)
        try:
            shown = path.relative_to(reader.root).as_posix()
        except ValueError:
            shown = path.as_posix()
        h.update(f"|{shown}|{size}|{digest}".encode())
    cache.save()
    return h.hexdigest()
