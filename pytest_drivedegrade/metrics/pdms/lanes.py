"""The lanes around the ego, in the ego frame, for the lane-based terms of the EPDMS (NAVSIM v2): which lane
direction a point drives in (DDC), how far it lies from a lane centreline running its way (LK), and whether it
is inside an intersection (both terms skip those states, as NAVSIM does).

A small interface on purpose: centreline segments with their direction, lane polygons and intersection
polygons as numpy arrays, built from the map expansion's lane layers (`data.maps.LaneMap`) or directly (tests).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ...data.geometry import wrap_angle as _wrap
from ...data.maps import LaneMap, RingSet
from .constants import EGO_SIZE
from .motion import EgoStates, box_corners, out_of_lane

#: Lanes, connectors and intersections whose bounding box comes within this of the ego are kept (m).
LANE_RADIUS_M: float = 80.0
#: A state's lanes are looked for among the centreline segments within this of the states' bounding box (m): a
#: lane whose centreline is farther away cannot hold the ego (lanes are narrower), and lane keeping counts a state
#: with no same-way centreline that near as off its lane either way.
NEAR_M: float = 10.0


@dataclass(frozen=True)
class LaneView:
    """Lanes in the ego frame: centreline segments `start`/`end` (S, 2) with their direction `yaw` (S,) and lane
    index `lane` (S,); each lane's polygon ring (`polygons`, one per lane, None for a lane without one); and the
    intersections' rings."""

    start: np.ndarray
    end: np.ndarray
    yaw: np.ndarray
    lane: np.ndarray
    polygons: tuple[np.ndarray | None, ...]
    intersections: tuple[np.ndarray, ...]
    #: the route centreline (K, 2) (`route.route_centreline`), what lane keeping and the driving direction read
    #: as NAVSIM does; None: no lane holds the ego, and the nearest same-way lane stands in (the former rule)
    route: np.ndarray | None = None

    @classmethod
    def of_centrelines(cls, centrelines: Sequence[np.ndarray], polygons: Sequence[np.ndarray | None] = (),
                       intersections: Sequence[np.ndarray] = ()) -> LaneView:
        """From ego-frame centrelines (N, 2) in travel order (one per lane), their polygons and intersections."""
        starts, ends, lanes = [], [], []
        for k, c in enumerate(centrelines):
            c = np.asarray(c, dtype=np.float64).reshape(-1, 2)
            if len(c) >= 2:
                starts.append(c[:-1])
                ends.append(c[1:])
                lanes.append(np.full(len(c) - 1, k))
        start = np.concatenate(starts) if starts else np.zeros((0, 2))
        end = np.concatenate(ends) if ends else np.zeros((0, 2))
        d = end - start
        rings = tuple(None if p is None else np.asarray(p, dtype=np.float64) for p in polygons)
        return cls(start, end, np.arctan2(d[:, 1], d[:, 0]), np.concatenate(lanes) if lanes else np.zeros(0, int),
                   rings + (None,) * (len(centrelines) - len(rings)),
                   tuple(np.asarray(r, dtype=np.float64) for r in intersections))

    @classmethod
    def of_map(cls, lane_map: LaneMap, pose: Sequence[float], radius: float = LANE_RADIUS_M) -> LaneView:
        """The lanes of `lane_map` near the ego at global `pose` (x, y, yaw), moved into its frame."""
        x, y, yaw = (float(v) for v in pose)
        c, s = np.cos(yaw), np.sin(yaw)

        def local(xy: np.ndarray) -> np.ndarray:
            d = np.asarray(xy, dtype=np.float64)[:, :2] - [x, y]
            return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)

        def near(xy: np.ndarray) -> bool:
            return bool(len(xy)) and bool(((xy.min(0) <= radius) & (xy.max(0) >= -radius)).all())

        def may_be_near(boxes: np.ndarray) -> np.ndarray:
            """(K,) bool per global bounding box (K, 4: x0, y0, x1, y1): its points, in the ego frame, may have a
            bounding box meeting [-radius, radius]^2. The box turned into the ego frame holds every point of
            it, so one whose turned box (grown by a metre against rounding) misses cannot be `near`."""
            mid = 0.5 * (boxes[:, :2] + boxes[:, 2:]) - [x, y]
            hx, hy = 0.5 * (boxes[:, 2] - boxes[:, 0]), 0.5 * (boxes[:, 3] - boxes[:, 1])
            u, v = c * mid[:, 0] + s * mid[:, 1], -s * mid[:, 0] + c * mid[:, 1]
            reach = radius + 1.0
            return ((np.abs(u) <= abs(c) * hx + abs(s) * hy + reach)
                    & (np.abs(v) <= abs(s) * hx + abs(c) * hy + reach))

        candidates = [lane for lane, ok in zip(lane_map.lanes, may_be_near(lane_map.centreline_boxes)) if ok]
        lanes = [(local(lane.centreline), None if lane.polygon is None else local(lane.polygon.exterior))
                 for lane in candidates if len(lane.centreline)]
        lanes = [(cl, poly) for cl, poly in lanes if near(cl)]
        junctions = [local(a.polygon.exterior)
                     for a, ok in zip(lane_map.intersections, may_be_near(lane_map.intersection_boxes)) if ok]
        return cls.of_centrelines([cl for cl, _ in lanes], [p for _, p in lanes],
                                  [j for j in junctions if near(j)])

    @cached_property
    def _lane_set(self) -> RingSet:
        """The lanes' polygons (an empty ring for a lane without one), tested together by every plan's query."""
        return RingSet([np.zeros((0, 2)) if ring is None else ring for ring in self.polygons])

    @cached_property
    def _junction_set(self) -> RingSet:
        return RingSet(self.intersections)

    def in_intersection(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bool: the points lie in an intersection."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        junctions = self._junction_set
        return np.asarray(junctions.contains(pts, np.arange(junctions.count)).any(axis=1), dtype=bool)

    @cached_property
    def _ends_by_x(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every segment end (the starts, then the ends) sorted by x: their x, their y and their segment."""
        ends = np.concatenate([self.start, self.end])
        order = np.argsort(ends[:, 0], kind="stable")
        return ends[order, 0], ends[order, 1], order % max(len(self.start), 1)

    def _near(self, pts: np.ndarray, margin: float) -> np.ndarray:
        """Indices (ascending) of the centreline segments with an end inside the points' bounding box grown by
        `margin`: the ends within its x-range found by bisection in `_ends_by_x`, then tested on y (the same
        closed comparisons as testing every end)."""
        lo, hi = pts.min(0) - margin, pts.max(0) + margin
        x, y, segment = self._ends_by_x
        first, stop = np.searchsorted(x, lo[0], side="left"), np.searchsorted(x, hi[0], side="right")
        ys = y[first:stop]
        marked = np.zeros(len(self.start), dtype=bool)  # a mark per segment, in place of np.unique's sort
        marked[segment[first:stop][(ys >= lo[1]) & (ys <= hi[1])]] = True
        return np.flatnonzero(marked)

    def _distances(self, pts: np.ndarray, segments: np.ndarray) -> np.ndarray:
        """(N, len(segments)) distance of each point to each of `segments`: each entry from its point and segment
        alone, so a column equals the same segment's column in any other selection. Written per coordinate (no
        (N, S, 2) temporaries, no reduction over a length-2 axis): the same sums in the same order as the dot
        product and `np.linalg.norm` over that axis, so the same bits, 10x faster (tests/unit/test_lanes_exact.py)."""
        ax, ay = self.start[segments, 0], self.start[segments, 1]
        bx, by = self.end[segments, 0] - ax, self.end[segments, 1] - ay
        px, py = pts[:, 0:1], pts[:, 1:2]
        t = np.clip(((px - ax) * bx + (py - ay) * by) / np.maximum(bx * bx + by * by, 1e-12), 0.0, 1.0)
        dx, dy = ax + t * bx - px, ay + t * by - py
        return np.sqrt(dx * dx + dy * dy)

    def _route_fit(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) each point's distance to the route centreline and the route's direction at its nearest point.
        Only the route segments whose bounding box meets the points' grown by NEAR_M are measured (a segment
        that misses it lies farther than NEAR_M from every point); where a point has none of them within NEAR_M,
        every segment is: the same nearest segment either way."""
        assert self.route is not None
        a, b = self.route[:-1], self.route[1:]
        lo, hi = pts.min(0) - NEAR_M, pts.max(0) + NEAR_M
        meets = ((np.maximum(a, b) >= lo) & (np.minimum(a, b) <= hi)).all(axis=1)
        if meets.any():
            d, heading = self._segments_fit(pts, a[meets], b[meets])
            if (d <= NEAR_M).all():
                return d, heading
        return self._segments_fit(pts, a, b)

    @staticmethod
    def _segments_fit(pts: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`_route_fit` over the segments a -> b (K, 2 each)."""
        ab = b - a
        t = np.clip(((pts[:, None, :] - a[None]) * ab[None]).sum(-1) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
        d = np.hypot(*(a[None] + t[..., None] * ab[None] - pts[:, None, :]).transpose(2, 0, 1))
        k = d.argmin(axis=1)
        return d[np.arange(len(pts)), k], np.arctan2(ab[k, 1], ab[k, 0])

    def multiple_lanes(self, corners: np.ndarray) -> np.ndarray:
        """(N,) bool for ego boxes' corners (N, 4, 2): NAVSIM's "in multiple lanes", more than one lane polygon
        holds a corner and none holds all four."""
        pts = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        lanes = np.unique(self.lane[self._near(pts, NEAR_M)]) if len(self.start) else np.zeros(0, int)
        if not len(lanes):
            return np.zeros(len(pts) // 4, dtype=bool)
        held = self._lane_set.contains(pts, lanes).reshape(-1, 4, len(lanes)).sum(axis=1)  # (N, lanes)
        return np.asarray(((held > 0).sum(axis=1) > 1) & ~(held == 4).any(axis=1), dtype=bool)

    def query(self, xy: np.ndarray, heading: np.ndarray) -> LaneQuery:
        """The lane figures DDC and LK read for states at `xy` (N, 2) heading `heading` (N,), computed together.
        With a route (NAVSIM's): `deviation` is the distance to the route centreline, and a state is oncoming
        when its centre lies in no lane running the route's way at its nearest route point (off every lane
        too, as NAVSIM's "not in an on-route lane"). Without one: the nearest centreline running the state's
        own way, and the state's heading, stand in."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        head = np.asarray(heading, dtype=np.float64).reshape(-1)
        near = self._near(pts, NEAR_M)
        dist = self._distances(pts, near) if len(near) else np.zeros((len(pts), 0))
        along = np.abs(_wrap(self.yaw[near][None, :] - head[:, None])) < np.pi / 2
        deviation = np.where(along, dist, np.inf).min(axis=1) if len(near) else np.full(len(pts), np.inf)
        if self.route is not None and len(self.route) >= 2:
            deviation, head = self._route_fit(pts)
        along_any = np.zeros(len(pts), dtype=bool)
        lane_of = self.lane[near]
        lanes = np.unique(lane_of)
        inside = self._lane_set.contains(pts, lanes)  # (N, lanes): every near lane's polygon at once
        for j in np.flatnonzero(inside.any(axis=0)).tolist():
            columns = np.flatnonzero(lane_of == lanes[j])
            seg = near[columns[dist[:, columns].argmin(axis=1)]]
            along_any |= inside[:, j] & (np.abs(_wrap(self.yaw[seg] - head)) < np.pi / 2)
        return LaneQuery(deviation, ~along_any, self.in_intersection(pts))


@dataclass(frozen=True)
class LaneQuery:
    """States against the lanes (`LaneView.query`): each state's distance to the route centreline (or the
    nearest centreline running its way; `deviation`, inf where none within NEAR_M), whether its centre lies in
    no lane running the route's way (`oncoming`, NAVSIM's "not in an on-route lane": off every lane counts), and
    whether it is inside an intersection (`in_intersection`)."""

    deviation: np.ndarray
    oncoming: np.ndarray
    in_intersection: np.ndarray


def astray(states: EgoStates, off: np.ndarray, path: np.ndarray, lanes: LaneView | None,
           size: np.ndarray = EGO_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Per state (N,) the masks NAVSIM's side-contact rules read: for NC, "in multiple lanes or in non-drivable
    area" (`off`: a corner off the drivable area; multiple lanes from the lane polygons, `LaneView.multiple_lanes`;
    without lanes, a corner more than half a lane from the expert's path stands in); for TTC, the same or the
    ego's tracked point inside an intersection (NAVSIM's intersection clause, read at its rear axle)."""
    if lanes is None or not len(lanes.start):
        nc = off | out_of_lane(states, path, size)
        return nc, nc
    nc = off | lanes.multiple_lanes(box_corners(states.xy, states.heading, size))
    return nc, nc | lanes.in_intersection(states.xy)
