"""The world's lane-level map (nuScenes map expansion 1.3 layers) against the world's own geometry and the
expert's drive, and the reader on a hand-written real-schema map with a known answer."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pytest_drivedegrade.data.maps import LaneMap, arcline_poses, parse_lane_map
from pytest_drivedegrade.data.vectormap import LENGTH, WIDTH, clip_polyline, extract
from pytest_drivedegrade.data.world import export
from pytest_drivedegrade.data.world.lanemap import ARC_M
from pytest_drivedegrade.data.world.roads import LANE_WIDTH
from pytest_drivedegrade.data.world.scene import make_scene
from pytest_drivedegrade.errors import DataError

SCENES = (0, 1, 3, 7)  # a right turn on two lanes, a right turn, a left turn, ...: see the junction asserts


def _scene_map(index: int, seed: int = 0) -> tuple[object, dict, LaneMap]:
    scene = make_scene(seed, index, f"scene-{index + 1:04d}")
    data = json.loads(json.dumps(export.map_expansion(scene, seed)))  # through JSON, as the reader sees it
    return scene, data, parse_lane_map(data, export.location(scene, seed))


@pytest.fixture(scope="module")
def maps() -> dict[int, tuple[object, dict, LaneMap]]:
    return {i: _scene_map(i) for i in SCENES}


def test_the_map_is_deterministic_and_has_the_full_schema(maps):
    scene, data, _ = maps[0]
    again = export.map_expansion(make_scene(0, 0, "scene-0001"), 0)
    assert json.dumps(again, sort_keys=True) == json.dumps(data, sort_keys=True)
    for layer in ("node", "line", "polygon", "drivable_area", "road_segment", "road_block", "lane", "ped_crossing",
                  "walkway", "stop_line", "carpark_area", "road_divider", "lane_divider", "traffic_light",
                  "lane_connector"):
        assert isinstance(data[layer], list), layer
    assert data["version"] == "1.3" and len(data["canvas_edge"]) == 2
    tokens = [r["token"] for name in ("node", "line", "polygon", "lane", "lane_connector") for r in data[name]]
    assert len(tokens) == len(set(tokens))
    assert set(data["arcline_path_3"]) == set(data["connectivity"]) == {
        r["token"] for r in data["lane"] + data["lane_connector"]}


def test_the_expert_drives_in_one_mapped_lane_at_every_keyframe(maps):
    """At every keyframe the closest lane's centreline passes within 0.26 m of the ego (0.5 m sampling), heads
    the ego's way, and its polygon holds the ego; the lanes the ego visits are a path of the connectivity graph."""
    for index, (scene, _, lane_map) in maps.items():
        by_token = {lane.token: lane for lane in lane_map.lanes}
        visited: list[str] = []
        for step in scene.key_steps:
            x, y = (float(v) for v in scene.ego.xy[step])
            lane = lane_map.closest_lane(x, y)
            assert lane is not None, (index, step)
            i = int(np.argmin(((lane.centreline[:, :2] - [x, y]) ** 2).sum(1)))
            assert float(lane.distance([x, y])) < 0.26
            turn = (lane.centreline[i, 2] - scene.ego.yaw[step] + np.pi) % (2 * np.pi) - np.pi
            assert abs(turn) < 0.1, (index, step, turn)
            assert lane.connector or lane.polygon.contains([x, y])[0]
            if not visited or visited[-1] != lane.token:
                visited.append(lane.token)
        for a, b in zip(visited[:-1], visited[1:]):
            assert b in by_token[a].outgoing and a in by_token[b].incoming, (index, a, b)


def test_layers_follow_the_painted_roads(maps):
    """Lanes lie on the drivable area, dividers on the painted line offsets, one crossing per painted zebra,
    one intersection segment per junction, connectors only at junctions."""
    rng = np.random.default_rng(1)
    for index, (scene, _, m) in maps.items():
        net = scene.net
        assert len(m.ped_crossings) == len(scene.crosswalks)
        assert sum(seg.is_intersection for seg in m.road_segments) == len(net.junctions)
        assert any(lane.connector for lane in m.lanes) == bool(net.junctions)
        for lane in m.lanes:
            ring = lane.polygon.exterior
            w = rng.dirichlet(np.ones(len(ring)), size=20)  # convex combinations: inside a lane's hull
            pts = lane.centreline[rng.integers(len(lane.centreline), size=20), :2] * 0.9 + 0.1 * (w @ ring)
            assert m.drivable.contains(pts).all(), (index, lane.token)
        poses = np.concatenate([lane.centreline[:, :2] for lane in m.lanes if not lane.connector])
        for line in m.road_dividers + m.lane_dividers:  # half a lane from the nearest lane's centreline
            d = np.sqrt(((line.xy[:, None, :] - poses[None, :, :]) ** 2).sum(-1)).min(1)
            assert np.all(np.abs(d - LANE_WIDTH / 2) < 0.03), (index, line.token, d)
        assert len(m.road_dividers) > 0 and len(m.lane_dividers) >= 2 * len(m.road_dividers)


def test_arcline_paths_trace_the_sampled_centreline(maps):
    """Each arcline path (at most ARC_M long) ends within 1 cm of its recorded end pose."""
    _, data, _ = maps[3]
    worst = 0.0
    for paths in data["arcline_path_3"].values():
        for p in paths:
            end = arcline_poses(p)[-1]
            worst = max(worst, float(np.hypot(*(end[:2] - p["end_pose"][:2]))))
            assert sum(p["segment_length"]) <= ARC_M * 1.5
    assert worst < 0.01


