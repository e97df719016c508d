"""Render the six cameras of a keyframe: ground by inverse perspective mapping, sky panorama, solids in
painter's order with back-face culling and near-plane clipping. Vectorised numpy / OpenCV, no pixel loops.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import NEAR_PLANE, clip_polygon_near, invert, quat_to_matrix, transform
from . import models
from .agents import Agent
from .rig import Rig
from .texture import MAP_RES, SKY_H, GroundMap

FACES = np.array([[4, 5, 7, 6], [0, 2, 3, 1], [2, 6, 7, 3], [0, 1, 5, 4], [1, 3, 7, 5]])
NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], np.float64)
SIGNS = np.array([[sx, sy, sz] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5) for sz in (0, 1)])
LEVEL_EDGES = (9.0, 18.0, 36.0)  # m forward  # m: ground distance at which the next coarser mip level takes over
GROUND_MAX = 350.0
DECAL_MAX = 90.0  # m: decals of farther parts are below a pixel or two
SOLID_MAX = 220.0
SHADOW_REACH = 80.0  # m: agents farther from the camera cast no shadow in its image
AA = cv2.LINE_AA
SHIFT = 4


@dataclass
class CameraPrecomp:
    """What depends only on the camera: the image-to-ground homography, row bands and sky directions."""

    ground_h: np.ndarray  # 3x3: image pixel (u, v, 1) -> ego-frame ground point, homogeneous
    horizon: int  # first row drawn as ground (rows above: sky panorama)
    bands: list[tuple[int, int]]  # row range per mip level, near levels last
    haze_rows: tuple[int, np.ndarray]  # first hazy row, per-row haze weight from there down
    sky_x: np.ndarray  # (W,) azimuth / 2 pi per column, at ego yaw 0
    sky_y: np.ndarray  # (horizon,) panorama row per image row


def precompute(rig: Rig, name: str, haze_m: float) -> CameraPrecomp:
    """Per camera (level, as the rig's are): rows map to ground distances, columns to azimuths."""
    cam = rig.cameras[name]
    h, w = cam.height, cam.width
    a = quat_to_matrix(cam.rotation) @ np.linalg.inv(cam.intrinsic)
    tx, ty, tz = cam.translation
    ground_h = np.stack([tx * a[2] - tz * a[0], ty * a[2] - tz * a[1], a[2]])
    fy, cy = cam.intrinsic[1, 1], cam.intrinsic[1, 2]
    depth = lambda v: fy * tz / np.maximum(v - cy, 1e-6)  # noqa: E731  forward depth of ground row v
    row = lambda d: int(min(h, max(0, np.ceil(cy + fy * tz / d))))  # noqa: E731  first row nearer than d
    horizon = row(GROUND_MAX)
    edges = [horizon] + [row(d) for d in reversed(LEVEL_EDGES)] + [h]
    bands = [(edges[i], edges[i + 1]) for i in range(len(edges) - 1)][::-1]
    rows = np.arange(horizon, h)
    haze = (1.0 - np.exp(-depth(rows + 0.5) / haze_m)).astype(np.float32)
    hazy_to = row(25.0)
    d_row = np.stack([np.arange(w), np.full(w, cy), np.ones(w)], -1) @ a.T  # azimuth: per column
    d_col = np.stack([np.full(horizon, cam.intrinsic[0, 2]), np.arange(horizon), np.ones(horizon)], -1) @ a.T
    el = np.degrees(np.arctan2(d_col[:, 2], np.hypot(d_col[:, 0], d_col[:, 1])))  # elevation: per row
    sky_rows = np.clip(np.round((40.0 - el) / 44.0 * (SKY_H - 1)), 0, SKY_H - 1).astype(np.int64)
    return CameraPrecomp(ground_h, horizon, bands, (horizon, haze[: max(hazy_to - horizon, 0)]),
                         np.arctan2(d_row[:, 1], d_row[:, 0]) / (2 * np.pi), sky_rows)


def draw_background(pre: CameraPrecomp, shape, ground: GroundMap, sky: np.ndarray, pose, style) -> np.ndarray:
    """Ground (a homography per mip band) and sky for one camera at ego pose (x, y, yaw): (H, W, 3) uint8."""
    ex, ey, yaw = pose
    h, w = shape
    c, s = np.cos(yaw), np.sin(yaw)
    ego = np.array([[c, -s, ex], [s, c, ey], [0.0, 0.0, 1.0]])
    img = np.empty((h, w, 3), np.uint8)
    border = tuple(float(x) for x in ground.verge)
    for level, (v0, v1) in enumerate(pre.bands):
        if v1 <= v0:
            continue
        k = 1 << level
        scale = MAP_RES * k
        to_map = np.array([[1 / scale, 0, -ground.origin[0] / scale - 0.5 + 0.5 / k],
                           [0, 1 / scale, -ground.origin[1] / scale - 0.5 + 0.5 / k], [0, 0, 1.0]])
        shift = np.array([[1.0, 0, 0], [0, 1.0, v0], [0, 0, 1.0]])
        m = to_map @ ego @ pre.ground_h @ shift
        cv2.warpPerspective(ground.levels[level], m, (w, v1 - v0), dst=img[v0:v1], flags=cv2.INTER_LINEAR
                            | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=border)
    r0, weights = pre.haze_rows
    if len(weights):  # the band * (1 - w) + horizon * w of float32, in place, truncated into the image
        band = img[r0:r0 + len(weights)].astype(np.float32)
        wgt = weights[:, None, None]
        np.multiply(band, 1 - wgt, out=band)
        band += style.sky_horizon.astype(np.float32) * wgt
        img[r0:r0 + len(weights)] = band
    if pre.horizon:  # the sky: row sky_y[r] at the columns the yaw turns to, copied by a nearest-pixel remap
        pw = sky.shape[1]
        cols = ((pre.sky_x + yaw / (2 * np.pi)) * pw).astype(np.int64) % pw
        at = np.empty((pre.horizon, w, 2), np.int16)  # (x, y) of each pixel in the panorama (< 2**15 wide)
        at[..., 0] = cols
        at[..., 1] = pre.sky_y[:, None]
        cv2.remap(sky, at, None, cv2.INTER_NEAREST, dst=img[: pre.horizon])  # type: ignore[call-overload]
    return img


def agent_parts(parts: models.Parts, agents: list[Agent], step: int) -> None:
    for a in agents:
        x, y = a.xy[step]
        yaw = float(a.yaw[step])
        if a.kind in ("car", "truck", "bus"):
            models.vehicle(parts, a.kind, x, y, yaw, a.size, a.colour, bool(a.braking[step]))
        else:
            models.person(parts, x, y, yaw, a.size, a.colour, a.kind == "cyclist")


def _corners(boxes: np.ndarray) -> np.ndarray:
    cx, cy, yaw, z0, z1, l, w = boxes.T
    c, s = np.cos(yaw), np.sin(yaw)
    lx, ly = SIGNS[:, 0][None] * l[:, None], SIGNS[:, 1][None] * w[:, None]
    z = np.where(SIGNS[:, 2][None] > 0, z1[:, None], z0[:, None])
    return np.stack([cx[:, None] + c[:, None] * lx - s[:, None] * ly,
                     cy[:, None] + s[:, None] * lx + c[:, None] * ly, z], -1)


def _fill_many(img, quads: np.ndarray, intrinsic, colours: np.ndarray) -> None:
    """Fill (n, k, 3) camera-frame convex polygons with (n, 3) colours; polygons crossing the near plane are
    clipped first."""
    front = (quads[:, :, 2] >= NEAR_PLANE).all(1)
    f = np.flatnonzero(front)
    if len(f):
        q = quads[f]
        uv = q[..., :2] / q[..., 2:3] @ intrinsic[:2, :2].T + intrinsic[:2, 2]
        pts = np.round(uv * (1 << SHIFT)).astype(np.int32)
        for p, c in zip(pts, colours[f].tolist()):
            cv2.fillConvexPoly(img, p, c, AA, SHIFT)
    for i in np.flatnonzero(~front):
        poly = clip_polygon_near(quads[i])
        if len(poly) >= 3:
            uv = poly[:, :2] / poly[:, 2:3] @ intrinsic[:2, :2].T + intrinsic[:2, 2]
            cv2.fillConvexPoly(img, np.round(uv * (1 << SHIFT)).astype(np.int32), colours[i].tolist(), AA, SHIFT)


def draw_solids(img: np.ndarray, parts: models.Parts, cam, world_to_cam: np.ndarray, cam_pos: np.ndarray,
                style) -> None:
    """Paint parts far to near; per part only faces that look at the camera, then their decals."""
    if not parts.boxes:
        return
    boxes = np.asarray(parts.boxes, np.float64)
    corners = _corners(boxes)
    cc = corners @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    z = cc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cc[..., 0] / z * cam.intrinsic[0, 0] + cam.intrinsic[0, 2]
        v = cc[..., 1] / z * cam.intrinsic[1, 1] + cam.intrinsic[1, 2]
    front = z > NEAR_PLANE
    allf = front.all(1)
    off = allf & ((u < 0).all(1) | (u > cam.width).all(1) | (v < 0).all(1) | (v > cam.height).all(1))
    near = np.linalg.norm(boxes[:, :2] - cam_pos[:2], axis=1) < SOLID_MAX
    keep = np.flatnonzero(front.any(1) & ~off & near)
    if not len(keep):
        return
    centre = corners[keep].mean(1)
    dist = np.linalg.norm(centre - cam_pos, axis=1)
    yaw = boxes[keep, 2]
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.stack([np.stack([c, -s, np.zeros_like(c)], -1), np.stack([s, c, np.zeros_like(c)], -1),
                    np.tile([0.0, 0.0, 1.0], (len(c), 1))], 1)  # (K, 3, 3)
    normals = np.einsum("kij,fj->kfi", rot, NORMALS)
    face_c = corners[keep][:, FACES].mean(2)
    visible = np.einsum("kfi,kfi->kf", normals, cam_pos - face_c) > 0
    shade = (0.55 + 0.5 * np.clip(normals @ style.sun, 0, None)) * style.light
    haze = 1.0 - np.exp(-dist / style.haze_m)
    sky = style.sky_horizon
    groups: list[tuple[np.ndarray, np.ndarray]] = []  # what _fill_many would get, call by call, far to near
    for j in np.argsort(-dist, kind="stable"):
        p = keep[j]
        cols = parts.colours[p] * shade[j][:, None] * (1 - haze[j]) + sky * haze[j]
        dec = parts.decals.get(p)
        faces = np.flatnonzero(visible[j])
        groups.append((cc[p][FACES[faces]], cols[faces]))
        if dec is not None and dist[j] < DECAL_MAX:
            sel = np.flatnonzero(np.isin(dec[0], faces))
            if len(sel):
                q = dec[1][sel] @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
                dc = dec[2][sel] * shade[j][dec[0][sel]][:, None] * (1 - haze[j]) + sky * haze[j]
                groups.append((q, dc))
    _fill_in_order(img, groups, cam.intrinsic)


def _fill_in_order(img, groups: list[tuple[np.ndarray, np.ndarray]], intrinsic) -> None:
    """`_fill_many(img, quads, intrinsic, colours)` for each group in turn, the same fills in the same order
    (per group: the polygons wholly in front, then the clipped ones), with every unclipped quad projected in
    one numpy pass instead of one per group: fewer numpy calls, the same pixels."""
    if not groups:
        return
    quads = np.concatenate([g[0] for g in groups])
    colours = np.concatenate([g[1] for g in groups])
    front: np.ndarray = np.asarray((quads[:, :, 2] >= NEAR_PLANE).all(1))
    q = quads[front]
    uv = q[..., :2] / q[..., 2:3] @ intrinsic[:2, :2].T + intrinsic[:2, 2]
    pts = iter(np.round(uv * (1 << SHIFT)).astype(np.int32))
    listed = colours.tolist()
    start = 0
    for group, _ in groups:
        stop = start + len(group)
        for i in range(start, stop):
            if front[i]:
                cv2.fillConvexPoly(img, next(pts), listed[i], AA, SHIFT)
        for i in range(start, stop):
            if not front[i]:
                poly = clip_polygon_near(quads[i])
                if len(poly) >= 3:
                    uv1 = poly[:, :2] / poly[:, 2:3] @ intrinsic[:2, :2].T + intrinsic[:2, 2]
                    cv2.fillConvexPoly(img, np.round(uv1 * (1 << SHIFT)).astype(np.int32), colours[i].tolist(), AA,
                                       SHIFT)
        start = stop


def draw_shadows(img, agents: list[Agent], step: int, cam, world_to_cam, style) -> None:
    """Dark contact shadows under every agent, drawn before the solids."""
    colour = tuple(float(x) for x in np.array([28, 28, 32]) * style.light)
    centre = -world_to_cam[:3, :3].T @ world_to_cam[:3, 3]  # the camera in the world
    for a in agents:
        x, y = a.xy[step]
        if np.hypot(np.hypot(x - centre[0], y - centre[1]), centre[2]) > SHADOW_REACH + 1.0:
            continue  # surely beyond the reach tested below (a shortcut: the same agents get shadows)
        box = np.array([[x, y, a.yaw[step], 0.02, 0.02, a.size[0] + 0.3, a.size[1] + 0.3]])
        top = _corners(box)[0][FACES[4]]
        pc = top @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
        if (pc[:, 2] > NEAR_PLANE).any() and np.linalg.norm(pc.mean(0)) < SHADOW_REACH:
            _fill_many(img, pc[None], cam.intrinsic, np.array([colour]))


def world_to_camera(rig: Rig, name: str, pose) -> tuple[np.ndarray, np.ndarray]:
    """4x4 world -> camera transform for ego pose (x, y, yaw), and the camera centre in the world."""
    ex, ey, yaw = pose
    cam = rig.cameras[name]
    ego = transform((np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)), (ex, ey, 0.0))
    cam_to_world = ego @ transform(cam.rotation, cam.translation)
    return invert(cam_to_world), cam_to_world[:3, 3]
