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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ..errors import DataError
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
    exactly on an edge may fall either way.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    ring = np.asarray(ring, dtype=np.float64).reshape(-1, 2)
    inside = np.zeros(len(xy), dtype=bool)
    if len(ring) < 3 or not len(xy):
        return inside
    lo, hi = ring.min(0), ring.max(0)
    cand = np.flatnonzero((xy[:, 0] >= lo[0]) & (xy[:, 0] <= hi[0]) & (xy[:, 1] >= lo[1]) & (xy[:, 1] <= hi[1]))
    if not len(cand):
        return inside
    x0, y0 = ring[:, 0], ring[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    edge = np.arange(len(ring))
    for i in range(0, len(cand), max(_CHUNK // len(ring), 1)):
        idx = cand[i:i + max(_CHUNK // len(ring), 1)]
        px, py = xy[idx, 0:1], xy[idx, 1:2]
        # edges that straddle the horizontal line through the point (half-open, so a vertex counts once)
        straddle = (y0[None, :] > py) != (y1[None, :] > py)
        pe, ee = np.nonzero(straddle)
        e = edge[ee]
        t = (py[pe, 0] - y0[e]) / (y1[e] - y0[e])
        crosses = px[pe, 0] < x0[e] + t * (x1[e] - x0[e])
        inside[idx] = np.bincount(pe[crosses], minlength=len(idx)) % 2 == 1
    return inside


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
