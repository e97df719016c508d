"""The PDMS-like score's constants (NAVSIM v1's, adapted to six waypoints over 3 s) and its result type.

Every threshold, weight and schedule the score uses is defined here once; `motion`, `agents`, `rules`,
`reference` and `prepared` import them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...constants import EGO_LENGTH, EGO_WIDTH, HORIZON_STEPS, STEP_SECONDS

#: Simulation step of the scored states (NAVSIM: 0.1 s) and the states from t = 0 to 3 s.
SIM_DT: float = 0.1
SUBSTEPS: int = round(STEP_SECONDS / SIM_DT)
N_STATES: int = HORIZON_STEPS * SUBSTEPS + 1
TIMES: np.ndarray = np.arange(N_STATES) * SIM_DT
#: State index of each waypoint (and of each future keyframe's agent boxes): 5, 10, .., 30.
KEY_STATES: np.ndarray = np.arange(1, HORIZON_STEPS + 1) * SUBSTEPS
#: The waypoint counts a plan may be scored at: six (3 s, the default) and NAVSIM's eight (4 s).
SCORED_POSES: tuple[int, ...] = (HORIZON_STEPS, 8)

#: NAVSIM v1 PDMScorerConfig: weights of the averaged terms and the progress threshold.
EP_WEIGHT, TTC_WEIGHT, COMFORT_WEIGHT = 5.0, 5.0, 2.0
PROGRESS_DISTANCE_THRESHOLD: float = 5.0  # m
#: Speeds at or below which the ego or an agent counts as stopped (get_collision_type, is_track_stopped) ...
STOPPED_SPEED: float = 5e-2  # m/s
#: ... and below which a state is not projected for TTC (PDMScorerConfig.stopped_speed_threshold).
TTC_STOPPED_SPEED: float = 5e-3  # m/s
#: TTC projections: NAVSIM's future_time_idcs 0, 3, 6, 9 at 0.1 s.
TTC_PROJECTIONS_S: tuple[float, ...] = (0.0, 0.3, 0.6, 0.9)
#: The TTC checks in NAVSIM's order: (state index, projection seconds, waypoint index) for every projection
#: from a 10 Hz state that lands on a waypoint time (where agents are annotated).
def ttc_schedule(poses: int = HORIZON_STEPS) -> tuple[tuple[int, float, int], ...]:
    """`TTC_SCHEDULE` of a plan of `poses` waypoints (its states up to poses x 0.5 s)."""
    return tuple(sorted((int(i - round(d / SIM_DT)), d, k) for k, i in enumerate(key_states(poses).tolist())
                        for d in TTC_PROJECTIONS_S if i - round(d / SIM_DT) >= 0))


def key_states(poses: int = HORIZON_STEPS) -> np.ndarray:
    """`KEY_STATES` of a plan of `poses` waypoints: 5, 10, .., 5 x poses."""
    return np.arange(1, poses + 1) * SUBSTEPS


def state_times(poses: int = HORIZON_STEPS) -> np.ndarray:
    """`TIMES` of a plan of `poses` waypoints: 0 .. poses x 0.5 s at SIM_DT (`poses` x SUBSTEPS + 1 states)."""
    return np.arange(poses * SUBSTEPS + 1) * SIM_DT


TTC_SCHEDULE: tuple[tuple[int, float, int], ...] = ttc_schedule()
#: nuPlan's is_agent_ahead / is_agent_behind angle tolerances (degrees off the ego heading).
AHEAD_DEG, BEHIND_DEG = 30.0, 150.0
#: Coarse categories that are static objects (nuScenes movable_object.* and static_object.* read as "other"):
#: an at-fault collision with one scores 1/2, and they never move.
STATIC_CATEGORIES: tuple[str, ...] = ("other",)
#: NAVSIM pdm_comfort_metrics bounds, (min, max), strict: name -> bounds.
COMFORT_BOUNDS: dict[str, tuple[float, float]] = {
    "lon_accel": (-4.05, 2.40),  # m/s^2
    "lat_accel": (-4.89, 4.89),  # m/s^2
    "jerk": (-8.37, 8.37),  # m/s^3, of the acceleration magnitude
    "lon_jerk": (-4.13, 4.13),  # m/s^3
    "yaw_accel": (-1.93, 1.93),  # rad/s^2
    "yaw_rate": (-0.95, 0.95),  # rad/s
}
#: Without lanes, "in multiple lanes" is read as: a corner of the ego box lies farther than half a lane from
#: the expert's path (the expert drives in its lane, the lane is 3.5 m wide).
HALF_LANE_M: float = 1.75
#: Below this speed (m/s) a state keeps the previous heading: the direction of a near-zero spline velocity
#: is noise (the bicycle model NAVSIM simulates does not turn on the spot either).
HEADING_MIN_SPEED: float = 0.5
#: Agents matched between consecutive keyframes (same category, sizes within SIZE_MATCH_M) move at most this.
MAX_AGENT_SPEED: float = 40.0  # m/s
SIZE_MATCH_M: float = 0.05

#: The ego boxes a run can score with (`--drivedegrade-ego-box`; length along the heading, width, m): the nuScenes
#: ego (a Renault Zoe, the default) and NAVSIM's (nuPlan's `get_pacifica_parameters`: front 4.049 + rear 1.127 m
#: long, 2.297 m wide), each centred on the tracked point (NAVSIM centres its 1.461 m ahead of the rear axle).
EGO_BOXES: dict[str, tuple[float, float]] = {"nuscenes": (EGO_LENGTH, EGO_WIDTH), "pacifica": (5.176, 2.297)}
#: The ego box (length along the heading, width), centred on the waypoint ...
EGO_SIZE = np.array([EGO_LENGTH, EGO_WIDTH])
#: ... its front edge, a box of no length across the ego's nose (a front contact is the ego's fault) ...
BUMPER_SIZE = np.array([0.0, EGO_WIDTH])
#: ... and half its diagonal: boxes whose centres lie farther apart than their half diagonals (plus a margin
#: above the touch tolerance) cannot touch, so the prepared frame does not test those pairs.
EGO_RADIUS = 0.5 * math.hypot(EGO_LENGTH, EGO_WIDTH)
FAR_MARGIN_M = 0.1
#: The expert's path continues straight this far beyond its last point (m).
EXTEND_M = 1000.0
#: The map around the ego the prepared frame keeps: polygons whose bounding box meets this window (m, each side).
LOCAL_MAP_M = 200.0

#: A drivable-area query: points (K, 2) in the map's frame -> (K,) bool.
DrivableQuery = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class PDMSResult:
    """One frame's PDMS and sub-scores; `map_scored` is False where no drivable area was given (dac fixed at 1).
    `progress_m` and `expert_progress_m` are the raw distances along the expert's path."""

    nc: float
    dac: float
    ttc: float
    ep: float
    comfort: float
    pdms: float
    map_scored: bool
    progress_m: float
    expert_progress_m: float
