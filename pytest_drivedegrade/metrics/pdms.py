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
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Collection, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..constants import EGO_LENGTH, EGO_WIDTH, HORIZON_STEPS, STEP_SECONDS
from ..data.frame import AgentBoxes, Frame
from .trajectory import _overlap_pairs

#: Simulation step of the scored states (NAVSIM: 0.1 s) and the states from t = 0 to 3 s.
SIM_DT: float = 0.1
SUBSTEPS: int = round(STEP_SECONDS / SIM_DT)
N_STATES: int = HORIZON_STEPS * SUBSTEPS + 1
TIMES: np.ndarray = np.arange(N_STATES) * SIM_DT
#: State index of each waypoint (and of each future keyframe's agent boxes): 5, 10, .., 30.
KEY_STATES: np.ndarray = np.arange(1, HORIZON_STEPS + 1) * SUBSTEPS

#: NAVSIM v1 PDMScorerConfig: weights of the averaged terms and the progress threshold.
EP_WEIGHT, TTC_WEIGHT, COMFORT_WEIGHT = 5.0, 5.0, 2.0
PROGRESS_DISTANCE_THRESHOLD: float = 5.0  # m
#: Speeds at or below which the ego or an agent counts as stopped (get_collision_type, is_track_stopped) ...
STOPPED_SPEED: float = 5e-2  # m/s
#: ... and below which a state is not projected for TTC (PDMScorerConfig.stopped_speed_threshold).
TTC_STOPPED_SPEED: float = 5e-3  # m/s
#: TTC projections: NAVSIM's future_time_idcs 0, 3, 6, 9 at 0.1 s.
TTC_PROJECTIONS_S: tuple[float, ...] = (0.0, 0.3, 0.6, 0.9)
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

_EGO_SIZE = np.array([EGO_LENGTH, EGO_WIDTH])
_BUMPER_SIZE = np.array([0.0, EGO_WIDTH])  # the front edge: a box of no length across the ego's nose
_EXTEND_M = 1000.0  # the expert's path continues straight beyond its last point

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

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class EgoStates:
    """A trajectory at 10 Hz from t = 0 to 3 s (N_STATES states), in the current ego frame."""

    xy: np.ndarray  # (N, 2) m, box centre
    velocity: np.ndarray  # (N, 2) m/s
    accel: np.ndarray  # (N, 2) m/s^2
    heading: np.ndarray  # (N,) rad, unwrapped
    speed: np.ndarray  # (N,) m/s

    @property
    def lon_accel(self) -> np.ndarray:
        return self.accel[:, 0] * np.cos(self.heading) + self.accel[:, 1] * np.sin(self.heading)

    @property
    def lat_accel(self) -> np.ndarray:
        return -self.accel[:, 0] * np.sin(self.heading) + self.accel[:, 1] * np.cos(self.heading)


def _waypoints(traj: Any, name: str) -> np.ndarray:
    arr = np.asarray(traj, dtype=np.float64)
    if arr.shape != (HORIZON_STEPS, 2):
        raise ValueError(f"{name} must have shape ({HORIZON_STEPS}, 2), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} has non-finite waypoints")
    return arr


def _wrap(angle: npt.ArrayLike) -> np.ndarray:
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def interpolate(waypoints: Any, velocity: Any = (0.0, 0.0)) -> EgoStates:
    """The 10 Hz states of six waypoints: a cubic spline through the origin (t = 0) and the waypoints with the
    given start velocity and a parabolic run-out (last two intervals share their acceleration); headings
    follow the velocity (held below HEADING_MIN_SPEED; a velocity more than 90 degrees off the heading is
    driving backwards)."""
    pts = np.vstack([np.zeros((1, 2)), _waypoints(waypoints, "trajectory")])
    v0 = np.asarray(velocity, dtype=np.float64).reshape(2)
    h, n = STEP_SECONDS, len(pts)
    a = np.zeros((n, n))
    rhs = np.zeros((n, 2))
    a[0, :2] = 2.0, 1.0
    rhs[0] = 6.0 / h * ((pts[1] - pts[0]) / h - v0)
    for k in range(1, n - 1):
        a[k, k - 1:k + 2] = 1.0, 4.0, 1.0
        rhs[k] = 6.0 / h**2 * (pts[k + 1] - 2.0 * pts[k] + pts[k - 1])
    a[-1, -2:] = -1.0, 1.0
    m = np.linalg.solve(a, rhs)  # second derivatives at the knots
    seg = np.minimum((TIMES / h + 1e-9).astype(int), n - 2)
    u = (TIMES - seg * h)[:, None]
    w = h - u
    m0, m1, p0, p1 = m[seg], m[seg + 1], pts[seg], pts[seg + 1]
    c0, c1 = p0 / h - m0 * h / 6.0, p1 / h - m1 * h / 6.0
    xy = m0 * w**3 / (6 * h) + m1 * u**3 / (6 * h) + c0 * w + c1 * u
    vel = -m0 * w**2 / (2 * h) + m1 * u**2 / (2 * h) - c0 + c1
    acc = m0 * w / h + m1 * u / h
    speed = np.hypot(vel[:, 0], vel[:, 1])
    headings = []
    current = 0.0
    # plain floats: a 31-step recurrence (the heading follows the velocity's direction, modulo driving backwards)
    for angle, fast in zip(np.arctan2(vel[:, 1], vel[:, 0]).tolist(), (speed >= HEADING_MIN_SPEED).tolist()):
        if fast:
            turn = (angle - current + math.pi) % (2 * math.pi) - math.pi
            if abs(turn) > math.pi / 2:  # moving backwards: the heading is opposite the velocity
                turn = (turn - math.pi + math.pi) % (2 * math.pi) - math.pi
            current += turn
        headings.append(current)
    return EgoStates(xy, vel, acc, np.array(headings), speed)


