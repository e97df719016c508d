"""PDMS-like score (spec 3): NAVSIM v1's PDM score of one plan, adapted to six waypoints over 3 s.

Pure numpy functions. A plan and the expert (ground-truth) trajectory are ``(6, 2)`` waypoints at
t = 0.5 .. 3.0 s in the current ego frame (x forward, y left, metres); the ego sits at the origin at t = 0 with
heading 0 and its current velocity. Agents are one ``AgentBoxes`` per waypoint time, in the same frame.

Per frame (NAVSIM v1, ``PDMScorer`` and ``pdm_score``; the adaptations are listed in spec/README.md,
"PDMS-like score (spec 3)")::

    pdms = nc * dac * (5 * ep + 5 * ttc + 2 * comfort) / 12

- ``nc``, no at-fault collisions, in {0, 1/2, 1}: the ego box at each waypoint time against the agent boxes;
  a collision is the ego's fault when the agent stands still (a static object always does) or the ego's
  front bumper hits it, or it is a side contact while the ego is astray (off the drivable area, or a corner
  more than half a lane from the expert's path: NAVSIM's "in multiple lanes" without lanes); not when the ego
  stands still or the agent is behind it (> 150 degrees off its heading). 0 for an at-fault collision with a
  vehicle, pedestrian or cyclist, 1/2 with a static object (category ``other``).
- ``dac``, drivable area compliance, in {0, 1}: 0 when a corner of the ego box leaves the drivable area at
  any 10 Hz state from 0 to 3 s. Without a map: 1, and the result says the map was not scored.
- ``ttc``, time to collision within bound, in {0, 1}: 0 when the ego box, moved on at constant velocity for
  0, 0.3, 0.6 or 0.9 s from some 10 Hz state, meets an agent box at that (annotated) time and the agent is
  ahead (< 30 degrees off the heading), or the ego is astray and the agent not behind.
- ``ep``, ego progress, in [0, 1]: distance made along the expert's path (the polyline through the origin and
  its waypoints, continued straight on; the end point's projection, at least 0), times ``nc * dac``, over the
  largest such value of the plan and the expert; when that largest value is at most 5 m, 1 for a plan with
  ``nc * dac > 0`` (else 0).
- ``comfort`` in {0, 1}: the 10 Hz states' longitudinal and lateral acceleration, jerk, longitudinal jerk, yaw
  rate and yaw acceleration, filtered as NAVSIM does (Savitzky-Golay), stay within NAVSIM's bounds.

The plan is interpolated to 10 Hz by a cubic spline through the origin and the six waypoints, starting with
the ego's current velocity and ending with a parabolic run-out (so constant-velocity and constant-acceleration
plans come out exact).

Modules, by job: `constants` (thresholds, weights, the TTC schedule, `PDMSResult`), `motion` (the 10 Hz states,
the ego box on the road, the expert's path and progress, comfort), `agents` (tracks across keyframes, box
contacts), `rules` (the at-fault and TTC decisions, progress and the weighted sum, written once), `reference`
(`pdm_score`: contacts found literally, the tests' oracle), `local_map` and `prepared` (`PreparedFrame`: one frame
prepared once, contacts found vectorised, judged by the same rules).
"""


from .agents import agent_steps, agent_tracks, first_seen, hits
from .constants import (
    AHEAD_DEG,
    BEHIND_DEG,
    COMFORT_BOUNDS,
    COMFORT_WEIGHT,
    EP_WEIGHT,
    HALF_LANE_M,
    HEADING_MIN_SPEED,
    KEY_STATES,
    LOCAL_MAP_M,
    MAX_AGENT_SPEED,
    N_STATES,
    PROGRESS_DISTANCE_THRESHOLD,
    SIM_DT,
    SIZE_MATCH_M,
    STATIC_CATEGORIES,
    STOPPED_SPEED,
    SUBSTEPS,
    TIMES,
    TTC_PROJECTIONS_S,
    TTC_SCHEDULE,
    TTC_STOPPED_SPEED,
    TTC_WEIGHT,
    DrivableQuery,
    PDMSResult,
)
from .local_map import LocalDrivable
from .motion import (
    EgoPose,
    EgoStates,
    box_corners,
    comfort_terms,
    expert_path,
    interpolate,
    is_comfortable,
    off_road,
    out_of_lane,
    path_distance,
    progress_along,
    savgol,
    waypoints,
)
from .prepared import PreparedFrame, score_plans, tracked_experts
from .reference import (
    collisions,
    frame_pdms,
    no_at_fault_collisions,
    pdm_score,
    projections,
    time_to_collision_within_bound,
)
from .rules import (
    Contact,
    at_fault,
    collision_score,
    ego_progress,
    pdms_result,
    relative_angle,
    ttc_fails,
    ttc_score,
)
from .tracked import initial_state, tracked_states

__all__ = [
    "AHEAD_DEG", "BEHIND_DEG", "COMFORT_BOUNDS", "COMFORT_WEIGHT", "EP_WEIGHT", "HALF_LANE_M", "HEADING_MIN_SPEED",
    "KEY_STATES", "LOCAL_MAP_M", "MAX_AGENT_SPEED", "N_STATES", "PROGRESS_DISTANCE_THRESHOLD", "SIM_DT",
    "SIZE_MATCH_M", "STATIC_CATEGORIES", "STOPPED_SPEED", "SUBSTEPS", "TIMES", "TTC_PROJECTIONS_S", "TTC_SCHEDULE",
    "TTC_STOPPED_SPEED", "TTC_WEIGHT", "Contact", "DrivableQuery", "EgoPose", "EgoStates", "LocalDrivable",
    "PDMSResult", "PreparedFrame", "agent_steps", "agent_tracks", "at_fault", "box_corners", "collision_score",
    "collisions", "comfort_terms", "ego_progress", "expert_path", "first_seen", "frame_pdms", "hits", "initial_state",
    "interpolate", "is_comfortable", "no_at_fault_collisions", "off_road", "out_of_lane", "path_distance",
    "pdm_score", "pdms_result", "progress_along", "projections", "relative_angle", "savgol", "score_plans",
    "time_to_collision_within_bound", "tracked_experts", "tracked_states", "ttc_fails", "ttc_score", "waypoints",
]
