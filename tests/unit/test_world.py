"""The generated world read back by the reader: futures equal the expert's log, commands follow the rule,
annotations are complete, generation is deterministic, images look like a road scene, the cache is atomic."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.data import geometry as geo
from pytest_drivedegrade.data.frame import command_from_future
from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.data.world import (
    WORLD_VERSION,
    agents,
    build,
    ensure_default_world,
    expert,
    export,
    tasks,
    write_world,
)
from pytest_drivedegrade.data.world.roads import Path as LanePath
from pytest_drivedegrade.data.world.scene import KEYFRAMES, make_scene


@pytest.fixture(scope="session")
def world(tmp_path_factory) -> Path:
    """Two scenes: one train (tables only), one val (rendered), on two worker processes."""
    return write_world(tmp_path_factory.mktemp("world") / "w", scenes=2, seed=3, workers=2)


def _tree_hash(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode() + p.read_bytes())
    return h.hexdigest()


def test_layout_is_nuscenes(world):
    tables = {p.stem for p in (world / WORLD_VERSION).glob("*.json")}
    assert tables >= {"scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor",
                      "sample_annotation", "instance", "category", "log", "visibility", "attribute", "map"}
    for cam in CAMERAS:
        assert len(list((world / "samples" / cam).glob("*.jpg"))) == KEYFRAMES  # the val scene only
    manifest = json.loads((world / build.MANIFEST).read_text())
    assert manifest["splits"] == {"train": ["scene-0001"], "val": ["scene-0003"]}  # the official lists agree
    assert len(manifest["fingerprint"]) == 32
    assert WORLD_VERSION == "v1.0-trainval"
    clouds = sorted((world / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    assert len(clouds) == 2 * KEYFRAMES  # every keyframe of both scenes, train included
    points = np.fromfile(clouds[0], np.float32).reshape(-1, 5)
    assert len(points) > 100 and set(np.unique(points[:, 4])) <= set(range(32))
    categories = json.loads((world / WORLD_VERSION / "category.json").read_text())
    assert {c["name"]: c["index"] for c in categories}["vehicle.car"] == 17


def test_futures_equal_the_expert_log_and_commands_follow_the_rule(world):
    reader = NuScenesReader(world, split="val")
    frames = list(reader.frames())
    assert len(frames) == KEYFRAMES and sum(f.scorable for f in frames) == KEYFRAMES - 6
    scene = make_scene(3, 1, "scene-0003")
    keys = scene.key_steps
    for k, frame in enumerate(frames):
        origin, yaw = scene.ego.xy[keys[k]], scene.ego.yaw[keys[k]]
        for step in range(6):
            if k + step + 1 < KEYFRAMES:
                expected = geo.se2_to_ego(scene.ego.xy[keys[k + step + 1]], origin, yaw)[0]
                np.testing.assert_allclose(frame.gt_future[step], expected, atol=1e-6)
        if frame.scorable:
            assert frame.command == command_from_future(frame.gt_future)
        assert frame.ego.velocity[0] == pytest.approx(scene.ego.speed[keys[k]], abs=1e-6)


def test_every_future_annotation_is_present(world):
    reader = NuScenesReader(world, split="val")
    per_sample: dict[str, int] = {}
    for rec in json.loads((world / WORLD_VERSION / "sample_annotation.json").read_text()):
        per_sample[rec["sample_token"]] = per_sample.get(rec["sample_token"], 0) + 1
    samples = {r["token"]: r for r in json.loads((world / WORLD_VERSION / "sample.json").read_text())}
    for frame in reader.scorable_frames():
        token = frame.token
        for boxes in frame.agents:
            token = samples[token]["next"]
            assert len(boxes) == per_sample.get(token, 0)
            assert set(boxes.category) <= {"vehicle", "pedestrian", "cyclist", "other"}


def test_images_look_like_a_road_scene(world):
    frame = NuScenesReader(world, split="val").scorable_frames(limit=1)[0]
    for cam in CAMERAS:
        img = NuScenesReader.load_image(frame.cameras[cam])
        assert img.shape == (450, 800, 3)
        assert img.std() > 15  # texture, not a flat fill
    front = NuScenesReader.load_image(frame.cameras["CAM_FRONT"]).astype(float)
    road = front[400:, 350:450]  # straight ahead, close: asphalt, nearly grey
    assert np.abs(road - road.mean(-1, keepdims=True)).mean() < 25
    assert front[:40].mean() > front[400:].mean()  # sky above is brighter than the road below


def test_generation_is_deterministic_and_the_same_on_any_number_of_workers(world, tmp_path):
    a = write_world(tmp_path / "a", scenes=3, seed=11, val_images=False, workers=1)
    b = write_world(tmp_path / "b", scenes=3, seed=11, val_images=False, workers=3)
    assert _tree_hash(a) == _tree_hash(b)
    c = write_world(tmp_path / "c", scenes=3, seed=12, val_images=False, workers=1)
    assert _tree_hash(a) != _tree_hash(c)
    again = write_world(tmp_path / "again", scenes=2, seed=3, workers=1)  # serial, in this process
    assert _tree_hash(again) == _tree_hash(world)  # images included: rendered on two workers there


def test_tables_joined_from_fragments_are_the_dumped_list(tmp_path):
    records = [{"b": 1, "a": [1.5, "x"]}, {"token": "t"}, {}]
    whole = export.dump(tmp_path / "whole.json", records)
    parts = [export.items_json(records[:1]), export.items_json([]), export.items_json(records[1:])]
    assert export.dump_items(tmp_path / "parts.json", parts) == whole
    assert export.dump_items(tmp_path / "empty.json", [export.items_json([])]) == export.dump(tmp_path / "e", [])


def test_tasks_come_back_in_task_order_and_rendering_ones_cost_more(monkeypatch):
    slow = tasks.SceneTask("/x", 0, 0, "a", False, render=True)
    fast = tasks.SceneTask("/x", 0, 1, "b", False)
    assert slow.cost > fast.cost
    assert tasks.default_workers(1) == 1 and 1 <= tasks.default_workers(100) <= tasks.MAX_WORKERS
    seen: list[str] = []
    monkeypatch.setattr(tasks, "run_task", lambda t: t.name)  # type: ignore[arg-type]
    assert tasks.run_tasks([fast, slow], workers=1, done=lambda t: seen.append(t.name)) == ["b", "a"]
    assert seen == ["b", "a"]


def test_event_fraction_over_many_scenes():
    """At least 30 % of keyframes leave what the ego status predicts, for vehicles and pedestrians alike."""
    scenes = [make_scene(0, i, "s") for i in range(12)]
    kinds = [e for s in scenes for e in s.events[: KEYFRAMES - 6]]
    fraction = sum(1 for k in kinds if k) / len(kinds)
    assert fraction >= 0.30
    assert {"brake", "vru", "bend"} <= set(kinds)
    for s in scenes:  # physically plausible: no contact, braking within B_MAX, speeds of urban traffic
        assert s.ego.min_gap >= 0.5
        assert s.ego.accel.min() >= -expert.B_MAX - 0.1 and 0.0 <= s.ego.speed.min() <= s.ego.speed.max() <= 15.0


def _straight_lane() -> LanePath:
    return LanePath.from_points(np.stack([np.linspace(0.0, 600.0, 1201), np.zeros(1201)], 1))


def test_expert_keeps_cruising_until_a_standing_truck_needs_firm_braking_then_stops_behind_it():
    lane, v = _straight_lane(), 12.0
    truck = agents.along(lane, 200.0, np.zeros(agents.SIM_STEPS), "truck", np.random.default_rng(0), "stopped")
    ego = expert.drive(lane, [truck], v, v, 70.0)
    onset = int(np.argmax(ego.accel < -0.5))
    gap = 200.0 - truck.size[0] / 2 - expert.EGO_LENGTH / 2 - ego.s
    assert np.all(ego.speed[: onset - 1] > v - 0.05)  # no early, IDM-style anticipation
    need = v**2 / (2 * (gap[onset - 2] - expert.S0))
    assert need == pytest.approx(expert.B_TRIGGER, abs=0.3)  # it waits until stopping needs B_TRIGGER
    assert ego.accel[onset + 2] <= -expert.B_TRIGGER + 0.1  # then brakes firmly
    assert ego.speed[-1] < 0.05 and expert.S0 - 0.5 < gap[-1] < expert.S0 + 1.0
    assert ego.react[onset + 2] == expert.REACT_VEHICLE


def test_expert_sees_a_lead_vehicle_brake_one_reaction_time_late():
    lane, v = _straight_lane(), 10.0
    speed = agents.speed_profile(v, [(5.0, -4.0, 0.0)])
    lead = agents.along(lane, 70.0 + 35.0, speed, "car", np.random.default_rng(1), "lead")
    ego = expert.drive(lane, [lead], v, v, 70.0)
    onset = int(np.argmax(ego.accel < -0.5))
    assert onset * agents.DT >= 5.0 + expert.REACTION * agents.DT - 0.15  # the brake lights come first
    assert ego.min_gap > 0.5


def test_events_measure_departures_from_the_ego_status_extrapolation():
    lane = _straight_lane()
    steady = expert.drive(lane, [], 10.0, 10.0, 70.0)  # cruising: exactly what the ego status predicts
    assert expert.keyframe_events(lane, steady, 30) == [""] * 30
    truck = agents.along(lane, 200.0, np.zeros(agents.SIM_STEPS), "truck", np.random.default_rng(0), "stopped")
    stop = expert.drive(lane, [truck], 10.0, 10.0, 70.0)
    assert "brake" in expert.keyframe_events(lane, stop, 30)


def test_ensure_default_world_builds_once_atomically(tmp_path, monkeypatch):
    calls = []

    def fake_write(out, *, train_images=False, progress=None, **_):
        calls.append(Path(out).name)
        assert not (tmp_path / f"world-{build.GENERATOR_VERSION}-seed0").exists()  # rendered aside first
        out.mkdir(parents=True)
        (out / build.MANIFEST).write_text(json.dumps({"train_images": train_images}))
        return out

    monkeypatch.setattr(build, "write_world", fake_write)
    first = ensure_default_world(tmp_path)
    second = ensure_default_world(tmp_path)
    assert first == second and (first / build.MANIFEST).is_file()
    assert len(calls) == 1 and calls[0].startswith(".world-tmp-")
    assert not list(tmp_path.glob(".world-tmp-*"))
    added = []
    monkeypatch.setattr(build, "add_train_images", lambda root, say: added.append(root) or (
        root / build.MANIFEST).write_text(json.dumps({"train_images": True})))
    ensure_default_world(tmp_path, train_images=True)
    ensure_default_world(tmp_path, train_images=True)
    assert added == [first]


def test_a_process_still_importing_its_script_gets_a_built_world_and_stops_only_before_the_lock(tmp_path,
                                                                                                   monkeypatch):
    """`tasks.stop_starting_worker` runs only where the world is missing (the lock its parent holds would never
    come): a spawned process of the user's own that reads a built world is not stopped."""
    target = build.default_world_dir(tmp_path)
    target.mkdir(parents=True)
    (target / build.MANIFEST).write_text(json.dumps({"train_images": False}))
    monkeypatch.setattr(tasks, "starting_worker", lambda: True)
    monkeypatch.setattr(tasks.os, "_exit", lambda code: (_ for _ in ()).throw(SystemExit(code)))
    assert ensure_default_world(tmp_path) == target
    with pytest.raises(SystemExit):
        ensure_default_world(tmp_path / "empty")