def box_corners(xy: np.ndarray, heading: np.ndarray, size: np.ndarray = _EGO_SIZE) -> np.ndarray:
    """Corners (N, 4, 2) of boxes (length along heading, width) centred at xy (N, 2): front-left, rear-left,
    rear-right, front-right."""
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    lx = np.array([0.5, -0.5, -0.5, 0.5])[None] * size[0]
    ly = np.array([0.5, 0.5, -0.5, -0.5])[None] * size[1]
    return np.stack([xy[:, 0:1] + c * lx - s * ly, xy[:, 1:2] + s * lx + c * ly], axis=-1)


def off_road(states: EgoStates, drivable: DrivableQuery | None, ego_pose: Any = None) -> np.ndarray:
    """Per state (N,) bool: a corner of the ego box lies outside the drivable area. `drivable` answers for
    points (K, 2) in the map's frame; `ego_pose` (x, y, yaw) maps ego-frame points there (None: the query takes
    ego-frame points). No query: nothing is off the road."""
    if drivable is None:
        return np.zeros(N_STATES, dtype=bool)
    pts = box_corners(states.xy, states.heading).reshape(-1, 2)
    if ego_pose is not None:
        x, y, yaw = (float(v) for v in ego_pose)
        c, s = np.cos(yaw), np.sin(yaw)
        pts = np.stack([x + c * pts[:, 0] - s * pts[:, 1], y + s * pts[:, 0] + c * pts[:, 1]], axis=1)
    inside = np.asarray(drivable(pts), dtype=bool).reshape(N_STATES, 4)
    return np.logical_not(inside.all(axis=1))


