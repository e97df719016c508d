"""The route's cameras rendered at any ego pose: the world renderer's steps (`data.world.export.render_scene`)
at the simulated pose instead of the logged one, JPEG round trip included, so that a planner sees what the data
root's images would have shown had the car been there. Only the cameras asked for are rendered."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from ..data.world import models, render, texture
from ..data.world.export import JPEG_QUALITY
from .routes import Route


class RouteCameras:
    """What a route's renders share (ground texture, sky, scenery, per-camera precomputation), built once; then
    `images(pose, step, cameras)`. The random streams are the exporter's, so the textures equal the data's."""

    def __init__(self, route: Route, cameras: Sequence[str]) -> None:
        scene = route.scene
        rng = np.random.default_rng([scene.seed, scene.index, 0x7E27])
        self.route = route
        self.cameras = tuple(cameras)
        self.ground = texture.ground_map(scene.net, scene.ego.xy, scene.style, scene.crosswalks, rng) \
            if self.cameras else None
        self.sky = texture.sky_panorama(scene.style, rng) if self.cameras else None
        self.static = models.Parts()
        if self.cameras:
            for prop in scene.props:
                getattr(models, prop.kind)(self.static, prop, rng)
        self.pre = {cam: render.precompute(route.rig, cam, scene.style.haze_m) for cam in self.cameras}

    def images(self, pose: tuple[float, float, float], step: int) -> dict[str, np.ndarray]:
        """RGB uint8 images of the cameras at world `pose` (x, y, yaw), agents at log `step`."""
        if self.ground is None or self.sky is None:
            return {}
        scene, rig = self.route.scene, self.route.rig
        parts = models.Parts(list(self.static.boxes), list(self.static.colours), dict(self.static.decals))
        render.agent_parts(parts, scene.agents, step)
        out = {}
        for cam in self.cameras:
            info = rig.cameras[cam]
            img = render.draw_background(self.pre[cam], (info.height, info.width), self.ground, self.sky, pose,
                                         scene.style)
            w2c, centre = render.world_to_camera(rig, cam, pose)
            render.draw_shadows(img, scene.agents, step, info, w2c, scene.style)
            render.draw_solids(img, parts, info, w2c, centre, scene.style)
            _, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY,
                                                                                  JPEG_QUALITY])
            decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR)
            assert decoded is not None  # a JPEG just encoded decodes
            out[cam] = cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)
        return out
