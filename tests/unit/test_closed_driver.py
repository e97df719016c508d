"""The reference closed-loop driver (planners/closed_driver.py): its committed weights load without a download,
it plans six finite waypoints from the front camera, the same input gives the same plan bit for bit, and its plan
depends on the camera (a black front camera moves it)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pytest_drivedegrade.closedloop import load_routes, route_of
from pytest_drivedegrade.closedloop.camera import RouteCameras
from pytest_drivedegrade.closedloop.loop_io import ego_status, route_command
from pytest_drivedegrade.data.world.scenarios import scenario_scene
from pytest_drivedegrade.floor import FEATURE_SIZE

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "planners"))
from closed_driver import WEIGHTS, ClosedDriver, DriverNet, preprocess  # noqa: E402
from train_closed_driver import (  # noqa: E402
    AUGMENT,
    BRAKE_WEIGHT,
    route_corruption,
    sample_weights,
    train,
    training_routes,
)

#: Farthest the driver may plan to move in 3 s standing behind a vehicle that stands in its lane (m).
STOPPED_REACH_M = 2.0


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


def _frame(route, t: int):
    """The front camera, ego status and command at log step `t` of `route`, the ego at its logged pose and speed
    with its logged past (what the closed loop gives the driver when it drives as the log did)."""
    ego = route.scene.ego
    pose = (float(ego.xy[t, 0]), float(ego.xy[t, 1]), float(ego.yaw[t]))
    past = [(float(ego.xy[t - 5 * j, 0]), float(ego.xy[t - 5 * j, 1]), float(ego.yaw[t - 5 * j]))
            for j in range(4, 0, -1) if t - 5 * j >= 0]
    status = ego_status(past, pose, float(ego.speed[t]), float(ego.accel[t]), 0.0)
    images = RouteCameras(route, ("CAM_FRONT",)).images(pose, t)
    return images, status, route_command(route, pose, float(ego.speed[t]))


def test_the_committed_weights_slow_for_a_standing_bus_and_drive_on_a_free_road() -> None:
    """Guards the weights' behaviour: on scenario 2 the logged expert brakes from step 100 and stands behind a
    broken-down bus from step 140 to 180. The driver, placed on the log, plans 3 s ahead over 20 m at step 40 (the
    bus far ahead, 7.8 m/s; the log 23.9 m) and under 8 m at step 120 (close behind it, 4.7 m/s; the log 3.7 m).
    Measured with the committed weights: 25.6 m and 6.6 m."""
    route = route_of(scenario_scene(0, 2))
    assert [a.kind for a in route.scene.agents if a.role == "stopped"] == ["bus"]
    driver = ClosedDriver()
    assert driver.predict(*_frame(route, 40))[-1, 0] > 20.0
    assert driver.predict(*_frame(route, 120))[-1, 0] < 8.0


@pytest.mark.xfail(strict=True, reason="the committed driver creeps behind a standing vehicle (9.2-9.6 m planned "
                   "in 3 s at 0 m/s): the collisions with standing vehicles the slice counts; a driver that meets "
                   "issue 38's targets must pass this")
def test_the_driver_stays_put_behind_a_standing_bus() -> None:
    route = route_of(scenario_scene(0, 2))
    driver = ClosedDriver()
    for t in (150, 160, 170):
        assert driver.predict(*_frame(route, t))[-1, 0] < STOPPED_REACH_M, t


def test_the_committed_weights_plan_a_known_frame() -> None:
    """The committed weights' plan on scenario 2's frame at step 40 (on its log), to 1e-3 m: new weights must
    update these numbers on purpose."""
    plan = ClosedDriver().predict(*_frame(route_of(scenario_scene(0, 2)), 40))
    np.testing.assert_allclose(plan, [[3.522, -0.6076], [7.8745, -1.0709], [12.3746, -1.6902],
                                      [17.0276, -2.3393], [21.2971, -3.1867], [25.5554, -3.6889]], atol=1e-3)


def test_braking_samples_are_drawn_twice_as_often() -> None:
    """A sample is a braking one when the expert's 3 s waypoint is short of 0.8 x speed x 3 s."""
    feats = np.zeros((3, FEATURE_SIZE), dtype=np.float32)
    feats[:, 0] = [10.0, 10.0, 0.0]
    plans = np.zeros((3, 12), dtype=np.float32)
    plans[:, 10] = [29.0, 20.0, 0.0]  # the last waypoint's x: on pace, braking, standing (0 < 0 is false)
    assert sample_weights(feats, plans).tolist() == [1.0, BRAKE_WEIGHT, 1.0]


def test_routes_are_driven_clean_or_under_an_image_quality_corruption_never_blackout() -> None:
    rng = np.random.default_rng(0)
    drawn = [route_corruption(rng, 0.5) for _ in range(400)]
    clean = sum(c.family == "clean" for c in drawn)
    assert 160 < clean < 240
    assert {c.family for c in drawn if c.family != "clean"} == set(AUGMENT)
    assert {c.severity for c in drawn if c.family != "clean"} == {1, 2, 3, 4, 5}
    assert "blackout" not in AUGMENT and {"gaussian_blur", "motion_blur"} <= set(AUGMENT)
    assert all(route_corruption(rng, 0.0).family == "clean" for _ in range(20))
    again = np.random.default_rng(0)
    assert [route_corruption(again, 0.5) for _ in range(400)] == drawn


def test_the_training_routes_are_not_the_slices(small_world: Path) -> None:
    """Training drives the train scenes and scenarios numbered from 1000; the slice the val scenes and
    scenarios from 0: no route, and no scene, in common."""
    train = training_routes(small_world, 6, 2 / 3)
    names = [r.name for r in train]
    assert names[:2] == ["scene-0001", "scene-0002"] and len(names) == 6
    assert all(n.startswith("scenario-10") for n in names[2:])
    assert not set(names) & {r.name for r in load_routes(small_world)}


def test_training_is_deterministic_for_a_seed() -> None:
    """The recipe's training step on the same data and seed gives the same weights, tensor for tensor, within a
    process (across processes the whole recipe's weights differ: docs/how-to/closed-loop.md)."""
    rng = np.random.default_rng(3)
    pix = rng.integers(0, 256, (40, 6, 45, 80), dtype=np.uint8)
    feats = rng.normal(size=(40, FEATURE_SIZE)).astype(np.float32)
    plans = rng.normal(size=(40, 12)).astype(np.float32)
    for brake_weight in (1.0, 2.0):  # a permutation an epoch, or weighted draws with replacement
        torch.manual_seed(0)
        start = DriverNet().state_dict()
        nets = [DriverNet(), DriverNet()]
        for net in nets:
            net.load_state_dict(start)
            train(net, pix, feats, plans, 2, seed=5, brake_weight=brake_weight)
        first, second = (n.state_dict() for n in nets)
        assert all(torch.equal(first[k], second[k]) for k in first)
        assert not torch.equal(first["head.4.weight"], start["head.4.weight"])
