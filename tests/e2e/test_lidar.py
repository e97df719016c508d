"""A LiDAR (fusion) planner gets the keyframe's LIDAR_TOP sweep through the frame context, as recorded: the same
points in every cell, the camera blackout included, and read-only."""

from __future__ import annotations

import hashlib
import json
from typing import Any

import numpy as np
import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import by_cell, read_csv  # noqa: E402

from pytest_drivedegrade.data.context import LIDAR_POINT_SIZE, FrameContext, load_points  # noqa: E402
from pytest_drivedegrade.data.nuscenes import NuScenesReader  # noqa: E402
from pytest_drivedegrade.errors import DataError  # noqa: E402

pytest_plugins = ["plugin_support"]

FUSION = '''
import hashlib
import json

import numpy as np
import pytest

T = 0.5 * np.arange(1, 7)


class Fusion:
    """Drives straight at its speed, sideways by the front camera's brightness and the nearest LiDAR return;
    logs what the sweep it was handed looked like (cell, frame, shape, digest, writeable)."""

    cameras = ("CAM_FRONT",)
    name = "fusion"

    def predict(self, images, ego, cmd, context):
        points = context.lidar_points()
        cell = os.environ.get("PYTEST_CURRENT_TEST", "").rpartition("::")[2].rpartition(" ")[0]
        with open({log!r}, "a") as fh:
            fh.write(json.dumps([cell, context.token, list(points.shape), str(points.dtype),
                                 hashlib.blake2b(points.tobytes(), digest_size=16).hexdigest(),
                                 bool(points.flags.writeable)]) + "\\n")
        ego_xyz = points[:, :3] @ context.lidar2ego[:3, :3].T + context.lidar2ego[:3, 3]
        nearest = float(np.min(np.hypot(ego_xyz[:, 0], ego_xyz[:, 1])))
        plan = np.zeros((6, 2))
        plan[:, 0] = max(ego.velocity[0], 0.0) * T
        plan[:, 1] = float(images["CAM_FRONT"][::8, ::8].mean()) / 255.0 + 0.01 * nearest
        return plan


@pytest.fixture(scope="session")
def planner():
    return Fusion()
'''


def test_a_fusion_planner_gets_the_recorded_sweep_in_every_cell(dd: Any):
    """Every call of every cell (clean, null, blind, blackout S1 and S5, jpeg) gets the keyframe's .pcd.bin
    points: (file size / 20, 5) float32, byte-identical to the file, read-only; the blackout changes the plan
    only through the camera."""
    log = dd.pytester.path / "calls.jsonl"
    dd.pytester.makepyfile(fusion=FUSION.format(log=str(log)))
    result = dd.run("-p", "no:xdist", planner="fusion.py", report="rl", families="blackout,jpeg")
    result.assert_outcomes(passed=7)
    files = {f.token: f.lidar_file for f in NuScenesReader(dd.world, split="val").frames()}
    calls = [json.loads(line) for line in log.read_text().splitlines()]
    cells = {c[0] for c in calls}
    assert {"clean", "blackout-s1", "blackout-s5", "jpeg-s5"} <= cells
    for cell, token, shape, dtype, digest, writeable in calls:
        raw = open(files[token], "rb").read()
        assert shape == [len(raw) // 20, LIDAR_POINT_SIZE] and shape[0] > 100 and dtype == "float32", (cell, token)
        assert digest == hashlib.blake2b(raw, digest_size=16).hexdigest() and not writeable, (cell, token)
    per_frame = {}
    for _cell, token, *_rest, digest, _w in calls:
        per_frame.setdefault(token, set()).add(digest)
    assert all(len(d) == 1 for d in per_frame.values()) and len(per_frame) == 4  # 4 frames, one sweep each
    rows = by_cell(read_csv(dd.pytester.path / "rl" / "fusion" / "cells.csv"))
    assert float(rows["blackout-s5"]["l2_avg"]) != float(rows["clean"]["l2_avg"])  # the camera still counts


def test_lidar_points_known_answer_and_bad_files(tmp_path):
    """The reader's layout (x, y, z, intensity, ring as float32) and a clear error for a truncated file; no sweep
    gives None."""
    pts = np.arange(20, dtype=np.float32).reshape(4, 5)
    path = tmp_path / "sweep.pcd.bin"
    pts.tofile(path)
    got = load_points(str(path))
    assert got.tolist() == pts.tolist() and not got.flags.writeable
    path.write_bytes(pts.tobytes()[:-4])
    with pytest.raises(DataError, match="truncated"):
        load_points(str(path))
    with pytest.raises(DataError, match="cannot read"):
        load_points(str(tmp_path / "missing.pcd.bin"))
    ctx = FrameContext("t", "s", "s", 0, 0, np.eye(4), {}, None, None)
    assert ctx.lidar_points() is None and ctx.lidar2ego is None
