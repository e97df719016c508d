"""Drivable area from the nuScenes map expansion (`maps/expansion/<location>.json`), for real nuScenes and the
embedded world alike.

Only the three tables the drivable area needs are read (schema of map expansion 1.3):

- ``node``: ``{"token", "x", "y"}``, global metres;
- ``polygon``: ``{"token", "exterior_node_tokens": [...], "holes": [{"node_tokens": [...]}, ...]}``;
- ``drivable_area``: ``{"token", "polygon_tokens": [...]}``.

A point is drivable when it lies inside the exterior ring of some drivable-area polygon and inside none of that
polygon's holes (even-odd rule per ring); polygons may overlap, the area is their union, as in the devkit's
``NuScenesMap.record_on_point``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import DataError
from .geometry import wrap_angle
from .tables import read_json

#: Where a data root keeps the map expansion, one JSON file per location (the log table's `location`).
EXPANSION_DIR = ("maps", "expansion")
#: The map expansion version whose schema this module reads and the world writes.
EXPANSION_VERSION = "1.3"
_CHUNK = 1 << 20  # point-edge pairs tested at a time (bounds the work arrays)


def expansion_path(root: str | os.PathLike[str], location: str) -> Path:
    """`<root>/maps/expansion/<location>.json`."""
    return Path(root).joinpath(*EXPANSION_DIR, f"{location}.json")


def points_in_ring(xy: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Even-odd (crossing number) test of points (N, 2) against one closed ring (M, 2): shape (N,) bool.

    The ring is closed implicitly (last vertex back to the first). Vectorised over points and edges; points
    exactly on an edge may fall either way. A ring tested many times keeps its `RingIndex`.
    """
    return RingIndex(ring).contains(xy)


