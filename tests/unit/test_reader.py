"""The reader on a nuScenes-format fixture written here by hand (real field names and types of the schema),
independent of the world's own writer; and on bad data."""

from __future__ import annotations

import json
import re
import shutil

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.data.frame import Command
from pytest_drivedegrade.data.nuscenes import NuScenesReader, coarse_category
from pytest_drivedegrade.errors import DataError

N_SAMPLES = 8
SPEED = 5.0  # m/s along global +y for scene-0103 (heading 90 deg); scene-0061 turns left


def _q(yaw):
    return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


def _write_fixture(root):
    """v1.0-mini with scene-0061 (mini_train: curving left) and scene-0103 (mini_val: straight north)."""
    v = root / "v1.0-mini"
    v.mkdir(parents=True)
    t = {k: [] for k in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor",
                         "sample_annotation", "instance", "category", "log", "attribute", "visibility", "map")}
    t["category"] = [{"token": "cat-car", "name": "vehicle.car", "description": "", "index": 1},
                     {"token": "cat-ped", "name": "human.pedestrian.adult", "description": "", "index": 2}]
    t["instance"] = [{"token": "inst-car", "category_token": "cat-car", "nbr_annotations": N_SAMPLES,
                      "first_annotation_token": "", "last_annotation_token": ""}]
    red = cv2.imencode(".jpg", np.full((90, 160, 3), (0, 0, 255), np.uint8))[1].tobytes()  # BGR red
    for cam in CAMERAS:
        t["sensor"].append({"token": f"sensor-{cam}", "channel": cam, "modality": "camera"})
        t["calibrated_sensor"].append({"token": f"cal-{cam}", "sensor_token": f"sensor-{cam}",
                                       "translation": [1.7, 0.0, 1.5], "rotation": [0.5, -0.5, 0.5, -0.5],
                                       "camera_intrinsic": [[126.6, 0.0, 80.0], [0.0, 126.6, 45.0], [0.0, 0.0, 1.0]]})
        (root / "samples" / cam).mkdir(parents=True)
    for si, name in enumerate(("scene-0061", "scene-0103")):
        t["log"].append({"token": f"log{si}", "logfile": "n008-2018", "vehicle": "n008",
                         "date_captured": "2018-08-01", "location": "singapore-onenorth"})
        toks = [f"s{si}-{k}" for k in range(N_SAMPLES)]
        t["scene"].append({"token": f"scene{si}", "log_token": f"log{si}", "nbr_samples": N_SAMPLES,
                           "first_sample_token": toks[0], "last_sample_token": toks[-1], "name": name,
                           "description": "fixture"})
        for k, tok in enumerate(toks):
            ts = 1_533_000_000_000_000 + si * 10**8 + k * 500_000
            if si == 0:  # left turn: heading grows by 0.25 rad per keyframe, on a circle of radius 10 m
                yaw = 0.25 * k
                pos = [10 * np.sin(yaw), 10 * (1 - np.cos(yaw)), 0.0]
            else:
                yaw, pos = np.pi / 2, [100.0, SPEED * 0.5 * k, 0.0]
            t["sample"].append({"token": tok, "timestamp": ts, "prev": toks[k - 1] if k else "",
                                "next": toks[k + 1] if k + 1 < N_SAMPLES else "", "scene_token": f"scene{si}"})
            t["ego_pose"].append({"token": f"pose-{tok}", "timestamp": ts, "rotation": _q(yaw),
                                  "translation": [float(p) for p in pos]})
            for cam in CAMERAS:
                fn = f"samples/{cam}/n008__{cam}__{ts}.jpg"
                (root / fn).write_bytes(red)
                t["sample_data"].append({"token": f"sd-{tok}-{cam}", "sample_token": tok,
                                         "ego_pose_token": f"pose-{tok}", "calibrated_sensor_token": f"cal-{cam}",
                                         "timestamp": ts, "fileformat": "jpg", "is_key_frame": True,
                                         "height": 90, "width": 160, "filename": fn, "prev": "", "next": ""})
            # a car 10 m ahead of the ego pose of this sample, same heading; a pedestrian in scene-0103 only
            ahead = np.array(pos[:2]) + 10 * np.array([np.cos(yaw), np.sin(yaw)])
            t["sample_annotation"].append({
                "token": f"ann-{tok}", "sample_token": tok, "instance_token": "inst-car", "visibility_token": "4",
                "attribute_tokens": [], "translation": [float(ahead[0]), float(ahead[1]), 0.8],
                "size": [1.9, 4.5, 1.6], "rotation": _q(yaw), "prev": "", "next": "", "num_lidar_pts": 5,
                "num_radar_pts": 0})
    for name, records in t.items():
        (v / f"{name}.json").write_text(json.dumps(records))
    return root


