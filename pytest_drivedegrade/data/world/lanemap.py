"""The scene's lane-level map in nuScenes map-expansion form (schema 1.3): lanes and lane connectors with
centrelines (`arcline_path_3`) and `connectivity`, road and lane dividers, pedestrian crossings and road segments
(junctions flagged `is_intersection`), over the `node`, `line` and `polygon` tables.

The map says what the renderer paints (`texture._paint_roads`, `_paint_markings`), so a map-using planner and a
lane-based score see the road the cameras see:

- traffic keeps right: a road's lanes of its own direction lie right of its centreline (offsets -(k + 1/2) 3.5 m),
  the oncoming lanes left; the parking shoulder beyond the outer lane is carriageway (road segment), not lane;
- outside junction squares a road is cut every `PIECE_M` of centreline into one road segment and one lane per lane
  and direction; inside a square the route's own movement (its turn, or straight on) and the straight-through
  movements are lane connectors, and the square is an intersection road segment;
- dividers are the painted lines: the road centre (yellow, or white dashed) is a `road_divider`, the lines between
  same-direction lanes (dashed) and at the outer lane's edge (solid) are `lane_divider`s, stopping 0.5 m short of
  a junction as painted; a zebra crossing is a `ped_crossing` over its painted stripes.

Centrelines are arcline paths of `ARC_M` each: a circular arc (or a straight) from the sampled pose with the
curvature that meets the next sampled heading, so the devkit's `discretize_lane` traces the lane within 1 cm.
Tokens derive from (seed, scene, counter), coordinates are rounded to 0.1 mm: the same seed gives the same bytes.
"""

from __future__ import annotations

import cv2
import numpy as np

from .roads import LANE_WIDTH, STEP, Junction, Path, Road, RoadNet, in_junction

PIECE_M = 40.0  # m of centreline per lane and road segment outside junctions
ARC_M = 5.0  # m of centreline per arcline path
LINE_GAP = 10.0  # m: the most between two nodes of a divider (the devkit tests a line's nodes against a patch)
PAINT_MARGIN = 0.5  # m: painted lines stop this far outside a junction square (texture._runs)
STRAIGHT_RADIUS = 999.0  # the radius a straight arcline path carries (its arc segments have zero length)
MIN_CURVATURE = 1e-4  # 1/m: flatter pieces are written as straights
ARC_TOLERANCE = 0.005  # m: an arcline path ends this close to the sampled centreline
POLY_TOLERANCE = 0.01  # m: polygons are simplified within this (as the drivable area)
CROSSWALK_HALF = 1.5  # m: half the painted crossing's length along the road
DASHED, SOLID, YELLOW = "DOUBLE_DASHED_WHITE", "SINGLE_SOLID_WHITE", "SINGLE_SOLID_YELLOW"
#: (direction, lane index) -> the divider segments on the lane's left and right
Sides = dict[tuple[int, int], tuple[list[dict], list[dict]]]


def _wrap(a: np.ndarray | float) -> np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _normal(yaw: np.ndarray) -> np.ndarray:
    return np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [a, b] (inclusive, at least two samples) where `mask` holds."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return [(int(a), int(b) - 1) for a, b in zip(edges[::2], edges[1::2]) if b - a >= 2]


def _pieces(a: int, b: int) -> list[tuple[int, int]]:
    n = max(1, round((b - a) * STEP / PIECE_M))
    cuts = np.linspace(a, b, n + 1).round().astype(int)
    return [(int(x), int(y)) for x, y in zip(cuts[:-1], cuts[1:]) if y > x]


def _arc_end(x: float, y: float, h: float, k: float, length: float) -> np.ndarray:
    if abs(k) < MIN_CURVATURE:
        return np.array([x + length * np.cos(h), y + length * np.sin(h)])
    return np.array([x + (np.sin(h + k * length) - np.sin(h)) / k, y + (np.cos(h) - np.cos(h + k * length)) / k])


