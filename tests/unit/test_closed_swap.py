"""Issue 40 (closed loop): at a junction route the route's command is swapped, the route changing with it, and
route completion measures whether the planner went where it was told. The privileged expert given the swapped
route completes it; a planner that ignores the command and turns where the log turned leaves it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pytest_drivedegrade.closedloop.expert import WorldExpert
from pytest_drivedegrade.closedloop.loop_io import route_command
from pytest_drivedegrade.closedloop.results import END_COMPLETE, END_DEVIATED
from pytest_drivedegrade.closedloop.routes import route_of
from pytest_drivedegrade.closedloop.simulate import run_route
from pytest_drivedegrade.closedloop.swap import SWAP_CELL, junction_routes, swap_cell, swapped_route
from pytest_drivedegrade.data.frame import Command
from pytest_drivedegrade.data.world.scenarios import scenario_scene


@pytest.fixture(scope="module")
def turning():
    """Scenario route 9 of world seed 0: its road turns left at a junction its logged ego drives through."""
    route = route_of(scenario_scene(0, 9))
    assert route.scene.net.junctions[0].turn == "left"
    return route


def test_the_swapped_route_goes_straight_on_and_its_command_says_so(turning) -> None:
    swap = swapped_route(turning)
    assert swap is not None and swap.name == f"{turning.name}-swap"
    j = turning.scene.net.junctions[0]
    n = int(np.searchsorted(turning.lane.s, j.s_route - j.half - 5.0))
    np.testing.assert_allclose(swap.lane.xy[:n], turning.lane.xy[:n], atol=1e-3)  # the same lane up to the junction
    assert swap.start_s == pytest.approx(turning.start_s, abs=0.3) and swap.length <= turning.length
    heading = np.array([np.cos(j.heading), np.sin(j.heading)])
    after = swap.lane.xy[swap.lane.s > j.s_route + j.half + 5.0]
    assert np.abs(np.diff(after @ np.array([-heading[1], heading[0]]))).max() < 1e-6  # straight on, no turn
    # at the square's edge the logged route says LEFT at 8 m/s, the swapped one STRAIGHT (before it, this route's
    # approach bends left, which both say)
    x, y, yaw = turning.lane.at(j.s_route - j.half)
    pose = (float(x), float(y), float(yaw))
    assert route_command(turning, pose, 8.0) == Command.LEFT
    assert route_command(swap, pose, 8.0) == Command.STRAIGHT


def test_on_a_straight_approach_the_command_changes_ten_metres_before_the_square() -> None:
    route = route_of(scenario_scene(0, 14))  # turns right after a straight approach
    swap, j = swapped_route(route), route.scene.net.junctions[0]
    assert swap is not None and j.turn == "right"
    for back, logged in ((20.0, Command.STRAIGHT), (10.0, Command.RIGHT), (5.0, Command.RIGHT)):
        x, y, yaw = route.lane.at(j.s_route - j.half - back)
        pose = (float(x), float(y), float(yaw))
        assert (route_command(route, pose, 8.0), route_command(swap, pose, 8.0)) == (logged, Command.STRAIGHT)


def test_only_routes_turning_at_a_junction_the_ego_enters_are_swapped() -> None:
    routes = [route_of(scenario_scene(0, i)) for i in range(10)]
    turns = [r.name for r in routes if r.scene.net.junctions and r.scene.net.junctions[0].turn != "straight"]
    got = [s.name[:-len("-swap")] for s in junction_routes(routes)]
    assert got and set(got) <= set(turns)
    straight = [r for r in routes if r.scene.net.junctions and r.scene.net.junctions[0].turn == "straight"]
    assert straight and all(swapped_route(r) is None for r in straight)  # no turning road built there
    assert all(swapped_route(r) is None for r in routes if not r.scene.net.junctions)


def test_the_expert_given_the_swapped_route_completes_it_and_a_command_ignoring_planner_does_not(turning) -> None:
    swap = swapped_route(turning)
    assert swap is not None
    told = run_route(WorldExpert([swap]), swap)
    assert (told.end, told.completion) == (END_COMPLETE, 1.0) and told.ds > 95
    ignoring = WorldExpert([replace(turning, name=swap.name)])  # the logged route's expert: turns whatever it is told
    went = run_route(ignoring, swap)
    assert went.end == END_DEVIATED and 0.3 < went.completion < 0.9 and went.ds < told.ds
    cell = swap_cell(WorldExpert([swap]), [turning])
    assert cell.cell == SWAP_CELL and [r.route for r in cell.runs] == [swap.name]
    assert cell.runs[0].completion == told.completion and cell.runs[0].ds == told.ds  # deterministic
