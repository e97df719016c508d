"""One closed-loop run in a Ray planner actor (`rayactor.PlannerActor.job`): the routes built once per actor,
the run returned as builtins (`cells.run_to_builtins`) with its seconds, so the controller's record is the one a
local run writes, bit for bit."""

from __future__ import annotations

from ..planning import Planner
from ..run import RunContext
from .cells import SWAP, run_to_builtins
from .routes import LIGHT_ROUTES, SCENARIO_ROUTES, Route, load_routes
from .simulate import PLAN_TIMEOUT_S, Corruption, Rules, Timings, run_route

#: The routes of each data root this actor drives (one in practice), built on its first run.
_ROUTES: dict[tuple[str, int, int], dict[str, Route]] = {}


def drive_one(context: RunContext, planner: Planner, *, family: str, severity: int, route: str, seed: int,
              plan_every: int, max_steps: int | None, agents: str = "log", collisions: str = "all",
              timeout: float = PLAN_TIMEOUT_S, scenarios: int = SCENARIO_ROUTES, lights: int = LIGHT_ROUTES,
              ) -> dict[str, object]:
    """Run (route, seed) of a cell with this actor's planner: {"run": builtins, "seconds": {...}}. The command
    swap's routes (`swap.junction_routes`, named ``<route>-swap``) are among the actor's routes, driven with clean
    cameras."""
    from .swap import junction_routes

    root = (str(context.reader.root), scenarios, lights)
    if root not in _ROUTES:
        routes = load_routes(context.reader.root, scenarios, lights=lights)
        _ROUTES[root] = {r.name: r for r in (*routes, *junction_routes(routes))}
    timings = Timings()
    corruption = Corruption() if family == SWAP else Corruption(family, severity)
    result = run_route(planner, _ROUTES[root][route], corruption, seed, timings,
                       plan_every=plan_every, max_steps=max_steps, agents=agents, rules=Rules(collisions, timeout))
    return {"run": run_to_builtins(result), "seconds": {"render": timings.render, "plan": timings.plan,
                                                         "track": timings.track, "score": timings.score}}
