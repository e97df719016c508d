"""Reactive agents in the closed loop: IDM's known answers, an agent that brakes for the ego stopped ahead of it
(where its log drives into it) and is rendered where it stopped, agents the ego never gets in front of replaying
their logs exactly, log replay as the untouched default, determinism."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest

from pytest_drivedegrade.closedloop import judge, route_of, run_route
from pytest_drivedegrade.closedloop.agents import IDM, leader_gap, run_world
from pytest_drivedegrade.closedloop.camera import RouteCameras
from pytest_drivedegrade.closedloop.routes import Route
from pytest_drivedegrade.data.frame import Command, EgoStatus
from pytest_drivedegrade.data.world.scene import make_scene
from pytest_drivedegrade.errors import DriveDegradeError

#: World seed 1, scene 0: a follower behind the ego whose log drives into an ego that stands still.
SEED, SCENE = 1, 0


class Stop:
    """Plans to stand still."""

    cameras: tuple[str, ...] = ()

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        return np.zeros((6, 2))


@pytest.fixture(scope="module")
def route() -> Route:
    return route_of(make_scene(SEED, SCENE, f"scene-{SCENE}"))


def _standing(route: Route) -> judge.Pose:
    ego = route.scene.ego
    return judge.Pose(float(ego.xy[0, 0]), float(ego.xy[0, 1]), float(ego.yaw[0]), 0.0, 0.0)


def test_idm_known_answers() -> None:
    idm = IDM()
    assert idm.acceleration(0.0, 10.0, 1e9, 0.0) == pytest.approx(1.0)  # free road from standstill: a
    assert idm.acceleration(10.0, 10.0, 1e9, 0.0) == pytest.approx(0.0, abs=1e-9)  # at the desired speed: 0
    assert idm.acceleration(0.0, 10.0, 2.0, 0.0) == pytest.approx(0.0)  # standing at the minimum gap: 0
    assert idm.acceleration(0.0, 10.0, 1.0, 0.0) == pytest.approx(-3.0)  # a (1 - (s0 / s)^2) = 1 - 4
    # approaching a standing leader at 10 m/s from 30 m: s* = 2 + 10 + 100 / (2 sqrt 1.5) = 52.82 m
    s_star = 2.0 + 10.0 + 100.0 / (2.0 * np.sqrt(1.5))
    assert idm.acceleration(10.0, 14.0, 30.0, 10.0) == pytest.approx(1 - (10 / 14) ** 4 - (s_star / 30) ** 2)
    assert idm.acceleration(10.0, 10.0, 0.5, 10.0) == -idm.max_brake  # the cap on IDM's unbounded braking


def test_an_agent_brakes_for_the_ego_standing_ahead_of_it(route: Route) -> None:
    pose = _standing(route)
    log_contacts = [c for t in range(route.end_step) for c in judge.collisions(route, pose, t, False)]
    follower = next(i for i, a in enumerate(route.scene.agents) if a.role == "follower")
    assert {who for _, who, _ in log_contacts} == {follower}  # replayed, the follower drives into the ego
    mine, world = run_world(route, "reactive")
    assert world is not None
    for t in range(1, route.end_step + 1):
        world.advance(t, pose)
    assert not [c for t in range(route.end_step + 1) for c in judge.collisions(mine, pose, t, False)]
    agent = mine.scene.agents[follower]
    assert agent.speed[-1] == 0.0 and agent.speed[:40].min() < agent.speed[0]  # it slowed and stopped
    found = leader_gap(agent, route.end_step, pose)
    assert found is not None and 1.0 < found[0] < 2.5  # standing about IDM's minimum gap (2 m) behind the ego
    for i, (ours, logged) in enumerate(zip(mine.scene.agents, route.scene.agents)):
        if i != follower:  # the ego is never in their way: their logs replay exactly
            assert ours.xy.tobytes() == logged.xy.tobytes() and ours.speed.tobytes() == logged.speed.tobytes()
    at, xyyaw = 60, (pose.x, pose.y, pose.yaw)  # 6 s in: the log's follower drove through, ours waits behind
    behind = RouteCameras(mine, ("CAM_BACK",)).images(xyyaw, at)["CAM_BACK"]
    assert not np.array_equal(behind, RouteCameras(route, ("CAM_BACK",)).images(xyyaw, at)["CAM_BACK"])
    assert np.array_equal(behind, RouteCameras(mine, ("CAM_BACK",)).images(xyyaw, at)["CAM_BACK"])


def test_a_reactive_run_leaves_the_scene_unwritten_and_repeats_bit_for_bit(route: Route) -> None:
    before = [a.xy.copy() for a in route.scene.agents]
    first, second = (run_route(Stop(), route, agents="reactive") for _ in range(2))
    assert first.trace.tobytes() == second.trace.tobytes() and first.ds == second.ds
    assert first.infractions == () and first.end == "blocked"
    assert all(np.array_equal(a.xy, b) for a, b in zip(route.scene.agents, before))


def test_log_replay_is_the_default_and_touches_nothing(route: Route) -> None:
    same, world = run_world(route, "log")
    assert same is route and world is None
    default, logged = run_route(Stop(), route), run_route(Stop(), route, agents="log")
    assert default.trace.tobytes() == logged.trace.tobytes() and default.ds == logged.ds


def test_an_unknown_agents_mode_names_the_valid_ones(route: Route) -> None:
    with pytest.raises(DriveDegradeError, match="'log'.*'reactive'"):
        run_route(Stop(), route, agents="smart")
