"""Traffic lights of the world's light scenes (spec 5, section 18): one light per scene on the route, for the ego's
direction of travel.

A light has a stop line across the lanes of the ego's direction (at arc length `s_line` on the route centreline),
a state schedule on the scene's sim clock (green, then `YELLOW_S` of yellow, red, then green again), a head on a
mast arm over those lanes `HEAD_AHEAD_M` past the line (the front camera still sees it from the line) whose lit
lamp shows the state, and a controlled area: the lanes of its direction from the stop line `AREA_M` on (what
NAVSIM's traffic-light compliance tests the ego's box against while the light is red, as NAVSIM tests the red
light's lane connector).

Written to the scene's map (`map_layers`) in the nuScenes map expansion's `stop_line` (type `TRAFFIC_LIGHT`) and
`traffic_light` layers; the nuScenes map has static lights only, so each `traffic_light` record carries its
schedule as the world's extension `states`: the state from each timestamp (microseconds) on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .roads import LANE_WIDTH, RoadNet

GREEN, YELLOW, RED = "green", "yellow", "red"
STATES = (GREEN, YELLOW, RED)
#: s of yellow between green and red (a 40-50 km/h street's amber).
YELLOW_S = 3.0
#: m past the stop line where the head hangs over the lanes; its lamps' height (m, bottom and top of the head).
HEAD_AHEAD_M, HEAD_Z = 12.0, (4.3, 6.1)
#: m of lane past the stop line that the light controls (NAVSIM's red-light area: the lane connector it guards).
AREA_M = 10.0
#: Lamp colours lit and dark (RGB), top to bottom: red, yellow, green.
LIT = {RED: (255, 30, 20), YELLOW: (255, 190, 0), GREEN: (20, 235, 70)}
DARK = {RED: (60, 20, 18), YELLOW: (60, 50, 15), GREEN: (15, 50, 25)}
HOUSING = (25, 25, 28)


@dataclass(frozen=True)
class TrafficLight:
    """One light: stop line at `s_line` on the route centreline across `lanes` lanes of the ego's direction; green
    before `t_yellow` (s on the sim clock), yellow for YELLOW_S, red until `t_green`, green after."""

    s_line: float
    lanes: int
    t_yellow: float
    t_green: float

    @property
    def t_red(self) -> float:
        return self.t_yellow + YELLOW_S

    def state_at(self, t_s: float) -> str:
        """The state at `t_s` seconds on the scene's sim clock."""
        if t_s < self.t_yellow or t_s >= self.t_green:
            return GREEN
        return YELLOW if t_s < self.t_red else RED

    def changes(self) -> list[tuple[float, str]]:
        """(time s, state from then on), from the scene's start."""
        return [(0.0, GREEN), (self.t_yellow, YELLOW), (self.t_red, RED), (self.t_green, GREEN)]

    def stop_line(self, net: RoadNet) -> np.ndarray:
        """(2, 2) the line's ends: the route's centreline, and the outer edge of its direction's last lane."""
        return _across(net, self.s_line, 0.0, -self.lanes * LANE_WIDTH)

    def along(self, net: RoadNet) -> np.ndarray:
        """(2,) the unit vector along the route at the stop line (the direction of travel)."""
        _, _, yaw = net.route.center.at(self.s_line)
        return np.array([np.cos(yaw), np.sin(yaw)])

    def area(self, net: RoadNet) -> np.ndarray:
        """(4, 2) the controlled area, counter-clockwise: the lanes from the stop line AREA_M on."""
        a = _across(net, self.s_line, 0.0, -self.lanes * LANE_WIDTH)
        b = _across(net, self.s_line + AREA_M, 0.0, -self.lanes * LANE_WIDTH)
        return np.array([a[1], b[1], b[0], a[0]])

    def head(self, net: RoadNet) -> tuple[float, float, float]:
        """The head's (x, y, yaw): over the middle of the lanes, facing the approaching ego."""
        x, y, yaw = net.route.center.at(self.s_line + HEAD_AHEAD_M)
        d = -self.lanes * LANE_WIDTH / 2
        return float(x - d * np.sin(yaw)), float(y + d * np.cos(yaw)), float(yaw + np.pi)

    def pole(self, net: RoadNet) -> tuple[float, float, float]:
        """The pole's (x, y, yaw) on the right curb, in line with the head."""
        x, y, yaw = net.route.center.at(self.s_line + HEAD_AHEAD_M)
        d = -(net.route.half_width + 0.4)
        return float(x - d * np.sin(yaw)), float(y + d * np.cos(yaw)), float(yaw)


