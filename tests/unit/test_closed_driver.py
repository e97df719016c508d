"""The reference closed-loop driver (planners/closed_driver.py): its committed weights load without a download,
it plans six finite waypoints from the front camera, the same input gives the same plan bit for bit, and its plan
depends on the camera (a black front camera moves it)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.closedloop import route_of
from pytest_drivedegrade.closedloop.camera import RouteCameras
from pytest_drivedegrade.closedloop.loop_io import ego_status, route_command
from pytest_drivedegrade.data.world.scenarios import scenario_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "planners"))
from closed_driver import WEIGHTS, ClosedDriver, preprocess  # noqa: E402


@pytest.fixture(scope="module")
def inputs():
    route = route_of(scenario_scene(0, 1))
    ego = route.scene.ego
    pose = (float(ego.xy[0, 0]), float(ego.xy[0, 1]), float(ego.yaw[0]))
    images = RouteCameras(route, ("CAM_FRONT",)).images(pose, 0)
    status = ego_status([], pose, float(ego.speed[0]), float(ego.accel[0]), 0.0)
    return images, status, route_command(route, pose, float(ego.speed[0]))


def test_the_committed_weights_plan_six_finite_waypoints_deterministically(inputs) -> None:
    assert WEIGHTS.is_file() and WEIGHTS.stat().st_size < 2_000_000
    driver = ClosedDriver()
    assert driver.cameras == ("CAM_FRONT",) and driver.trained_on.get("recipe") == "planners/train_closed_driver.py"
    plan = driver.predict(*inputs)
    assert plan.shape == (6, 2) and np.isfinite(plan).all() and plan[-1, 0] > plan[0, 0]
    assert driver.predict(*inputs).tobytes() == plan.tobytes()


def test_the_plan_depends_on_the_front_camera(inputs) -> None:
    images, status, cmd = inputs
    driver = ClosedDriver()
    dark = {"CAM_FRONT": np.zeros_like(images["CAM_FRONT"])}
    assert preprocess(images).shape == (6, 45, 80)
    assert np.abs(driver.predict(dark, status, cmd) - driver.predict(images, status, cmd)).max() > 0.05
