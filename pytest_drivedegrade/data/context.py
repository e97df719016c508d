"""The frame context (SPEC section 8): what a temporal, calibrated planner needs to know about a keyframe
besides its images, as UniAD / VAD / BEVFormer build it in their `img_metas`.

Everything is read-only and never names the corruption applied. A planner receives it as the `context` argument
of ``predict(images, ego, cmd, context)`` when its `predict` declares that parameter. A LiDAR or fusion planner
asks for the keyframe's LIDAR_TOP sweep with ``context.lidar_points()``: the file as recorded, never corrupted
(the ladder corrupts cameras only), read only when asked.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np

from ..errors import DataError
from . import geometry as geo
from .frame import Frame

#: Length of the BEVFormer / UniAD CAN-bus vector.
CAN_BUS_SIZE = 18
#: Values per point of a nuScenes LIDAR_TOP ``.pcd.bin``: x, y, z (m, sensor frame), intensity, ring index.
LIDAR_POINT_SIZE = 5


def load_points(path: str) -> np.ndarray:
    """A nuScenes ``.pcd.bin`` sweep as a read-only (N, 5) float32 array (x, y, z, intensity, ring), as the
    devkit's ``LidarPointCloud.from_file`` reads it; a missing or truncated file is a DataError."""
    try:
        raw = np.fromfile(path, dtype=np.float32)
    except OSError as exc:
        raise DataError(f"cannot read the LIDAR_TOP sweep {path}: {exc}; restore the file or re-extract the "
                        f"data set") from exc
    size = os.path.getsize(path)
    if raw.size % LIDAR_POINT_SIZE or size % 4 or not raw.size:
        raise DataError(f"LIDAR_TOP sweep {path} holds {size} bytes, not a whole, non-empty number of points of "
                        f"{LIDAR_POINT_SIZE} float32 values (x, y, z, intensity, ring): the file is truncated; "
                        "restore it")
    points = raw.reshape(-1, LIDAR_POINT_SIZE)
    if not np.isfinite(points[:, :3]).all():
        raise DataError(f"LIDAR_TOP sweep {path} holds a non-finite point coordinate (NaN or inf); restore it")
    points.setflags(write=False)
    return points


def _frozen(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class CameraCalibration:
    """One camera: `intrinsic` (3x3) for the delivered image size, `sensor2ego` (4x4, camera -> ego, metres),
    `image_size` (width, height) in pixels."""

    intrinsic: np.ndarray
    sensor2ego: np.ndarray
    image_size: tuple[int, int]


@dataclass(frozen=True)
class FrameContext:
    """A keyframe's identity, time, pose and calibration (nuScenes conventions: quaternions (w, x, y, z), a
    record's transform maps its own frame into its parent's; the ego frame has x forward, y left, z up).

    - `index`: position of the keyframe in its scene (0 at the scene's first keyframe).
    - `timestamp`: microseconds.
    - `ego2global`: 4x4, ego -> global.
    - `calibration`: camera -> `CameraCalibration`.
    - `lidar2img`: camera -> 4x4 projection of LIDAR_TOP points into that camera's pixels (``K @ inv(cam2ego) @
      lidar2ego``, with K padded to 4x4), as mmdet3d builds it; None when the data set has no LIDAR_TOP.
    - `can_bus`: BEVFormer's 18 values: ego2global translation (3), rotation quaternion (4), acceleration (3),
      rotation rate (3), velocity (3), then the heading in radians and in degrees (0..360). From the CAN bus
      expansion when present, else from the ego status the reader derived from `ego_pose`.
    - `lidar2ego`: 4x4, LIDAR_TOP -> ego; None when the data set has no LIDAR_TOP.
    - `lidar_file`: the keyframe's LIDAR_TOP sweep ("" without one); read it with `lidar_points()`.
    """

    token: str
    scene_token: str
    scene_name: str
    index: int
    timestamp: int
    ego2global: np.ndarray
    calibration: Mapping[str, CameraCalibration]
    lidar2img: Mapping[str, np.ndarray] | None
    can_bus: np.ndarray | None
    lidar2ego: np.ndarray | None = None
    lidar_file: str = ""

    def lidar_points(self) -> np.ndarray | None:
        """The keyframe's LIDAR_TOP points, (N, 5) float32 read-only in the sensor frame (`lidar2ego` maps them
        to the ego frame), as recorded: the same in every cell, blackout included. None when there is no sweep
        (a data set without LIDAR_TOP, a closed-loop step at a simulated pose). Each call reads the file anew,
        so the array is the caller's own."""
        return load_points(self.lidar_file) if self.lidar_file else None

    @classmethod
    def of(cls, frame: Frame) -> FrameContext:
        """The context of a reader's frame (arrays read-only, mappings immutable)."""
        rotation, translation = frame.ego_pose
        calibration = {name: CameraCalibration(_frozen(cam.intrinsic), _frozen(geo.transform(cam.rotation,
                                                                                              cam.translation)),
                                               (int(cam.width), int(cam.height)))
                       for name, cam in frame.cameras.items()}
        lidar2img, lidar2ego = None, None
        if frame.lidar is not None:
            lidar2ego = geo.transform(*frame.lidar)
            lidar2img = {}
            for name, cal in calibration.items():
                viewpad = np.eye(4)
                viewpad[:3, :3] = cal.intrinsic
                lidar2img[name] = _frozen(viewpad @ geo.invert(cal.sensor2ego) @ lidar2ego)
        return cls(frame.token, frame.scene_token, frame.scene_name, int(frame.index), int(frame.timestamp),
                   _frozen(geo.transform(rotation, translation)), MappingProxyType(calibration),
                   None if lidar2img is None else MappingProxyType(lidar2img), _frozen(can_bus(frame)),
                   None if lidar2ego is None else _frozen(lidar2ego), frame.lidar_file)

    def private(self) -> FrameContext:
        """A copy whose every array is new and read-only: what one ``predict`` call gets, so a planner that
        flips a flag back (``setflags(write=True)``) and writes changes only its own copy, never the context
        the next cell or frame receives (about 20 small arrays: microseconds)."""
        calibration = {name: CameraCalibration(_frozen(cal.intrinsic), _frozen(cal.sensor2ego), cal.image_size)
                       for name, cal in self.calibration.items()}
        lidar2img = None if self.lidar2img is None else {k: _frozen(v) for k, v in self.lidar2img.items()}
        return replace(self, ego2global=_frozen(self.ego2global), calibration=MappingProxyType(calibration),
                       lidar2img=None if lidar2img is None else MappingProxyType(lidar2img),
                       can_bus=None if self.can_bus is None else _frozen(self.can_bus),
                       lidar2ego=None if self.lidar2ego is None else _frozen(self.lidar2ego))


def can_bus(frame: Frame) -> np.ndarray:
    """BEVFormer's 18-value CAN-bus vector of a keyframe (see `FrameContext`)."""
    rotation, translation = frame.ego_pose
    if frame.can is not None:
        accel, rate, vel = frame.can["accel"], frame.can["rotation_rate"], frame.can["vel"]
    else:  # no CAN bus expansion: the motion terms of the ego status, in the ego frame
        ego = frame.ego
        accel, rate, vel = (*ego.acceleration, 0.0), (0.0, 0.0, ego.yaw_rate), (*ego.velocity, 0.0)
    degrees = float(np.degrees(geo.quat_yaw(rotation))) % 360.0
    return np.array([*translation, *rotation, *accel, *rate, *vel, np.radians(degrees), degrees], dtype=np.float64)