UNGUARDED = """
import sys, time
from pytest_drivedegrade.data.world import build, tasks

def quick(task):  # this process's share of the build: quick, so the test waits only for the workers' start
    time.sleep(0.2)
    return None

tasks._here = quick
build.ensure_default_world(sys.argv[1])  # at the top level, no main guard: the spawned workers re-run it
print("BUILT")
"""


def test_a_script_without_a_main_guard_gets_the_reason_not_a_hang(tmp_path):
    """The world's spawned build workers import the main script: one that builds the world (or calls pytest.main)
    at its top level re-ran the build in each worker, which waited for ever on the lock its parent held. Now each
    such worker stops saying why, and the parent's build fails naming the guard (it hung before the fix)."""
    import subprocess
    import sys

    script = tmp_path / "unguarded.py"
    script.write_text(UNGUARDED)
    proc = subprocess.run([sys.executable, str(script), str(tmp_path / "cache")], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])})
    assert proc.returncode != 0 and "BUILT" not in proc.stdout
    assert "this build worker stopped" in proc.stderr  # each worker's own line
    assert "DriveDegradeError: a process building the embedded world stopped" in proc.stderr
    assert 'if __name__ == "__main__":' in proc.stderr
    assert not (tmp_path / "cache" / f"world-{build.GENERATOR_VERSION}-seed0").exists()  # nothing half-built kept


