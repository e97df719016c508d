"""The world's map (nuScenes map expansion, drivable area) against the world's own geometry and the painted
ground, and the reader's map queries on the world and on a hand-written real-schema map."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from pytest_drivedegrade.data.maps import DrivableArea, MapPolygon, expansion_path, parse_drivable_area, points_in_ring
from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.data.world import WORLD_VERSION, export, texture, write_world
from pytest_drivedegrade.data.world.roads import SIDEWALK, RoadNet
from pytest_drivedegrade.data.world.scene import make_scene
from pytest_drivedegrade.errors import DataError

MARGIN = 0.05  # m: points this close to a carriageway edge are not judged (the map is within 0.01 m of it)
ASPHALT, OFF, EDGE = 1, -1, 0


def _nearest(pts: np.ndarray, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the nearest of `samples` (M, 2) and its index, for points (N, 2)."""
    d2 = (pts**2).sum(1)[:, None] + (samples**2).sum(1)[None, :] - 2.0 * pts @ samples.T
    idx = d2.argmin(1)
    return np.sqrt(((pts - samples[idx]) ** 2).sum(1)), idx


def _segment_distance(pts: np.ndarray, line: np.ndarray, order: np.ndarray, reach: float) -> np.ndarray:
    """Exact distance of points (N, 2) to a polyline (M, 2) where it is below `reach` (farther: some value
    above `reach`). Points go in chunks along the line (`order`), each against the segments near its box."""
    a, b = line[:-1], line[1:]
    ab = b - a
    len2 = np.maximum((ab**2).sum(1), 1e-12)
    best = np.full(len(pts), np.inf)
    for i in range(0, len(pts), 128):
        idx = order[i:i + 128]
        p = pts[idx]
        lo, hi = p.min(0) - reach - 0.5, p.max(0) + reach + 0.5
        seg = np.flatnonzero(((a >= lo) & (a <= hi)).all(1) | ((b >= lo) & (b <= hi)).all(1))
        if not len(seg):
            continue
        q = p[:, None, :]
        t = np.clip(((q - a[seg]) * ab[seg]).sum(-1) / len2[seg], 0.0, 1.0)
        best[idx] = np.linalg.norm(q - (a[seg] + t[..., None] * ab[seg]), axis=-1).min(1)
    return best


def surface(net: RoadNet, pts: np.ndarray, margin: float = MARGIN) -> tuple[np.ndarray, np.ndarray]:
    """What the renderer paints at each point, from the road geometry (not from the map): ASPHALT within a
    road's half width of its centreline polyline or inside a junction square, OFF farther than `margin` outside
    all of them, EDGE in between; and whether an OFF point is on a sidewalk (within SIDEWALK of a carriageway).
    """
    outside = np.full(len(pts), np.inf)  # signed distance outside the nearest carriageway (negative inside)
    for road in net.roads:
        line = road.center.xy
        # every 2 m: the exact distance lies at most 1 m below the distance to the nearest of these samples
        coarse, which = _nearest(pts, line[::8])
        reach = road.half_width + SIDEWALK + 1.0
        near = np.flatnonzero(coarse - 1.0 < reach - 1.0 + margin)  # the others are OFF, past the sidewalks
        exact = _segment_distance(pts[near], line, np.argsort(which[near], kind="stable"), reach)
        d = coarse.copy()
        d[near] = np.minimum(coarse[near], exact)
        outside = np.minimum(outside, d - road.half_width)
    for j in net.junctions:
        c, s = np.cos(j.heading), np.sin(j.heading)
        rel = pts - j.center
        uv = np.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c], axis=1)
        outside = np.minimum(outside, np.abs(uv).max(1) - j.half)
    label = np.where(outside <= -margin, ASPHALT, np.where(outside >= margin, OFF, EDGE))
    return label, (label == OFF) & (outside < SIDEWALK)