class RingIndex:
    """One closed ring ready for `points_in_ring`'s test, done many times: its bounding box and edges computed once
    (a `RingSet` of one). `contains` is that test: the points outside the box are out, the others go through the
    ring's crossing test in chunks (bounding the work arrays)."""

    __slots__ = ("lo", "hi", "edges")

    def __init__(self, ring: np.ndarray) -> None:
        self.edges = RingSet([ring])
        self.lo: np.ndarray = self.edges.lo[0]  # unused without three vertices
        self.hi: np.ndarray = self.edges.hi[0]

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bool: each point (N, 2) lies inside the ring."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        inside = np.zeros(len(xy), dtype=bool)
        edges = len(self.edges.x0)
        if not edges or not len(xy):
            return inside
        lo, hi = self.lo, self.hi
        cand = np.flatnonzero((xy[:, 0] >= lo[0]) & (xy[:, 0] <= hi[0]) & (xy[:, 1] >= lo[1]) & (xy[:, 1] <= hi[1]))
        step = max(_CHUNK // edges, 1)
        for i in range(0, len(cand), step):
            idx = cand[i:i + step]
            inside[idx] = self.edges.parity(xy[idx])[:, 0]
        return inside


class RingSet:
    """Several closed rings tested together, all their edges in one crossing test (a frame's lane polygons
    against each plan's states, a local map's rings): the (point, edge) pairs and the arithmetic of
    `RingIndex.contains`, so the same parity bits. Rings of fewer than three vertices have no edges."""

    def __init__(self, rings: Sequence[np.ndarray]) -> None:
        arrays = [np.asarray(r, dtype=np.float64).reshape(-1, 2) for r in rings]
        edged = [(i, r) for i, r in enumerate(arrays) if len(r) >= 3]
        start = np.concatenate([r for _, r in edged]) if edged else np.zeros((0, 2))
        end = np.concatenate([np.roll(r, -1, axis=0) for _, r in edged]) if edged else np.zeros((0, 2))
        self.count = len(arrays)
        self.x0, self.y0, self.x1, self.y1 = start[:, 0], start[:, 1], end[:, 0], end[:, 1]
        self.ring = np.concatenate([np.full(len(r), i) for i, r in edged]) if edged else np.zeros(0, np.int64)
        self.y_low, self.y_high = np.minimum(self.y0, self.y1), np.maximum(self.y0, self.y1)
        self.lo = np.array([r.min(0) if len(r) else np.zeros(2) for r in arrays]).reshape(-1, 2)
        self.hi = np.array([r.max(0) if len(r) else np.zeros(2) for r in arrays]).reshape(-1, 2)

    def parity(self, pts: np.ndarray, rings: np.ndarray | None = None) -> np.ndarray:
        """(P, R) bool: an odd number of each ring's edges crosses the ray from each point (P, 2) towards +x, for
        the rings `rings` (indices, R of them; None: all) in that order. Only an edge whose y-range meets the
        points' can straddle one (y_low <= y < y_high): the same pairs as testing every edge, far fewer tests."""
        chosen = np.arange(self.count) if rings is None else np.asarray(rings, dtype=np.int64)
        column = np.full(self.count, -1)
        column[chosen] = np.arange(len(chosen))
        if not len(pts) or not len(chosen):
            return np.zeros((len(pts), len(chosen)), dtype=bool)
        px, py = pts[:, 0:1], pts[:, 1:2]
        band = np.flatnonzero((self.y_low <= py.max()) & (self.y_high > py.min()) & (column[self.ring] >= 0))
        straddle = (self.y0[band][None, :] > py) != (self.y1[band][None, :] > py)
        pe, e = np.nonzero(straddle)
        e = band[e]
        t = (py[pe, 0] - self.y0[e]) / (self.y1[e] - self.y0[e])
        crosses = px[pe, 0] < self.x0[e] + t * (self.x1[e] - self.x0[e])
        counts = np.bincount(pe[crosses] * len(chosen) + column[self.ring[e[crosses]]],
                             minlength=len(pts) * len(chosen))
        return counts.reshape(len(pts), len(chosen)) % 2 == 1

    def contains(self, pts: np.ndarray, rings: np.ndarray) -> np.ndarray:
        """(P, R) bool: each point lies inside each of `rings`, as `RingIndex.contains` finds it (a point
        outside a ring's bounding box is outside it; a ring without three vertices holds nothing)."""
        chosen = np.asarray(rings, dtype=np.int64)
        lo, hi = self.lo[chosen], self.hi[chosen]
        px, py = pts[:, 0:1], pts[:, 1:2]
        boxed = (px >= lo[:, 0]) & (px <= hi[:, 0]) & (py >= lo[:, 1]) & (py <= hi[:, 1])
        return self.parity(pts, chosen) & boxed


@dataclass(frozen=True)
class MapPolygon:
    """One map polygon in global metres: an exterior ring and its holes, each (K, 2), not repeating the first
    vertex at the end."""

    exterior: np.ndarray
    holes: tuple[np.ndarray, ...] = ()

    def contains(self, xy: npt.ArrayLike) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        inside = points_in_ring(xy, self.exterior)
        for hole in self.holes:
            if inside.any():
                inside[inside] &= ~points_in_ring(xy[inside], hole)
        return inside


@dataclass(frozen=True)
class DrivableArea:
    """The drivable-area polygons of one location; `contains` (also the instance called) is the vectorised
    point query: points (..., 2) in global metres -> bool (...)."""

    location: str
    polygons: tuple[MapPolygon, ...] = field(default_factory=tuple)

    def contains(self, xy: npt.ArrayLike) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        flat = xy.reshape(-1, 2)
        inside = np.zeros(len(flat), dtype=bool)
        for poly in self.polygons:
            rest = np.flatnonzero(~inside)
            if not len(rest):
                break
            inside[rest] = poly.contains(flat[rest])
        return inside.reshape(xy.shape[:-1])

    __call__ = contains

    def arrays(self) -> list[np.ndarray]:
        """The exterior rings alone, as (K, 2) arrays (holes are in `polygons`)."""
        return [p.exterior for p in self.polygons]


def parse_drivable_area(data: dict, location: str, source: str = "") -> DrivableArea:
    """The drivable area of a parsed map expansion JSON object."""
    try:
        nodes = {n["token"]: (float(n["x"]), float(n["y"])) for n in data.get("node", [])}
        polygons = {p["token"]: p for p in data.get("polygon", [])}
        out = []
        for record in data.get("drivable_area", []):
            tokens = record.get("polygon_tokens")
            if tokens is None:  # a single-polygon record, as the other polygon layers write it
                tokens = [record["polygon_token"]]
            for tok in tokens:
                poly = polygons[tok]
                exterior = np.array([nodes[n] for n in poly["exterior_node_tokens"]], dtype=np.float64)
                holes = tuple(np.array([nodes[n] for n in h["node_tokens"]], dtype=np.float64)
                              for h in poly.get("holes", []) if len(h.get("node_tokens", [])) >= 3)
                out.append(MapPolygon(exterior.reshape(-1, 2), holes))
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"map expansion {source or location} is malformed ({type(exc).__name__}: {exc}); "
                        f"re-extract or regenerate the map") from exc
    return DrivableArea(location, tuple(out))


