"""Textures of a scene: the top-down ground map (roads, markings, curbs, sidewalks, grain) and the sky panorama.

The ground map is painted once per scene at `MAP_RES` metres per pixel over the area the ego can see, then
sampled per camera pixel by inverse perspective mapping (cv2.remap) in `render.py`. Fine detail (lane-marking
edges, asphalt grain, paver joints, cracks) is what blur, noise and compression destroy.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .roads import LANE_WIDTH, SIDEWALK, Path, RoadNet, in_junction

MAP_RES = 0.08  # m per map pixel
SHIFT = 2  # sub-pixel bits for cv2 drawing
SKY_H = 512


@dataclass
class GroundMap:
    levels: list[np.ndarray]  # mip pyramid, level 0 at MAP_RES
    origin: np.ndarray  # world (x, y) of pixel (0, 0)
    verge: np.ndarray  # colour beyond the map


def noise(rng: np.random.Generator, shape: tuple[int, int], scale: int) -> np.ndarray:
    """Smooth value noise in [-1, 1] with features about `scale` pixels wide."""
    small = rng.standard_normal((max(shape[0] // scale, 2) + 2, max(shape[1] // scale, 2) + 2)).astype(np.float32)
    big = cv2.resize(small, (shape[1] + 2 * scale, shape[0] + 2 * scale), interpolation=cv2.INTER_CUBIC)
    big = big[scale:scale + shape[0], scale:scale + shape[1]]
    return np.clip(big / 1.5, -1, 1)


class _Painter:
    """Draws world-frame geometry into the map image."""

    def __init__(self, img: np.ndarray, origin: np.ndarray):
        self.img, self.origin = img, origin

    def px(self, xy: np.ndarray) -> np.ndarray:
        return np.round((np.asarray(xy) - self.origin) / MAP_RES * (1 << SHIFT)).astype(np.int32)

    def line(self, xy: np.ndarray, width_m: float, colour) -> None:
        th = max(int(round(width_m / MAP_RES)), 1)
        aa = cv2.LINE_AA if th < 8 else cv2.LINE_8  # wide fills: anti-aliasing costs much, shows little
        cv2.polylines(self.img, [self.px(xy)], False, tuple(float(c) for c in colour), th, aa, SHIFT)

    def lines(self, runs: list[np.ndarray], width_m: float, colour) -> None:
        runs = [self.px(r) for r in runs if len(r) >= 2]
        if runs:
            th = max(int(round(width_m / MAP_RES)), 1)
            cv2.polylines(self.img, runs, False, tuple(float(c) for c in colour), th, cv2.LINE_AA, SHIFT)

    def poly(self, xy: np.ndarray, colour) -> None:
        cv2.fillConvexPoly(self.img, self.px(xy), tuple(float(c) for c in colour), cv2.LINE_AA, SHIFT)


def _runs(path: Path, net: RoadNet, mask_extra: np.ndarray | None = None, dash: float = 0.0) -> list[np.ndarray]:
    """Pieces of `path` outside junctions (and, when `dash` > 0, only the 3 m dashes of a dash+gap pattern)."""
    keep = ~in_junction(net, path.xy, 0.5)
    if dash > 0:
        keep &= (path.s % dash) < 3.0
    if mask_extra is not None:
        keep &= mask_extra
    edges = np.flatnonzero(np.diff(np.concatenate([[0], keep.astype(np.int8), [0]])))
    return [path.xy[a:b] for a, b in zip(edges[::2], edges[1::2]) if b - a >= 2]


def _junction_square(j, grow: float) -> np.ndarray:
    c, s = np.cos(j.heading), np.sin(j.heading)
    u, v = np.array([c, s]), np.array([-s, c])
    h = j.half + grow
    return np.array([j.center + a * h * u + b * h * v for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])


def _paint_roads(p: _Painter, net: RoadNet, style, rng) -> None:
    asphalt = np.full(3, style.asphalt)
    for grow, colour in ((SIDEWALK, style.sidewalk), (0.3, style.sidewalk * 1.15), (0.0, asphalt)):
        for road in net.roads:
            p.line(road.center.xy, 2 * (road.half_width + grow), colour)
        for j in net.junctions:
            p.poly(_junction_square(j, grow if grow < SIDEWALK else grow - 1.0), colour)
    for road in net.roads:  # paver joints across the sidewalks
        for side in (-1.0, 1.0):
            inner, outer = road.center.offset(side * (road.half_width + 0.3)), road.center.offset(
                side * (road.half_width + SIDEWALK))
            n = min(len(inner.xy), len(outer.xy))
            idx = np.arange(0, n, int(1.2 / 0.25))
            keep = ~in_junction(net, inner.xy[idx], 1.0)
            segs = [np.stack([inner.xy[i], outer.xy[i]]) for i in idx[keep]]
            p.lines(segs, 0.04, style.sidewalk * 0.8)
    for _ in range(int(rng.integers(20, 60))):  # cracks and tar seams on the carriageway
        road = net.roads[int(rng.integers(len(net.roads)))]
        s0, d0 = rng.uniform(0, road.center.length), rng.uniform(-road.half_width, road.half_width)
        steps = rng.normal(0, 0.6, size=(int(rng.integers(4, 12)), 2)).cumsum(0)
        x, y, yaw = road.center.at(s0)
        base = np.array([x, y]) + d0 * np.array([-np.sin(yaw), np.cos(yaw)])
        p.line(base + steps, 0.05, asphalt * 0.6)


def _paint_markings(p: _Painter, net: RoadNet, style, crosswalks: list[float], stop_lines=()) -> None:
    white, yellow = (235, 235, 228), (225, 185, 40)
    for road in net.roads:
        c = road.center
        for side in (-1.0, 1.0):
            p.lines(_runs(c.offset(side * road.lanes * LANE_WIDTH), net), 0.15, white)
            for k in range(1, road.lanes):
                p.lines(_runs(c.offset(side * k * LANE_WIDTH), net, dash=9.0), 0.15, white)
        if style.yellow_centre:
            for side in (-1.0, 1.0):
                p.lines(_runs(c.offset(side * 0.15), net), 0.12, yellow)
        else:
            p.lines(_runs(c, net, dash=6.0), 0.15, white)
    route = net.route
    for s_c in crosswalks:
        x, y, yaw = route.center.at(s_c)
        u, v = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        for d in np.arange(-route.half_width + 0.6, route.half_width - 0.3, 1.0):
            q = np.array([x, y]) + d * v
            p.poly(np.array([q - 1.5 * u, q + 1.5 * u, q + 1.5 * u + 0.5 * v, q - 1.5 * u + 0.5 * v]), white)
    for j in net.junctions:  # stop line across the ego's side of the approach
        c, s = np.cos(j.heading), np.sin(j.heading)
        u, v = np.array([c, s]), np.array([-s, c])
        q = j.center - (j.half + 0.5) * u
        w = route.lanes * LANE_WIDTH
        p.poly(np.array([q - 0.25 * u, q + 0.25 * u, q + 0.25 * u - w * v, q - 0.25 * u - w * v]), white)
    for a, b, u in stop_lines:  # a traffic light's stop line: a 0.5 m bar from the line on, across its lanes
        p.poly(np.array([a, b, b + 0.5 * u, a + 0.5 * u]), white)


def ground_map(net: RoadNet, ego_xy: np.ndarray, style, crosswalks: list[float],
               rng: np.random.Generator, stop_lines=()) -> GroundMap:
    """Paint the ground around the ego's drive into a mip pyramid (uint8 throughout: the map is large).
    `stop_lines`: the traffic lights' lines as (end, end, unit vector along the road), painted white (none but
    in the light scenes: the painting draws nothing from `rng`, so every other ground is as it was).

    The map is tens of megabytes: every step after the painting works in place (a fresh array that size costs
    more in page faults than the arithmetic), with the same saturating arithmetic as fresh arrays would give."""
    lo, hi = ego_xy.min(0) - 100.0, ego_xy.max(0) + 100.0
    h, w = (np.ceil((hi - lo) / MAP_RES).astype(int))[::-1]
    img = np.empty((h, w, 3), np.uint8)
    img[0] = np.clip(style.verge, 0, 255).astype(np.uint8)
    img[1:] = img[0]  # row copies: much faster than broadcasting one pixel over the image
    p = _Painter(img, lo)
    _paint_roads(p, net, style, rng)
    _paint_markings(p, net, style, crosswalks, stop_lines)
    small = (h // 4 + 1, w // 4 + 1)
    patches = 1.0 + 0.10 * noise(rng, small, 75) + 0.06 * noise(rng, small, 10)
    factor = cv2.resize((patches * style.light * 128).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    np.clip(factor, 0, 255, out=factor)
    three = cv2.merge([factor.astype(np.uint8)] * 3)
    cv2.multiply(img, three, dst=img, scale=1 / 128)
    grain = rng.integers(0, 18, size=(h, w), dtype=np.uint8)  # surface grain, +-9 grey levels
    cv2.add(img, cv2.merge([grain] * 3, dst=three), dst=img)
    three.fill(9)
    cv2.subtract(img, three, dst=img)
    levels = [img]
    for _ in range(3):
        levels.append(cv2.pyrDown(levels[-1]))
    return GroundMap(levels, lo, np.asarray(style.verge, np.float32) * style.light)


def sky_panorama(style, rng: np.random.Generator, width: int = 2048, height: int = SKY_H) -> np.ndarray:
    """An equirectangular sky over azimuth 0..2pi and elevation -4..+40 degrees, with clouds and a far skyline."""
    el = np.linspace(40.0, -4.0, height)[:, None]
    frac = np.clip(el / 40.0, 0, 1) ** 0.6
    sky = style.sky_horizon[None, None, :] * (1 - frac[..., None]) + style.sky_top[None, None, :] * frac[..., None]
    sky = np.repeat(sky, width, axis=1).astype(np.float32)
    n = noise(rng, (height, width), 40) + 0.5 * noise(rng, (height, width), 12)
    cover = np.clip((n - (1.0 - 1.6 * style.clouds)) * 2.0, 0, 1) * np.clip(el / 4.0, 0, 1)
    sky = sky * (1 - cover[..., None]) + np.array([235, 236, 240], np.float32) * cover[..., None]
    ridge = 1.2 + 2.5 * np.abs(noise(rng, (1, width), 25))[0] + 1.5 * np.abs(noise(rng, (1, width), 4))[0]
    rows = (40.0 - ridge) / 44.0 * (height - 1)
    below = np.arange(height)[:, None] >= rows[None, :]
    far = 0.55 * style.sky_horizon + 0.45 * np.array([60, 80, 70])
    sky[below] = far
    return np.clip(sky, 0, 255).astype(np.uint8)
