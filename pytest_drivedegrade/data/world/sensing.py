"""What the rig senses of the agents at a keyframe: a LIDAR_TOP point cloud and each box's visible fraction.

Both come from ray casts against the agents' boxes (the annotation boxes: the solids the renderer draws fill
them) and the ground plane; scenery (buildings, trees, poles) is not an occluder, since building it costs as much
as the rest of a scene's tables. Ego frame throughout (x forward, y left, z up, ground at z = 0).

- LIDAR_TOP: the nuScenes rig's mounting, 32 rings from -30.67 to +10.67 degrees of elevation (the HDL-32E's),
  one ray per degree of azimuth, 70 m range. A ray returns the nearest hit; hits on boxes are all kept (so
  `num_lidar_pts` is the count of rays whose nearest hit is that box), ground hits only every `GROUND_EVERY`-th
  degree of azimuth, to keep the files small. Points are written in the sensor frame as nuScenes' ``.pcd.bin``:
  float32 (x, y, z, intensity, ring index), 5 values per point.
- Visibility: a 3 x 3 grid of samples on each face of the box that faces the rig; a sample is seen when some
  camera has it in its image and the segment from that camera to it crosses no other box. The visible fraction is
  the area-weighted share of seen samples, mapped to nuScenes' visibility tokens.
"""

from __future__ import annotations

import functools

import numpy as np

from ...constants import CAMERAS
from ..geometry import NEAR_PLANE, quat_to_matrix
from .agents import Agent
from .rig import Rig

#: The nuScenes rig's LIDAR_TOP calibrated_sensor (the same record on every nuScenes log).
LIDAR_TRANSLATION = (0.943713, 0.0, 1.84023)
LIDAR_ROTATION = (0.7077955119163518, -0.006492242056004365, 0.010646214713995808, -0.7063073142877817)
RINGS = 32
ELEVATION = (-30.67, 10.67)  # degrees, lowest and highest ring
AZIMUTH_STEP = 1.0  # degrees
LIDAR_RANGE = 70.0  # m
GROUND_EVERY = 30  # keep the ground return of every 30th degree of azimuth (12 spokes)
INTENSITY = {"ground": 8.0, "box": 40.0}
GRID = 3  # visibility samples per face edge
RIG_CENTRE = np.array([1.0, 0.0, 1.55])  # m, ego frame: the middle of the six cameras
#: (upper bound of the visible fraction, nuScenes visibility token): 0-40 %, 40-60 %, 60-80 %, 80-100 %.
VISIBILITY_LEVELS = ((0.4, "1"), (0.6, "2"), (0.8, "3"))

_R_LIDAR = quat_to_matrix(LIDAR_ROTATION)
_T_LIDAR = np.array(LIDAR_TRANSLATION)
_N_AZ = int(round(360 / AZIMUTH_STEP))
_EL = np.radians(np.linspace(*ELEVATION, RINGS))
_AZ = np.radians(np.arange(_N_AZ) * AZIMUTH_STEP)
_DIR_SENSOR = np.stack([np.cos(_EL)[:, None] * np.cos(_AZ)[None], np.cos(_EL)[:, None] * np.sin(_AZ)[None],
                        np.sin(_EL)[:, None] * np.ones_like(_AZ)[None]], -1)  # (rings, azimuths, 3)