def load_drivable_area(root: str | os.PathLike[str], location: str) -> DrivableArea | None:
    """The drivable area of `location` under data root `root`, or None when the root has no map file for it."""
    path = expansion_path(root, location)
    if not location or not path.is_file():
        return None
    data = read_json(path, "map expansion", "re-extract or regenerate the map")
    if not isinstance(data, dict):
        raise DataError(f"map expansion {path} is a JSON {type(data).__name__}, not an object; re-extract or "
                        "regenerate the map")
    return parse_drivable_area(data, location, str(path))


# --- the lane-level layers (lanes, connectors, dividers, crossings, road segments) -------------------------------

#: (first, middle, last) segment turn signs of an arcline path's shape: +1 left, -1 right, 0 straight (the
#: devkit's `compute_segment_sign`).
ARC_SIGNS = {"LSL": (1, 0, 1), "LSR": (1, 0, -1), "RSL": (-1, 0, 1), "RSR": (-1, 0, -1), "LRL": (1, -1, 1),
             "RLR": (-1, 1, -1)}
CENTRELINE_STEP = 0.5  # m between the centreline poses the reader samples


def _advance(x: float, y: float, h: float, curvature: float, t: np.ndarray) -> np.ndarray:
    """Poses (len(t), 3) `t` metres along a circle of `curvature` (a line at 0) from pose (x, y, h)."""
    if abs(curvature) < 1e-12:
        return np.stack([x + t * np.cos(h), y + t * np.sin(h), np.full(len(t), h)], axis=1)
    return np.stack([x + (np.sin(h + curvature * t) - np.sin(h)) / curvature,
                     y + (np.cos(h) - np.cos(h + curvature * t)) / curvature, h + curvature * t], axis=1)


def arcline_poses(path: dict, step: float = CENTRELINE_STEP) -> np.ndarray:
    """Poses (M, 3) (x, y, yaw) every ~`step` m along one arcline path record, both ends included: three
    segments of constant curvature (sign / radius) from `start_pose`, as nuScenes map expansion 1.3 writes them."""
    x, y, h = (float(v) for v in path["start_pose"][:3])
    lengths = [float(v) for v in path["segment_length"]]
    s = np.linspace(0.0, sum(lengths), max(int(np.ceil(sum(lengths) / step)) + 1, 2))
    out = np.empty((len(s), 3))
    done = 0.0
    for k, (sign, length) in enumerate(zip(ARC_SIGNS[str(path["shape"])], lengths)):
        curvature = sign / float(path["radius"])
        pick = (s >= done) & ((s <= done + length) if k == 2 else (s < done + length))
        out[pick] = _advance(x, y, h, curvature, s[pick] - done)
        x, y, h = (float(v) for v in _advance(x, y, h, curvature, np.array([length]))[0])
        done += length
    out[:, 2] = wrap_angle(out[:, 2])
    return out