def _fit(xy: np.ndarray, yaw: np.ndarray, s: np.ndarray, a: int, b: int) -> list[tuple[int, int, float]]:
    """(a, b, curvature) pieces of samples a..b, each one arc from pose a that meets heading b and ends within
    `ARC_TOLERANCE` of sample b; a piece that misses (a bend starting inside it) is halved."""
    length = float(s[b] - s[a])
    k = float(_wrap(yaw[b] - yaw[a])) / max(length, 1e-9)
    miss = np.linalg.norm(_arc_end(float(xy[a, 0]), float(xy[a, 1]), float(yaw[a]), k, length) - xy[b])
    if miss <= ARC_TOLERANCE or b - a < 2:
        return [(a, b, k)]
    m = (a + b) // 2
    return _fit(xy, yaw, s, a, m) + _fit(xy, yaw, s, m, b)


def arclines(xy: np.ndarray, yaw: np.ndarray) -> list[dict]:
    """Arcline path records (`start_pose`, `end_pose`, `shape`, `radius`, `segment_length`) along a sampled
    centreline (N, 2) with headings (N,), at most `ARC_M` each: a left (`LSL`) or right (`RSR`) arc as the first
    segment, or a straight as the middle one; shorter where the curvature changes (see `_fit`)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    n = max(1, round(s[-1] / ARC_M))
    cuts = np.unique(np.searchsorted(s, np.linspace(0.0, s[-1], n + 1)).clip(0, len(s) - 1))
    pose = np.column_stack([xy, _wrap(yaw)]).tolist()
    out = []
    for a, b, k in _fit_all(xy, yaw, s, cuts):
        length = float(s[b] - s[a])
        if abs(k) < MIN_CURVATURE:
            shape, radius, seg = "LSL", STRAIGHT_RADIUS, [0.0, length, 0.0]
        else:
            shape, radius, seg = ("LSL" if k > 0 else "RSR"), 1.0 / abs(k), [length, 0.0, 0.0]
        out.append({"start_pose": [round(v, 6) for v in pose[a]], "end_pose": [round(v, 6) for v in pose[b]],
                    "shape": shape, "radius": round(radius, 6), "segment_length": [round(v, 6) for v in seg]})
    return out


def _fit_all(xy: np.ndarray, yaw: np.ndarray, s: np.ndarray, cuts: np.ndarray) -> list[tuple[int, int, float]]:
    """`_fit` of every piece between consecutive `cuts`, the first try of all pieces at once: a piece whose arc
    meets its end (not within 1e-12 m of the tolerance, where the two ways of summing could disagree) is one arc
    with the curvature `_fit` computes; the others go through `_fit` itself."""
    a, b = cuts[:-1], cuts[1:]
    length = s[b] - s[a]
    k = _wrap(yaw[b] - yaw[a]) / np.maximum(length, 1e-9)
    x, y, h = xy[a, 0], xy[a, 1], yaw[a]
    flat = np.abs(k) < MIN_CURVATURE
    kk = np.where(flat, 1.0, k)
    end_x = np.where(flat, x + length * np.cos(h), x + (np.sin(h + kk * length) - np.sin(h)) / kk)
    end_y = np.where(flat, y + length * np.sin(h), y + (np.cos(h) - np.cos(h + kk * length)) / kk)
    miss = np.hypot(end_x - xy[b, 0], end_y - xy[b, 1])
    whole = ((miss <= ARC_TOLERANCE) | (b - a < 2)) & (np.abs(miss - ARC_TOLERANCE) > 1e-12)
    out: list[tuple[int, int, float]] = []
    for i, (ai, bi, ki) in enumerate(zip(a.tolist(), b.tolist(), k.tolist())):
        out += [(ai, bi, ki)] if whole[i] else _fit(xy, yaw, s, ai, bi)
    return out


class MapTables:
    """The geometric tables (`node`, `line`, `polygon`) and the layers, filled as records are added."""

    def __init__(self, token, seed: int, index: int) -> None:
        self._token, self.seed, self.index = token, seed, index
        self.count = 0
        self.layers: dict[str, list[dict]] = {name: [] for name in (
            "node", "line", "polygon", "lane", "lane_connector", "road_segment", "road_divider", "lane_divider",
            "ped_crossing")}
        self.arcline_path_3: dict[str, list[dict]] = {}
        self.connectivity: dict[str, dict[str, list[str]]] = {}
        self.ends: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # lane token -> (first, last) centreline pose

    def token(self, kind: str) -> str:
        self.count += 1
        return self._token(self.seed, "lanemap", kind, self.index, self.count)

    def nodes(self, xy: np.ndarray) -> list[str]:
        toks = [self.token("node") for _ in range(len(xy))]
        self.layers["node"] += [{"token": t, "x": round(x, 4), "y": round(y, 4)}
                                for t, (x, y) in zip(toks, np.asarray(xy, dtype=np.float64).tolist())]
        return toks

    def polygon(self, ring: np.ndarray) -> str:
        """A polygon of the ring's vertices that Douglas-Peucker keeps within POLY_TOLERANCE: the original
        (float64) vertices, so two polygons sharing an edge share its coordinates exactly (no sliver between)."""
        flat = (ring - ring[0]).astype(np.float32)
        simple = cv2.approxPolyDP(flat.reshape(-1, 1, 2), POLY_TOLERANCE, True).reshape(-1, 2)
        rows = [tuple(v) for v in flat.tolist()]
        first = dict(zip(reversed(rows), range(len(rows) - 1, -1, -1)))  # a vertex -> its first index in ring
        keep = [first[tuple(v)] for v in simple.tolist()]
        tok = self.token("polygon")
        self.layers["polygon"].append({"token": tok, "exterior_node_tokens": self.nodes(ring[keep]), "holes": []})
        return tok

    def line(self, xy: np.ndarray) -> tuple[str, list[str]]:
        o = xy[0]
        simple = cv2.approxPolyDP((xy - o).astype(np.float32).reshape(-1, 1, 2), POLY_TOLERANCE, False)
        toks = self.nodes(_densify(simple.reshape(-1, 2).astype(np.float64) + o))
        tok = self.token("line")
        self.layers["line"].append({"token": tok, "node_tokens": toks})
        return tok, toks

    def lane(self, layer: str, ring: np.ndarray, centre: np.ndarray, yaw: np.ndarray,
             sides: tuple[list[dict], list[dict]] = ([], [])) -> str:
        """A lane (or lane connector) with its polygon, centreline and, for lanes, its edge lines and dividers."""
        tok = self.token(layer)
        record: dict = {"token": tok, "polygon_token": self.polygon(ring)}
        if layer == "lane":
            n = _normal(yaw[[0, -1]])
            half = LANE_WIDTH / 2
            record.update({"lane_type": "CAR", "left_lane_divider_segments": sides[0],
                           "right_lane_divider_segments": sides[1],
                           "from_edge_line_token": self.line(np.stack([centre[0] - half * n[0],
                                                                       centre[0] + half * n[0]]))[0],
                           "to_edge_line_token": self.line(np.stack([centre[-1] - half * n[1],
                                                                     centre[-1] + half * n[1]]))[0]})
        self.layers[layer].append(record)
        self.arcline_path_3[tok] = arclines(centre, yaw)
        self.ends[tok] = (np.array([*centre[0], yaw[0]]), np.array([*centre[-1], yaw[-1]]))
        return tok

    def link(self, reach: float = 1.0) -> None:
        """`connectivity`: lane B follows lane A where B starts within `reach` of A's end, heading the same way."""
        toks = list(self.ends)
        first = np.array([self.ends[t][0] for t in toks]).reshape(-1, 3)
        last = np.array([self.ends[t][1] for t in toks]).reshape(-1, 3)
        gap = np.linalg.norm(last[:, None, :2] - first[None, :, :2], axis=-1)
        turn = np.abs(_wrap(last[:, None, 2] - first[None, :, 2]))
        follows = (gap < reach) & (turn < np.pi / 4) & ~np.eye(len(toks), dtype=bool)
        for i, t in enumerate(toks):
            self.connectivity[t] = {"incoming": [toks[j] for j in np.flatnonzero(follows[:, i])],
                                    "outgoing": [toks[j] for j in np.flatnonzero(follows[i])]}


