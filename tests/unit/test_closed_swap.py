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


def test_a_junction_route_whose_logged_drive_stays_near_the_swapped_lane_is_not_driven() -> None:
    """Scenario route 14 turns right, but the logged drive ends 1.4 m from the swapped lane: the planner that
    turns where the log turned completes its swapped route, so it cannot tell whether the command was followed
    and the cell leaves it out; route 9's logged lane ends 42 m off the swapped one and is driven."""
    from pytest_drivedegrade.closedloop.leaderboard import DEVIATION_M
    from pytest_drivedegrade.closedloop.swap import parting_m

    near, far = route_of(scenario_scene(0, 14)), route_of(scenario_scene(0, 9))
    swap_near, swap_far = swapped_route(near), swapped_route(far)
    assert swap_near is not None and swap_far is not None
    assert parting_m(near, swap_near) < 2.0 < DEVIATION_M < parting_m(far, swap_far) < 45.0
    went = run_route(WorldExpert([replace(near, name=swap_near.name)]), swap_near)
    assert (went.end, went.completion) == (END_COMPLETE, 1.0)  # ignored the command, scored as if it followed
    assert [s.name for s in junction_routes([near, far])] == [swap_far.name]


def test_the_swap_cell_has_no_retention_and_its_figure_stands_beside_clean_on_the_same_routes() -> None:
    from pytest_drivedegrade.closedloop.analysis import RunRow
    from pytest_drivedegrade.scoring.closed_loop import analyse_rows, check_section

    def row(route: str, ds: float, completion: float) -> RunRow:
        return RunRow(route, 0, ds, completion, "complete" if completion == 1.0 else "route_deviation", "t" + route)

    clean = [row("a", 90.0, 1.0), row("b", 80.0, 1.0), row("c", 70.0, 0.5)]
    swap = [row("a-swap", 60.0, 0.6), row("c-swap", 50.0, 0.4)]
    got = analyse_rows({"closed-clean": clean, SWAP_CELL: swap})
    cell = {c.cell: c for c in got.cells}[SWAP_CELL]
    assert cell.retention is None and cell.retention_ci is None and cell.separable_from_null is None
    assert got.command_swap == {"cell": SWAP_CELL, "routes": 2, "runs": 2, "unscored": 0,
                                "command_followed": pytest.approx(0.5), "complete_runs": 0, "ds_mean": 55.0,
                                "clean_runs": 2, "clean_completion": pytest.approx(0.75), "clean_ds_mean": 80.0}
    assert got.axes == analyse_rows({"closed-clean": clean}).axes  # no axis rests on it
    section = {**got.figures(), "verdict": got.figures()["verdict"]}
    assert check_section(section, None) == []
    section["command_swap"] = {**section["command_swap"], "command_followed": 1.0}
    assert any(p.startswith("closed_loop.command_swap.command_followed") for p in check_section(section, None))
    assert analyse_rows({"closed-clean": clean}).figures()["command_swap"] is None


def test_a_ray_actor_drives_the_swapped_route_as_this_process_does(small_world) -> None:
    """`remote.drive_one` (a Ray planner actor's job) knows the swapped routes and drives them with clean
    cameras: the run it returns is the local run, bit for bit."""
    from types import SimpleNamespace

    from pytest_drivedegrade.closedloop.cells import run_from_builtins, trace_digest
    from pytest_drivedegrade.closedloop.remote import drive_one
    from pytest_drivedegrade.closedloop.routes import load_routes

    routes = load_routes(small_world, scenarios=15, lights=0)
    swap = junction_routes(routes)
    assert [s.name for s in swap] == ["scenario-0013-braking-swap", "scenario-0014-blocked-swap"]
    context = SimpleNamespace(reader=SimpleNamespace(root=small_world))
    got = drive_one(context, WorldExpert(swap), family="command_swap", severity=0, route=swap[1].name, seed=0,
                    plan_every=5, max_steps=None, scenarios=15, lights=0)
    remote = run_from_builtins(got["run"])  # type: ignore[arg-type]
    local = run_route(WorldExpert(swap), swap[1], seed=0)
    assert (remote.route, remote.end, remote.completion, remote.ds) == (local.route, local.end, local.completion,
                                                                        local.ds)
    assert trace_digest(remote) == trace_digest(local) and remote.end == END_COMPLETE
