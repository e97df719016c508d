"""Geometry: quaternions, rigid transforms between global, ego and camera frames, and pinhole projection.

Conventions follow nuScenes: quaternions are (w, x, y, z); a record's (rotation, translation) maps points of
its own frame into its parent frame (calibrated_sensor: camera -> ego, ego_pose: ego -> global). The ego frame
has x forward, y left, z up; a camera frame has x right, y down, z along the optical axis.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

#: Rotation taking camera axes (x right, y down, z forward) to ego axes for a camera looking along ego +x.
CAM_TO_EGO_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

#: Points closer than this to the image plane (m, camera z) are clipped before projection.
NEAR_PLANE = 0.1


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """3x3 rotation matrix of a (w, x, y, z) quaternion (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(m: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) quaternion of a rotation matrix, with w >= 0 (Shepperd's method, numerically stable)."""
    m = np.asarray(m, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q) / np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return tuple(float(v) for v in q)  # type: ignore[return-value]


def yaw_to_quat(yaw: float) -> tuple[float, float, float, float]:
    """Quaternion of a rotation by `yaw` radians about +z."""
    return (float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2)))


def quat_yaw(q: Sequence[float]) -> float:
    """Heading (rad, about +z) of the x axis rotated by quaternion `q`."""
    m = quat_to_matrix(q)
    return float(np.arctan2(m[1, 0], m[0, 0]))


def quat_yaws(q: np.ndarray) -> np.ndarray:
    """Headings of (N, 4) (w, x, y, z) quaternions, vectorised."""
    w, x, y, z = np.asarray(q, dtype=float).reshape(-1, 4).T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def transform(rotation: Sequence[float], translation: Sequence[float]) -> np.ndarray:
    """4x4 homogeneous matrix of a (quaternion, translation) record: child frame -> parent frame."""
    t = np.eye(4)
    t[:3, :3] = quat_to_matrix(rotation)
    t[:3, 3] = np.asarray(translation, dtype=float)
    return t


def invert(t: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    inv = np.eye(4)
    inv[:3, :3] = t[:3, :3].T
    inv[:3, 3] = -t[:3, :3].T @ t[:3, 3]
    return inv


def apply(t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    return p @ t[:3, :3].T + t[:3, 3]


def ego_to_global(points: np.ndarray, ego_rotation: Sequence[float], ego_translation: Sequence[float]) -> np.ndarray:
    return apply(transform(ego_rotation, ego_translation), points)


def global_to_ego(points: np.ndarray, ego_rotation: Sequence[float], ego_translation: Sequence[float]) -> np.ndarray:
    return apply(invert(transform(ego_rotation, ego_translation)), points)


def ego_to_camera(points: np.ndarray, cam_rotation: Sequence[float], cam_translation: Sequence[float]) -> np.ndarray:
    return apply(invert(transform(cam_rotation, cam_translation)), points)


def camera_to_ego(points: np.ndarray, cam_rotation: Sequence[float], cam_translation: Sequence[float]) -> np.ndarray:
    return apply(transform(cam_rotation, cam_translation), points)


def project(points_cam: np.ndarray, intrinsic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of (N, 3) camera-frame points: (N, 2) pixel (u, v) and a mask of points in front."""
    p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
    front = p[:, 2] > NEAR_PLANE
    z = np.where(front, p[:, 2], 1.0)
    uv = (p[:, :2] / z[:, None]) @ np.asarray(intrinsic)[:2, :2].T + np.asarray(intrinsic)[:2, 2]
    return uv, front


def camera_rotation(yaw: float, pitch: float = 0.0) -> tuple[float, float, float, float]:
    """Quaternion of a level camera mounted at `yaw` (rad, left positive) and `pitch` (rad, down positive)."""
    cp, sp = np.cos(pitch), np.sin(pitch)
    tilt = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    cy, sy = np.cos(yaw), np.sin(yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return matrix_to_quat(rz @ tilt @ CAM_TO_EGO_BASE)


def intrinsic_matrix(focal: float, width: int, height: int, cx: float | None = None,
                     cy: float | None = None) -> np.ndarray:
    """3x3 pinhole camera matrix; the principal point defaults to the image centre."""
    return np.array([[focal, 0.0, width / 2 if cx is None else cx],
                     [0.0, focal, height / 2 if cy is None else cy],
                     [0.0, 0.0, 1.0]])


def clip_polygon_near(poly: np.ndarray, near: float = NEAR_PLANE) -> np.ndarray:
    """Clip a closed (N, 3) camera-frame polygon against the plane z = near (Sutherland-Hodgman, one plane)."""
    out: list[np.ndarray] = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.asarray(out).reshape(-1, 3)


def se2_to_ego(xy: np.ndarray, origin_xy: np.ndarray | Sequence[float], origin_yaw: float) -> np.ndarray:
    """(N, 2) global planar points into the frame of a pose at `origin_xy` with heading `origin_yaw`."""
    c, s = np.cos(origin_yaw), np.sin(origin_yaw)
    d = np.asarray(xy, dtype=float).reshape(-1, 2) - np.asarray(origin_xy, dtype=float)[:2]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)


_TURN = 2 * np.pi


def wrap_angle(a: npt.ArrayLike) -> np.ndarray:
    """Angle(s) wrapped into [-pi, pi): (a + pi) mod 2 pi - pi, with the bits of numpy's remainder.

    For float64 angles within a turn of the range (a + pi in [-2 pi, 4 pi), as every difference of two wrapped
    angles is) the remainder is taken without numpy's fmod, 2.5x faster: x itself on [0, 2 pi), x - 2 pi above,
    which is exact there (Sterbenz), and x + 2 pi rounded below 0, the addition numpy's remainder makes itself
    (a zero comes out +0 either way). Anything else goes through numpy's remainder
    (tests/unit/test_lanes_exact.py holds the two equal bit for bit)."""
    x = np.asarray(a) + np.pi
    if x.dtype == np.float64 and x.size and x.min() >= -_TURN and x.max() < 2 * _TURN:
        return x + np.where(x < 0, _TURN, np.where(x >= _TURN, -_TURN, 0.0)) - np.pi
    return x % _TURN - np.pi
