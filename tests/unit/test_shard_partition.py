"""Scene shards: contiguous, balanced by frame count, whole scenes, in order, and the I/N syntax."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pytest_drivedegrade.errors import DriveDegradeError
from pytest_drivedegrade.shards import Shard, partition, shard_frames


def frames_of(sizes: list[int]) -> list[SimpleNamespace]:
    return [SimpleNamespace(scene_token=f"s{i}", token=f"s{i}f{k}") for i, n in enumerate(sizes) for k in range(n)]


def test_known_partition():
    frames = frames_of([34, 34, 10, 10, 34, 20])  # 142 frames: ideal cuts at 47.3 and 94.7
    shards = partition(frames, 3)  # type: ignore[arg-type]
    assert [len(s) for s in shards] == [34, 54, 54]  # cumulative 34 is nearest 47.3, 88 nearest 94.7
    assert [f.token for s in shards for f in s] == [f.token for f in frames]
    assert shard_frames(frames, Shard(2, 3)) == shards[1]  # type: ignore[arg-type]


@given(st.lists(st.integers(1, 40), min_size=1, max_size=30), st.integers(1, 8))
def test_partition_properties(sizes, count):
    frames = frames_of(sizes)
    if count > len(sizes):
        with pytest.raises(DriveDegradeError, match="cannot split"):
            partition(frames, count)  # type: ignore[arg-type]
        return
    shards = partition(frames, count)  # type: ignore[arg-type]
    assert len(shards) == count and all(shards)
    assert [f for s in shards for f in s] == frames  # order kept, nothing lost or repeated
    scenes = [{f.scene_token for f in s} for s in shards]
    assert all(a.isdisjoint(b) for i, a in enumerate(scenes) for b in scenes[i + 1:])  # whole scenes
    # balanced: each cut is within the largest scene of its ideal position
    total, biggest = sum(sizes), max(sizes)
    done = 0
    for k, shard in enumerate(shards[:-1], start=1):
        done += len(shard)
        assert abs(done - total * k / count) <= biggest


@pytest.mark.parametrize(("text", "shard"), [("1/1", Shard(1, 1)), (" 3 / 8 ", Shard(3, 8))])
def test_shard_syntax(text, shard):
    assert Shard.parse(text) == shard and shard.label == f"shard-{shard.index}-of-{shard.count}"


@pytest.mark.parametrize("text", ["0/2", "3/2", "2", "a/b", "1/0"])
def test_bad_shard_syntax(text):
    with pytest.raises(DriveDegradeError):
        Shard.parse(text)