@pytest.fixture()
def fixture_root(tmp_path):
    return _write_fixture(tmp_path / "nuscenes")


def test_splits_and_frame_counts(fixture_root):
    val = NuScenesReader(fixture_root, split="mini_val")
    assert val.version == "v1.0-mini"
    frames = list(val.frames())
    assert [f.scene_name for f in frames] == ["scene-0103"] * N_SAMPLES
    assert len(val.scorable_frames()) == N_SAMPLES - 6
    assert val.skipped["fewer than six future keyframes (not scored)"] == 6
    assert len(list(NuScenesReader(fixture_root, split="all").frames())) == 2 * N_SAMPLES
    train = NuScenesReader(fixture_root, split="mini_train")
    assert {f.scene_name for f in train.frames()} == {"scene-0061"}
    # the mini scenes belong to the official trainval splits too
    assert {f.scene_name for f in NuScenesReader(fixture_root, split="val").frames()} == {"scene-0103"}
    assert {f.scene_name for f in NuScenesReader(fixture_root, split="train").frames()} == {"scene-0061"}


def test_straight_scene_future_ego_command_and_agents(fixture_root):
    frame = NuScenesReader(fixture_root, split="mini_val").scorable_frames()[1]
    expected = np.stack([SPEED * 0.5 * np.arange(1, 7), np.zeros(6)], 1)
    np.testing.assert_allclose(frame.gt_future, expected, atol=1e-9)
    assert frame.command == Command.STRAIGHT
    assert frame.ego.velocity == pytest.approx((SPEED, 0.0), abs=1e-6)
    assert frame.ego.acceleration == pytest.approx((0.0, 0.0), abs=1e-6)
    assert frame.ego.yaw_rate == pytest.approx(0.0, abs=1e-9)
    # past: the last four keyframes, oldest first; at keyframe 1 the missing ones are extrapolated
    np.testing.assert_allclose(frame.ego.past_xy, [[-10.0, 0], [-7.5, 0], [-5.0, 0], [-2.5, 0]], atol=1e-9)
    assert len(frame.agents) == 6
    for step, boxes in enumerate(frame.agents, start=1):
        assert boxes.category == ("vehicle",)
        np.testing.assert_allclose(boxes.center[0], [SPEED * 0.5 * step + 10.0, 0.0], atol=1e-9)
        np.testing.assert_allclose(boxes.size[0], [4.5, 1.9])
        assert boxes.yaw[0] == pytest.approx(0.0, abs=1e-9)
    cam = frame.cameras["CAM_FRONT"]
    assert cam.width == 160 and cam.intrinsic[0, 0] == pytest.approx(126.6)
    img = NuScenesReader.load_image(cam)
    assert img.shape == (90, 160, 3) and img.dtype == np.uint8
    assert img[..., 0].mean() > 200 and img[..., 2].mean() < 50  # RGB order: the red file reads red


def test_turning_scene_gives_left_command_and_yaw_rate(fixture_root):
    frame = NuScenesReader(fixture_root, split="mini_train").scorable_frames()[1]
    assert frame.command == Command.LEFT
    assert frame.gt_future[-1, 1] > 2.0
    assert frame.ego.yaw_rate == pytest.approx(0.25 / 0.5, rel=1e-6)
    chord = 2 * 10 * np.sin(0.125)
    assert np.hypot(*frame.ego.velocity) == pytest.approx(chord / 0.5, rel=1e-6)


def test_an_ego_only_read_is_the_full_read_without_boxes_and_trains_the_same_floor(fixture_root):
    """The floor reads its train split with `agents=False`: every frame is the full read's with empty boxes, and
    the floor's training arrays are the same bytes (so its weights are); the fixture's frames do carry boxes."""
    import dataclasses
    import pickle

    from pytest_drivedegrade.data.frame import AgentBoxes
    from pytest_drivedegrade.floor import frames_to_arrays

    reader = NuScenesReader(fixture_root, split="all")
    full, bare = reader.scorable_frames(), reader.scorable_frames(agents=False)
    assert any(len(boxes) for f in full for boxes in f.agents)  # the full read has boxes to leave out
    assert all(len(boxes) == 0 for f in bare for boxes in f.agents)
    assert [pickle.dumps(dataclasses.replace(f, agents=tuple(AgentBoxes.empty() for _ in f.agents))) for f in full] \
        == [pickle.dumps(f) for f in bare]
    for a, b in zip(frames_to_arrays(full), frames_to_arrays(bare)):
        assert a.tobytes() == b.tobytes()
    assert len(list(reader.frames(agents=False))) == len(list(reader.frames()))


