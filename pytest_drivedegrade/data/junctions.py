"""Where another command is meaningful (spec 5, issue 40): the ego at or approaching a junction whose lane map
allows a manoeuvre other than the logged command's, and the path the privileged expert would drive for it.

From the ego's lane (the closest lane centreline within `ON_LANE_M`, heading within `ON_LANE_RAD`, not a connector:
a frame already inside the junction is committed) the lane graph is walked forward over `outgoing` links up to the
distance the logged future covers plus `REACH_MARGIN_M`; each lane connector met is a manoeuvre the map allows,
named by its heading change (more than `TURN_RAD` to the left: LEFT, to the right: RIGHT, else STRAIGHT). A
manoeuvre whose command differs from the logged one is the frame's alternative (the first, in RIGHT, LEFT,
STRAIGHT order, when there are several).

The expert's path for it: the logged future's progress along its own path (its arc length at each waypoint) laid
along the map's centrelines of that manoeuvre (the ego's lane from the ego's projection, the connector, the lane
after it), in the ego frame. So the privileged expert given the other route drives the same speeds through the
other manoeuvre; the logged future is its plan under the logged route. A frame whose two paths end less than
`MIN_SEPARATION_M` apart is not scored (the manoeuvres do not part within the horizon).

Pure functions over a `LaneMap`; nothing here reads files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .frame import Command
from .maps import Lane, LaneMap

ON_LANE_M = 2.5  # m: the ego is on a lane whose centreline passes this close
ON_LANE_RAD = np.pi / 4  # rad: ... and whose direction is within this of the ego's heading
TURN_RAD = np.pi / 6  # rad: a connector turning more than this is a turn
REACH_MARGIN_M = 5.0  # m: connectors this far beyond the logged future's reach still count
MIN_SEPARATION_M = 1.0  # m: the two manoeuvres' endpoints must part by at least this


@dataclass(frozen=True)
class Alternative:
    """A frame's alternative command and the expert's path for it, (HORIZON_STEPS, 2) in the ego frame."""

    command: Command
    path: np.ndarray


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def manoeuvre(lane: Lane) -> Command:
    """A connector's manoeuvre from its heading change (start to end)."""
    c = lane.centreline
    turn = _wrap(float(c[-1, 2] - c[0, 2])) if len(c) >= 2 else 0.0
    return Command.LEFT if turn > TURN_RAD else Command.RIGHT if turn < -TURN_RAD else Command.STRAIGHT


def ego_lane(lane_map: LaneMap, pose: tuple[float, float, float]) -> tuple[Lane, int] | None:
    """The lane (not a connector) the ego drives along, and the index of its centreline pose nearest the ego."""
    x, y, yaw = pose
    best: tuple[float, Lane, int] | None = None
    for lane in lane_map.lanes:
        c = lane.centreline
        if lane.connector or not len(c):
            continue
        d = np.hypot(c[:, 0] - x, c[:, 1] - y)
        i = int(d.argmin())
        if d[i] <= ON_LANE_M and abs(_wrap(float(c[i, 2]) - yaw)) <= ON_LANE_RAD and (best is None or d[i] < best[0]):
            best = (float(d[i]), lane, i)
    return None if best is None else (best[1], best[2])


def _length(xy: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0


def connectors_ahead(lane_map: LaneMap, start: Lane, index: int, reach: float) -> list[tuple[Lane, list[Lane]]]:
    """Each connector reachable from `start` (from centreline pose `index`) within `reach` m, with the lanes
    leading to it (start first), in the map's order of `outgoing` links."""
    by_token = {lane.token: lane for lane in lane_map.lanes}
    found: list[tuple[Lane, list[Lane]]] = []
    todo = [(start, [start], _length(start.centreline[index:, :2]))]
    while todo:
        lane, chain, dist = todo.pop(0)
        for token in lane.outgoing:
            nxt = by_token.get(token)
            if nxt is None or nxt in chain:
                continue
            if nxt.connector:
                found.append((nxt, chain))
            elif dist <= reach:
                todo.append((nxt, [*chain, nxt], dist + _length(nxt.centreline[:, :2])))
    return found


def _along(path: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points at arc lengths `s` along polyline `path` (N, 2); beyond its end, straight on along its last
    direction."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    path = path[keep]
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    x, y = np.interp(s, cum, path[:, 0]), np.interp(s, cum, path[:, 1])
    over = s > cum[-1]
    if over.any() and len(path) >= 2:
        d = (path[-1] - path[-2]) / max(np.linalg.norm(path[-1] - path[-2]), 1e-9)
        x[over], y[over] = path[-1, 0] + d[0] * (s[over] - cum[-1]), path[-1, 1] + d[1] * (s[over] - cum[-1])
    return np.stack([x, y], axis=-1)


def _to_ego(xy: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    x, y, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    d = xy - np.array([x, y])
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=-1)


def expert_path(chain: list[Lane], connector: Lane, index: int, gt_future: np.ndarray,
                by_token: dict[str, Lane], pose: tuple[float, float, float]) -> np.ndarray:
    """The logged future's arc lengths laid along `chain` (from pose `index`), the connector and the lane after it,
    in the ego frame."""
    after = [by_token[t] for t in connector.outgoing if t in by_token][:1]
    parts = [chain[0].centreline[index:, :2], *(lane.centreline[:, :2] for lane in chain[1:]),
             connector.centreline[:, :2], *(lane.centreline[:, :2] for lane in after)]
    local = _to_ego(np.concatenate(parts), pose)
    local = local - local[0]  # from the ego, not from its projection on the centreline: only the manoeuvre differs
    fut = np.asarray(gt_future, dtype=np.float64)
    s = np.cumsum(np.linalg.norm(np.diff(np.concatenate([[[0.0, 0.0]], fut]), axis=0), axis=1))
    return _along(local, s)


def alternative(lane_map: LaneMap | None, pose: tuple[float, float, float] | None, gt_future: np.ndarray,
                command: Command) -> Alternative | None:
    """The frame's alternative command and the expert's path for it, or None where no other command is
    meaningful (no map or pose, not on a lane, no junction within reach, or no manoeuvre that parts)."""
    if lane_map is None or pose is None:
        return None
    on = ego_lane(lane_map, pose)
    if on is None:
        return None
    lane, index = on
    fut = np.asarray(gt_future, dtype=np.float64)
    reach = _length(np.concatenate([[[0.0, 0.0]], fut])) + REACH_MARGIN_M
    by_token = {x.token: x for x in lane_map.lanes}
    options: dict[Command, tuple[Lane, list[Lane]]] = {}
    for connector, chain in connectors_ahead(lane_map, lane, index, reach):
        options.setdefault(manoeuvre(connector), (connector, chain))
    for other in (Command.RIGHT, Command.LEFT, Command.STRAIGHT):
        if other == command or other not in options:
            continue
        connector, chain = options[other]
        path = expert_path(chain, connector, index, fut, by_token, pose)
        if np.linalg.norm(path[-1] - fut[-1]) >= MIN_SEPARATION_M:
            return Alternative(other, path)
    return None
