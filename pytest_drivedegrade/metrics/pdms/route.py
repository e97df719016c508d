"""The route centreline NAVSIM's lane keeping and driving direction read (PDM-Closed's `centerline`, the
on-route lanes), built from the lane map and the logged future, since the data carry no mission route.

NAVSIM's centreline is the chain of lane (and connector) centrelines from the ego's current lane along the
route, following each lane into one of its successors (never sideways into a neighbour). Here the route is the
logged future's: of every chain from a lane holding the ego now, following `Lane.outgoing`, long enough to
cover the logged future, the one the logged future's points stay closest to (the largest of their distances
to it the smallest; ties to the first in map order). A same-direction lane change of the plan is then off the
route, as in NAVSIM.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ...data.geometry import wrap_angle
from ...data.maps import Lane, LaneMap

#: A lane holds the ego when its polygon contains the ego's centre (or, for a lane without a polygon, its
#: centreline passes within this, m) and it runs within 90 degrees of the ego's heading there.
HOLD_M: float = 2.0
#: Chains are followed this far (m) past the farthest logged point, and at most this many lanes deep.
ROUTE_MARGIN_M, ROUTE_DEPTH = 20.0, 12
#: A lane whose centreline's bounding box is farther than this from the ego (m) cannot hold it (lanes are narrower).
NEAR_BOX_M: float = 10.0


def _holds(lane: Lane, xy: np.ndarray, yaw: float) -> bool:
    """The lane holds a point heading `yaw` (global): inside its polygon (or near its centreline) and along it."""
    line = lane.centreline
    if len(line) < 2:
        return False
    d = np.hypot(line[:, 0] - xy[0], line[:, 1] - xy[1])
    k = int(d.argmin())
    inside = bool(lane.polygon.contains(xy[None])[0]) if lane.polygon is not None else float(d[k]) <= HOLD_M
    return inside and abs(float(wrap_angle(line[k, 2] - yaw))) < np.pi / 2


def _polyline_distance(line: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the polyline (K, 2)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    den = np.maximum((ab * ab).sum(1), 1e-12)
    t = np.clip(((pts[:, None, :] - a[None]) * ab[None]).sum(-1) / den, 0.0, 1.0)
    near = a[None] + t[..., None] * ab[None]
    return np.asarray(np.hypot(*(near - pts[:, None, :]).transpose(2, 0, 1)).min(axis=1))


def _length(line: np.ndarray) -> float:
    return float(np.hypot(*np.diff(line[:, :2], axis=0).T).sum())


def _chains(lanes: dict[str, Lane], start: str, reach: float) -> list[list[str]]:
    """Every chain of lanes from `start` following `outgoing` until its centrelines run `reach` m (or
    ROUTE_DEPTH lanes, or a lane without successors), depth first in map order."""
    out: list[list[str]] = []
    stack: list[tuple[list[str], float]] = [([start], 0.0)]
    while stack:
        chain, run = stack.pop()
        line = lanes[chain[-1]].centreline
        run += _length(line)
        nexts = [t for t in lanes[chain[-1]].outgoing if t in lanes and t not in chain]
        if run >= reach or len(chain) >= ROUTE_DEPTH or not nexts:
            out.append(chain)
            continue
        stack.extend((chain + [t], run) for t in reversed(nexts))
    return out


#: The last lane maps' token indexes, by the map's id (the map kept beside it, so the id cannot be reused).
_BY_TOKEN: dict[int, tuple[LaneMap, dict[str, Lane]]] = {}


def _lanes_by_token(lane_map: LaneMap) -> dict[str, Lane]:
    """The map's lanes with a centreline, by token; built once per map (a real map has thousands)."""
    found = _BY_TOKEN.get(id(lane_map))
    if found is None or found[0] is not lane_map:
        if len(_BY_TOKEN) >= 8:
            _BY_TOKEN.clear()
        found = _BY_TOKEN[id(lane_map)] = (lane_map, {lane.token: lane for lane in lane_map.lanes
                                                      if len(lane.centreline) >= 2})
    return found[1]


def route_centreline(lane_map: LaneMap, pose: Sequence[float], logged: npt.ArrayLike) -> np.ndarray | None:
    """The route centreline (K, 2) in the ego frame at global `pose` (x, y, yaw), for the logged future
    `logged` (M, 2, ego frame): see the module docstring. None when no lane holds the ego."""
    x, y, yaw = (float(v) for v in pose)
    c, s = np.cos(yaw), np.sin(yaw)
    pts = np.asarray(logged, dtype=np.float64).reshape(-1, 2)
    world = np.stack([x + c * pts[:, 0] - s * pts[:, 1], y + s * pts[:, 0] + c * pts[:, 1]], axis=1)
    world = np.vstack([[x, y], world])
    by_token = _lanes_by_token(lane_map)
    box = lane_map.centreline_boxes
    near = (box[:, 0] <= x + NEAR_BOX_M) & (box[:, 2] >= x - NEAR_BOX_M) & (box[:, 1] <= y + NEAR_BOX_M) \
        & (box[:, 3] >= y - NEAR_BOX_M)
    starts = [lane.token for lane, ok in zip(lane_map.lanes, near.tolist())
              if ok and lane.token in by_token and _holds(lane, np.array([x, y]), yaw)]
    if not starts:
        return None
    reach = float(np.hypot(*(world - world[0]).T).max()) + ROUTE_MARGIN_M
    best: tuple[float, np.ndarray] | None = None
    for start in starts:  # the start lane counted whole: the ego may be anywhere along it
        for chain in _chains(by_token, start, reach + _length(by_token[start].centreline)):
            line = np.concatenate([by_token[t].centreline[:, :2] for t in chain])
            worst = float(_polyline_distance(line, world).max())
            if best is None or worst < best[0]:
                best = (worst, line)
    assert best is not None
    d = best[1] - [x, y]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)


def route_progress(route: np.ndarray, start: np.ndarray, end: np.ndarray) -> float:
    """NAVSIM v2's raw progress along its centreline (`PDMScorer._calculate_progress`): the arc length of `end`'s
    nearest point on the route (K, 2) less `start`'s (shapely's `project`: clamped to the route's ends, the first
    nearest segment), at least 0."""
    a, b = route[:-1], route[1:]
    ab = b - a
    length = np.hypot(ab[:, 0], ab[:, 1])
    at = np.concatenate([[0.0], np.cumsum(length)])

    def along(point: np.ndarray) -> float:
        den = np.where(length > 0, length**2, 1.0)
        t = np.clip(((point - a) * ab).sum(1) / den, 0.0, 1.0)
        k = int(np.hypot(*(a + t[:, None] * ab - point).T).argmin())
        return float(at[k] + t[k] * length[k])

    return max(along(np.asarray(end, dtype=np.float64)) - along(np.asarray(start, dtype=np.float64)), 0.0)
