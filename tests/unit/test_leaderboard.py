"""The closed loop's Driving Score as the CARLA leaderboard computes it (spec/leaderboard.md): the penalty factors
with known answers, CollisionTest's de-duplication, MinimumSpeedRouteTest's checkpoints, the outside-route-lanes
test on an oncoming lane, the collision rules, and a hung predict that leaves its run unscored."""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np
import pytest

from pytest_drivedegrade.closedloop import judge, route_of, run_route
from pytest_drivedegrade.closedloop.cells import run_from_builtins, run_to_builtins
from pytest_drivedegrade.closedloop.leaderboard import (
    PENALTIES,
    CollisionFilter,
    Limits,
    MinSpeed,
    check_rule,
    driving_score,
    penalty,
    percent_factor,
)
from pytest_drivedegrade.closedloop.results import END_UNSCORED, Infraction, RunResult
from pytest_drivedegrade.closedloop.routes import Route
from pytest_drivedegrade.closedloop.simulate import Rules
from pytest_drivedegrade.data.frame import Command, EgoStatus
from pytest_drivedegrade.data.world.roads import LANE_WIDTH, in_junction
from pytest_drivedegrade.data.world.scene import make_scene


@pytest.fixture(scope="module")
def route() -> Route:
    return route_of(make_scene(1, 0, "scene-0"))


def test_the_fixed_factors_are_the_leaderboards() -> None:
    assert PENALTIES == {"collision_pedestrian": 0.50, "collision_vehicle": 0.60, "collision_static": 0.65,
                         "red_light": 0.70, "stop_sign": 0.80, "scenario_timeout": 0.70,
                         "yield_emergency_vehicle": 0.70}


def test_percentage_factors_with_known_answers() -> None:
    # outside route lanes: coefficient 0, "increases": 25 % of the route outside -> x 0.75
    assert percent_factor("outside_route_lanes", 25.0) == pytest.approx(0.75)
    assert percent_factor("outside_route_lanes", 100.0) == pytest.approx(0.0)
    # min speed: coefficient 0.7, "decreases": 60 % of the traffic's speed -> 1 - 0.3 x 0.4 = 0.88; 0 % -> 0.7
    assert percent_factor("min_speed", 60.0) == pytest.approx(0.88)
    assert percent_factor("min_speed", 0.0) == pytest.approx(0.70)


def test_driving_score_multiplies_every_infraction() -> None:
    infractions = [("collision_vehicle", None), ("collision_vehicle", None), ("red_light", None),
                   ("outside_route_lanes", 10.0), ("min_speed", 50.0), ("off_road", None)]
    expected = 100 * 0.8 * 0.6 * 0.6 * 0.7 * 0.9 * 0.85
    assert driving_score(0.8, infractions) == pytest.approx(expected)
    assert penalty([]) == 1.0 and driving_score(1.0, []) == 100.0
    assert driving_score(1.0, [("outside_route_lanes", 100.0)]) == 0.0


def test_collision_filter_counts_as_collision_test_does() -> None:
    f = CollisionFilter()
    here = np.array([0.0, 0.0])
    assert not f.counts(3, here, 0.05, 0.0)  # the ego (nearly) standing: not counted
    assert f.counts(3, here, 2.0, 0.0)
    assert not f.counts(3, here + [6.0, 0.0], 2.0, 1.0)  # the same actor within 5 s
    assert not f.counts(4, here + [3.0, 0.0], 2.0, 1.0)  # another actor within 5 m of the last collision
    f.update(here + [6.0, 0.0], 1.0)  # the ego 6 m away: the place is forgotten, the actor not yet
    assert not f.counts(3, here + [6.0, 0.0], 2.0, 1.0)
    assert f.counts(4, here + [6.0, 0.0], 2.0, 1.0)
    f.update(here + [20.0, 0.0], 7.0)  # 6 s later, 14 m on: both forgotten
    assert f.counts(4, here + [20.0, 0.0], 2.0, 7.0)
    assert f.counts(None, here + [40.0, 0.0], 2.0, 8.0)  # a static object, 20 m on


