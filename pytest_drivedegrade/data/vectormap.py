"""The vectorised local map VAD and MapTR train and evaluate on: dividers, pedestrian crossings and road boundaries
within a box around the ego, as polylines in the ego frame, from a `maps.LaneMap`.

As their `VectorizedLocalMap` does with the nuScenes map expansion: the box is 60 m along the ego's heading and
30 m across (their point-cloud range, +-30 m by +-15 m); dividers are the `road_divider` and `lane_divider` lines
clipped to it; crossings are the `ped_crossing` rings and boundaries the outline of the union of `road_segment`
and `lane` polygons, both clipped to the box shrunk by 0.2 m (so the box's own edge is no boundary). The union is
taken on a 5 cm raster (OpenCV, no shapely here): boundaries are within about 3 cm of the exact outline, which the
devkit test checks against the official devkit's shapely geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .geometry import se2_to_ego
from .maps import LaneMap, MapPolygon

LENGTH, WIDTH = 60.0, 30.0  # m: the box along the ego's heading and across it
EDGE = 0.2  # m: crossings and boundaries are clipped to the box shrunk by this (MapTR's `local_patch`)
RASTER = 0.05  # m per pixel of the union's raster
MARGIN = 1.0  # m of raster beyond the box, so the union's outline is not cut by the raster's edge
SHIFT = 4  # fractional bits of the raster's polygon vertices


@dataclass(frozen=True)
class VectorMap:
    """One sample's local map: polylines (N, 2) in the ego frame (x forward, y left), metres."""

    dividers: tuple[np.ndarray, ...]
    ped_crossings: tuple[np.ndarray, ...]
    boundaries: tuple[np.ndarray, ...]


def clip_polyline(xy: np.ndarray, half_x: float, half_y: float) -> list[np.ndarray]:
    """The pieces of a polyline (N, 2) inside the box |x| <= half_x, |y| <= half_y (Liang-Barsky per segment;
    consecutive inside segments stay one piece)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    pieces: list[list[np.ndarray]] = []
    open_end = False
    for p, q in zip(xy[:-1], xy[1:]):
        d = q - p
        t0, t1 = 0.0, 1.0
        for pk, qk in ((-d[0], p[0] + half_x), (d[0], half_x - p[0]), (-d[1], p[1] + half_y), (d[1], half_y - p[1])):
            if pk == 0.0:
                if qk < 0.0:
                    t0, t1 = 1.0, 0.0
                continue
            r = qk / pk
            t0, t1 = (max(t0, r), t1) if pk < 0 else (t0, min(t1, r))
        if t0 > t1:
            open_end = False
            continue
        a, b = p + t0 * d, p + t1 * d
        if open_end and t0 == 0.0:
            pieces[-1].append(b)
        else:
            pieces.append([a, b])
        open_end = t1 == 1.0
    out = [np.array(pc) for pc in pieces]
    return [pc for pc in out if np.linalg.norm(np.diff(pc, axis=0), axis=1).sum() > 1e-9]  # not a touched corner


def _ring_pieces(ring: np.ndarray, half_x: float, half_y: float) -> list[np.ndarray]:
    """A closed ring (K, 2) clipped as a polyline: one closed piece (first point repeated) when inside; a piece
    that runs through the ring's first vertex stays one piece."""
    pieces = clip_polyline(np.concatenate([ring, ring[:1]]), half_x, half_y)
    if len(pieces) >= 2 and np.array_equal(pieces[-1][-1], pieces[0][0]):
        pieces = [np.concatenate([pieces[-1], pieces[0][1:]]), *pieces[1:-1]]
    return pieces


def _raster_union(polygons: list[MapPolygon], pose: tuple[float, float, float]) -> np.ndarray:
    """The union of polygons on a raster over the box plus MARGIN; pixel (r, c) is ego (x, y) =
    (c, r) * RASTER - (LENGTH / 2 + MARGIN, WIDTH / 2 + MARGIN)."""
    shape = (round((WIDTH + 2 * MARGIN) / RASTER) + 1, round((LENGTH + 2 * MARGIN) / RASTER) + 1)
    mask = np.zeros(shape, dtype=np.uint8)
    origin = np.array([LENGTH / 2 + MARGIN, WIDTH / 2 + MARGIN])

    def px(ring: np.ndarray) -> np.ndarray:
        return np.round((se2_to_ego(ring, pose[:2], pose[2]) + origin) / RASTER * (1 << SHIFT)).astype(np.int32)

    for poly in polygons:
        if not poly.holes:
            cv2.fillPoly(mask, [px(poly.exterior)], 255, cv2.LINE_8, SHIFT)
            continue
        one = np.zeros_like(mask)
        cv2.fillPoly(one, [px(poly.exterior)], 255, cv2.LINE_8, SHIFT)
        cv2.fillPoly(one, [px(h) for h in poly.holes], 0, cv2.LINE_8, SHIFT)
        mask |= one
    return mask


def _near(polygon: MapPolygon, pose: tuple[float, float, float], reach: float) -> bool:
    lo, hi = polygon.exterior.min(0), polygon.exterior.max(0)
    return bool(lo[0] - reach <= pose[0] <= hi[0] + reach and lo[1] - reach <= pose[1] <= hi[1] + reach)


def boundaries(lane_map: LaneMap, pose: tuple[float, float, float]) -> list[np.ndarray]:
    """The outline of the union of road segments and lanes near `pose`, clipped to the shrunk box."""
    reach = float(np.hypot(LENGTH, WIDTH)) / 2 + MARGIN
    polygons = [a.polygon for a in lane_map.road_segments if _near(a.polygon, pose, reach)]
    polygons += [lane.polygon for lane in lane_map.lanes if lane.polygon is not None and not lane.connector
                 and _near(lane.polygon, pose, reach)]
    if not polygons:
        return []
    contours, _ = cv2.findContours(_raster_union(polygons, pose), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    origin = np.array([LENGTH / 2 + MARGIN, WIDTH / 2 + MARGIN])
    out: list[np.ndarray] = []
    for contour in contours:
        simple = cv2.approxPolyDP(contour, 1.0, True).reshape(-1, 2).astype(np.float64)
        if len(simple) >= 3:
            out += _ring_pieces(simple * RASTER - origin, LENGTH / 2 - EDGE, WIDTH / 2 - EDGE)
    return out


def extract(lane_map: LaneMap, pose: tuple[float, float, float]) -> VectorMap:
    """The vectorised local map around a global ego pose (x, y, yaw)."""
    reach = float(np.hypot(LENGTH, WIDTH)) / 2
    dividers: list[np.ndarray] = []
    for line in lane_map.road_dividers + lane_map.lane_dividers:
        if len(line.xy) >= 2 and _near(MapPolygon(line.xy), pose, reach):
            dividers += clip_polyline(se2_to_ego(line.xy, pose[:2], pose[2]), LENGTH / 2, WIDTH / 2)
    crossings: list[np.ndarray] = []
    for area in lane_map.ped_crossings:
        if _near(area.polygon, pose, reach):
            crossings += _ring_pieces(se2_to_ego(area.polygon.exterior, pose[:2], pose[2]),
                                      LENGTH / 2 - EDGE, WIDTH / 2 - EDGE)
    return VectorMap(tuple(dividers), tuple(crossings), tuple(boundaries(lane_map, pose)))