def _world_area(seed: int, index: int) -> tuple[object, DrivableArea]:
    scene = make_scene(seed, index, f"scene-{index + 1:04d}")
    data = json.loads(json.dumps(export.map_expansion(scene, seed)))  # through JSON, as the reader sees it
    return scene, parse_drivable_area(data, export.location(scene, seed))


def _in_box(pts, centre, size, yaw) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    rel = pts - centre
    u, v = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
    return (np.abs(u) < size[0] / 2) & (np.abs(v) < size[1] / 2)


def sample_points(scene, rng: np.random.Generator, n_uniform: int, n_road: int, n_building: int) -> dict:
    """Points where the cameras see the ground (the ego's drive +- 100 m, the painted map), points across the
    roads (carriageway, curb, sidewalk and a little beyond) and points inside buildings."""
    lo, hi = scene.ego.xy.min(0) - 100.0, scene.ego.xy.max(0) + 100.0
    uniform = rng.uniform(lo, hi, size=(n_uniform, 2))
    roads = scene.net.roads
    which = rng.integers(len(roads), size=n_road)
    across = []
    for k, road in enumerate(roads):
        m = int((which == k).sum())
        x, y, yaw = road.center.at(rng.uniform(0.0, road.center.length, m))
        d = rng.uniform(-1.0, 1.0, m) * (road.half_width + SIDEWALK + 2.0)
        across.append(np.stack([x - d * np.sin(yaw), y + d * np.cos(yaw)], 1))
    buildings = [p for p in scene.props if p.kind == "building"]
    inside = []
    for p in (rng.choice(len(buildings), n_building) if buildings else []):
        b = buildings[int(p)]
        u, v = rng.uniform(-0.5, 0.5, 2) * np.array(b.size[:2])
        c, s = np.cos(b.yaw), np.sin(b.yaw)
        inside.append(b.xy + np.array([c * u - s * v, s * u + c * v]))
    return {"uniform": uniform, "across roads": np.concatenate(across),
            "buildings": np.array(inside).reshape(-1, 2)}


def test_map_polygons_agree_with_the_world_geometry():
    """Asphalt inside, sidewalks, verge and buildings outside: every judged point of 12 scenes agrees."""
    rng = np.random.default_rng(0)
    tested = agreed = sidewalk = buildings = edge = 0
    for index in range(12):
        scene, area = _world_area(0, index)
        assert area.polygons and all(len(p.exterior) >= 4 and not p.holes for p in area.polygons)
        for kind, pts in sample_points(scene, rng, 6000, 6000, 300).items():
            label, on_sidewalk = surface(scene.net, pts)
            got = area.contains(pts)
            judged = label != EDGE
            tested += int(judged.sum())
            agreed += int((got[judged] == (label[judged] == ASPHALT)).sum())
            sidewalk += int(on_sidewalk.sum())
            edge += int((~judged).sum())
            if kind == "buildings":
                buildings += len(pts)
                assert not got.any(), f"scene {index}: a building footprint lies in the drivable area"
                assert (label == OFF).all()
            bad = judged & (got != (label == ASPHALT))
            assert not bad.any(), f"scene {index} ({kind}): {pts[bad][:5]} disagree"
    assert tested == agreed and tested > 140_000 and sidewalk > 10_000 and buildings > 3000
    assert edge < 0.02 * tested


#: A sidewalk label colour whose joints (x 0.8) blended with grey asphalt never look like sidewalk or curb (x 1.15).
SIDEWALK_LABEL = np.array([40.0, 90.0, 10.0])


def _painted(rgb: np.ndarray) -> np.ndarray:
    """ASPHALT for grey >= 200 (asphalt, or a crack blended into it), OFF for sidewalk, curb or verge colours,
    EDGE for anything else (anti-aliased edges, and paver joints, which the painter draws across sidewalks
    after the asphalt, so that a few run onto a crossing road)."""
    grey = (rgb.min(1) >= 200) & (np.ptp(rgb, axis=1) <= 2)
    off = np.zeros(len(rgb), dtype=bool)
    for colour in (SIDEWALK_LABEL, SIDEWALK_LABEL * 1.15, np.zeros(3)):
        off |= (np.abs(rgb - np.minimum(colour, 255)) <= 1.0).all(1)
    return np.where(grey, ASPHALT, np.where(off, OFF, EDGE))


