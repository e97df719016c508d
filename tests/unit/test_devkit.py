"""The world through the official nuscenes-devkit, walked as mmdet3d's, UniAD's and VAD's converters walk it.

nuscenes-devkit 1.2.0 pins numpy < 2, so it never enters the project's environment: it lives in a separate venv
whose python DRIVEDEGRADE_DEVKIT_PYTHON names (`.ci/run` makes one:
``python -m venv /tmp/dd-devkit && /tmp/dd-devkit/bin/pip install nuscenes-devkit==1.2.0``). The walk
(`devkit_walk.py`) runs there in a subprocess and prints a JSON summary this test checks.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.data.geometry import wrap_angle
from pytest_drivedegrade.data.maps import expansion_path, parse_lane_map
from pytest_drivedegrade.data.vectormap import extract
from pytest_drivedegrade.data.world import export, write_world
from pytest_drivedegrade.data.world.build import DEFAULT_SCENES, split_names
from pytest_drivedegrade.data.world.scene import KEYFRAMES, make_scene

WALK = Path(__file__).with_name("devkit_walk.py")
ENV_VAR = "DRIVEDEGRADE_DEVKIT_PYTHON"


def _devkit_python() -> str:
    python = os.environ.get(ENV_VAR, "")
    if not python:
        pytest.skip(f"{ENV_VAR} is not set: point it at a python with nuscenes-devkit==1.2.0 in its own venv "
                    "(python -m venv /tmp/dd-devkit && /tmp/dd-devkit/bin/pip install nuscenes-devkit==1.2.0)")
    if not Path(python).is_file():
        pytest.skip(f"{ENV_VAR}={python} does not exist")
    probe = subprocess.run([python, "-c", "import nuscenes"], capture_output=True, text=True)
    if probe.returncode:
        pytest.skip(f"{ENV_VAR}={python} cannot import nuscenes: {probe.stderr.strip()[-300:]}")
    return python


def test_the_devkit_walks_every_file_a_converter_asks_for(tmp_path):
    python = _devkit_python()
    root = write_world(tmp_path / "world", scenes=2, seed=5, train_images=True)
    run = subprocess.run([python, str(WALK), str(root)], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    print(json.dumps(out, sort_keys=True), file=sys.stderr)  # the summary, for -s and CI logs
    manifest = json.loads((root / "drivedegrade_world.json").read_text())
    # the official split lists, filtered to the available scenes, are the world's own split
    assert out["available"] == out["scenes"] == manifest["splits"]["train"] + manifest["splits"]["val"]
    assert out["train"] == manifest["splits"]["train"] and out["val"] == manifest["splits"]["val"]
    assert out["samples"] == 2 * KEYFRAMES and out["samples_per_split"] == {"train": KEYFRAMES, "val": KEYFRAMES}
    assert out["missing_files"] == [] and out["pose_mismatch"] == 0 and out["boxes_mismatch"] == 0
    assert out["can_bus_scenes"] == 2
    translation, rotation = out["lidar_calibration"]
    assert translation == [0.943713, 0.0, 1.84023] and rotation[0] == pytest.approx(0.7077955119163518)
    assert ["vehicle.car", 17] in out["categories"]
    # visibility and point counts vary, and the devkit's own points_in_box agrees with num_lidar_pts
    assert out["annotations"] > 0 and len(out["visibility"]) >= 2 and out["zero_lidar_pts"] > 0
    assert out["lidar_points"] > 100 * out["samples"]
    assert abs(out["points_in_boxes"] - out["num_lidar_pts"]) <= 0.01 * out["num_lidar_pts"] + 5


MAP_SCRIPT = Path(__file__).with_name("devkit_map.py")


def _polyline_gap(a: list, b: list) -> float:
    """The largest distance from a point of polylines `a` (densified every 0.25 m) to the nearest segment of
    polylines `b` (0 when `a` is empty, inf when only `b` is)."""
    pts = []
    for line in a:
        xy = np.asarray(line, dtype=float).reshape(-1, 2)
        for p, q in zip(xy[:-1], xy[1:]):
            n = max(int(np.linalg.norm(q - p) / 0.25), 1)
            pts.append(p + np.linspace(0.0, 1.0, n + 1)[:, None] * (q - p))
    if not pts:
        return 0.0
    segs = [np.stack([xy[:-1], xy[1:]], 1) for xy in (np.asarray(ln, dtype=float).reshape(-1, 2) for ln in b)
            if len(xy) >= 2]
    if not segs:
        return float("inf")
    p, s = np.concatenate(pts), np.concatenate(segs)
    d = s[:, 1] - s[:, 0]
    t = np.clip(((p[:, None] - s[None, :, 0]) * d[None]).sum(-1) / np.maximum((d**2).sum(-1), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(p[:, None] - (s[None, :, 0] + t[..., None] * d[None]), axis=-1).min(1).max())


def _val_samples(tmp_path: Path) -> tuple[dict, dict]:
    """The default world's val scenes (same seed and index, so the same scenes): their map files under
    `tmp_path` and every keyframe as a query (pose, the logged next 3 s), with the parsed lane maps."""
    queries: dict[str, list[dict]] = {}
    lane_maps = {}
    train, val = split_names(DEFAULT_SCENES)
    for name in val:
        index = len(train) + val.index(name)
        scene = make_scene(0, index, name)
        location = export.location(scene, 0)
        data = export.map_expansion(scene, 0)
        export.dump(expansion_path(tmp_path, location), data)
        lane_maps[location] = parse_lane_map(json.loads(json.dumps(data)), location)
        steps = scene.key_steps
        queries[location] = [{"token": f"{location}/{k}", "pose": [float(scene.ego.xy[st, 0]),
                                                                 float(scene.ego.xy[st, 1]), float(scene.ego.yaw[st])],
                              "future": scene.ego.xy[steps[k + 1:k + 7]].tolist()} for k, st in enumerate(steps)]
    return queries, lane_maps


def test_the_devkit_reads_the_lane_map_and_agrees_with_the_vector_map(tmp_path):
    """On every keyframe of the default world's val scenes: the devkit's closest lane is the reader's and the one
    the expert drives (heading its way, centreline poses equal to the reader's), the logged 3 s future follows a
    centreline, and the project's VAD-style vectorised map has dividers and boundaries and matches the devkit's
    shapely geometry (dividers and crossings to 1 mm, boundaries to 10 cm on the 5 cm raster)."""
    python = _devkit_python()
    queries, lane_maps = _val_samples(tmp_path)
    (tmp_path / "queries.json").write_text(json.dumps(queries))
    run = subprocess.run([python, str(MAP_SCRIPT), str(tmp_path), str(tmp_path / "queries.json")],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    answers = json.loads(run.stdout.strip().splitlines()[-1])
    with_crossings, worst = 0, {"dividers": 0.0, "crossings": 0.0, "boundaries": 0.0}
    for location, samples in queries.items():
        lane_map = lane_maps[location]
        by_token = {lane.token: lane for lane in lane_map.lanes}
        for s in samples:
            dev, (x, y, yaw) = answers[s["token"]], s["pose"]
            ours = lane_map.closest_lane(x, y, 2.0)
            assert ours is not None and dev["closest_lane"] in by_token, s["token"]
            mine = by_token[dev["closest_lane"]]
            np.testing.assert_allclose(np.asarray(dev["closest_poses"]), mine.centreline, atol=1e-6)
            assert float(mine.distance([x, y])) == pytest.approx(float(ours.distance([x, y])), abs=1e-9)
            i = int(np.argmin(((mine.centreline[:, :2] - [x, y]) ** 2).sum(1)))
            assert float(mine.distance([x, y])) < 0.26 and abs(wrap_angle(mine.centreline[i, 2] - yaw)) < 0.1
            assert dev["on_point"]["drivable_area"] and (dev["on_point"]["lane"] or mine.connector)
            assert dev["future_gap"] < 0.3, s["token"]
            assert dev["in_radius"]["road_segment"] >= 1 and dev["in_radius"]["road_divider"] >= 1
            vm, want = extract(lane_map, (x, y, yaw)), dev["vector"]
            assert vm.dividers and vm.boundaries, s["token"]
            assert len(vm.ped_crossings) == want["crossing_polygons"]  # a ring's pieces joined at its start
            with_crossings += bool(vm.ped_crossings)
            for kind, got, ref, tol in (("dividers", vm.dividers, want["dividers"], 1e-3),
                                        ("crossings", vm.ped_crossings, want["crossings"], 1e-3),
                                        ("boundaries", vm.boundaries, want["boundaries"], 0.1)):
                got_lists = [g.tolist() for g in got]
                gap = max(_polyline_gap(got_lists, ref), _polyline_gap(ref, got_lists))
                assert gap < tol, (s["token"], kind, gap)
                worst[kind] = max(worst[kind], gap)
    samples_total = sum(map(len, queries.values()))
    print(json.dumps({"samples": samples_total, "with_crossings": with_crossings, "worst_gap_m": worst}),
          file=sys.stderr)  # for -s and CI logs
    assert samples_total == len(queries) * KEYFRAMES and with_crossings >= 10  # the val scenes' zebras come into view