@dataclass(frozen=True)
class Lane:
    """A lane or lane connector: its polygon, its centreline poses (N, 3) (x, y, yaw) in the direction of travel,
    and the lanes before and after it (`connectivity`)."""

    token: str
    polygon: MapPolygon | None
    centreline: np.ndarray
    connector: bool = False
    incoming: tuple[str, ...] = ()
    outgoing: tuple[str, ...] = ()

    def distance(self, xy: npt.ArrayLike) -> np.ndarray:
        """Distance (m) of points (..., 2) to the nearest centreline pose."""
        xy = np.asarray(xy, dtype=np.float64)
        flat = xy.reshape(-1, 2)
        d = np.sqrt(((flat[:, None, :] - self.centreline[None, :, :2]) ** 2).sum(-1)).min(1)
        return d.reshape(xy.shape[:-1])


@dataclass(frozen=True)
class MapLine:
    """A road or lane divider: its polyline (N, 2), global metres."""

    token: str
    xy: np.ndarray


@dataclass(frozen=True)
class MapArea:
    """A pedestrian crossing or a road segment: its polygon; road segments say whether they are a junction."""

    token: str
    polygon: MapPolygon
    is_intersection: bool = False


@dataclass(frozen=True)
class MapLight:
    """A traffic light of the map's `traffic_light` layer: the polygon of its stop line (`stop_line` layer: the
    lanes it controls past the line), its stop line (2, 2), and its state changes (timestamp us, "GREEN" /
    "YELLOW" / "RED"), in time order (the world's extension `states`; a light without them is never red)."""

    token: str
    area: MapPolygon
    line: np.ndarray
    changes: tuple[tuple[int, str], ...]

    def status_at(self, timestamps: npt.ArrayLike) -> np.ndarray:
        """The status at each timestamp (us): the last change at or before it ("GREEN" before the first)."""
        times = np.array([t for t, _ in self.changes], dtype=np.int64)
        names = np.array(["GREEN", *(s for _, s in self.changes)])
        return names[np.searchsorted(times, np.asarray(timestamps, dtype=np.int64), side="right")]


def parse_lights(data: dict, polygons: dict, nodes: dict, lines: dict) -> tuple[MapLight, ...]:
    """The map's traffic lights with their stop lines (`stop_line` records of type TRAFFIC_LIGHT)."""
    stops = {r["token"]: r for r in data.get("stop_line", [])}
    out = []
    for rec in data.get("traffic_light", []):
        stop = stops.get(rec.get("stop_line_token", ""))
        if stop is None or not stop.get("polygon_token"):
            continue
        line = np.array([nodes[n] for n in lines[rec["line_token"]]["node_tokens"]], dtype=np.float64) \
            if rec.get("line_token") in lines else np.zeros((0, 2))
        changes = tuple(sorted((int(c["timestamp"]), str(c["status"]).upper()) for c in rec.get("states", [])))
        out.append(MapLight(rec["token"], _polygon_of(stop["polygon_token"], polygons, nodes), line, changes))
    return tuple(out)


def bounding_boxes(rings: Sequence[np.ndarray]) -> np.ndarray:
    """(K, 4) each point set's bounding box (x0, y0, x1, y1) over its first two columns, global metres; an empty
    one NaN (a box no overlap test keeps)."""
    boxes = [(*r[:, :2].min(0), *r[:, :2].max(0)) if len(r) else (np.nan,) * 4 for r in rings]
    return np.array(boxes, dtype=np.float64).reshape(-1, 4)


@dataclass(frozen=True)
class LaneMap:
    """The lane-level layers of one location (map expansion 1.3), with its drivable area."""

    location: str
    lanes: tuple[Lane, ...]
    road_dividers: tuple[MapLine, ...]
    lane_dividers: tuple[MapLine, ...]
    ped_crossings: tuple[MapArea, ...]
    road_segments: tuple[MapArea, ...]
    drivable: DrivableArea
    lights: tuple[MapLight, ...] = ()  # the `traffic_light` layer (`parse_lights`)

    @cached_property
    def centreline_boxes(self) -> np.ndarray:
        """(L, 4) each lane's centreline bounding box (`bounding_boxes`), in `lanes` order: what `LaneView.of_map`
        skips far lanes by."""
        return bounding_boxes([lane.centreline for lane in self.lanes])

    @cached_property
    def intersections(self) -> tuple[MapArea, ...]:
        """The road segments flagged as intersections (junctions), in map order."""
        return tuple(a for a in self.road_segments if a.is_intersection)

    @cached_property
    def intersection_boxes(self) -> np.ndarray:
        """(K, 4) the bounding box of each intersection's exterior ring (`bounding_boxes`), in `intersections`
        order."""
        return bounding_boxes([a.polygon.exterior for a in self.intersections])

    def closest_lane(self, x: float, y: float, radius: float = 5.0) -> Lane | None:
        """The lane or connector whose centreline passes closest to (x, y), if within `radius` m (the devkit's
        `get_closest_lane`, on the centrelines sampled every `CENTRELINE_STEP`)."""
        best, found = radius, None
        for lane in self.lanes:
            c = lane.centreline
            if not len(c):
                continue
            lo, hi = c[:, :2].min(0) - radius, c[:, :2].max(0) + radius
            if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]:
                d = float(lane.distance([x, y]))
                if d <= best:
                    best, found = d, lane
        return found