def _across(net: RoadNet, s: float, d0: float, d1: float) -> np.ndarray:
    x, y, yaw = net.route.center.at(s)
    n = np.array([-np.sin(yaw), np.cos(yaw)])
    p = np.array([x, y], dtype=np.float64)
    return np.stack([p + d0 * n, p + d1 * n])


def segments_cross(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether segment `a` (2, 2) and segment `b` (2, 2) intersect (touching counts, as shapely's `intersects`)."""
    def side(p, q, r) -> float:
        return float((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]))

    def on(p, q, r) -> bool:  # r on segment pq, given collinear
        return bool(min(p[0], q[0]) <= r[0] <= max(p[0], q[0]) and min(p[1], q[1]) <= r[1] <= max(p[1], q[1]))

    d1, d2 = side(b[0], b[1], a[0]), side(b[0], b[1], a[1])
    d3, d4 = side(a[0], a[1], b[0]), side(a[0], a[1], b[1])
    if d1 * d2 < 0 and d3 * d4 < 0:
        return True
    return (d1 == 0 and on(b[0], b[1], a[0])) or (d2 == 0 and on(b[0], b[1], a[1])) or \
        (d3 == 0 and on(a[0], a[1], b[0])) or (d4 == 0 and on(a[0], a[1], b[1]))


def map_layers(lights, net: RoadNet, token: Callable[..., str], seed: int, index: int, time0: int,
               ) -> dict[str, list[dict]]:
    """The lights as nuScenes map-expansion records: `node`, `line` and `polygon` rows to add, and the
    `stop_line` and `traffic_light` layers (`time0`: the scene's first timestamp, microseconds)."""
    out: dict[str, list[dict]] = {"node": [], "line": [], "polygon": [], "stop_line": [], "traffic_light": []}

    def nodes(points: np.ndarray, *key) -> list[str]:
        toks = [token(seed, "map-light-node", index, *key, k) for k in range(len(points))]
        out["node"] += [{"token": t, "x": round(float(x), 4), "y": round(float(y), 4)}
                        for t, (x, y) in zip(toks, points.tolist())]
        return toks

    for j, light in enumerate(lights):
        line = light.stop_line(net)
        tl_tok, sl_tok = token(seed, "map-traffic-light", index, j), token(seed, "map-stop-line", index, j)
        line_tok, area_tok = token(seed, "map-light-line", index, j), token(seed, "map-light-area", index, j)
        out["line"].append({"token": line_tok, "node_tokens": nodes(line, j, "line")})
        out["polygon"].append({"token": area_tok, "exterior_node_tokens": nodes(light.area(net), j, "area"),
                               "holes": []})
        out["stop_line"].append({"token": sl_tok, "polygon_token": area_tok, "stop_line_type": "TRAFFIC_LIGHT",
                                 "ped_crossing_tokens": [], "traffic_light_tokens": [tl_tok],
                                 "road_block_token": "", "line_token": line_tok})
        x, y, yaw = light.head(net)
        out["traffic_light"].append({
            "token": tl_tok, "line_token": line_tok, "stop_line_token": sl_tok, "traffic_light_type": "VERTICAL",
            "from_road_block_token": "",
            "items": [{"color": c.upper(), "shape": "CIRCLE", "rel_pos": {"tx": 0.0, "ty": 0.0, "tz": z, "rx": 0.0,
                                                                           "ry": 0.0, "rz": 0.0},
                       "to_road_block_tokens": []} for c, z in zip((RED, YELLOW, GREEN), (1.5, 0.9, 0.3))],
            "pose": {"tx": round(x, 4), "ty": round(y, 4), "tz": HEAD_Z[0], "rx": 0.0, "ry": 0.0,
                     "rz": round(yaw, 6)},
            "states": [{"timestamp": time0 + int(round(t * 1e6)), "status": s.upper()} for t, s in light.changes()]})
    return out


__all__ = ["AREA_M", "GREEN", "RED", "STATES", "YELLOW", "YELLOW_S", "TrafficLight", "map_layers",
           "segments_cross"]
