"""The command swap in the closed loop (spec 5, issue 40): at a junction route the route's command is swapped, the
route changing with it, and route completion measures whether the planner went where it was told.

A route whose road turns at a junction (`data.world.roads.build_roads`: left or right, with a road straight on
beyond the square) that its logged ego enters is a junction route. Its swapped route keeps everything but the
lane: up to the junction square the route's own lane, then straight on through the square and along the road
beyond it, at the same lateral offset (the lane the ego drove). The navigation command the planner is given is
the route's (`loop_io.route_command`), so at the junction it now says STRAIGHT where the logged route said LEFT or
RIGHT; progress, deviation and completion are measured along the swapped lane. The route is as long as the
logged drive, or as the swapped lane allows from the start when that is shorter.

The privileged expert given the swapped route (`expert.WorldExpert` over the swapped routes: the logged speeds
along the swapped lane) completes it; a planner that ignores the command and turns where the log turned leaves
the swapped lane at the junction and the run ends deviated, its completion the share driven before it.
Only junction routes whose logged lane gets farther than the route deviation (`leaderboard.DEVIATION_M`) from
the swapped lane are driven (`junction_routes`): on the others the logged drive ends soon after the junction and
a planner that ignores the command completes the swapped route or nearly. `swap_cell` runs the swapped routes
as one closed cell, ``closed-command_swap``; the plugin drives the same cell (`plugin.closed.drive`,
``--drivedegrade-closed-cells ...,command_swap``) and `closedloop.analysis.swap_figures` reads it.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import replace

import numpy as np

from ..data.world.expert import KEY_EVERY
from ..data.world.roads import Path as LanePath
from ..data.world.roads import in_junction
from ..data.world.scene import KEYFRAMES
from ..planning import Planner
from .cells import SWAP, closed_id
from .leaderboard import DEVIATION_M
from .results import CellResult
from .routes import Route
from .simulate import Rules, Timings, run_route

#: The closed cell of swapped routes.
SWAP_CELL = closed_id(SWAP, 0)
#: The road straight on beyond a turning junction reaches this far (m) from the junction's centre
#: (`roads.build_roads`' ``ahead`` road).
AHEAD_M = 90.0
#: Metres of the swapped lane kept clear of its end (the tracker reads a little beyond the route's end).
END_MARGIN_M = 10.0
_RULES = Rules()


def _lane_offset(route: Route) -> float:
    """The route lane's signed lateral offset (m, left positive) from the road's centreline."""
    _, d = route.scene.net.route.center.project(route.scene.lane.xy[:1])
    return float(d[0])


def swapped_lane(route: Route) -> LanePath | None:
    """The route's lane with its turn at the junction replaced by straight on (None: no turning junction)."""
    net = route.scene.net
    if not net.junctions or net.junctions[0].turn == "straight":
        return None
    j = net.junctions[0]
    centre = net.route.center
    before = centre.xy[centre.s <= j.s_route - j.half]
    heading = np.array([np.cos(j.heading), np.sin(j.heading)])
    if not len(before):
        return None
    u0 = float((before[-1] - j.center) @ heading)
    t = np.arange(u0, AHEAD_M + 1e-9, 0.5)[1:]
    straight = j.center + t[:, None] * heading
    return LanePath.from_points(np.concatenate([before, straight])).offset(_lane_offset(route))


def swapped_route(route: Route) -> Route | None:
    """The junction route's swapped route (named ``<route>-swap``), or None when `route` is not a junction route:
    no junction where the road turns, or the logged ego never enters it."""
    lane = swapped_lane(route)
    if lane is None:
        return None
    ego = route.scene.ego
    if not in_junction(route.scene.net, ego.xy[route.start_step:(KEYFRAMES - 1) * KEY_EVERY + 1]).any():
        return None
    start_s = float(lane.project(ego.xy[route.start_step:route.start_step + 1])[0][0])
    length = min(route.length, lane.length - start_s - END_MARGIN_M)
    return replace(route, name=f"{route.name}-swap", scene=replace(route.scene, lane=lane), start_s=start_s,
                   length=float(length))


def parting_m(route: Route, swap: Route) -> float:
    """How far (m) the route's logged lane gets from its swapped lane along the swapped route (0.5 m steps):
    where a planner that turns where the log turned ends up, at most, measured from where it was told to go."""
    s = np.arange(swap.start_s, swap.start_s + swap.length + 1e-9, 0.5)
    x, y, _ = swap.lane.at(s)
    _, d = route.lane.project(np.stack([x, y], axis=1))
    return float(np.abs(d).max())


def junction_routes(routes: Sequence[Route]) -> list[Route]:
    """The swapped routes of the junction routes among `routes`, in their order: those whose logged lane parts
    from the swapped lane by more than the leaderboard's route deviation (`DEVIATION_M`) before the route ends,
    so that a planner that turns where the log turned ends deviated. A route whose logged drive ends soon after
    the junction (its lanes a few metres apart by then) would score such a planner complete: it cannot tell
    whether the command was followed, and is left out."""
    out = []
    for route in routes:
        swap = swapped_route(route)
        if swap is not None and parting_m(route, swap) > DEVIATION_M:
            out.append(swap)
    return out


def swap_cell(planner: Planner, routes: Sequence[Route], seeds: tuple[int, ...] = (0,),
              timings: Timings | None = None, *, agents: str = "log", pool: Executor | None = None,
              rules: Rules = _RULES) -> CellResult:
    """The ``closed-command_swap`` cell: every junction route of `routes`, swapped, under every seed, clean
    cameras (route-major, as `simulate.run_cell`)."""
    runs = [run_route(planner, route, seed=seed, timings=timings, agents=agents, pool=pool, rules=rules)
            for route in junction_routes(routes) for seed in seeds]
    return CellResult.of(SWAP_CELL, runs)


__all__ = ["SWAP_CELL", "junction_routes", "parting_m", "swap_cell", "swapped_lane", "swapped_route"]
