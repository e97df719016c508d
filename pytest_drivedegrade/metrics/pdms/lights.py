"""EPDMS traffic-light compliance (`tlc`): NAVSIM v2's `PDMScorer._calculate_traffic_light_compliance` (the
hydraMDP++ metric). A plan scores 0 when the ego's box at any tracked state intersects the area of a light that is
red at that state's time (NAVSIM: the polygon of the red light's lane connector on the route, `red_light_<id>`),
1 otherwise; not scored (NaN) where the frame's map has no traffic light, as before spec 5 everywhere.

The areas come from the map's `traffic_light` and `stop_line` layers (`data.maps.parse_lights`): the stop line's
polygon, the lanes the light controls past its line, in the frame the plan's states are in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...constants import EGO_LENGTH, EGO_WIDTH
from ...data.maps import LaneMap
from .constants import SIM_DT, SUBSTEPS
from .motion import EgoStates

EGO_SIZE = np.array([EGO_LENGTH, EGO_WIDTH])


@dataclass(frozen=True)
class RedArea:
    """One light's controlled area (convex polygon (K, 2), the states' frame) and, per tracked state, whether the
    light is red at that state's time."""

    polygon: np.ndarray
    red: np.ndarray


def box_corners(xy: np.ndarray, heading: float, size: npt.ArrayLike = EGO_SIZE) -> np.ndarray:
    """(4, 2) corners of a box centred at `xy` with `heading` and (length, width) `size`."""
    length, width = (float(v) for v in np.asarray(size, dtype=np.float64).reshape(2))
    c, s = math.cos(heading), math.sin(heading)
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length / 2, width / 2]
    return np.asarray(xy, dtype=np.float64) + local @ np.array([[c, s], [-s, c]])


def convex_intersect(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether convex polygons `a` and `b` ((K, 2) each, either orientation) intersect, touching included
    (shapely's `intersects`): no edge normal of either separates them."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
        pa, pb = a @ normals.T, b @ normals.T
        if ((pa.max(0) < pb.min(0)) | (pb.max(0) < pa.min(0))).any():
            return False
    return True


def traffic_light_compliance(states: EgoStates, areas: Sequence[RedArea] | None,
                             size: npt.ArrayLike = EGO_SIZE) -> float:
    """0 when the ego's box at a state meets an area while its light is red, 1 otherwise, NaN without lights."""
    if areas is None:
        return math.nan
    for i in range(len(states.xy)):
        live = [area for area in areas if i < len(area.red) and area.red[i]]
        if not live:
            continue
        box = box_corners(states.xy[i], float(states.heading[i]), size)
        if any(convex_intersect(box, area.polygon) for area in live):
            return 0.0
    return 1.0


def state_times(n_states: int, t0_us: int) -> np.ndarray:
    """The timestamps (microseconds) of `n_states` tracked states from `t0_us` on, SIM_DT apart."""
    return t0_us + np.round(np.arange(n_states) * SIM_DT * 1e6).astype(np.int64)


def red_areas(lane_map: LaneMap | None, pose: Sequence[float] | None, timestamp: int, poses: int,
              ) -> tuple[RedArea, ...] | None:
    """The map's lights as `RedArea`s in the ego frame at global `pose` (x, y, yaw), red per tracked state of a
    plan of `poses` waypoints from `timestamp` (us); None when the map has no lights (tlc not scored)."""
    if lane_map is None or pose is None or not lane_map.lights:
        return None
    x, y, yaw = (float(v) for v in pose)
    c, s = math.cos(yaw), math.sin(yaw)
    times = state_times(poses * SUBSTEPS + 1, int(timestamp))
    out = []
    for light in lane_map.lights:
        d = light.area.exterior[:, :2] - [x, y]
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
        out.append(RedArea(local, light.status_at(times) == "RED"))
    return tuple(out)


__all__ = ["RedArea", "box_corners", "convex_intersect", "red_areas", "state_times", "traffic_light_compliance"]
