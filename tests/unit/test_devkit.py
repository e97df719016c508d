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

import pytest

from pytest_drivedegrade.data.world import write_world
from pytest_drivedegrade.data.world.scene import KEYFRAMES

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
