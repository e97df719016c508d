"""The run's dataset fingerprint covers the scored frames' files (Trust case 6), with cached digests."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from pytest_drivedegrade.data import content
from pytest_drivedegrade.run import RunContext
from pytest_drivedegrade.settings import RunSettings


@pytest.fixture()
def world(small_world: Path, tmp_path: Path) -> Path:
    """A private copy of the shared small world (`conftest.small_world`), which these tests edit."""
    return Path(shutil.copytree(small_world, tmp_path / "world", copy_function=shutil.copy2))


def _open(root: Path, cache: Path | None, frames: int | None = 4) -> RunContext:
    return RunContext.open(RunSettings(data=root, frames=frames, timeout=0.0), digest_cache=cache)


def test_a_swapped_image_changes_the_fingerprint_the_manifest_does_not(world: Path, tmp_path: Path) -> None:
    """Trust case 6: the world's manifest is unchanged, but the content of one scored image is not."""
    before = _open(world, None)
    front = Path(before.frames[1].cameras["CAM_FRONT"].path)
    other = Path(before.frames[2].cameras["CAM_FRONT"].path)
    assert front.read_bytes() != other.read_bytes()
    shutil.copyfile(other, front)
    after = _open(world, None)
    assert after.reader.fingerprint() == before.reader.fingerprint()  # the manifest-based id cannot see it
    assert after.dataset_fingerprint != before.dataset_fingerprint
    # a file the run does not score (an unscored frame's image) does not change it
    scored = {c.path for f in _open(world, None, frames=None).frames for c in f.cameras.values()}
    unscored = next(p for p in sorted((world / "samples").rglob("*.jpg")) if str(p) not in scored)
    unscored.write_bytes(unscored.read_bytes() + b"\0")
    assert _open(world, None).dataset_fingerprint == after.dataset_fingerprint


def test_a_table_edit_changes_the_fingerprint(world: Path) -> None:
    before = _open(world, None).dataset_fingerprint
    table = next(world.glob("v1.0-*/sample_annotation.json"))
    rows = json.loads(table.read_text())
    rows[0]["translation"][0] += 0.5
    table.write_text(json.dumps(rows))
    assert _open(world, None).dataset_fingerprint != before


def test_digests_are_cached_by_size_and_mtime(world: Path, tmp_path: Path) -> None:
    """A rerun reads no file (all cache hits) and gives the same fingerprint as no cache; a rewritten file is
    read again, and a file with the same size but new content and mtime changes the fingerprint."""
    cache_dir = tmp_path / "cache"
    ctx = _open(world, cache_dir)
    files = list(content.scored_files(ctx.reader, ctx.frames))
    assert len(files) == len({str(f) for f in files}) >= 6 * 4
    first = content.DigestCache(content.cache_file(cache_dir, world))
    assert set(first.entries) == {str(f.absolute()) for f in files}
    uncached = _open(world, None).dataset_fingerprint
    assert _open(world, cache_dir).dataset_fingerprint == ctx.dataset_fingerprint == uncached

    cache = content.DigestCache(content.cache_file(cache_dir, world))
    for f in files:
        cache.digest(f)
    assert (cache.hits, cache.misses) == (len(files), 0)

    front = Path(ctx.frames[0].cameras["CAM_FRONT"].path)
    data = bytearray(front.read_bytes())
    data[len(data) // 2] ^= 0xFF  # same size, other content
    st = front.stat()
    front.write_bytes(bytes(data))
    os.utime(front, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert _open(world, cache_dir).dataset_fingerprint != ctx.dataset_fingerprint
    again = content.DigestCache(content.cache_file(cache_dir, world))
    assert again.entries[str(front.absolute())][2] == content.file_digest(front)


def test_an_unreadable_cache_is_ignored(world: Path, tmp_path: Path) -> None:
    cache_dir = tmp_path / "cache"
    path = content.cache_file(cache_dir, world)
    path.parent.mkdir(parents=True)
    path.write_text("{broken")
    assert _open(world, cache_dir).dataset_fingerprint == _open(world, None).dataset_fingerprint
    assert json.loads(path.read_text())["version"] == content.CACHE_VERSION


def test_lidar_sweeps_are_in_the_fingerprint_and_the_run_key(world: Path) -> None:
    """Issue 37 H4: the LIDAR_TOP sweep of a scored frame (what `FrameContext.lidar_points` reads) changed in
    place (same size: points moved) changes the dataset fingerprint and so the run key, so a LiDAR planner's
    stored cells are recomputed and two data sets differing only in LiDAR are not the same data to the gate,
    `compare` and `merge`; an unscored frame's sweep does not. On the old code the fingerprint was unchanged."""
    import numpy as np

    from pytest_drivedegrade.data.context import LIDAR_POINT_SIZE

    before = _open(world, None)
    sweep = Path(before.frames[1].lidar_file)
    assert sweep.is_file() and sweep.stat().st_size % (4 * LIDAR_POINT_SIZE) == 0
    points = np.fromfile(sweep, dtype=np.float32).copy()
    points[0] += 1.0
    points.tofile(sweep)
    after = _open(world, None)
    assert after.reader.fingerprint() == before.reader.fingerprint()  # the manifest cannot see it
    assert after.dataset_fingerprint != before.dataset_fingerprint
    assert sweep in set(content.scored_files(after.reader, after.frames))
    # an unscored frame's sweep: not read by the run, not in its fingerprint
    every = _open(world, None, frames=None).frames
    scored = {f.lidar_file for f in after.frames}
    unscored = next(Path(f.lidar_file) for f in every if f.lidar_file and f.lidar_file not in scored)
    unscored.write_bytes(unscored.read_bytes()[::-1])
    assert _open(world, None).dataset_fingerprint == after.dataset_fingerprint