def path_distance(path: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Distance of points (K, 2) to a polyline (M, 2), its first and last segments continued straight."""
    a, b = path[:-1], path[1:]
    ab = b - a
    t = ((pts[:, None, :] - a[None]) * ab[None]).sum(-1) / (ab**2).sum(1)[None]
    lo, hi = np.zeros(len(a)), np.ones(len(a))
    lo[0], hi[-1] = -np.inf, np.inf
    t = np.clip(t, lo[None], hi[None])
    return np.linalg.norm(a[None] + t[..., None] * ab[None] - pts[:, None, :], axis=-1).min(1)


def out_of_lane(states: EgoStates, path: np.ndarray) -> np.ndarray:
    """Per state (N,) bool: a corner of the ego box lies more than HALF_LANE_M from the expert's path, the
    stand-in for NAVSIM's "in multiple lanes" where the map has no lanes."""
    corners = box_corners(states.xy, states.heading).reshape(-1, 2)
    far = path_distance(path, corners) > HALF_LANE_M
    return np.asarray(far.reshape(N_STATES, 4).any(axis=1), dtype=bool)


# -- agents ----------------------------------------------------------------------------------------------------

def _steps(agents: Sequence[AgentBoxes]) -> list[AgentBoxes]:
    steps = list(agents)[:HORIZON_STEPS]
    return steps + [AgentBoxes.empty()] * (HORIZON_STEPS - len(steps))


def agent_tracks(agents: Sequence[AgentBoxes]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Identities and velocities of the boxes of consecutive keyframes (AgentBoxes carry no instance ids).

    Boxes of neighbouring keyframes are the same agent when category and size agree (within SIZE_MATCH_M: an
    annotated instance keeps its size) and the move fits MAX_AGENT_SPEED; pairs are taken nearest first.
    Returns per step the track id of each box (N,) and its velocity (N, 2) m/s: the central difference where
    the agent is seen at both neighbouring keyframes, else the one-sided one, NaN when seen only once.
    """
    steps = _steps(agents)
    ids: list[np.ndarray] = []
    next_id = 0
    for k, boxes in enumerate(steps):
        cur = np.full(len(boxes), -1, dtype=np.int64)
        if k and len(boxes) and len(steps[k - 1]):
            prev = steps[k - 1]
            cat_p, cat_c = np.asarray(prev.category, dtype=object), np.asarray(boxes.category, dtype=object)
            dist = np.linalg.norm(np.asarray(prev.center)[:, None] - np.asarray(boxes.center)[None], axis=-1)
            size_gap = np.abs(np.asarray(prev.size)[:, None] - np.asarray(boxes.size)[None]).max(-1)
            ok = (cat_p[:, None] == cat_c[None]) & (size_gap <= SIZE_MATCH_M) & (dist <= MAX_AGENT_SPEED * STEP_SECONDS)
            used_p = np.zeros(len(prev), dtype=bool)
            pi, ci = np.nonzero(ok)
            for j in np.argsort(dist[pi, ci], kind="stable"):
                p, c = pi[j], ci[j]
                if not used_p[p] and cur[c] < 0:
                    used_p[p], cur[c] = True, ids[k - 1][p]
        fresh = cur < 0
        cur[fresh] = np.arange(next_id, next_id + int(fresh.sum()))
        next_id += int(fresh.sum())
        ids.append(cur)
    where = [{int(t): i for i, t in enumerate(step_ids)} for step_ids in ids]
    velocities = []
    for k, boxes in enumerate(steps):
        vel = np.full((len(boxes), 2), np.nan)
        centers = np.asarray(boxes.center, dtype=np.float64).reshape(-1, 2)
        for i, t in enumerate(ids[k]):
            before = where[k - 1].get(int(t)) if k else None
            after = where[k + 1].get(int(t)) if k + 1 < len(steps) else None
            a = np.asarray(steps[k - 1].center, dtype=np.float64)[before] if before is not None else centers[i]
            b = np.asarray(steps[k + 1].center, dtype=np.float64)[after] if after is not None else centers[i]
            span = STEP_SECONDS * ((before is not None) + (after is not None))
            if span:
                vel[i] = (b - a) / span
        velocities.append(vel)
    return ids, velocities


def _hits(center: np.ndarray, heading: float, boxes: AgentBoxes, size: np.ndarray = _EGO_SIZE) -> np.ndarray:
    """Indices of the agent boxes an ego-sized box (or `size`) at (center, heading) overlaps or touches."""
    n = len(boxes)
    if not n:
        return np.zeros(0, dtype=np.int64)
    centers = np.asarray(boxes.center, dtype=np.float64).reshape(-1, 2)
    sizes = np.asarray(boxes.size, dtype=np.float64).reshape(-1, 2)
    over = _overlap_pairs(np.broadcast_to(center, (n, 2)), np.broadcast_to(size, (n, 2)), np.full(n, heading),
                          centers, sizes, np.asarray(boxes.yaw, dtype=np.float64).reshape(-1))
    return np.flatnonzero(over)


def _relative_angle(xy: np.ndarray, heading: float, other: np.ndarray) -> float:
    """Angle (rad, 0..pi) between the ego heading and the direction from the ego to `other` (0 when they
    coincide), as nuPlan's get_agent_relative_angle."""
    d = np.asarray(other, dtype=np.float64) - xy
    norm = float(np.hypot(d[0], d[1]))
    if norm < 1e-9:
        return 0.0
    return float(np.arccos(np.clip((d[0] * np.cos(heading) + d[1] * np.sin(heading)) / norm, -1.0, 1.0)))


def expert_contacts(expert: EgoStates, agents: Sequence[AgentBoxes], ids: list[np.ndarray]) -> set[int]:
    """Tracks the expert's own box touches at some waypoint time: annotation artefacts (or the expert's own
    contacts), ignored for every plan, as NAVSIM ignores tracks that collide with the ego at the start."""
    steps = _steps(agents)
    out: set[int] = set()
    for k, i in enumerate(KEY_STATES):
        out.update(int(ids[k][j]) for j in _hits(expert.xy[i], float(expert.heading[i]), steps[k]))
    return out


def no_at_fault_collisions(states: EgoStates, agents: Sequence[AgentBoxes], ids: list[np.ndarray],
                           velocities: list[np.ndarray], astray: np.ndarray, ignore: Collection[int] = (),
                           static_categories: Sequence[str] = STATIC_CATEGORIES) -> float:
    """NC in {0, 0.5, 1}: NAVSIM's collision classification at each waypoint time (where agents are annotated).

    In time order, per colliding track not ignored: ego stopped -> not at fault; agent stopped (or static) ->
    at fault; agent behind -> not at fault; the ego's front edge touches it -> at fault; else (a side contact)
    at fault only while the ego is `astray` (off the drivable area or out of its lane, per state). A
    not-at-fault track is ignored from then on.
    """
    steps = _steps(agents)
    ignored = set(ignore)
    score = 1.0
    for k, i in enumerate(KEY_STATES):
        xy, heading = states.xy[i], float(states.heading[i])
        boxes = steps[k]
        for j in _hits(xy, heading, boxes):
            track = int(ids[k][j])
            if track in ignored:
                continue
            static = boxes.category[j] in static_categories
            agent_speed = float(np.hypot(*velocities[k][j]))  # NaN when unknown: moving
            centre = np.asarray(boxes.center, dtype=np.float64)[j]
            if states.speed[i] <= STOPPED_SPEED:
                at_fault = False  # the ego stands still
            elif static or agent_speed <= STOPPED_SPEED:
                at_fault = True  # it hits a standing agent
            elif _relative_angle(xy, heading, centre) > np.deg2rad(BEHIND_DEG):
                at_fault = False  # hit from behind
            else:
                nose = xy + 0.5 * EGO_LENGTH * np.array([np.cos(heading), np.sin(heading)])
                single = AgentBoxes(centre[None], np.asarray(boxes.size, dtype=np.float64)[j][None],
                                    np.asarray(boxes.yaw, dtype=np.float64)[j:j + 1], (boxes.category[j],))
                front = len(_hits(nose, heading, single, _BUMPER_SIZE)) > 0
                at_fault = front or bool(astray[i])  # a side contact is the ego's fault only when astray
            if at_fault:
                score = min(score, 0.5 if static else 0.0)
            else:
                ignored.add(track)
    return score


def time_to_collision_within_bound(states: EgoStates, agents: Sequence[AgentBoxes], ids: list[np.ndarray],
                                   astray: np.ndarray, ignore: Collection[int] = ()) -> float:
    """TTC in {0, 1}: for every 10 Hz state and projection d in TTC_PROJECTIONS_S that lands on a waypoint time,
    the ego box moved on at the state's speed along its heading for d seconds, against that time's agents.
    An agent ahead (< AHEAD_DEG) fails it; so does one not behind (<= BEHIND_DEG) while the ego is `astray`
    (off the drivable area or out of its lane); any other track is ignored from then on. States slower than
    TTC_STOPPED_SPEED are skipped."""
    steps = _steps(agents)
    pairs = sorted((int(i - round(d / SIM_DT)), d, k) for k, i in enumerate(KEY_STATES) for d in TTC_PROJECTIONS_S
                   if i - round(d / SIM_DT) >= 0)
    ignored = set(ignore)
    for i, d, k in pairs:
        speed = float(states.speed[i])
        if speed < TTC_STOPPED_SPEED:
            continue
        xy, heading = states.xy[i], float(states.heading[i])
        moved = xy + speed * d * np.array([np.cos(heading), np.sin(heading)])
        boxes = steps[k]
        for j in _hits(moved, heading, boxes):
            track = int(ids[k][j])
            if track in ignored:
                continue
            angle = _relative_angle(xy, heading, np.asarray(boxes.center, dtype=np.float64)[j])
            if angle < np.deg2rad(AHEAD_DEG) or (astray[i] and angle <= np.deg2rad(BEHIND_DEG)):
                return 0.0
            ignored.add(track)
    return 1.0


# -- comfort ---------------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=32)
def _savgol_operator(n: int, window: int, poly: int, deriv: int, delta: float) -> np.ndarray:
    """(n, n) matrix M with M @ y == scipy.signal.savgol_filter(y, window, poly, deriv, delta) (mode 'interp'):
    least-squares polynomials over sliding windows (for an even window, evaluated half a sample right of the
    window's middle, as scipy does), the first and last window's polynomial for the samples near the ends."""
    window = min(window, n)
    half, even = window // 2, window % 2 == 0
    op = np.zeros((n, n))

    def row(start: int, at: float) -> np.ndarray:
        x = np.arange(window, dtype=np.float64) + start - at
        return np.linalg.pinv(np.vander(x, poly + 1, increasing=True))[deriv] * math.factorial(deriv) / delta**deriv

    for i in range(n):
        if i < half:
            op[i, :window] = row(0, i)
        elif i >= n - half:
            op[i, n - window:] = row(n - window, i)
        else:
            start = i - half + int(even)
            op[i, start:start + window] = row(start, i + 0.5 * even)
    return op


def _savgol(y: np.ndarray, window: int, poly: int, deriv: int = 0) -> np.ndarray:
    return _savgol_operator(len(y), window, poly, deriv, SIM_DT) @ y


def comfort_terms(states: EgoStates) -> dict[str, np.ndarray]:
    """NAVSIM's comfort signals over the states (window sizes of pdm_comfort_metrics, capped at the 31 states):
    accelerations fitted over all states (order 2); jerks as the derivative (order 2, all states) of the
    accelerations smoothed over 8; yaw rate and yaw acceleration from the heading over 5 (orders 2 and 3)."""
    n = len(states.heading)
    lon, lat = states.lon_accel, states.lat_accel
    mag = np.hypot(states.accel[:, 0], states.accel[:, 1])
    out = {
        "lon_accel": _savgol(lon, n, 2),
        "lat_accel": _savgol(lat, n, 2),
        "jerk": _savgol(_savgol(mag, 8, 2), n, 2, 1),
        "lon_jerk": _savgol(_savgol(lon, 8, 2), n, 2, 1),
        "yaw_accel": _savgol(states.heading, 5, 3, 2),
        "yaw_rate": _savgol(states.heading, 5, 2, 1),
    }
    return {k: np.round(v, 8) for k, v in out.items()}


def is_comfortable(states: EgoStates) -> float:
    """1.0 when every comfort signal stays strictly within its COMFORT_BOUNDS at every state, else 0.0."""
    terms = comfort_terms(states)
    return float(all(((terms[k] > lo) & (terms[k] < hi)).all() for k, (lo, hi) in COMFORT_BOUNDS.items()))


# -- progress --------------------------------------------------------------------------------------------------

def expert_path(expert: Any, final_heading: float = 0.0) -> np.ndarray:
    """The expert's path: the polyline from the origin through its waypoints (repeats dropped), continued
    straight for 1 km along `final_heading` (its heading at 3 s, which stays put while it stands; a standing
    expert's path is that ray from the origin)."""
    pts = [np.zeros(2)]
    for p in _waypoints(expert, "expert"):
        if np.hypot(*(p - pts[-1])) > 1e-6:
            pts.append(p)
    ahead = _EXTEND_M * np.array([np.cos(final_heading), np.sin(final_heading)])
    return np.vstack([pts, pts[-1] + ahead])


def progress_along(path: np.ndarray, point: np.ndarray) -> float:
    """Arc length along `path` of the point's nearest point on it (a point behind the start: negative)."""
    a, b = path[:-1], path[1:]
    ab = b - a
    length = np.hypot(ab[:, 0], ab[:, 1])
    t = ((point - a) * ab).sum(1) / length**2
    lo = np.zeros(len(a))
    lo[0] = -np.inf  # before the start: straight back along the first segment
    t = np.clip(t, lo, 1.0)
    dist = np.hypot(*(a + t[:, None] * ab - point).T)
    k = int(dist.argmin())
    return float(np.concatenate([[0.0], np.cumsum(length)])[k] + t[k] * length[k])


def ego_progress(plan_m: float, plan_multiplier: float, expert_m: float, expert_multiplier: float) -> float:
    """NAVSIM's normalised progress of the plan against the expert (PDM-Closed there): raw progress (at least 0)
    times the multiplicative metrics, over the larger of the two; 1 (0 for a plan multiplied by 0) when that
    larger value is at most PROGRESS_DISTANCE_THRESHOLD."""
    plan_raw = max(plan_m, 0.0) * plan_multiplier
    top = max(plan_raw, max(expert_m, 0.0) * expert_multiplier)
    if top > PROGRESS_DISTANCE_THRESHOLD:
        return plan_raw / top
    return 1.0 if plan_multiplier > 0 else 0.0


# -- the score -------------------------------------------------------------------------------------------------

def pdm_score(plan: Any, expert: Any, agents: Sequence[AgentBoxes], ego_velocity: Any = (0.0, 0.0),
              drivable: DrivableQuery | None = None, ego_pose: Any = None, *,
              static_categories: Sequence[str] = STATIC_CATEGORIES) -> PDMSResult:
    """The PDMS-like score of one plan (see the module docstring and spec/README.md, spec 3).

    plan, expert: (6, 2) waypoints in the ego frame; agents: one AgentBoxes per waypoint time (missing steps
    are empty); ego_velocity: (vx, vy) m/s at t = 0 in the ego frame; drivable: a vectorised query points (K, 2)
    -> bool in the map's frame, or None (no map: dac 1, `map_scored` False); ego_pose: the ego's (x, y, yaw) in
    the map's frame (None: the query takes ego-frame points).
    """
    plan_arr, expert_arr = _waypoints(plan, "plan"), _waypoints(expert, "expert")
    steps = _steps(agents)
    ids, velocities = agent_tracks(steps)
    ps, es = interpolate(plan_arr, ego_velocity), interpolate(expert_arr, ego_velocity)
    plan_off, expert_off = off_road(ps, drivable, ego_pose), off_road(es, drivable, ego_pose)
    ignore = expert_contacts(es, steps, ids)
    path = expert_path(expert_arr, float(es.heading[-1]))
    astray = plan_off | out_of_lane(ps, path)  # off the road or across a lane line: side contacts count
    nc = no_at_fault_collisions(ps, steps, ids, velocities, astray, ignore, static_categories)
    dac = 0.0 if plan_off.any() else 1.0
    ttc = time_to_collision_within_bound(ps, steps, ids, astray, ignore)
    comfort = is_comfortable(ps)
    plan_m, expert_m = progress_along(path, plan_arr[-1]), progress_along(path, expert_arr[-1])
    # the expert's own collisions are ignored (expert_contacts), so its multiplier is its DAC
    ep = ego_progress(plan_m, nc * dac, expert_m, 0.0 if expert_off.any() else 1.0)
    weighted = (EP_WEIGHT * ep + TTC_WEIGHT * ttc + COMFORT_WEIGHT * comfort) / (EP_WEIGHT + TTC_WEIGHT
                                                                                   + COMFORT_WEIGHT)
    return PDMSResult(nc, dac, ttc, ep, comfort, nc * dac * weighted, drivable is not None, max(plan_m, 0.0),
                      max(expert_m, 0.0))


def frame_pdms(plan: Any, frame: Frame, drivable: DrivableQuery | None = None, *,
               static_categories: Sequence[str] = STATIC_CATEGORIES) -> PDMSResult:
    """`pdm_score` of a plan on a reader frame: its ground truth, agents, ego velocity and global pose; pass the
    frame's `reader.drivable_area(frame)` (or None) as `drivable`."""
    return pdm_score(plan, frame.gt_future, frame.agents, frame.ego.velocity, drivable,
                     frame.pose, static_categories=static_categories)


# -- the fast path: one frame prepared once, many plans scored -----------------------------------------------

#: Half the diagonal of the ego box: two boxes whose centres are farther apart than the sum of their half
#: diagonals (plus a margin above the touch tolerance) cannot touch, so those pairs are not tested at all.
_EGO_RADIUS = 0.5 * math.hypot(EGO_LENGTH, EGO_WIDTH)
_FAR_MARGIN_M = 0.1
#: The map around the ego kept per frame: polygons whose bounding box meets this window (m, each side).
LOCAL_MAP_M = 200.0


class LocalDrivable:
    """A drivable-area query restricted to the polygons near one point (in the map's frame): points inside the
    window are tested against the rings of the polygons whose bounding box meets it (no other polygon can hold
    them), all edges at once with `maps.points_in_ring`'s crossing rule; a point outside the window goes to
    the whole map's query."""

    def __init__(self, drivable: Any, center: Any, half: float = LOCAL_MAP_M) -> None:
        self.full = drivable
        c = np.asarray(center, dtype=np.float64).reshape(2)
        self.lo, self.hi = c - half, c + half
        polygons = [p for p in getattr(drivable, "polygons", ()) if len(p.exterior) >= 3
                    and (p.exterior.min(0) <= self.hi).all() and (p.exterior.max(0) >= self.lo).all()]
        rings = [(k, False, p.exterior) for k, p in enumerate(polygons)]
        rings += [(k, True, h) for k, p in enumerate(polygons) for h in p.holes if len(h) >= 3]
        self.n_polygons, self.n_rings = len(polygons), len(rings)
        self.ring_polygon = np.array([r[0] for r in rings], dtype=np.int64)
        self.ring_hole = np.array([r[1] for r in rings], dtype=bool)
        edges = [(np.asarray(r[2], dtype=np.float64).reshape(-1, 2), i) for i, r in enumerate(rings)]
        start = np.concatenate([e for e, _ in edges]) if edges else np.zeros((0, 2))
        end = np.concatenate([np.roll(e, -1, axis=0) for e, _ in edges]) if edges else np.zeros((0, 2))
        self.x0, self.y0, self.x1, self.y1 = start[:, 0], start[:, 1], end[:, 0], end[:, 1]
        self.edge_ring = np.concatenate([np.full(len(e), i) for e, i in edges]) if edges else np.zeros(0, np.int64)

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not ((pts >= self.lo) & (pts <= self.hi)).all():
            return np.asarray(self.full(pts), dtype=bool).reshape(-1)
        if not self.n_rings:
            return np.zeros(len(pts), dtype=bool)
        px, py = pts[:, 0:1], pts[:, 1:2]
        straddle = (self.y0[None, :] > py) != (self.y1[None, :] > py)
        pe, e = np.nonzero(straddle)
        t = (py[pe, 0] - self.y0[e]) / (self.y1[e] - self.y0[e])
        crosses = px[pe, 0] < self.x0[e] + t * (self.x1[e] - self.x0[e])
        counts = np.bincount(pe[crosses] * self.n_rings + self.edge_ring[e[crosses]],
                             minlength=len(pts) * self.n_rings).reshape(len(pts), self.n_rings)
        odd = counts % 2 == 1
        in_exterior = odd[:, ~self.ring_hole]  # (P, polygons): exterior rings come first, one per polygon
        in_hole = np.zeros_like(in_exterior)
        if self.ring_hole.any():
            holes = np.flatnonzero(self.ring_hole)
            np.logical_or.at(in_hole.T, self.ring_polygon[holes], odd[:, holes].T)
        return np.asarray((in_exterior & ~in_hole).any(axis=1), dtype=bool)


@dataclass(frozen=True)
class PreparedFrame:
    """What `pdm_score` derives from the frame alone (expert states and path, agent tracks and speeds, the
    expert's contacts and progress, the map around the ego), prepared once per frame and shared by every cell.

    ``score(plan)`` equals ``pdm_score(plan, expert, agents, ...)`` (tests/unit/test_pdms.py checks it on the
    world and on the known-answer frames); it tests all agent boxes of a waypoint time (and all TTC projections)
    in one vectorised separating-axis call, after dropping the pairs too far apart to touch.
    """

    expert: np.ndarray
    steps: tuple[AgentBoxes, ...]
    ids: tuple[np.ndarray, ...]
    velocities: tuple[np.ndarray, ...]
    ego_velocity: np.ndarray
    drivable: DrivableQuery | None
    ego_pose: Any
    static_categories: tuple[str, ...]
    ignore: frozenset[int]
    path: np.ndarray
    expert_m: float
    expert_multiplier: float
    # every agent box of the six waypoint times, flat, in (time, index) order
    step_of: np.ndarray  # (M,) waypoint index 0..5
    index: np.ndarray  # (M,) index of the box within its time's AgentBoxes
    centers: np.ndarray  # (M, 2)
    sizes: np.ndarray  # (M, 2)
    yaws: np.ndarray  # (M,)
    reach: np.ndarray  # (M,) half diagonal + the ego's + margin

    @classmethod
    def prepare(cls, expert: Any, agents: Sequence[AgentBoxes], ego_velocity: Any = (0.0, 0.0),
                drivable: DrivableQuery | None = None, ego_pose: Any = None, *,
                static_categories: Sequence[str] = STATIC_CATEGORIES) -> PreparedFrame:
        """Prepare a frame from the arguments of `pdm_score` (less the plan)."""
        expert_arr = _waypoints(expert, "expert")
        steps = _steps(agents)
        ids, velocities = agent_tracks(steps)
        velocity = np.asarray(ego_velocity, dtype=np.float64).reshape(2)
        if drivable is not None and ego_pose is not None and hasattr(drivable, "polygons"):
            drivable = LocalDrivable(drivable, [float(ego_pose[0]), float(ego_pose[1])])
        es = interpolate(expert_arr, velocity)
        expert_off = off_road(es, drivable, ego_pose)
        ignore = expert_contacts(es, steps, ids)
        path = expert_path(expert_arr, float(es.heading[-1]))
        parts = [(k, j, np.asarray(b.center, dtype=np.float64).reshape(-1, 2)[j],
                  np.asarray(b.size, dtype=np.float64).reshape(-1, 2)[j],
                  float(np.asarray(b.yaw, dtype=np.float64).reshape(-1)[j]))
                 for k, b in enumerate(steps) for j in range(len(b))]
        sizes = np.array([p[3] for p in parts], dtype=np.float64).reshape(-1, 2)
        return cls(expert_arr, tuple(steps), tuple(ids), tuple(velocities), velocity, drivable, ego_pose,
                   tuple(static_categories), frozenset(ignore), path, progress_along(path, expert_arr[-1]),
                   0.0 if expert_off.any() else 1.0,
                   np.array([p[0] for p in parts], dtype=np.int64), np.array([p[1] for p in parts], dtype=np.int64),
                   np.array([p[2] for p in parts], dtype=np.float64).reshape(-1, 2), sizes,
                   np.array([p[4] for p in parts], dtype=np.float64),
                   0.5 * np.hypot(sizes[:, 0], sizes[:, 1]) + _EGO_RADIUS + _FAR_MARGIN_M)

    @classmethod
    def of(cls, frame: Frame, drivable: DrivableQuery | None = None, *,
           static_categories: Sequence[str] = STATIC_CATEGORIES) -> PreparedFrame:
        """Prepare a reader frame, as `frame_pdms` scores it."""
        return cls.prepare(frame.gt_future, frame.agents, frame.ego.velocity, drivable, frame.pose,
                           static_categories=static_categories)

    def _hit_pairs(self, xy: np.ndarray, heading: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego boxes at xy (Q, 2) / heading (Q,) against the agent boxes of waypoint `step` (Q,): the (query,
        flat agent) pairs that overlap or touch, in (query, agent) order."""
        q, a = np.nonzero(step[:, None] == self.step_of[None, :])
        if len(q):
            near = np.hypot(*(self.centers[a] - xy[q]).T) <= self.reach[a]
            q, a = q[near], a[near]
        if not len(q):
            return q, a
        over = _overlap_pairs(xy[q], np.broadcast_to(_EGO_SIZE, (len(q), 2)), heading[q], self.centers[a],
                              self.sizes[a], self.yaws[a])
        return q[over], a[over]

    def _nc(self, states: EgoStates, astray: np.ndarray) -> float:
        """`no_at_fault_collisions`, all waypoint times at once."""
        keys = np.asarray(KEY_STATES)
        qs, ags = self._hit_pairs(states.xy[keys], states.heading[keys], np.arange(HORIZON_STEPS))
        ignored = set(self.ignore)
        score = 1.0
        for q, flat in zip(qs.tolist(), ags.tolist()):
            k, j, i = self.step_of[flat], int(self.index[flat]), int(keys[q])
            track = int(self.ids[k][j])
            if track in ignored:
                continue
            boxes = self.steps[k]
            xy, heading = states.xy[i], float(states.heading[i])
            static = boxes.category[j] in self.static_categories
            agent_speed = float(np.hypot(*self.velocities[k][j]))
            if states.speed[i] <= STOPPED_SPEED:
                at_fault = False
            elif static or agent_speed <= STOPPED_SPEED:
                at_fault = True
            elif _relative_angle(xy, heading, self.centers[flat]) > np.deg2rad(BEHIND_DEG):
                at_fault = False
            else:
                nose = xy + 0.5 * EGO_LENGTH * np.array([np.cos(heading), np.sin(heading)])
                single = AgentBoxes(self.centers[flat][None], self.sizes[flat][None], self.yaws[flat:flat + 1],
                                    (boxes.category[j],))
                front = len(_hits(nose, heading, single, _BUMPER_SIZE)) > 0
                at_fault = front or bool(astray[i])
            if at_fault:
                score = min(score, 0.5 if static else 0.0)
            else:
                ignored.add(track)
        return score

    def _ttc(self, states: EgoStates, astray: np.ndarray) -> float:
        """`time_to_collision_within_bound`, every (state, projection) pair at once."""
        pairs = _ttc_pairs()
        i_arr, d_arr, k_arr = pairs[:, 0].astype(np.int64), pairs[:, 1], pairs[:, 2].astype(np.int64)
        speed = states.speed[i_arr]
        moving = speed >= TTC_STOPPED_SPEED
        i_arr, d_arr, k_arr, speed = i_arr[moving], d_arr[moving], k_arr[moving], speed[moving]
        heading = states.heading[i_arr]
        moved = states.xy[i_arr] + (speed * d_arr)[:, None] * np.stack([np.cos(heading), np.sin(heading)], 1)
        qs, ags = self._hit_pairs(moved, heading, k_arr)
        ignored = set(self.ignore)
        for q, flat in zip(qs.tolist(), ags.tolist()):
            k, j, i = int(k_arr[q]), int(self.index[flat]), int(i_arr[q])
            track = int(self.ids[k][j])
            if track in ignored:
                continue
            angle = _relative_angle(states.xy[i], float(states.heading[i]), self.centers[flat])
            if angle < np.deg2rad(AHEAD_DEG) or (astray[i] and angle <= np.deg2rad(BEHIND_DEG)):
                return 0.0
            ignored.add(track)
        return 1.0

    def score(self, plan: Any) -> PDMSResult:
        """The PDMS-like score of one plan on this frame (equal to `pdm_score`)."""
        plan_arr = _waypoints(plan, "plan")
        ps = interpolate(plan_arr, self.ego_velocity)
        plan_off = off_road(ps, self.drivable, self.ego_pose)
        astray = plan_off | out_of_lane(ps, self.path)
        nc = self._nc(ps, astray)
        dac = 0.0 if plan_off.any() else 1.0
        ttc = self._ttc(ps, astray)
        comfort = is_comfortable(ps)
        plan_m = progress_along(self.path, plan_arr[-1])
        ep = ego_progress(plan_m, nc * dac, self.expert_m, self.expert_multiplier)
        weighted = (EP_WEIGHT * ep + TTC_WEIGHT * ttc + COMFORT_WEIGHT * comfort) / (EP_WEIGHT + TTC_WEIGHT
                                                                                       + COMFORT_WEIGHT)
        return PDMSResult(nc, dac, ttc, ep, comfort, nc * dac * weighted, self.drivable is not None,
                          max(plan_m, 0.0), max(self.expert_m, 0.0))


@functools.lru_cache(maxsize=1)
def _ttc_pairs() -> np.ndarray:
    """NAVSIM's TTC (state index, projection seconds, waypoint index) pairs in its order, as (P, 3) floats."""
    pairs = sorted((int(i - round(d / SIM_DT)), d, k) for k, i in enumerate(KEY_STATES) for d in TTC_PROJECTIONS_S
                   if i - round(d / SIM_DT) >= 0)
    out = np.array(pairs, dtype=np.float64)
    out.setflags(write=False)
    return out