def _densify(pts: np.ndarray) -> np.ndarray:
    """A polyline (M, 2) with each segment p -> q cut into k = ceil(|q - p| / LINE_GAP) (at least 1) equal parts:
    the points p + t (q - p), t = i / k as `np.linspace(0, 1, k + 1)` gives them (i * (1 / k), the last exactly 1)."""
    d = pts[1:] - pts[:-1]
    ratio = np.hypot(d[:, 0], d[:, 1]) / LINE_GAP
    k = np.ceil(ratio)
    near = np.flatnonzero(np.abs(ratio - np.round(ratio)) < 1e-9)  # where a last-bit difference could matter
    k[near] = [np.ceil(np.linalg.norm(d[j]) / LINE_GAP) for j in near]
    k = np.maximum(k, 1).astype(np.int64)
    seg = np.repeat(np.arange(len(k)), k)
    i = np.arange(1, len(seg) + 1) - np.repeat(np.cumsum(k) - k, k)  # 1..k within each segment
    t = i.astype(np.float64) * (1.0 / k)[seg]
    t[i == k[seg]] = 1.0
    return np.concatenate([pts[:1], pts[:-1][seg] + t[:, None] * d[seg]])


def _strip(xy: np.ndarray, yaw: np.ndarray, d_right: float, d_left: float) -> np.ndarray:
    """The counter-clockwise ring between two offsets of a centreline piece (right edge forward, left back)."""
    n = _normal(yaw)
    return np.concatenate([xy + d_right * n, (xy + d_left * n)[::-1]])