def test_limit_gives_one_contiguous_run_per_scene_stable(fixture_root):
    reader = NuScenesReader(fixture_root, split="all")
    full = reader.scorable_frames()  # two scenes of two scorable frames each
    sub = reader.scorable_frames(limit=2)
    assert [f.token for f in sub] == [full[0].token, full[2].token]
    assert [f.token for f in NuScenesReader(fixture_root, split="all").scorable_frames(limit=2)] == \
        [f.token for f in sub]
    assert reader.fingerprint() == NuScenesReader(fixture_root, split="all").fingerprint()
    assert reader.fingerprint() != NuScenesReader(fixture_root, split="mini_val").fingerprint()


def test_with_split_reads_another_split_without_rereading_the_tables(fixture_root):
    """The floor's train split comes from the val reader's tables: the same frames, counts and fingerprint as
    a reader opened on that split, and the val reader is left as it was."""
    val = NuScenesReader(fixture_root, split="mini_val")
    before = [f.token for f in val.frames()]
    train = val.with_split("mini_train")
    fresh = NuScenesReader(fixture_root, split="mini_train")
    assert [f.token for f in train.frames()] == [f.token for f in fresh.frames()]
    assert train.skipped == fresh.skipped and train.fingerprint() == fresh.fingerprint()
    assert train.samples is val.samples  # shared, not re-read
    assert [f.token for f in val.frames()] == before and val.split == "mini_val"
    with pytest.raises(DataError, match="unknown split 'test-ish'"):
        val.with_split("test-ish")


@pytest.mark.parametrize("name,category", [("vehicle.car", "vehicle"), ("vehicle.bus.rigid", "vehicle"),
                                           ("human.pedestrian.child", "pedestrian"),
                                           ("vehicle.bicycle", "cyclist"), ("vehicle.motorcycle", "cyclist"),
                                           ("movable_object.barrier", "other")])
def test_coarse_categories(name, category):
    assert coarse_category(name) == category


# --- bad data -------------------------------------------------------------------------------------------

def test_missing_table_names_the_file(fixture_root):
    (fixture_root / "v1.0-mini" / "ego_pose.json").unlink()
    with pytest.raises(DataError, match=r"ego_pose\.json"):
        NuScenesReader(fixture_root, split="all")


