"""Routes: each val scene of the embedded world is one route, regenerated from the world's manifest, and so is
each of the world's scenario scenes (`data.world.scenarios`: generated for the closed loop only, so the open-loop
frames never change; `SCENARIO_ROUTES` of them follow the val routes).

A route starts at the logged ego state of the scene's first keyframe and follows the scene's lane (the path the
logged expert drove); its length is the distance the logged ego covers over the scene's keyframes. The world's
generator is deterministic in (seed, index), so the scene (roads, agents' logs, scenery, appearance) is the
one the data root's tables and images were written from.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data.nuscenes import WORLD_MANIFEST
from ..data.world.expert import KEY_EVERY
from ..data.world.rig import Rig
from ..data.world.roads import Path as LanePath
from ..data.world.scenarios import light_scene, scenario_scene
from ..data.world.scene import KEYFRAMES, Scene, make_scene
from ..errors import DataError

#: Scenario routes after the val routes: with the default world's 6 val scenes, 24 distinct routes (30 with the
#: light routes).
SCENARIO_ROUTES = 18
#: Light routes (`data.world.scenarios.light_scene`: a traffic light whose red meets the ego) after them.
LIGHT_ROUTES = 6
#: Held-out routes (`held_out_routes`): scenario and light scenes numbered from HELD_OUT_FROM, in neither the slice
#: nor the reference driver's training routes (planners/train_closed_driver.py numbers them from 1000 and refuses
#: to reach HELD_OUT_FROM); choices about a driver are made on them, not on the slice.
HELD_OUT_FROM, HELD_OUT_SCENARIOS, HELD_OUT_LIGHTS = 3000, 24, 16


@dataclass(frozen=True)
class Route:
    """One route: its scene (world seed, index, name), the lane it follows, where it starts and how long it is.

    `start_step` is the 10 Hz log step of the start (the first keyframe); `length` (m) the logged ego's arc length
    from there to the scene's last keyframe; `start_s` its arc length on `lane` at the start."""

    name: str
    scene: Scene
    rig: Rig
    start_step: int
    start_s: float
    length: float

    @property
    def lane(self) -> LanePath:
        return self.scene.lane

    @property
    def end_step(self) -> int:
        """The last log step the agents have (the run stops there at the latest: the scene's end)."""
        return int(len(self.scene.ego.s) - 1)


def route_of(scene: Scene, rig: Rig | None = None) -> Route:
    """The route of one world scene (rig: the nuScenes-like rig at the world's image size)."""
    start = 0
    last = (KEYFRAMES - 1) * KEY_EVERY
    length = float(scene.ego.s[last] - scene.ego.s[start])
    return Route(scene.name, scene, rig or Rig.nuscenes_like(False), start, float(scene.ego.s[start]), length)


def load_routes(root: str | os.PathLike[str], scenarios: int = SCENARIO_ROUTES,
                limit: int | None = None, lights: int = LIGHT_ROUTES) -> list[Route]:
    """The routes of a world data root: its val scenes, in split order, then its first `scenarios` scenario
    scenes, then its first `lights` light scenes; the first `limit` of them only (None: all). A data root that is
    not the embedded world (no manifest) has no geometry to render at a new pose: DataError."""
    manifest_path = Path(root) / WORLD_MANIFEST
    if not manifest_path.is_file():
        raise DataError(f"{root}: the closed loop needs the embedded world (no {WORLD_MANIFEST}); real logs cannot "
                        "be rendered at a pose the car did not drive")
    manifest = json.loads(manifest_path.read_text())
    seed, full_size = int(manifest["seed"]), bool(manifest.get("full_size", False))
    train, val = list(manifest["splits"]["train"]), list(manifest["splits"]["val"])
    names = train + val
    rig = Rig.nuscenes_like(full_size)
    limit = len(val) + scenarios + lights if limit is None else limit
    n_scenarios = min(scenarios, max(limit - len(val), 0))
    return [*(route_of(make_scene(seed, names.index(name), name), rig) for name in val[:limit]),
            *(route_of(scenario_scene(seed, i), rig) for i in range(n_scenarios)),
            *(route_of(light_scene(seed, i), rig) for i in range(min(lights, max(limit - len(val) - scenarios, 0))))]


def held_out_routes(root: str | os.PathLike[str]) -> list[Route]:
    """The held-out routes of a world data root: HELD_OUT_SCENARIOS scenario scenes and HELD_OUT_LIGHTS light
    scenes of its seed, numbered from HELD_OUT_FROM (benchmarks/closedloop.py --held-out)."""
    seed = int(json.loads((Path(root) / WORLD_MANIFEST).read_text())["seed"])
    return [*(route_of(scenario_scene(seed, HELD_OUT_FROM + i)) for i in range(HELD_OUT_SCENARIOS)),
            *(route_of(light_scene(seed, HELD_OUT_FROM + i)) for i in range(HELD_OUT_LIGHTS))]


def lane_progress(route: Route, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Progress along the route (m from the start, may be negative) and lateral offset of points (N, 2)."""
    s, d = route.lane.project(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    return s - route.start_s, d