def test_map_matches_the_painted_asphalt():
    """The renderer's own painter, with label colours: painted asphalt is inside, sidewalk and verge outside."""
    for index in (0, 1, 3):
        scene, area = _world_area(0, index)
        net = scene.net
        centre = net.junctions[0].center if net.junctions else scene.ego.xy[0]
        origin = centre - 60.0
        size = int(120.0 / texture.MAP_RES)
        img = np.zeros((size, size, 3), np.uint8)  # verge (0, 0, 0)
        style = SimpleNamespace(asphalt=250.0, sidewalk=SIDEWALK_LABEL)
        texture._paint_roads(texture._Painter(img, origin), net, style, np.random.default_rng(index))
        rng = np.random.default_rng(index)
        rows, cols = rng.integers(0, size, 60_000), rng.integers(0, size, 60_000)
        pts = origin + np.stack([cols, rows], 1) * texture.MAP_RES  # pixel centres (the painter's convention)
        painted = _painted(img[rows, cols].astype(float))
        label, _ = surface(net, pts, margin=2.5 * texture.MAP_RES)  # the painter rounds widths to a pixel
        judged = (painted != EDGE) & (label != EDGE)
        assert judged.sum() > 50_000
        assert (painted[judged] == label[judged]).all()  # the painter and the geometry agree, so ...
        got = area.contains(pts[judged])
        assert (got == (painted[judged] == ASPHALT)).all()  # ... the map agrees with the painted ground
        assert (painted[judged] == ASPHALT).sum() > 5000 and (painted[judged] == OFF).sum() > 5000


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return write_world(tmp_path_factory.mktemp("mapworld") / "w", scenes=2, seed=4, val_images=False)


def test_world_writes_a_map_per_location_and_the_reader_loads_it(world):
    logs = json.loads((world / WORLD_VERSION / "log.json").read_text())
    assert [r["location"] for r in logs] == ["ddworld-s4-scene-0001", "ddworld-s4-scene-0003"]
    for r in logs:
        data = json.loads(expansion_path(world, r["location"]).read_text())
        assert data["version"] == "1.3" and len(data["drivable_area"]) == 1
        nodes = {n["token"] for n in data["node"]}
        polygons = {p["token"]: p for p in data["polygon"]}
        assert set(data["drivable_area"][0]["polygon_tokens"]) <= set(polygons)  # the lane layers' are the rest
        assert all(set(p["exterior_node_tokens"]) <= nodes and p["holes"] == [] for p in polygons.values())
    reader = NuScenesReader(world, split="all")
    frames = reader.scorable_frames()
    assert {f.location for f in frames} == {r["location"] for r in logs}
    for f in frames:
        area = reader.drivable_area(f)
        assert area is reader.drivable_area(f.location)  # read once per location
        assert area(f.to_global(np.zeros((1, 2))))[0]  # the ego stands on the road ...
        assert area(f.to_global(f.gt_future)).all()  # ... and the expert stays on it
    assert reader.drivable_area("nowhere") is None


def test_frame_pose_maps_ego_frame_points_to_the_world(world):
    frame = NuScenesReader(world, split="val").scorable_frames(limit=3)[1]
    scene = make_scene(4, 1, "scene-0003")
    k = next(i for i in range(len(scene.key_steps)) if scene.ego.xy[scene.key_steps[i], 0] == frame.pose[0])
    steps = scene.key_steps[k + 1:k + 7]
    np.testing.assert_allclose(frame.to_global(frame.gt_future), scene.ego.xy[steps], atol=1e-6)
    assert frame.pose[2] == pytest.approx(scene.ego.yaw[scene.key_steps[k]])


