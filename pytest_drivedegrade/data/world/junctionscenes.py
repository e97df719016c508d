"""Junction scenes for the command probe (spec 5, issue 40): scenes whose route turns at a junction the ego
reaches while its frames are scored, so the lane map allows another manoeuvre (`data.junctions.alternative`).

The default world's val split holds 4 such frames from 2 scenes: too few for a command label with a scene-cluster
interval (`scoring.clusters.MIN_SCENES_FOR_CONFIDENCE`). A world built with ``junction_scenes=N`` (``drivedegrade
world --junction-scenes N``) adds N scenes in a split of their own, ``junction``, rendered at build like val. Each
is an open-loop scene of `scene.make_scene`, drawn at scene numbers from `JUNCTION_BASE` (an index space no world's
open-loop scenes reach, so its random stream is its own): the numbers are taken in order, keeping those whose road
turns left or right at a junction and whose logged ego enters the junction's square at a scored keyframe (so the
frames approaching it are scored; a scene whose ego is held up behind traffic never gets there). Of the first 16
scenes the road alone kept (a turn within `MAX_JUNCTION_S` m), 8 had frames with an alternative command; the ego's
entry picks 10 of them, 9 with such frames (the tenth crawls in at 3 m/s, where the two manoeuvres part by less than
`junctions.MIN_SEPARATION_M` within the horizon). The train and val scenes, their tables,
images and the floor trained on them are untouched; a world with N = 0 is byte for byte the world without the
option (tests/unit/test_junction_world.py).
"""

from __future__ import annotations

import numpy as np

from .expert import KEY_EVERY
from .roads import build_roads, in_junction
from .scene import KEYFRAMES, make_scene

#: Junction scenes are numbered from here in the scene index space (scenario scenes start at 100_000).
JUNCTION_BASE = 200_000
#: The furthest junction centre (m along the route) a junction scene may have.
MAX_JUNCTION_S = 200.0
#: The split the junction scenes form in a world's manifest.
JUNCTION_SPLIT = "junction"
#: Scene numbers tried per junction scene wanted before giving up (about one draw in four is kept).
TRIES_PER_SCENE = 50
#: The keyframes of a scene that are scored (each needs six future keyframes).
SCORED_KEYFRAMES = KEYFRAMES - 6


def turns_at_junction(seed: int, index: int) -> bool:
    """Whether scene `index` of the world with `seed` turns left or right at a junction its logged ego enters at
    a scored keyframe. `scene.make_scene` draws its roads first from this same stream, so the cheap road check
    comes first and the scene is generated only for a road that turns."""
    net = build_roads(np.random.default_rng([seed, index, 0x5EED]))
    if not net.junctions or net.junctions[0].turn == "straight" or net.junctions[0].s_route > MAX_JUNCTION_S:
        return False
    scene = make_scene(seed, index, "probe")
    return bool(in_junction(scene.net, scene.ego.xy[np.arange(SCORED_KEYFRAMES) * KEY_EVERY]).any())


def junction_indices(seed: int, n: int) -> list[int]:
    """The scene numbers of a world's `n` junction scenes, in order (deterministic in (seed, n))."""
    found: list[int] = []
    for index in range(JUNCTION_BASE, JUNCTION_BASE + TRIES_PER_SCENE * max(n, 1)):
        if len(found) == n:
            break
        if turns_at_junction(seed, index):
            found.append(index)
    if len(found) < n:
        raise RuntimeError(f"world seed {seed}: only {len(found)} of {n} junction scenes in "
                           f"{TRIES_PER_SCENE * n} draws")
    return found


def junction_names(n: int) -> list[str]:
    """The junction scenes' names (no official nuScenes list names them)."""
    return [f"ddjunction-{i + 1:04d}" for i in range(n)]


__all__ = ["JUNCTION_BASE", "JUNCTION_SPLIT", "junction_indices", "junction_names", "turns_at_junction"]