def _lanes_of(t: MapTables, layer: str, road: Road, xy: np.ndarray, yaw: np.ndarray,
              sides: Sides | None = None) -> None:
    """One lane (or connector) per lane and direction on a centreline piece; forward lanes right of it."""
    n = _normal(yaw)
    for direction in (1, -1):
        for k in range(road.lanes):
            inner, outer = -direction * k * LANE_WIDTH, -direction * (k + 1) * LANE_WIDTH
            centre = xy + (inner + outer) / 2 * n
            ring = _strip(xy, yaw, min(inner, outer), max(inner, outer))
            heading = yaw if direction == 1 else yaw + np.pi
            if direction == -1:
                centre, heading = centre[::-1], heading[::-1]
            t.lane(layer, ring, centre, heading, (sides or {}).get((direction, k), ([], [])))


def _dividers(t: MapTables, road: Road, net: RoadNet, a: int, b: int, yellow: bool) -> Sides:
    """The painted lines of one piece as divider records; the divider nodes each lane has on its left and right
    (a lane's left is its inner offset, its right its outer one, in either direction)."""
    c = road.center
    kind_of = {0.0: YELLOW if yellow else DASHED}
    kind_of.update({s * k * LANE_WIDTH: SOLID if k == road.lanes else DASHED
                    for s in (-1, 1) for k in range(1, road.lanes + 1)})
    nodes_at: dict[float, list[str]] = {d: [] for d in kind_of}
    for p, q in _runs(~in_junction(net, c.xy[a:b + 1], PAINT_MARGIN)):
        xy, yaw = c.xy[a + p:a + q + 1], c.yaw[a + p:a + q + 1]
        n = _normal(yaw)
        for d in sorted(kind_of):
            line, nodes = t.line(xy + d * n)
            nodes_at[d] += nodes
            if d == 0.0:
                t.layers["road_divider"].append({"token": t.token("road_divider"), "line_token": line,
                                                 "road_segment_token": ""})
            else:
                t.layers["lane_divider"].append({"token": t.token("lane_divider"), "line_token": line,
                                                 "lane_divider_segments": [{"node_token": x, "segment_type": kind_of[d]}
                                                                           for x in nodes]})

    def segments(d: float) -> list[dict]:
        return [{"node_token": x, "segment_type": kind_of[d]} for x in nodes_at[d]]

    return {(direction, k): (segments(-direction * k * LANE_WIDTH + 0.0), segments(-direction * (k + 1) * LANE_WIDTH))
            for direction in (1, -1) for k in range(road.lanes)}