def test_min_speed_closes_a_checkpoint_every_quarter_of_the_route() -> None:
    m = MinSpeed(100.0)
    failed = [m.tick(p, 5.0, 10.0) for p in np.arange(0.0, 60.0, 1.0)]  # half the expert's speed
    assert [v for v in failed if v is not None] == [50.0, 50.0]  # closed past 25 m and past 50 m
    assert MinSpeed(100.0).finish(90.0) is None  # the last checkpoint only beyond 95 % of the route
    fast = MinSpeed(100.0)
    assert [fast.tick(p, 12.0, 10.0) for p in range(0, 100)] == [None] * 100  # 120 %: no infraction
    assert fast.finish(99.0) is None


def test_limits_scale_the_blocked_time_to_the_scene_and_keep_30_m() -> None:
    assert Limits.of(20.0) == Limits(30.0, 10.0)
    assert Limits.of(1000.0) == Limits(30.0, 180.0)
    assert check_rule("at_fault") == "at_fault"
    with pytest.raises(ValueError, match="all or at_fault"):
        check_rule("sometimes")


def test_the_oncoming_lane_and_the_verge_are_outside_the_route_lanes(route: Route) -> None:
    centre = route.scene.net.route.center
    i = len(centre.xy) // 3
    while bool(in_junction(route.scene.net, centre.xy[i])[0]):
        i += 40
    x, y = centre.xy[i]
    yaw = float(centre.yaw[i])
    left = np.array([-np.sin(yaw), np.cos(yaw)])
    road = route.scene.net.route

    def at(d: float) -> judge.Pose:
        return judge.Pose(float(x + d * left[0]), float(y + d * left[1]), yaw, 5.0, 0.0)

    assert not judge.outside_route_lanes(route, at(-0.5 * LANE_WIDTH))  # the ego's own lane
    assert judge.outside_route_lanes(route, at(0.5 * LANE_WIDTH))  # the oncoming lane
    assert not judge.outside_route_lanes(route, at(-road.half_width - 0.4))  # the shoulder, within 0.5 m
    assert judge.outside_route_lanes(route, at(-road.half_width - 1.0))  # the verge


def test_a_run_keeps_its_percentage_infractions_through_the_store() -> None:
    run = RunResult("r", 0, 42.0, 0.5, "complete", (Infraction("collision_vehicle", 1, 5, "lead"),
                                                   Infraction("outside_route_lanes", 2, 10, "", 12.5)),
                    np.zeros((2, 3)))
    back = run_from_builtins(run_to_builtins(run))
    assert back.infractions == run.infractions
    old = {**run_to_builtins(run), "infractions": [["collision_vehicle", 1, 5, "lead"]]}  # a spec-4 record
    assert run_from_builtins(old).infractions == (Infraction("collision_vehicle", 1, 5, "lead"),)


class Hangs:
    """Drives straight on, then hangs in its third predict (a sleep that would outlast the session)."""

    cameras: tuple[str, ...] = ()

    def __init__(self) -> None:
        self.calls = 0

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        self.calls += 1
        if self.calls == 3:
            time.sleep(3600)
        return np.stack([np.arange(1, 7) * 4.0, np.zeros(6)], axis=1)


def test_a_hung_predict_leaves_the_run_unscored_within_the_timeout(route: Route) -> None:
    t0 = time.perf_counter()
    run = run_route(Hangs(), route, rules=Rules(timeout=0.5))
    assert time.perf_counter() - t0 < 30.0
    assert run.end == END_UNSCORED and run.ds is None and run.steps == 2
    assert "step 2" in run.error and "0.5 s" in run.error


def test_the_at_fault_rule_never_scores_below_every_collision(route: Route) -> None:
    class Straight:
        cameras: tuple[str, ...] = ()

        def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
            return np.stack([np.arange(1, 7) * 6.0, np.zeros(6)], axis=1)

    every, at_fault = run_route(Straight(), route), run_route(Straight(), route, rules=Rules("at_fault"))
    assert every.ds is not None and at_fault.ds is not None and every.ds <= at_fault.ds
    assert every.trace.tobytes() == at_fault.trace.tobytes()  # the rule scores; it never moves the ego
