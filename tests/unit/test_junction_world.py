"""Issue 40 (enough junction frames for a command label): a world's junction scenes, in a split of their own.

The default world's val split holds 4 frames where another command is meaningful, all from one scene: no interval
over scenes can label a planner on them. `drivedegrade world --junction-scenes N` adds N scenes whose route turns at
a junction the logged ego enters while its frames are scored (own scene numbers, so their own random stream); the
train and val scenes keep every record, so the floor and every cell on val are unchanged."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pytest_drivedegrade.data.junctions import alternative
from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.data.world.build import MANIFEST, WORLD_VERSION, write_world
from pytest_drivedegrade.data.world.junctionscenes import (
    JUNCTION_BASE,
    JUNCTION_SPLIT,
    junction_indices,
    turns_at_junction,
)
from pytest_drivedegrade.errors import DataError


@pytest.fixture(scope="module")
def worlds(tmp_path_factory):
    """A 2-scene world (tables only) and the same world with 2 junction scenes."""
    root = tmp_path_factory.mktemp("jw")
    plain = write_world(root / "plain", scenes=2, val_images=False, workers=1)
    more = write_world(root / "more", scenes=2, val_images=False, workers=1, junction_scenes=2)
    return plain, more


def test_junction_scenes_are_drawn_from_their_own_numbers_deterministically() -> None:
    got = junction_indices(0, 3)
    assert got == junction_indices(0, 3) and got == sorted(got) and got[0] >= JUNCTION_BASE
    assert all(turns_at_junction(0, i) for i in got)
    skipped = [i for i in range(JUNCTION_BASE, got[-1]) if i not in got]
    assert skipped and not any(turns_at_junction(0, i) for i in skipped)  # the first that turn, in order
    assert junction_indices(0, 0) == []


def test_train_and_val_keep_every_record_and_the_junction_split_is_its_own(worlds) -> None:
    plain, more = worlds
    a, b = (json.loads((w / MANIFEST).read_text()) for w in (plain, more))
    assert JUNCTION_SPLIT not in a["splits"] and b["splits"][JUNCTION_SPLIT] == ["ddjunction-0001", "ddjunction-0002"]
    assert (a["splits"]["train"], a["splits"]["val"]) == (b["splits"]["train"], b["splits"]["val"])
    assert a["events"]["train"] == b["events"]["train"] and a["events"]["val"] == b["events"]["val"]
    assert a["fingerprint"] != b["fingerprint"]
    for table in ("scene", "sample", "ego_pose", "sample_data", "sample_annotation", "instance", "log"):
        old = json.loads((plain / WORLD_VERSION / f"{table}.json").read_text())
        new = json.loads((more / WORLD_VERSION / f"{table}.json").read_text())
        assert new[:len(old)] == old and len(new) > len(old), table  # the junction scenes' records appended
    for split in ("train", "val"):
        old = [f.token for f in NuScenesReader(plain, split=split).scorable_frames(agents=False)]
        assert [f.token for f in NuScenesReader(more, split=split).scorable_frames(agents=False)] == old


def test_every_junction_scene_gives_frames_where_another_command_is_meaningful(worlds) -> None:
    reader = NuScenesReader(worlds[1], split=JUNCTION_SPLIT)
    per_scene: dict[str, int] = {}
    for f in reader.scorable_frames(agents=False):
        alt = alternative(reader.lane_map(f), f.pose, f.gt_future, f.command)
        per_scene[f.scene_token] = per_scene.get(f.scene_token, 0) + (alt is not None)
        if alt is not None:
            assert alt.command != f.command and np.linalg.norm(alt.path[-1] - f.gt_future[-1]) >= 1.0
    assert len(per_scene) == 2 and all(n >= 2 for n in per_scene.values()), per_scene


def test_a_world_without_junction_scenes_says_how_to_get_them(worlds) -> None:
    with pytest.raises(DataError, match="--junction-scenes N"):
        NuScenesReader(worlds[0], split=JUNCTION_SPLIT)
    with pytest.raises(DataError, match="junction_scenes is a count"):
        write_world(worlds[0].parent / "bad", scenes=2, val_images=False, junction_scenes=-1)