def _real_schema_map(root, location: str) -> None:
    """A map expansion file written by hand in the real schema: a 40 m x 40 m square with a 10 m x 10 m hole
    (an island), an overlapping second record that covers half of the hole, and a walkway (not drivable)."""
    nodes = {"a": (0, 0), "b": (40, 0), "c": (40, 40), "d": (0, 40),
             "h1": (15, 15), "h2": (15, 25), "h3": (25, 25), "h4": (25, 15),
             "p1": (22, 10), "p2": (60, 10), "p3": (60, 30), "p4": (22, 30), "w1": (-10, -10), "w2": (-1, -10)}
    data = {"version": "1.3", "node": [{"token": k, "x": float(x), "y": float(y)} for k, (x, y) in nodes.items()],
            "polygon": [{"token": "sq", "exterior_node_tokens": ["a", "b", "c", "d"],
                         "holes": [{"node_tokens": ["h1", "h2", "h3", "h4"]}]},
                        {"token": "right", "exterior_node_tokens": ["p1", "p2", "p3", "p4"], "holes": []},
                        {"token": "walk", "exterior_node_tokens": ["w1", "w2", "d"], "holes": []}],
            "drivable_area": [{"token": "da0", "polygon_tokens": ["sq"]},
                              {"token": "da1", "polygon_tokens": ["right"]}],
            "walkway": [{"token": "w0", "polygon_token": "walk"}]}
    path = expansion_path(root, location)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def test_reader_loads_a_real_nuscenes_map_expansion_with_holes(world, tmp_path):
    import shutil

    root = tmp_path / "nuscenes"
    shutil.copytree(world / WORLD_VERSION, root / WORLD_VERSION)
    logs = json.loads((root / WORLD_VERSION / "log.json").read_text())
    for r in logs:
        r["location"] = "singapore-onenorth"
    (root / WORLD_VERSION / "log.json").write_text(json.dumps(logs))
    reader = NuScenesReader(root, split="all")
    frame = reader.scorable_frames(limit=1)[0]
    assert frame.location == "singapore-onenorth" and reader.drivable_area(frame) is None  # no map: None
    _real_schema_map(root, "singapore-onenorth")
    area = NuScenesReader(root, split="all").drivable_area(frame)
    assert len(area.polygons) == 2 and len(area.polygons[0].holes) == 1
    np.testing.assert_array_equal(area.arrays()[0], [[0, 0], [40, 0], [40, 40], [0, 40]])
    pts = np.array([[5, 5], [18, 20], [24, 20], [50, 20], [45, 5], [-1, 3], [39.9, 39.9], [70, 20], [-5, -8]])
    np.testing.assert_array_equal(area(pts), [True, False, True, True, False, False, True, False, False])
    assert area(pts[:8].reshape(2, 4, 2)).shape == (2, 4)
    with pytest.raises(DataError, match="malformed"):
        parse_drivable_area({"drivable_area": [{"token": "x", "polygon_tokens": ["missing"]}]}, "x")


def test_points_in_ring_matches_a_brute_force_crossing_count():
    rng = np.random.default_rng(5)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 40))
    ring = np.stack([np.cos(angles), np.sin(angles)], 1) * rng.uniform(0.4, 1.0, (40, 1))  # star-shaped
    pts = rng.uniform(-1.1, 1.1, (3000, 2))
    expected = []
    for x, y in pts:
        n = 0
        for (x0, y0), (x1, y1) in zip(ring, np.roll(ring, -1, 0)):
            if (y0 > y) != (y1 > y) and x < x0 + (y - y0) / (y1 - y0) * (x1 - x0):
                n += 1
        expected.append(n % 2 == 1)
    np.testing.assert_array_equal(points_in_ring(pts, ring), expected)
    assert MapPolygon(ring).contains(np.zeros((0, 2))).shape == (0,)
