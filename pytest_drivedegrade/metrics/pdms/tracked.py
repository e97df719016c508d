"""The states the PDMS scores: plans tracked as NAVSIM tracks them (`metrics.tracking`: the poses interpolated
to 10 Hz, an LQR controller steering a lagged kinematic bicycle model) from the ego's logged state at t = 0."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ...constants import HORIZON_STEPS
from ...data.frame import EgoStatus
from .. import tracking  # the module, its names read at call time: `tracking` imports this package's constants
from .constants import SCORED_POSES
from .motion import EgoStates  # and motion, so a name taken from it here would not exist yet if it came first


def initial_state(ego: EgoStatus | tracking.InitialState | npt.ArrayLike) -> tracking.InitialState:
    """The tracker's state at t = 0: the ego status's velocity, logged acceleration and yaw rate (NAVSIM's
    t = 0 state), a given `InitialState`, or a bare velocity (vx, vy) with no acceleration or yaw rate."""
    if isinstance(ego, tracking.InitialState):
        return ego
    if isinstance(ego, EgoStatus):
        return tracking.InitialState.of(ego)
    vx, vy = (float(v) for v in np.asarray(ego, dtype=np.float64).reshape(2))
    return tracking.InitialState(vx, vy)


def tracked_states(plans: np.ndarray, starts: Sequence[tracking.InitialState]) -> list[EgoStates]:
    """Plans (B, 6, 2) (or (B, 8, 2): 4 s) tracked from one start each, in one batch, as the score's `EgoStates`
    (body-frame velocity and acceleration rotated into the ego frame: zero lateral acceleration after t = 0). A
    plan's states are bit-identical whichever plans share its batch (tests/unit/test_pdms.py checks it), so a cell
    split over processes scores as one."""
    arr = np.asarray(plans, dtype=np.float64)
    arr = arr.reshape(-1, arr.shape[-2] if arr.ndim >= 2 and arr.shape[-2] in SCORED_POSES else HORIZON_STEPS, 2)
    firsts = list(starts)
    if len(firsts) != len(arr):
        raise ValueError(f"{len(firsts)} initial states for {len(arr)} plans")
    if not len(arr):
        return []
    states = tracking.track_plans(arr, firsts)
    return [states.ego_states(b) for b in range(len(states))]