def lane_layers(net: RoadNet, crosswalks: list[float], token, seed: int, index: int, yellow: bool) -> MapTables:
    """Every lane-level layer of one scene's roads (see the module docstring)."""
    t = MapTables(token, seed, index)
    route_pieces: list[tuple[int, int, str]] = []
    for r, road in enumerate(net.roads):
        c = road.center
        inside = in_junction(net, c.xy)
        # where another road's carriageway overlaps the route's (the arm the route turns onto), the route's lanes
        # are the map's: the other road's lanes start where it leaves the route (a fork, as painted)
        shared = _on_route(net, c.xy, net.route.half_width + road.half_width) if r else np.zeros(len(c.xy), bool)
        for a0, b0 in _runs(~inside & ~shared):
            for a, b in _pieces(a0, b0):
                xy, yaw = c.xy[a:b + 1], c.yaw[a:b + 1]
                lo = a - _overlap(inside, shared, a0 - 1, -1, net, road) if a == a0 else a
                hi = b + _overlap(inside, shared, b0 + 1, 1, net, road) if b == b0 else b
                seg = t.token("road_segment")
                t.layers["road_segment"].append({"token": seg, "polygon_token": t.polygon(
                    _strip(c.xy[lo:hi + 1], c.yaw[lo:hi + 1], -road.half_width, road.half_width)),
                    "is_intersection": False, "drivable_area_token": ""})
                if r == 0:
                    route_pieces.append((a, b, seg))
                _lanes_of(t, "lane", road, xy, yaw, _dividers(t, road, net, a, b, yellow))
        for a, b in _runs(inside):
            if a > 0 and b < len(c.xy) - 1:  # a run through a square (not a road that starts in one)
                _lanes_of(t, "lane_connector", road, c.xy[a - 1:b + 2], c.yaw[a - 1:b + 2])
    for j in net.junctions:
        _junction(t, net, j)
    _crossings(t, net, crosswalks, route_pieces)
    t.link()
    return t


def _overlap(inside: np.ndarray, shared: np.ndarray, i: int, way: int, net: RoadNet, road: Road) -> int:
    """Samples a road segment reaches past its piece's end `i - way` so that it overlaps its neighbour (no crack
    in the union): one into a junction square, or into the route's carriageway where another road leaves it."""
    if not 0 <= i < len(inside):
        return 0
    if inside[i]:
        return 1
    if not shared[i]:
        return 0
    run = _runs(shared[i::way] if way == 1 else shared[i::-1])
    return min(run[0][1] + 1 if run else 1, round(2 * (net.route.half_width + road.half_width) / STEP))


def _on_route(net: RoadNet, xy: np.ndarray, reach: float) -> np.ndarray:
    """Samples (N, 2) within `reach` of the route's centreline (beside it, not beyond its ends)."""
    along, lateral = net.route.center.project(xy)
    return (np.abs(lateral) < reach) & (along >= 0.0) & (along <= net.route.center.length)


def _junction(t: MapTables, net: RoadNet, j: Junction) -> None:
    """The square as an intersection segment; where the route turns, the straight-on connector of its approach."""
    u, v = np.array([np.cos(j.heading), np.sin(j.heading)]), np.array([-np.sin(j.heading), np.cos(j.heading)])
    square = np.array([j.center + a * j.half * u + b * j.half * v for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    t.layers["road_segment"].append({"token": t.token("road_segment"), "polygon_token": t.polygon(square),
                                     "is_intersection": True, "drivable_area_token": ""})
    if j.turn != "straight":
        s = np.arange(-j.half - STEP, j.half + STEP + 1e-9, STEP)
        straight = Path(j.center + s[:, None] * u, np.full(len(s), j.heading), s - s[0])
        _lanes_of(t, "lane_connector", Road(straight, net.route.lanes), straight.xy, straight.yaw)


def _crossings(t: MapTables, net: RoadNet, crosswalks: list[float], pieces: list[tuple[int, int, str]]) -> None:
    """Each painted zebra crossing of the route: the rectangle over its stripes (texture._paint_markings)."""
    route = net.route
    for s_c in crosswalks:
        x, y, yaw = route.center.at(s_c)
        u, v = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        d = np.arange(-route.half_width + 0.6, route.half_width - 0.3, 1.0)
        q = np.array([float(x), float(y)])
        ring = np.array([q + a * CROSSWALK_HALF * u + w * v for a, w in ((-1, d[0]), (1, d[0]), (1, d[-1] + 0.5),
                                                                         (-1, d[-1] + 0.5))])
        i = int(round(s_c / STEP))
        seg = next((tok for a, b, tok in pieces if a <= i <= b), "")
        t.layers["ped_crossing"].append({"token": t.token("ped_crossing"), "polygon_token": t.polygon(ring),
                                         "road_segment_token": seg})
