"""Query the world's lane-level maps with the official nuscenes-devkit's `NuScenesMap`; print a JSON answer.

Run by tests/unit/test_devkit.py in the devkit's own interpreter: ``python devkit_map.py DATAROOT QUERIES.json``.
QUERIES maps a location to its samples ``{"token", "pose": [x, y, yaw], "future": [[x, y], ...]}``. Per sample it
answers with the devkit's own calls: `layers_on_point`, `get_closest_lane` and its `discretize_lanes` poses,
`get_records_in_radius` counts, the distance from the logged future to `discretize_centerlines`, and the
VAD/MapTR vectorised map (`get_map_geom` on a 60 m x 30 m patch along the ego's heading: dividers, crossings, the
outline of the union of road segments and lanes clipped to the patch shrunk by 0.2 m) in the ego frame.
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np
from nuscenes.map_expansion import map_api
from shapely import ops
from shapely.geometry import LineString, MultiLineString, Polygon, box

LENGTH, WIDTH, EDGE = 60.0, 30.0, 0.2
LAYERS = ["lane", "lane_connector", "road_divider", "lane_divider", "ped_crossing", "road_segment"]


def lines_of(geom) -> list:
    """The LineStrings of a (multi)line geometry, as coordinate lists."""
    if geom.is_empty:
        return []
    if isinstance(geom, LineString):
        return [list(geom.coords)]
    if isinstance(geom, MultiLineString):
        return [list(g.coords) for g in geom.geoms]
    return [c for g in getattr(geom, "geoms", []) for c in lines_of(g)]


def to_ego(lines: list) -> list:
    """Patch frame (rotated by yaw - 90 deg: forward is +y, left is -x) to the ego frame (x forward, y left)."""
    return [[[y, -x] for x, y in line] for line in lines]


def vector_map(m: map_api.NuScenesMap, x: float, y: float, yaw: float) -> dict:
    patch, angle = (x, y, LENGTH, WIDTH), math.degrees(yaw) - 90.0
    dividers = [c for layer in ("road_divider", "lane_divider")
                for line in m.explorer._get_layer_line(patch, angle, layer) for c in lines_of(line)]
    local = box(-WIDTH / 2 + EDGE, -LENGTH / 2 + EDGE, WIDTH / 2 - EDGE, LENGTH / 2 - EDGE)
    crossings, seen = [], 0
    for multi in m.explorer._get_layer_polygon(patch, angle, "ped_crossing"):
        for poly in multi.geoms:
            pieces = lines_of(poly.exterior.intersection(local))
            crossings += pieces
            seen += bool(pieces)
    polys = [p for layer in ("road_segment", "lane") for multi in m.explorer._get_layer_polygon(patch, angle, layer)
             for p in multi.geoms]
    union = ops.unary_union(polys)
    # shapely's noding leaves zero-area slivers where collinear edges of neighbouring polygons meet: holes under
    # 1 dm^2 (a 5 cm raster's resolution) are no boundary
    rings = [r for p in getattr(union, "geoms", [union])
             for r in (p.exterior, *(h for h in p.interiors if Polygon(h).area >= 0.01))]
    boundaries = [c for r in rings for c in lines_of(r.intersection(local))]
    return {"dividers": to_ego(dividers), "crossings": to_ego(crossings), "crossing_polygons": seen,
            "boundaries": to_ego(boundaries)}


def main(root: str, queries: dict) -> dict:
    out = {}
    for location, samples in queries.items():
        map_api.locations.append(location)  # the devkit knows only nuScenes' four maps by name
        m = map_api.NuScenesMap(dataroot=root, map_name=location)
        centres = np.concatenate([np.asarray(c)[:, :2] for c in m.discretize_centerlines(0.5) if len(c)])
        for s in samples:
            x, y, yaw = s["pose"]
            lane = m.get_closest_lane(x, y, radius=2.0)
            poses = m.discretize_lanes([lane], 0.5)[lane] if lane else []
            future = np.asarray(s["future"]).reshape(-1, 2)
            gap = np.sqrt(((future[:, None, :] - centres[None]) ** 2).sum(-1)).min(1) if len(future) else []
            out[s["token"]] = {
                "on_point": m.layers_on_point(x, y, ["lane", "road_segment", "drivable_area", "ped_crossing"]),
                "closest_lane": lane, "closest_poses": [list(p) for p in poses],
                "in_radius": {k: len(v) for k, v in m.get_records_in_radius(x, y, 30.0, LAYERS).items()},
                "future_gap": float(np.max(gap)) if len(gap) else 0.0,
                "vector": vector_map(m, x, y, yaw)}
    return out


if __name__ == "__main__":
    with open(sys.argv[2]) as fh:
        print(json.dumps(main(sys.argv[1], json.load(fh))))