def test_cli_world_writes_a_world(tmp_path, capsys, monkeypatch):
    import functools

    from pytest_drivedegrade.cli import main

    monkeypatch.setattr(build, "write_world", functools.partial(write_world, val_images=False))  # fast

    out = tmp_path / "cli"
    assert main(["world", "--out", str(out), "--scenes", "2", "--seed", "3"]) == 0
    manifest = json.loads((out / build.MANIFEST).read_text())
    assert (manifest["scenes"], manifest["seed"], manifest["train_images"]) == (2, 3, False)
    # named after the official split lists: the first train scene and the first val scene of nuScenes
    assert manifest["splits"] == {"train": ["scene-0001"], "val": ["scene-0003"]}
    counts = {p.stem: len(json.loads(p.read_text())) for p in (out / WORLD_VERSION).glob("*.json")}
    assert counts["scene"] == 2 and counts["log"] == 2
    assert counts["sample"] == counts["ego_pose"] == 2 * KEYFRAMES  # one keyframe = one sample = one pose
    # six cameras and LIDAR_TOP at every keyframe
    assert counts["sample_data"] == 2 * KEYFRAMES * (len(CAMERAS) + 1) and counts["sensor"] == len(CAMERAS) + 1
    assert counts["sample_annotation"] > 0 and counts["instance"] > 0
    assert sorted(p.name for p in (out / "can_bus").iterdir()) == ["scene-0001_pose.json", "scene-0003_pose.json"]
    assert not list(out.rglob("*.jpg"))  # val_images=False: tables only, no frames written
    err = capsys.readouterr().err
    assert f"wrote {out} (2 scenes, fingerprint {manifest['fingerprint']})" in err
    assert "drivedegrade world: 2 scenes in " in err  # one closing progress line, not a line per scene
    assert "scene-0001" not in err and err.count("\n") <= 3  # not a terminal: milestones only