def test_missing_root_and_ambiguous_version(fixture_root, tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        NuScenesReader(tmp_path / "nope")
    shutil.copytree(fixture_root / "v1.0-mini", fixture_root / "v1.0-trainval")
    with pytest.raises(DataError, match="several version folders"):
        NuScenesReader(fixture_root)
    assert NuScenesReader(fixture_root, version="v1.0-mini", split="all").version == "v1.0-mini"
    with pytest.raises(DataError, match="unknown split"):
        NuScenesReader(fixture_root, version="v1.0-mini", split="test-ish")


def test_missing_and_truncated_images_name_file_and_frame(fixture_root):
    frame = NuScenesReader(fixture_root, split="mini_val").scorable_frames()[0]
    cam = frame.cameras["CAM_BACK"]
    data = open(cam.path, "rb").read()
    open(cam.path, "wb").write(data[: len(data) // 2])
    with pytest.raises(DataError, match="truncated JPEG") as err:
        NuScenesReader.load_image(cam)
    assert cam.path in str(err.value) and frame.token in str(err.value)
    (fixture_root / frame.cameras["CAM_FRONT"].path).unlink()
    with pytest.raises(DataError, match="missing image"):
        NuScenesReader.load_image(frame.cameras["CAM_FRONT"])


def _edit(root, table, fn):
    path = root / "v1.0-mini" / f"{table}.json"
    records = json.loads(path.read_text())
    path.write_text(json.dumps(fn(records)))


def test_dangling_ego_pose_skips_scene_with_count(fixture_root):
    _edit(fixture_root, "ego_pose", lambda r: [x for x in r if x["token"] != "pose-s1-3"])
    reader = NuScenesReader(fixture_root, split="all")
    frames = list(reader.frames())
    assert {f.scene_name for f in frames} == {"scene-0061"}
    assert reader.skipped["sample points at a missing record"] == N_SAMPLES
    assert any("pose-s1-3" in p for p in reader.problems)
    with pytest.raises(DataError, match="pose-s1-3"):
        list(NuScenesReader(fixture_root, split="all", strict=True).frames())


def test_missing_camera_record_skips_the_frame(fixture_root):
    _edit(fixture_root, "sample_data", lambda r: [x for x in r if x["token"] != "sd-s1-2-CAM_BACK_LEFT"])
    reader = NuScenesReader(fixture_root, split="mini_val")
    tokens = [f.token for f in reader.frames()]
    assert "s1-2" not in tokens and len(tokens) == N_SAMPLES - 1
    assert reader.skipped["sample points at a missing record"] == 1
    assert any("s1-2" in p and "CAM_BACK_LEFT" in p for p in reader.problems)


def test_scene_without_keyframes_is_counted(fixture_root):
    def empty(records):
        records[1]["first_sample_token"], records[1]["nbr_samples"] = "", 0
        return records
    _edit(fixture_root, "scene", empty)
    reader = NuScenesReader(fixture_root, split="all")
    assert {f.scene_name for f in reader.frames()} == {"scene-0061"}
    assert reader.skipped["scene without keyframes"] == 1
    assert any("scene-0103" in p for p in reader.problems)


def test_can_bus_expansion_overrides_finite_differences(fixture_root):
    can = fixture_root / "can_bus"
    can.mkdir()
    recs = [{"utime": 1_533_000_100_000_000 + i * 20_000, "vel": [7.0, 0.1, 0.0], "accel": [0.5, 0.2, 9.8],
             "rotation_rate": [0.0, 0.0, 0.05], "pos": [0, 0, 0], "orientation": [1, 0, 0, 0]} for i in range(300)]
    (can / "scene-0103_pose.json").write_text(json.dumps(recs))
    frame = NuScenesReader(fixture_root, split="mini_val").scorable_frames()[0]
    assert frame.ego.velocity == (7.0, 0.1)
    assert frame.ego.acceleration == (0.5, 0.2)
    assert frame.ego.yaw_rate == 0.05


def test_contiguous_subset_shares_and_centres_runs_per_scene():
    """Shares by largest remainder (10, 5, 3 frames; 6 wanted: 3.33, 1.67, 1.0 -> 3, 2, 1), each run centred."""
    from types import SimpleNamespace

    from pytest_drivedegrade.data.nuscenes import contiguous_subset

    frames = [SimpleNamespace(scene_token=s, token=f"{s}{i}") for s, n in (("a", 10), ("b", 5), ("c", 3))
              for i in range(n)]
    got = [f.token for f in contiguous_subset(frames, 6)]  # type: ignore[arg-type]
    assert got == ["a3", "a4", "a5", "b1", "b2", "c1"]
    assert [f.token for f in contiguous_subset(frames, 2)] == ["a4", "b2"]  # type: ignore[arg-type]



@pytest.mark.parametrize(("content", "problem"), [
    (b"", r"empty image file .*\(frame s1-0\) \(0 bytes\)"),
    (b"\x00garbage, not an image", r"undecodable image .*\(frame s1-0\)"),
    (cv2.imencode(".jpg", np.zeros((1, 1, 3), np.uint8))[1].tobytes(),
     r"wrong-size image .*\(frame s1-0\): 1 x 1 pixels, but sample_data and the calibration say 160 x 90"),
    (cv2.imencode(".png", np.zeros((90, 161, 3), np.uint8))[1].tobytes(),
     r"wrong-size image .*\(frame s1-0\): 161 x 90 pixels, but .* say 160 x 90"),
])
def test_empty_undecodable_and_wrong_size_images_are_data_errors_naming_file_and_frame(fixture_root, content,
                                                                                         problem):
    """Trust case 10: a 0-byte JPEG (an OpenCV assertion before), a file that is no image, a 1 x 1 image and
    one a pixel too wide are DataErrors naming the file and the frame token, never decoded silently."""
    frame = NuScenesReader(fixture_root, split="mini_val").scorable_frames()[0]
    cam = frame.cameras["CAM_FRONT"]
    open(cam.path, "wb").write(content)
    with pytest.raises(DataError, match=problem) as err:
        NuScenesReader.load_image(cam)
    assert cam.path in str(err.value)


@pytest.mark.parametrize("name", ["../../../../etc/passwd", "/etc/passwd", "samples/../../outside.jpg", ".."])
def test_file_names_that_leave_the_data_root_are_refused_naming_the_row(fixture_root, name):
    """Trust case 10: a sample_data file name that leaves the data root (`../../../../etc/passwd` was read) is a
    DataError at start-up naming the table and the record's token; one that stays inside after `..` is fine."""
    _edit(fixture_root, "sample_data", lambda rows: [dict(r, filename=name) if r["token"] == "sd-s1-0-CAM_BACK"
                                                     else r for r in rows])
    with pytest.raises(DataError, match=r"sample_data.json: the record with token 'sd-s1-0-CAM_BACK': filename "
                                         f"'{re.escape(name)}' leaves the data root"):
        NuScenesReader(fixture_root, split="mini_val").scorable_frames()


def test_a_name_that_stays_inside_the_root_is_accepted(fixture_root):
    def detour(rows):
        for r in rows:
            if r["token"] == "sd-s1-0-CAM_BACK":
                r["filename"] = "samples/CAM_FRONT/../" + r["filename"].removeprefix("samples/")
        return rows

    _edit(fixture_root, "sample_data", detour)
    frame = NuScenesReader(fixture_root, split="mini_val").scorable_frames()[0]
    assert NuScenesReader.load_image(frame.cameras["CAM_BACK"]).shape == (90, 160, 3)


@pytest.mark.parametrize(("table", "edit", "problem"), [
    ("sample", lambda rows: {"records": rows}, r"sample.json is a JSON dict, not a list of records"),
    ("sample_data", lambda rows: [*rows[:3], "sd-x", *rows[3:]], r"sample_data.json: record 3 is a JSON str, "
                                                                   "not an object"),
    ("sample_data", lambda rows: [{k: v for k, v in r.items() if k != "filename" or r["token"] != "sd-s0-1-CAM_BACK"}
                                  for r in rows],
     r"sample_data.json: the record with token 'sd-s0-1-CAM_BACK' lacks the field 'filename'"),
    ("sample_data", lambda rows: [dict(r, width="160") if r["token"] == "sd-s1-4-CAM_FRONT" else r for r in rows],
     r"sample_data.json: the record with token 'sd-s1-4-CAM_FRONT' has width='160' \(str\), expected int"),
    ("ego_pose", lambda rows: [dict(r, timestamp=True) if r["token"] == "pose-s1-2" else r for r in rows],
     r"ego_pose.json: the record with token 'pose-s1-2' has timestamp=True \(bool\), expected int"),
    ("scene", lambda rows: [dict(rows[0], token=7), *rows[1:]],
     r"scene.json: record 0 has token=7 \(int\), expected str"),
])
def test_malformed_table_rows_are_named_by_table_and_token_at_start_up(fixture_root, table, edit, problem):
    """Trust case 10: a table that is not a list of objects, a row missing a required key or with a wrong type
    is a DataError naming the table file and the row's token when the reader opens, not a KeyError later."""
    _edit(fixture_root, table, edit)
    with pytest.raises(DataError, match=problem):
        NuScenesReader(fixture_root, split="all")


def _confined_before(root, name):
    """`tables.confined`'s test as written before issue 23's fourth pass (three paths parsed from the name)."""
    import os
    from pathlib import Path

    normal = os.path.normpath(name)
    if not name.strip() or Path(name).is_absolute() or Path(name).drive or Path(normal).parts[:1] == ("..",):
        return None
    return root / normal


_PARTS = ["..", ".", "", "samples", "CAM_FRONT", "a.jpg", "/", "//", " ", "~", "C:", "..a", "a..", "\\..\\"]


@settings(max_examples=400, deadline=None)
@given(st.lists(st.sampled_from(_PARTS), min_size=1, max_size=7).map("/".join) | st.text(min_size=1, max_size=12))
def test_confinement_refuses_exactly_what_it_refused_before_its_rewrite(name):
    """Attack on the rewritten `confined` (one path parsed instead of three): for hostile names (``..`` chains,
    absolute and doubled roots, drives, blanks) it refuses exactly the names the earlier form refused and
    returns the same path for the others, and whatever it returns stays under the root."""
    import os
    from pathlib import Path

    from pytest_drivedegrade.data.tables import confined

    root = Path("/data/root")
    expected = _confined_before(root, name) if name.isprintable() and "\x00" not in name else None
    try:
        got = confined(root, name, "sample_data.json: the record with token 't'")
    except DataError:
        got = None
    assert got == expected
    if got is not None:
        assert os.path.normpath(got).startswith(str(root) + os.sep) or os.path.normpath(got) == str(root)
