"""Reference planner: constant velocity. Extrapolates the current ego velocity for 3 s; no camera, no training.

It is the simplest floor a learned planner must beat, and a worked example of the planner contract:

    pytest --drivedegrade planners/constant_velocity.py
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest

from pytest_drivedegrade.constants import HORIZON_STEPS, STEP_SECONDS
from pytest_drivedegrade.planning import Command, EgoStatus

#: Waypoint times, seconds: 0.5, 1.0, ..., 3.0.
TIMES = STEP_SECONDS * np.arange(1, HORIZON_STEPS + 1, dtype=np.float64)


class ConstantVelocity:
    """Waypoints p(t) = v * t with v the current (vx, vy) in the ego frame. Reads no camera."""

    cameras: tuple[str, ...] = ()
    name = "constant_velocity"
    fingerprint = "constant_velocity-1"

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        return TIMES[:, None] * np.asarray(ego.velocity, dtype=np.float64)[None, :]


@pytest.fixture(scope="session")
def planner() -> ConstantVelocity:
    """The planner the suite certifies."""
    return ConstantVelocity()
