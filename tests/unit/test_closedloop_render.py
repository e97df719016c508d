"""The faster closed-loop rendering draws the same pixels: at the logged pose, every camera at several keyframes
equals the data's image (the cached backdrop and the culled agents change nothing), and a route's backdrop is
built once per process."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.closedloop import camera as camera_module
from pytest_drivedegrade.closedloop import load_routes
from pytest_drivedegrade.closedloop.camera import RouteCameras, backdrop
from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.data.nuscenes import NuScenesReader


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from pytest_drivedegrade.data.world import write_world
    return write_world(tmp_path_factory.mktemp("w"), scenes=2, seed=3)


def test_every_camera_at_logged_poses_equals_the_datas_images(world: Path) -> None:
    route = load_routes(world)[0]
    frames = [f for f in NuScenesReader(world).frames() if f.scene_name == route.name]
    cams = RouteCameras(route, CAMERAS)
    ego = route.scene.ego
    for k in (0, 17, 39):
        t = 5 * k
        images = cams.images((float(ego.xy[t, 0]), float(ego.xy[t, 1]), float(ego.yaw[t])), t)
        for cam in CAMERAS:
            assert np.array_equal(images[cam], NuScenesReader.load_image(frames[k].cameras[cam])), (k, cam)


def test_a_routes_backdrop_is_built_once_and_shared(world: Path) -> None:
    first, again = load_routes(world)[0], load_routes(world)[0]  # two Route objects of one scene
    assert backdrop(first) is backdrop(again)
    assert RouteCameras(again, ("CAM_FRONT",)).backdrop is backdrop(first)
    assert RouteCameras(again, ()).backdrop is None  # a planner that reads no camera builds nothing
    assert len(camera_module._BACKDROPS) <= camera_module.BACKDROPS_KEPT
