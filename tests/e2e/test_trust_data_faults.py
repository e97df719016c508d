"""Issue 37, "Data faults outside the images": NaN/inf in the CAN bus or the cameras' calibration and an unreadable
LiDAR sweep are the data set's faults, named with the frame's token and counted as data errors (not the
planner's contract failures); a NaN ego pose refuses the run naming the frame, before any cell runs, where it
failed every cell with a traceback."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import by_cell, no_traceback, read_csv  # noqa: E402

pytest_plugins = ["plugin_support"]

#: Reads the CAN bus, the pose, the calibration and the LiDAR sweep, and passes any NaN on into its plan (as a
#: real planner's network would).
CONTEXT_PLANNER = '''
import numpy as np
import pytest


class Ctx:
    cameras = ("CAM_FRONT",)
    name = "ctx"

    def predict(self, images, ego, cmd, context):
        plan = np.zeros((6, 2))
        plan[:, 0] = 2.0 * np.arange(1, 7)
        taint = 0.0 * (context.can_bus.sum() + context.calibration["CAM_FRONT"].intrinsic.sum())
        points = context.lidar_points()
        plan[:, 1] = float(images["CAM_FRONT"][::16, ::16].mean()) / 255.0 + taint
        plan[:, 1] += 0.0 if points is None else 0.0 * float(points[:, :3].sum())
        return plan


@pytest.fixture(scope="session")
def planner():
    return Ctx()
'''


def broken_world(small_world: Path, tmp_path: Path, how: str) -> tuple[Path, str]:
    """A copy of the small world with one scored frame's data broken `how`; (root, that frame's token)."""
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    root = Path(shutil.copytree(small_world, tmp_path / "broken", copy_function=shutil.copy2))
    frame = RunContext.open(RunSettings(data=root, frames=4, timeout=0.0)).frames[1]
    tables = next(root.glob("v1.0-*"))
    if how == "can":
        path = root / "can_bus" / f"{frame.scene_name}_pose.json"
        rows = json.loads(path.read_text())
        for row in rows:
            row["vel"][0] = float("inf")
        path.write_text(json.dumps(rows))
    elif how == "lidar":
        Path(frame.lidar_file).write_bytes(b"\0\0\0")
    elif how == "intrinsic":
        path = tables / "calibrated_sensor.json"
        rows = json.loads(path.read_text())
        cam = next(r for r in rows if r.get("camera_intrinsic"))
        cam["camera_intrinsic"][0][0] = float("nan")
        path.write_text(json.dumps(rows))
    else:  # the ego pose of the frame's LIDAR_TOP / camera sample_data
        data = json.loads((tables / "sample_data.json").read_text())
        poses = {r["ego_pose_token"] for r in data if r["sample_token"] == frame.token}
        path = tables / "ego_pose.json"
        rows = json.loads(path.read_text())
        for row in rows:
            if row["token"] in poses:
                row["translation"][0] = float("nan")
        path.write_text(json.dumps(rows))
    return root, frame.token


@pytest.mark.parametrize("how", ["can", "lidar", "intrinsic"])
def test_a_non_finite_input_or_unreadable_sweep_is_a_data_fault_named_with_the_frame(dd, small_world, tmp_path,
                                                                                      how):
    root, token = broken_world(small_world, tmp_path, how)
    dd.pytester.makepyfile(ctx=CONTEXT_PLANNER)
    result = dd.run(planner="ctx.py", families="jpeg", severities="1", data=root)
    no_traceback(result)
    text = result.stdout.str()
    rows = by_cell(read_csv(dd.folder("ctx") / "cells.csv"))
    assert "frames failed the planner contract" not in text, text
    assert all(row["conformance_errors"] == "0" for row in rows.values()), rows
    assert int(rows["clean"]["data_errors"]) >= 1, rows["clean"]
    expect = {"can": "CAN bus vel (can_bus/", "lidar": "LIDAR_TOP sweep", "intrinsic": "calibration intrinsic"}[how]
    assert f"frame '{token}'" in text and expect in text, text
    assert "non-finite value (NaN or inf)" in text or how == "lidar", text


def test_a_nan_ego_pose_refuses_the_run_naming_the_frame(dd, small_world, tmp_path):
    root, token = broken_world(small_world, tmp_path, "pose")
    dd.pytester.makepyfile(ctx=CONTEXT_PLANNER)
    result = dd.run(planner="ctx.py", families="jpeg", severities="1", data=root)
    no_traceback(result)
    text = result.stdout.str() + result.stderr.str()
    assert result.ret == pytest.ExitCode.USAGE_ERROR, text
    assert not (dd.pytester.path / "rep").exists()  # before any cell ran
    # the broken pose is frame `token`'s own, and in the ground-truth future of the frame before it, named first
    assert "non-finite value (NaN or inf) in its" in text and "so it cannot be scored" in text, text
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    frames = NuScenesReader(root, split="val").scorable_frames(limit=4)
    first = next(f for f in frames if f.token == token or not np.isfinite(f.gt_future).all())
    assert f"frame '{first.token}'" in text, text


def test_a_data_root_whose_path_is_not_utf8_is_a_usage_error(dd, small_world, tmp_path):
    """Issue 37 (low): it ended in an INTERNALERROR (the certificate, UTF-8 JSON, could not record the path)."""
    import os

    odd = os.fsdecode(bytes(tmp_path) + b"/w\xff")
    shutil.copytree(small_world, odd)
    dd.pytester.makepyfile(ctx=CONTEXT_PLANNER)
    result = dd.run(planner="ctx.py", families="jpeg", severities="1", data=Path(odd), subprocess=True)
    text = result.stdout.str() + result.stderr.str()
    assert result.ret == pytest.ExitCode.USAGE_ERROR, text
    assert "INTERNALERROR" not in text and "--drivedegrade-data: the path b'" in text and "not valid UTF-8" in text