def _polygon_of(token: str, polygons: dict, nodes: dict) -> MapPolygon:
    poly = polygons[token]
    exterior = np.array([nodes[n] for n in poly["exterior_node_tokens"]], dtype=np.float64).reshape(-1, 2)
    holes = tuple(np.array([nodes[n] for n in h["node_tokens"]], dtype=np.float64)
                  for h in poly.get("holes", []) if len(h.get("node_tokens", [])) >= 3)
    return MapPolygon(exterior, holes)


def parse_lane_map(data: dict, location: str, source: str = "") -> LaneMap:
    """The lane-level layers of a parsed map expansion JSON object (real nuScenes or the world's): centrelines
    from `arcline_path_3` (a lane without one gets an empty (0, 3) centreline), lines from `line`."""
    try:
        nodes = {n["token"]: (float(n["x"]), float(n["y"])) for n in data.get("node", [])}
        polygons = {p["token"]: p for p in data.get("polygon", [])}
        lines = {ln["token"]: ln for ln in data.get("line", [])}
        arcs, links = data.get("arcline_path_3", {}), data.get("connectivity", {})
        lanes = []
        for layer in ("lane", "lane_connector"):
            for rec in data.get(layer, []):
                paths = [arcline_poses(p) for p in arcs.get(rec["token"], [])]
                centre = np.concatenate(paths) if paths else np.zeros((0, 3))
                poly = _polygon_of(rec["polygon_token"], polygons, nodes) if rec.get("polygon_token") else None
                link = links.get(rec["token"], {})
                lanes.append(Lane(rec["token"], poly, centre, layer == "lane_connector",
                                  tuple(link.get("incoming", ())), tuple(link.get("outgoing", ()))))

        def line_layer(name: str) -> tuple[MapLine, ...]:
            return tuple(MapLine(r["token"], np.array([nodes[n] for n in lines[r["line_token"]]["node_tokens"]],
                                                      dtype=np.float64).reshape(-1, 2))
                         for r in data.get(name, []))

        def area_layer(name: str) -> tuple[MapArea, ...]:
            return tuple(MapArea(r["token"], _polygon_of(r["polygon_token"], polygons, nodes),
                                 bool(r.get("is_intersection", False))) for r in data.get(name, []))

        out = LaneMap(location, tuple(lanes), line_layer("road_divider"), line_layer("lane_divider"),
                      area_layer("ped_crossing"), area_layer("road_segment"),
                      parse_drivable_area(data, location, source), parse_lights(data, polygons, nodes, lines))
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"map expansion {source or location} is malformed ({type(exc).__name__}: {exc}); "
                        f"re-extract or regenerate the map") from exc
    return out


def load_lane_map(root: str | os.PathLike[str], location: str) -> LaneMap | None:
    """The lane-level map of `location` under data root `root`, or None when the root has no map file for it."""
    path = expansion_path(root, location)
    if not location or not path.is_file():
        return None
    data = read_json(path, "map expansion", "re-extract or regenerate the map")
    if not isinstance(data, dict):
        raise DataError(f"map expansion {path} is not a JSON object; re-extract or regenerate the map")
    return parse_lane_map(data, location, str(path))