def test_the_reader_on_a_real_schema_map():
    """A hand-written map in the real files' schema: an LSR arcline (left quarter circle, straight, right
    quarter circle) ends where geometry says, dividers and crossings come back with their nodes."""
    r = 10.0
    nodes = [{"token": f"n{i}", "x": x, "y": y} for i, (x, y) in enumerate(
        [(-1, -1), (30, -1), (30, 30), (-1, 30), (0, 0), (20, 0), (5, 5), (6, 5), (6, 6)])]
    data = {
        "version": "1.3", "node": nodes,
        "polygon": [{"token": "p0", "exterior_node_tokens": ["n0", "n1", "n2", "n3"], "holes": []},
                    {"token": "p1", "exterior_node_tokens": ["n6", "n7", "n8"], "holes": []}],
        "line": [{"token": "l0", "node_tokens": ["n4", "n5"]}],
        "drivable_area": [{"token": "d", "polygon_tokens": ["p0"]}],
        "lane": [{"token": "L", "polygon_token": "p0", "lane_type": "CAR", "left_lane_divider_segments": [],
                  "right_lane_divider_segments": []}],
        "lane_connector": [{"token": "C", "polygon_token": "p1"}],
        "arcline_path_3": {"L": [{"start_pose": [0.0, 0.0, 0.0], "end_pose": [20.0, 25.0, 0.0], "shape": "LSR",
                                  "radius": r, "segment_length": [np.pi * r / 2, 5.0, np.pi * r / 2]}]},
        "connectivity": {"L": {"incoming": [], "outgoing": ["C"]}, "C": {"incoming": ["L"], "outgoing": []}},
        "road_divider": [{"token": "rd", "line_token": "l0", "road_segment_token": ""}],
        "lane_divider": [], "ped_crossing": [{"token": "pc", "polygon_token": "p1", "road_segment_token": None}],
        "road_segment": [{"token": "rs", "polygon_token": "p0", "is_intersection": True,
                          "drivable_area_token": "d"}]}
    m = parse_lane_map(data, "boston-seaport")
    lane = m.lanes[0]
    assert lane.centreline[-1] == pytest.approx([20.0, 25.0, 0.0], abs=1e-9)
    mid = lane.centreline[np.argmin(np.abs(lane.centreline[:, 1] - 12.5))]
    assert mid[0] == pytest.approx(10.0, abs=1e-9) and mid[2] == pytest.approx(np.pi / 2, abs=1e-9)
    assert lane.outgoing == ("C",) and m.lanes[1].connector and m.lanes[1].centreline.shape == (0, 3)
    assert m.road_dividers[0].xy.tolist() == [[0.0, 0.0], [20.0, 0.0]]
    assert m.ped_crossings[0].polygon.contains([[5.6, 5.2]])[0] and m.road_segments[0].is_intersection
    assert m.closest_lane(10.2, 12.0).token == "L" and m.closest_lane(100.0, 100.0) is None
    del data["line"]
    with pytest.raises(DataError, match="malformed"):
        parse_lane_map(data, "boston-seaport", "x.json")



def test_clip_polyline_known_answers():
    pieces = clip_polyline(np.array([[-10.0, 0.0], [10.0, 0.0]]), 5.0, 1.0)
    assert len(pieces) == 1 and pieces[0].tolist() == [[-5.0, 0.0], [5.0, 0.0]]
    zigzag = np.array([[-4.0, 0.0], [0.0, 3.0], [4.0, 0.0]])  # leaves |y| <= 1 and comes back
    pieces = clip_polyline(zigzag, 5.0, 1.0)
    assert len(pieces) == 2
    np.testing.assert_allclose(pieces[0], [[-4.0, 0.0], [-4.0 + 4.0 / 3.0, 1.0]])
    np.testing.assert_allclose(pieces[1], [[4.0 - 4.0 / 3.0, 1.0], [4.0, 0.0]])
    inside = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.0]])
    assert np.array_equal(clip_polyline(inside, 5.0, 1.0)[0], inside)
    assert clip_polyline(np.array([[6.0, 0.0], [9.0, 0.0]]), 5.0, 1.0) == []


def test_the_vector_map_of_every_keyframe_has_dividers_and_boundaries_in_the_box(maps):
    """The VAD-style extraction (60 m along the heading, 30 m across): dividers and boundaries at every keyframe,
    everything inside the box; beside the ego (outside junctions, where dividers stop) the nearest divider lies
    1.75 m to its side."""
    beside = total = 0
    for index, (scene, _, lane_map) in maps.items():
        for step in scene.key_steps[::4]:
            pose = (float(scene.ego.xy[step, 0]), float(scene.ego.xy[step, 1]), float(scene.ego.yaw[step]))
            vm = extract(lane_map, pose)
            assert vm.dividers and vm.boundaries, (index, step)
            for line in vm.dividers + vm.ped_crossings + vm.boundaries:
                assert np.all(np.abs(line) <= np.array([LENGTH, WIDTH]) / 2 + 1e-9)
            # where each divider crosses the ego's lateral axis (x = 0)
            near = np.array([p[1] + (q[1] - p[1]) * (0.0 - p[0]) / (q[0] - p[0]) for d in vm.dividers
                             for p, q in zip(d[:-1], d[1:]) if min(p[0], q[0]) <= 0.0 < max(p[0], q[0])])
            total += 1
            if len(near):
                beside += 1
                assert np.min(np.abs(np.abs(near) - LANE_WIDTH / 2)) < 0.05, (index, step)
    assert beside >= 0.75 * total
