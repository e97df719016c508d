"""The route's cameras rendered at any ego pose: the world renderer's steps (`data.world.export.render_scene`)
at the simulated pose instead of the logged one, JPEG round trip included, so that a planner sees what the data
root's images would have shown had the car been there. Only the cameras asked for are rendered.

Faster than rendering a keyframe from scratch, with the same pixels: the backdrop (ground, sky, scenery) is built
once per route and process, and agents the renderer would skip (too far for their parts or shadows) are never
modelled."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..data.world import models, render, texture
from ..data.world.agents import DT
from ..data.world.export import camera_jpeg, scene_backdrop
from .routes import Route

#: Agents farther than this from the ego (m) have no part the renderer draws (a part's centre within 6 m of its
#: agent's, the camera within 3 m of the ego, parts beyond render.SOLID_MAX skipped): they are not modelled.
SOLID_REACH = render.SOLID_MAX + 25.0
#: Agents farther than this from the camera (m) cast no shadow the renderer draws (it stops at 80 m).
SHADOW_REACH = 81.0
#: Routes whose backdrops a process keeps (ground maps are 40 to 70 MB each at 800x450: about 0.5 GB at most).
BACKDROPS_KEPT = 8


@dataclass
class Backdrop:
    """What every render of a route shares and nothing in a run changes: ground texture, sky, static scenery and
    the per-camera precomputation (filled as cameras are asked for). Built by the exporter's random streams in the
    exporter's order, so the textures equal the data's."""

    ground: texture.GroundMap
    sky: np.ndarray
    static: models.Parts
    pre: dict[str, render.CameraPrecomp] = field(default_factory=dict)

    def camera(self, route: Route, cam: str) -> render.CameraPrecomp:
        if cam not in self.pre:
            self.pre[cam] = render.precompute(route.rig, cam, route.scene.style.haze_m)
        return self.pre[cam]


_BACKDROPS: OrderedDict[tuple[int, int, str, int, int], Backdrop] = OrderedDict()
_LOCK = threading.Lock()


def backdrop(route: Route) -> Backdrop:
    """The route's backdrop, built once per process and kept for the next runs of the route (other seeds, other
    cells; the reactive copy of a route shares its scene's backdrop): the least recently used goes first."""
    scene = route.scene
    front = route.rig.cameras["CAM_FRONT"]
    key = (int(scene.seed), int(scene.index), scene.name, int(front.width), int(front.height))
    with _LOCK:
        if key in _BACKDROPS:
            _BACKDROPS.move_to_end(key)
            return _BACKDROPS[key]
        made = _BACKDROPS[key] = Backdrop(*scene_backdrop(scene))
        while len(_BACKDROPS) > BACKDROPS_KEPT:
            _BACKDROPS.popitem(last=False)
        return made


class RouteCameras:
    """A route's cameras at any pose: `images(pose, step)`; the backdrop comes from the process's cache."""

    def __init__(self, route: Route, cameras: Sequence[str]) -> None:
        self.route = route
        self.cameras = tuple(cameras)
        self.backdrop = backdrop(route) if self.cameras else None
        self.pre = {cam: self.backdrop.camera(route, cam) for cam in self.cameras} if self.backdrop else {}

    def parts(self, pose: tuple[float, float, float], step: int) -> models.Parts:
        """The scenery's and the near agents' parts at log `step` (what every camera at `pose` draws)."""
        assert self.backdrop is not None
        back = self.backdrop
        parts = models.Parts(list(back.static.boxes), list(back.static.colours), dict(back.static.decals))
        near = [a for a in self.route.scene.agents if np.hypot(*(a.xy[step] - pose[:2])) < SOLID_REACH]
        render.agent_parts(parts, near, step)
        if self.route.scene.lights:
            models.light_parts(parts, self.route.scene.net, self.route.scene.lights, step, DT)
        return parts

    def one(self, cam: str, parts: models.Parts, pose: tuple[float, float, float], step: int) -> np.ndarray:
        """Camera `cam`'s RGB uint8 image at world `pose` with `parts` (`parts`), through the JPEG round trip.
        Reads the backdrop and `parts` only: cameras may render on threads at once."""
        assert self.backdrop is not None
        back = self.backdrop
        buf = camera_jpeg(self.route.scene, self.route.rig, cam, self.pre[cam], (back.ground, back.sky, back.static),
                          parts, pose, step, shadow_reach=SHADOW_REACH)
        decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        assert decoded is not None  # a JPEG just encoded decodes
        return cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)

    def images(self, pose: tuple[float, float, float], step: int) -> dict[str, np.ndarray]:
        """RGB uint8 images of the cameras at world `pose` (x, y, yaw), agents at log `step`."""
        if self.backdrop is None:
            return {}
        parts = self.parts(pose, step)
        return {cam: self.one(cam, parts, pose, step) for cam in self.cameras}


def images_at(route: Route, cameras: Sequence[str], pose: tuple[float, float, float], keyframe: int
              ) -> dict[str, np.ndarray]:
    """The route's `cameras` as they would have looked from world `pose` (x, y, yaw) at log keyframe `keyframe`
    (its agents where they were then): the images a second stage starting off the logged pose reads (NAVSIM
    renders them in advance by Gaussian splatting; the world renders them exactly). At the logged pose they are
    the data's images, byte for byte."""
    from ..data.world.expert import KEY_EVERY

    return RouteCameras(route, cameras).images(pose, int(keyframe) * KEY_EVERY)
