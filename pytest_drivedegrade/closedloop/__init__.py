"""The closed loop (SPEC section 13): the planner drives the embedded world through a degraded camera stream.

`routes` turns the world's val scenes into routes, `camera` renders a route's cameras at any ego pose,
`simulate` runs one (route, seed) through planner -> tracker -> bicycle model (`loop_io`: what the planner is
given, `judge`: collisions, off-road, the road ahead at one step), `results` holds the typed run and
cell results (Driving Score, completion, infractions, identification bounds), `expert` is the privileged
reference driver that validates the simulator, `percept` the privileged bound of a driver that perceives the few
numbers the expert's rule needs and plans with that rule.
"""

from __future__ import annotations

from .results import CellResult, Infraction, RunResult
from .routes import Route, load_routes, route_of
from .simulate import Corruption, run_cell, run_route

__all__ = ["CellResult", "Corruption", "Infraction", "Route", "RunResult", "load_routes", "route_of", "run_cell",
           "run_route"]
