"""What the planner is given at a route step: the simulated ego status, the route command and the frame
context of the simulated pose (nuScenes conventions, as `data.context.FrameContext.of` builds for a keyframe)."""

from __future__ import annotations

from collections.abc import Sequence
from types import MappingProxyType

import numpy as np

from ..constants import HORIZON_STEPS, PAST_STEPS, STEP_SECONDS
from ..data import geometry as geo
from ..data.context import CameraCalibration, FrameContext
from ..data.frame import Command, EgoStatus, command_from_future
from ..data.world import sensing
from ..data.world.export import timestamp
from .routes import Route, lane_progress


def to_ego(xy: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    """World points (N, 2) in the ego frame of world `pose` (x, y, yaw)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    rel = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - np.array(pose[:2])
    return np.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c], axis=1)


def ego_status(history: Sequence[tuple[float, float, float]], pose: tuple[float, float, float], speed: float,
               accel: float, yaw_rate: float) -> EgoStatus:
    """The ego status of the simulated state: body-frame velocity, acceleration (lateral: the centripetal v x yaw
    rate, as the reader derives it from poses), yaw rate, and the last
    PAST_STEPS route-step poses in the current frame (oldest first; before the start, the reader's rule:
    extrapolated back at the current velocity)."""
    past = np.zeros((PAST_STEPS, 2))
    for n in range(1, PAST_STEPS + 1):
        row = PAST_STEPS - n
        past[row] = to_ego(np.array(history[-n][:2]), pose)[0] if n <= len(history) else \
            -np.array([speed, 0.0]) * n * STEP_SECONDS
    return EgoStatus((float(speed), 0.0), (float(accel), float(speed * yaw_rate)), float(yaw_rate), past)


def route_command(route: Route, pose: tuple[float, float, float], speed: float) -> Command:
    """The navigation command: where the route's lane goes over the next 3 s at the current speed (at least
    2 m/s), with the reader's threshold rule (`command_from_future`)."""
    s, _ = lane_progress(route, np.array(pose[:2]))
    ahead = route.start_s + float(s[0]) + max(speed, 2.0) * STEP_SECONDS * np.arange(1, HORIZON_STEPS + 1)
    x, y, _ = route.lane.at(ahead)
    return command_from_future(to_ego(np.stack([x, y], axis=1), pose))


def _calibration(route: Route) -> tuple[dict[str, CameraCalibration], dict[str, np.ndarray]]:
    calibration, lidar2img = {}, {}
    lidar2ego = geo.transform(sensing.LIDAR_ROTATION, sensing.LIDAR_TRANSLATION)
    for name, cam in route.rig.cameras.items():
        cal = CameraCalibration(np.array(cam.intrinsic, dtype=np.float64),
                                geo.transform(cam.rotation, cam.translation), (int(cam.width), int(cam.height)))
        calibration[name] = cal
        viewpad = np.eye(4)
        viewpad[:3, :3] = cal.intrinsic
        lidar2img[name] = viewpad @ geo.invert(cal.sensor2ego) @ lidar2ego
    return calibration, lidar2img


def frame_context(route: Route, step: int, pose: tuple[float, float, float], status: EgoStatus) -> FrameContext:
    """The context of route step `step` at the simulated `pose`: index = the route step, time = the scene's
    first keyframe plus 0.5 s a step, ego2global of the pose, the rig's calibration, the CAN-bus vector of the
    simulated motion."""
    rotation, translation = geo.yaw_to_quat(pose[2]), (pose[0], pose[1], 0.0)
    calibration, lidar2img = _calibration(route)
    degrees = float(np.degrees(pose[2])) % 360.0
    can = np.array([*translation, *rotation, *status.acceleration, 0.0, 0.0, 0.0, status.yaw_rate,
                    *status.velocity, 0.0, np.radians(degrees), degrees], dtype=np.float64)
    stamp = timestamp(route.scene, 0) + int(round(step * STEP_SECONDS * 1e6))
    ctx = FrameContext(f"{route.name}/closed/{step}", route.name, route.name, int(step), stamp,
                       geo.transform(rotation, translation), MappingProxyType(calibration),
                       MappingProxyType(lidar2img), can)
    return ctx.private()
