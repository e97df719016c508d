"""The camera rig of the world: the six nuScenes cameras with the real rig's mounting and focal lengths.

Mounting positions (m, ego frame) and yaws are those of the nuScenes Renault Zoe rig (rounded); focal lengths
are nuScenes' at 1600 x 900 (about 1266 px; the rear camera is wider, about 809 px) scaled with the image width.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...constants import CAMERAS, REFERENCE_WIDTH
from ..frame import CameraInfo
from ..geometry import camera_rotation, intrinsic_matrix

#: name -> (translation x, y, z in m; yaw in degrees, left positive; focal length in px at 1600 x 900)
MOUNTS = {
    "CAM_FRONT": ((1.70, 0.016, 1.51), 0.0, 1266.4),
    "CAM_FRONT_RIGHT": ((1.55, -0.493, 1.50), -55.0, 1260.8),
    "CAM_FRONT_LEFT": ((1.52, 0.495, 1.51), 55.0, 1272.6),
    "CAM_BACK": ((0.03, 0.003, 1.58), 180.0, 809.2),
    "CAM_BACK_LEFT": ((1.04, 0.485, 1.59), 110.0, 1256.7),
    "CAM_BACK_RIGHT": ((1.01, -0.481, 1.56), -110.0, 1259.5),
}
FULL_SIZE = (1600, 900)
DEFAULT_SIZE = (800, 450)


@dataclass
class Rig:
    cameras: dict[str, CameraInfo]

    @staticmethod
    def nuscenes_like(full_size: bool = False) -> Rig:
        """The rig at 800 x 450 (default) or 1600 x 900."""
        width, height = FULL_SIZE if full_size else DEFAULT_SIZE
        scale = width / REFERENCE_WIDTH
        cams = {}
        for name in CAMERAS:
            (tx, ty, tz), yaw, focal = MOUNTS[name]
            k = intrinsic_matrix(focal * scale, width, height)
            cams[name] = CameraInfo(name, "", width, height, k, camera_rotation(np.radians(yaw)),
                                    (float(tx), float(ty), float(tz)))
        return Rig(cams)