_DIR_EGO = _DIR_SENSOR @ _R_LIDAR.T
#: The sensor's azimuth 0 looks along ego -y (the real mounting is yawed by -90 degrees): column offset of ego 0.
_COL_OFFSET = int(round(np.degrees(-np.arctan2(_DIR_EGO[RINGS // 2, 0, 1], _DIR_EGO[RINGS // 2, 0, 0])) / AZIMUTH_STEP))
# The same for every scan (computed once, not per keyframe): each ray's distance to the ground, and which ground
# returns are kept (within range, on one of the GROUND_EVERY spokes).
with np.errstate(divide="ignore"):
    _GROUND = np.where(_DIR_EGO[..., 2].ravel() < 0, -_T_LIDAR[2] / _DIR_EGO[..., 2].ravel(), np.inf)
#: Each ray's rise per metre of horizontal travel (ego frame).
_SLOPE = _DIR_EGO[..., 2].ravel() / np.hypot(_DIR_EGO[..., 0], _DIR_EGO[..., 1]).ravel()
_GROUND_KEPT = (_GROUND <= LIDAR_RANGE) & ((np.tile(np.arange(_N_AZ), RINGS) - _COL_OFFSET) % GROUND_EVERY == 0)


def boxes_at(agents: list[Agent], step: int, pose) -> np.ndarray:
    """(N, 6) boxes (x, y, yaw, length, width, height) of the agents at `step` in the ego frame at `pose`."""
    ex, ey, eyaw = pose
    c, s = np.cos(eyaw), np.sin(eyaw)
    out = np.empty((len(agents), 6))
    for i, a in enumerate(agents):
        dx, dy = a.xy[step, 0] - ex, a.xy[step, 1] - ey
        out[i] = (c * dx + s * dy, -s * dx + c * dy, float(a.yaw[step]) - eyaw, *a.size)
    return out


def _slab(origin: np.ndarray, direction: np.ndarray, boxes: np.ndarray, box_of: np.ndarray) -> np.ndarray:
    """Entry distance along each ray (pairs: (P, 3) directions against boxes `box_of` (P,) of (B, 6) `boxes`,
    from (P, 3) origins or one (3,) origin for all); inf where it misses.

    What depends only on a box (its rotation, extents, and with one origin that origin in its frame) is computed
    once per box and gathered per pair: the same arithmetic on the same numbers as per pair, fewer operations."""
    c_b, s_b = np.cos(boxes[:, 2]), np.sin(boxes[:, 2])
    lo_b = np.stack([-boxes[:, 3] / 2, -boxes[:, 4] / 2, np.zeros(len(boxes))], -1)
    hi_b = np.stack([boxes[:, 3] / 2, boxes[:, 4] / 2, boxes[:, 5]], -1)
    c, s = c_b[box_of], s_b[box_of]
    if origin.ndim == 1:
        ox, oy = origin[0] - boxes[:, 0], origin[1] - boxes[:, 1]
        o_b = np.stack([c_b * ox + s_b * oy, -s_b * ox + c_b * oy, np.full(len(boxes), origin[2])], -1)
        low, high, inside = (lo_b - o_b)[box_of], (hi_b - o_b)[box_of], ((o_b >= lo_b) & (o_b <= hi_b))[box_of]
    else:
        ox, oy = origin[:, 0] - boxes[box_of, 0], origin[:, 1] - boxes[box_of, 1]
        o = np.stack([c * ox + s * oy, -s * ox + c * oy, origin[:, 2]], -1)
        lo, hi = lo_b[box_of], hi_b[box_of]
        low, high, inside = lo - o, hi - o, (o >= lo) & (o <= hi)  # inside: a ray parallel to a slab
    d = np.stack([c * direction[:, 0] + s * direction[:, 1], -s * direction[:, 0] + c * direction[:, 1],
                  direction[:, 2]], -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = low / d, high / d
    parallel = d == 0  # always or never within that slab
    t0 = np.where(parallel, np.where(inside, -np.inf, np.inf), t0)
    t1 = np.where(parallel, np.inf, t1)
    near = np.minimum(t0, t1).max(-1)
    far = np.maximum(t0, t1).min(-1)
    hit = (far >= np.maximum(near, 0.0)) & (near >= 0.0)
    return np.where(hit, near, np.inf)


def lidar_scan(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cast the LIDAR_TOP rays against `boxes` (ego frame) and the ground.

    Returns the (P, 5) float32 point cloud in the sensor frame and the number of points on each box.
    """
    n_rays = RINGS * _N_AZ
    best = np.full(n_rays, np.inf)
    owner = np.full(n_rays, -1)
    ground = _GROUND
    if len(boxes):
        rel = boxes[:, :2] - _T_LIDAR[:2]
        dist = np.hypot(rel[:, 0], rel[:, 1])
        radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
        near = np.flatnonzero(dist - radius < LIDAR_RANGE)
        centre = np.degrees(np.arctan2(rel[near, 1], rel[near, 0]))
        half = np.degrees(np.arcsin(np.clip(radius[near] / np.maximum(dist[near], 1e-6), 0, 1)))
        half = np.where(dist[near] <= radius[near], 180.0, half) + 2 * AZIMUTH_STEP  # margin for the mount's tilt
        c0 = np.floor((centre - half) / AZIMUTH_STEP).astype(int) + _COL_OFFSET
        width = np.minimum(np.ceil(2 * half / AZIMUTH_STEP).astype(int) + 1, _N_AZ)
        box_of = np.repeat(near, width)
        start = np.repeat(np.cumsum(width) - width, width)
        col = (np.repeat(c0, width) + np.arange(width.sum()) - start) % _N_AZ
        rays = (np.arange(RINGS)[:, None] * _N_AZ + col[None]).ravel()
        box_of = np.tile(box_of, RINGS)
        # drop the pairs that cannot hit: at the box's nearest horizontal distance a falling ray is already below
        # the ground or a rising one above the roof (then the whole box is out of its reach); the others are cast
        # as before, in the same order, so the nearest hits and their ties are the same
        z_at = _T_LIDAR[2] + np.maximum(dist - radius, 0.0)[box_of] * _SLOPE[rays]
        can = np.where(_SLOPE[rays] > 0, z_at <= boxes[box_of, 5] + 0.01, z_at >= -0.01)
        rays, box_of = rays[can], box_of[can]
        t = _slab(_T_LIDAR, _DIR_EGO.reshape(-1, 3)[rays], boxes, box_of)
        hit = np.flatnonzero(np.isfinite(t) & (t <= LIDAR_RANGE))
        order = hit[np.lexsort((t[hit], rays[hit]))]
        first = order[np.unique(rays[order], return_index=True)[1]]
        best[rays[first]], owner[rays[first]] = t[first], box_of[first]
    on_box = owner >= 0
    on_box &= best < ground
    on_ground = ~on_box & _GROUND_KEPT
    keep = np.flatnonzero(on_box | on_ground)
    t = np.where(on_box, best, ground)[keep]
    points = _DIR_SENSOR.reshape(-1, 3)[keep] * t[:, None]  # the sensor frame: origin at the sensor
    ring = (keep // _N_AZ).astype(np.float32)
    intensity = np.where(on_box[keep], INTENSITY["box"], INTENSITY["ground"])
    cloud = np.column_stack([points, intensity, ring]).astype(np.float32)
    counts = np.bincount(owner[keep][on_box[keep]], minlength=len(boxes)) if len(boxes) else np.zeros(0, int)
    return cloud, counts


def _unit_faces() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples on the unit box's five faces (the bottom rests on the ground): (5, GRID^2, 3) points in box units
    (x, y in -0.5..0.5, z in 0..1), (5, 3) normals, and (5, 3) the axes whose product is the face's area."""
    g = (np.arange(GRID) + 0.5) / GRID - 0.5
    u, v = [a.ravel() for a in np.meshgrid(g, g)]
    half = np.full_like(u, 0.5)
    pts = np.stack([np.stack([half, u, v + 0.5], -1), np.stack([-half, u, v + 0.5], -1),
                    np.stack([u, half, v + 0.5], -1), np.stack([u, -half, v + 0.5], -1),
                    np.stack([u, v, half + 0.5], -1)])
    normals = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]])
    area_axes = np.array([[0, 1, 1], [0, 1, 1], [1, 0, 1], [1, 0, 1], [1, 1, 0]], float)
    return pts, normals, area_axes


_FACE_PTS, _FACE_NORMALS, _FACE_AREA = _unit_faces()


@functools.lru_cache(maxsize=32)
def _rotation(quaternion: tuple[float, ...]) -> np.ndarray:
    """A camera's rotation matrix, computed once per camera, not per keyframe (never written to)."""
    return quat_to_matrix(quaternion)


def visible_fractions(boxes: np.ndarray, targets, rig: Rig) -> np.ndarray:
    """The visible fraction (0..1) of each box index in `targets` across the six cameras, `boxes` occluding."""
    targets = np.asarray(targets, int)
    out = np.zeros(len(targets))
    if not len(targets):
        return out
    b = boxes[targets]
    dims = b[:, 3:6]  # length, width, height
    c, s = np.cos(b[:, 2]), np.sin(b[:, 2])
    local = _FACE_PTS[None] * dims[:, None, None, :]  # (T, 5, G, 3)
    world = np.stack([b[:, 0, None, None] + c[:, None, None] * local[..., 0] - s[:, None, None] * local[..., 1],
                      b[:, 1, None, None] + s[:, None, None] * local[..., 0] + c[:, None, None] * local[..., 1],
                      local[..., 2]], -1)
    normal = np.stack([c[:, None] * _FACE_NORMALS[:, 0] - s[:, None] * _FACE_NORMALS[:, 1],
                       s[:, None] * _FACE_NORMALS[:, 0] + c[:, None] * _FACE_NORMALS[:, 1],
                       np.broadcast_to(_FACE_NORMALS[:, 2], (len(b), 5))], -1)  # (T, 5, 3)
    facing = np.einsum("tfi,tfi->tf", normal, RIG_CENTRE - world.mean(2)) > 0  # faces that face the rig
    area = np.prod(np.where(_FACE_AREA[None] > 0, dims[:, None, :], 1.0), -1)  # (T, 5)
    weight = np.repeat((area * facing / GRID ** 2)[..., None], GRID ** 2, -1).ravel()
    owner = np.repeat(np.arange(len(b)), 5 * GRID ** 2)
    pts = world.reshape(-1, 3)
    keep = np.flatnonzero(weight > 0)
    pts, owner_k = pts[keep], owner[keep]
    seen = np.zeros(len(pts), bool)
    sample_of, centres = [], []
    for name in CAMERAS:
        cam = rig.cameras[name]
        rot, centre = _rotation(tuple(cam.rotation)), np.asarray(cam.translation)
        pc = (pts - centre) @ rot  # camera frame
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = pc[:, 0] / z * cam.intrinsic[0, 0] + cam.intrinsic[0, 2]
            v = pc[:, 1] / z * cam.intrinsic[1, 1] + cam.intrinsic[1, 2]
        inside = np.flatnonzero((z > NEAR_PLANE) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height))
        sample_of.append(inside)
        centres.append(np.broadcast_to(centre, (len(inside), 3)))
    view_sample = np.concatenate(sample_of)  # one row per (sample, camera that has it in its image)
    if len(view_sample):
        view_centre = np.concatenate(centres)
        seg = pts[view_sample] - view_centre
        length = np.linalg.norm(seg, axis=1)
        direction = seg / length[:, None]
        # candidate occluders: another box whose footprint circle comes within reach of the segment (2D)
        # (V, B) arrays per coordinate, not (V, B, 2) ones: the same sums of two products, less memory traffic
        rx, ry = boxes[None, :, 0] - view_centre[:, 0, None], boxes[None, :, 1] - view_centre[:, 1, None]
        sx, sy = seg[:, 0, None], seg[:, 1, None]
        along = np.clip((rx * sx + ry * sy) / np.maximum(sx ** 2 + sy ** 2, 1e-9), 0.0, 1.0)
        gap = np.hypot(rx - along * sx, ry - along * sy)
        reach = gap <= 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])[None]
        reach[np.arange(len(view_sample)), targets[owner_k[view_sample]]] = False
        view_of, box_of = np.nonzero(reach)
        t = _slab(view_centre[view_of], direction[view_of], boxes, box_of)
        blocked = np.zeros(len(view_sample), bool)
        np.logical_or.at(blocked, view_of, t < length[view_of] - 1e-3)
        seen[view_sample[~blocked]] = True
    total = np.bincount(owner, weights=weight, minlength=len(b))
    vis = np.bincount(owner_k, weights=weight[keep] * seen, minlength=len(b))
    np.divide(vis, total, out=out, where=total > 0)
    return out


def visibility_token(fraction: float) -> str:
    """nuScenes visibility token of a visible fraction: "1" (0-40 %), "2" (40-60 %), "3" (60-80 %), "4"."""
    for upper, tok in VISIBILITY_LEVELS:
        if fraction < upper:
            return tok
    return "4"
