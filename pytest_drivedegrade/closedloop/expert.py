"""The world's own expert as a closed-loop driver (privileged): at each route step it plans the logged expert's
future (`data.world.expert.drive`'s arc lengths at +0.5 .. +3 s along the route's lane) from the simulated pose,
and is driven through the same tracker as any planner. It validates the simulator: it must score DS >= 95."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..constants import HORIZON_STEPS
from ..data.context import FrameContext
from ..data.frame import Command, EgoStatus
from .loop_io import to_ego
from .routes import Route
from .simulate import PLAN_EVERY


def log_ahead(route: Route, t: int) -> np.ndarray:
    """The logged ego's arc lengths on the route's lane at +0.5 .. +3 s from sim step `t` (past the log's end,
    extrapolated at its last speed)."""
    log = route.scene.ego
    steps = t + PLAN_EVERY * np.arange(1, HORIZON_STEPS + 1)
    last = len(log.s) - 1
    return np.where(steps <= last, log.s[np.minimum(steps, last)], log.s[last] + log.speed[last] * (steps - last) * 0.1)


class WorldExpert:
    """Reads no camera; knows the routes (by name) and plans from the route's log at the context's step."""

    cameras: tuple[str, ...] = ()
    name = "world_expert"

    def __init__(self, routes: Sequence[Route]) -> None:
        self._routes = {r.name: r for r in routes}
        self._route: Route | None = None

    def reset(self, route: str) -> None:
        self._route = self._routes[route]

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command,
                context: FrameContext | None = None) -> np.ndarray:
        if self._route is None or context is None:
            raise RuntimeError("the world expert needs reset(route) and the frame context")
        route = self._route
        x, y, _ = route.lane.at(log_ahead(route, route.start_step + PLAN_EVERY * context.index))
        pose = (float(context.ego2global[0, 3]), float(context.ego2global[1, 3]),
                float(np.arctan2(context.ego2global[1, 0], context.ego2global[0, 0])))
        return to_ego(np.stack([x, y], axis=1), pose)
