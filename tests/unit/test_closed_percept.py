"""The percept bound (`closedloop.percept`): the world expert's rule driven from what a camera could tell, read from
the world. Known answers for the rule on hand-made percepts, the cruise speed recovered from the first ego status,
the world's percept where the answer is known, and the bound itself driving a light route and scenario routes
without an infraction the camera could have prevented."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.closedloop import route_of, run_route
from pytest_drivedegrade.closedloop.percept import (
    BEND_AHEAD,
    CRUISE_RANGE,
    FAR_M,
    LANE_AHEAD,
    STOP_MARGIN,
    V_TOP,
    Percept,
    PerceptExpert,
    WorldPercept,
    YellowDecision,
    cruise_from_status,
    on_lane,
    plan_arcs,
    tracked_lead_speed,
)
from pytest_drivedegrade.constants import EGO_LENGTH
from pytest_drivedegrade.data.frame import Command, EgoStatus
from pytest_drivedegrade.data.world.expert import B_MAX, S0, idm
from pytest_drivedegrade.data.world.lights import RED
from pytest_drivedegrade.data.world.scenarios import light_scene, scenario_scene

STRAIGHT = np.stack([np.asarray(LANE_AHEAD), np.zeros(len(LANE_AHEAD))], axis=1)
OPEN_ROAD = np.full(len(BEND_AHEAD), V_TOP)


def road(**kw) -> Percept:
    return Percept(STRAIGHT, OPEN_ROAD, **kw)


@settings(max_examples=60, deadline=None)
@given(st.floats(*CRUISE_RANGE), st.floats(0.3, 0.99))
def test_the_cruise_speed_is_recovered_from_a_free_road_status(v0: float, share: float) -> None:
    v = share * v0
    status = EgoStatus((v, 0.0), (idm(v, v0, None, 0.0), 0.0), 0.0)
    assert cruise_from_status(status) == pytest.approx(v0, rel=1e-9)


def test_a_status_that_is_not_speeding_up_keeps_its_speed_within_the_worlds_range() -> None:
    assert cruise_from_status(EgoStatus((11.0, 0.0), (-1.0, 0.0), 0.0)) == 11.0
    assert cruise_from_status(EgoStatus((3.0, 0.0), (0.0, 0.0), 0.0)) == CRUISE_RANGE[0]
    assert cruise_from_status(EgoStatus((30.0, 0.0), (0.5, 0.0), 0.0)) == CRUISE_RANGE[1]


def test_on_a_free_straight_road_it_keeps_its_cruise_speed() -> None:
    arcs = plan_arcs(road(), 10.0, 10.0)
    assert arcs == pytest.approx(10.0 * 0.5 * np.arange(1, 7), abs=1e-9)


def test_it_stops_before_a_red_line_and_drives_on_at_green() -> None:
    red = plan_arcs(road(line=20.0, red=True), 8.0, 10.0)
    assert np.all(np.diff(red) >= 0) and red[-1] <= 20.0 - STOP_MARGIN + 1e-9
    assert red[-1] > 20.0 - STOP_MARGIN - 1.5  # it stops at the line, not far short of it
    assert plan_arcs(road(line=20.0), 8.0, 10.0)[-1] > 24.0
    # stopped 1 m past its target (less than PAST_LINE_M past the line): it holds
    assert plan_arcs(road(line=1.0, red=True), 0.3, 10.0)[-1] < 0.05


def test_at_yellow_it_goes_on_where_stopping_would_need_more_than_b_yellow() -> None:
    close = plan_arcs(road(line=STOP_MARGIN + 3.0, yellow=True), 12.0, 12.0)  # 144 / 6 = 24 m/s^2 to stop
    assert close[-1] > 30.0
    far = plan_arcs(road(line=40.0, yellow=True), 12.0, 12.0)
    assert far[-1] <= 40.0 - STOP_MARGIN + 1e-9


def test_the_yellow_decision_is_taken_once_and_kept_until_no_line_is_read() -> None:
    """The run this prevents (lights-3001, measured): yellow read 21.7 m from the stop at 9.8 m/s (2.2 m/s^2 to
    stop: stop), then the line read 2.7 m nearer than it was at 7.9 m/s (3.8 m/s^2: go on, decided again), so the
    ego sped back up and the light turned red before its tail cleared the line."""
    first, nearer = road(line=STOP_MARGIN + 21.7, yellow=True), road(line=STOP_MARGIN + 8.2, yellow=True)
    decide = YellowDecision()
    assert decide.update(first, 9.8) is False and decide.update(nearer, 7.9) is False
    assert plan_arcs(nearer, 7.9, 10.0, decide.going)[-1] <= 8.2 + 1e-9  # it keeps stopping
    assert plan_arcs(nearer, 7.9, 10.0)[-1] > 8.2 + 5.0  # deciding again would go on
    assert decide.update(road(), 7.0) is False and decide.going is None  # no line read: forgotten
    assert decide.update(nearer, 7.9) is True  # a new line, read late: go on, and keep going
    assert decide.update(road(line=STOP_MARGIN + 30.0, yellow=True), 7.9) is True
    red = plan_arcs(road(line=STOP_MARGIN + 4.0, red=True), 7.9, 10.0, True)  # red after going on: it brakes
    assert red[-1] == pytest.approx(7.9 ** 2 / (2 * B_MAX), abs=0.2) and red[-1] == red[-2]  # at B_MAX, to a stop
    red_first = YellowDecision()
    assert red_first.update(road(line=30.0, red=True), 12.0) is False
    assert red_first.update(road(line=STOP_MARGIN + 3.0, yellow=True), 12.0) is False


@settings(max_examples=60, deadline=None)
@given(st.floats(0.0, 15.0), st.floats(0.0, 15.0), st.floats(0.0, 15.0), st.floats(1.0, 40.0))
def test_the_tracked_lead_speed_is_what_moved_the_gap(lead: float, v0: float, v1: float, gap: float) -> None:
    """A lead at constant speed, the ego from v0 to v1 at constant acceleration over 0.5 s: the gap's change gives
    the lead's speed back; a lead that stands reads 0 however the ego moves."""
    dt = 0.5
    after = gap + lead * dt - 0.5 * (v0 + v1) * dt
    assert tracked_lead_speed(after, gap, v1, v0, dt) == pytest.approx(lead, abs=1e-9)
    assert tracked_lead_speed(gap - 0.5 * (v0 + v1) * dt, gap, v1, v0, dt) == pytest.approx(0.0, abs=1e-9)
    assert tracked_lead_speed(gap - 20.0, gap, v1, v0, dt) == 0.0  # a nearer obstacle appeared: it reads standing


def test_it_stops_behind_a_standing_obstacle_and_follows_a_moving_one() -> None:
    arcs = plan_arcs(road(gap=25.0, lead_speed=0.0), 10.0, 10.0)
    assert arcs[-1] < 25.0 - 1.0 and np.all(np.diff(arcs) >= -1e-12)
    follow = plan_arcs(road(gap=15.0, lead_speed=10.0), 10.0, 12.0)
    assert follow[-1] < 15.0 + 10.0 * 3.0 - S0  # never closer than S0 to where the lead will be
    assert plan_arcs(road(gap=FAR_M, lead_speed=0.0), 10.0, 10.0)[-1] == pytest.approx(30.0)


def test_points_on_the_perceived_lane_go_straight_on_past_its_end() -> None:
    bend = STRAIGHT.copy()
    bend[:, 1] = 0.01 * bend[:, 0] ** 2
    pts = on_lane(bend, np.array([0.0, 10.0, 45.0, 54.0]))
    assert pts[:3] == pytest.approx(bend[[0, 3, 8]])
    slope = (bend[-1] - bend[-2]) / (LANE_AHEAD[-1] - LANE_AHEAD[-2])
    assert pts[3] == pytest.approx(bend[-1] + 9.0 * slope)


def test_the_worlds_percept_on_the_log_of_a_light_route() -> None:
    route = route_of(light_scene(0, 0))
    world, log = WorldPercept(route), route.scene.ego
    light = route.scene.lights[0]
    s_stop = float(world.lights.s_stop[0])
    red_steps = [t for t in range(len(log.s)) if light.state_at(t * 0.1) == RED and log.s[t] + EGO_LENGTH / 2 < s_stop]
    assert red_steps, "the light route has a red phase before the log reaches its line"
    t = red_steps[0]
    pose = (float(log.xy[t, 0]), float(log.xy[t, 1]), float(log.yaw[t]))
    p = world.at(t, float(log.s[t]), pose)
    assert p.red and not p.yellow
    assert p.line == pytest.approx(s_stop - float(log.s[t]) - EGO_LENGTH / 2, abs=1e-9)
    assert p.lane[0] == pytest.approx([0.0, 0.0], abs=0.05)  # the logged ego is on its lane, heading along it
    assert np.all(np.diff(p.lane[:, 0]) > 0)


@pytest.mark.parametrize("scene", [light_scene(0, 0), light_scene(0, 3), scenario_scene(0, 1), scenario_scene(0, 2),
                                   scenario_scene(0, 3)], ids=lambda s: s.name)
def test_the_bound_drives_lights_a_braking_lead_a_blocked_lane_and_a_crossing_without_an_infraction(scene) -> None:
    route = route_of(scene)
    run = run_route(PerceptExpert([route]), route)
    kinds = [i.kind for i in run.infractions if i.kind != "min_speed"]
    assert run.end == "complete" and kinds == [], (run.end, kinds)
    assert run.ds is not None and run.ds >= 90.0


def test_the_bound_refuses_to_plan_without_its_route() -> None:
    route = route_of(scenario_scene(0, 1))
    with pytest.raises(RuntimeError, match="reset"):
        PerceptExpert([route]).predict({}, EgoStatus((5.0, 0.0), (0.0, 0.0), 0.0), Command.STRAIGHT, context=None)
