"""Where the ego goes: a plan's 10 Hz states (a cubic spline through its waypoints), its box on and off the road,
the expert's path and progress along it, and NAVSIM's comfort signals over the states."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...constants import HORIZON_STEPS, STEP_SECONDS
from .constants import (
    COMFORT_BOUNDS,
    EGO_SIZE,
    EXTEND_M,
    HALF_LANE_M,
    HEADING_MIN_SPEED,
    SCORED_POSES,
    SIM_DT,
    TIMES,
    DrivableQuery,
    state_times,
)

#: The ego's (x, y, yaw) in the map's frame (m, m, rad), as `Frame.pose`.
EgoPose = Sequence[float]


@dataclass(frozen=True)
class EgoStates:
    """A trajectory at 10 Hz from t = 0 to 3 s (N_STATES states), in the current ego frame."""

    xy: np.ndarray  # (N, 2) m, box centre
    velocity: np.ndarray  # (N, 2) m/s
    accel: np.ndarray  # (N, 2) m/s^2
    heading: np.ndarray  # (N,) rad, unwrapped
    speed: np.ndarray  # (N,) m/s
    #: the bicycle model's yaw rate (rad/s) at each state, where the states were tracked (`tracking`); None else
    yaw_rate: np.ndarray | None = None

    @property
    def lon_accel(self) -> np.ndarray:
        return self.accel[:, 0] * np.cos(self.heading) + self.accel[:, 1] * np.sin(self.heading)

    @property
    def lat_accel(self) -> np.ndarray:
        return -self.accel[:, 0] * np.sin(self.heading) + self.accel[:, 1] * np.cos(self.heading)


def waypoints(traj: npt.ArrayLike, name: str) -> np.ndarray:
    """`traj` as finite (6, 2) float64 waypoints, or (8, 2) (NAVSIM's 4 s, `SCORED_POSES`); a ValueError naming
    `name` otherwise."""
    arr = np.asarray(traj, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) not in SCORED_POSES:
        raise ValueError(f"{name} must have shape ({HORIZON_STEPS}, 2) or (8, 2), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} has non-finite waypoints")
    return arr


def _spline(pts: np.ndarray, v0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities and accelerations at TIMES of the cubic spline through `pts` (knots STEP_SECONDS
    apart) with start derivative `v0` and a parabolic run-out (the last two intervals share their acceleration)."""
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
    times = TIMES if n == HORIZON_STEPS + 1 else state_times(n - 1)
    seg = np.minimum((times / h + 1e-9).astype(int), n - 2)
    u = (times - seg * h)[:, None]
    w = h - u
    m0, m1, p0, p1 = m[seg], m[seg + 1], pts[seg], pts[seg + 1]
    c0, c1 = p0 / h - m0 * h / 6.0, p1 / h - m1 * h / 6.0
    xy = m0 * w**3 / (6 * h) + m1 * u**3 / (6 * h) + c0 * w + c1 * u
    vel = -m0 * w**2 / (2 * h) + m1 * u**2 / (2 * h) - c0 + c1
    acc = m0 * w / h + m1 * u / h
    return xy, vel, acc


def _headings(vel: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Headings that follow the velocity's direction (held below HEADING_MIN_SPEED; a velocity more than 90
    degrees off the heading is driving backwards), unwrapped from 0."""
    headings = []
    current = 0.0
    # plain floats: a 31-step recurrence
    for angle, fast in zip(np.arctan2(vel[:, 1], vel[:, 0]).tolist(), (speed >= HEADING_MIN_SPEED).tolist()):
        if fast:
            turn = (angle - current + math.pi) % (2 * math.pi) - math.pi
            if abs(turn) > math.pi / 2:  # moving backwards: the heading is opposite the velocity
                turn = (turn - math.pi + math.pi) % (2 * math.pi) - math.pi
            current += turn
        headings.append(current)
    return np.array(headings)


def interpolate(plan: npt.ArrayLike, velocity: npt.ArrayLike = (0.0, 0.0)) -> EgoStates:
    """The 10 Hz states of six waypoints: a cubic spline through the origin (t = 0) and the waypoints with the
    given start velocity and a parabolic run-out (last two intervals share their acceleration); headings
    follow the velocity (held below HEADING_MIN_SPEED; a velocity more than 90 degrees off the heading is
    driving backwards)."""
    pts = np.vstack([np.zeros((1, 2)), waypoints(plan, "trajectory")])
    v0 = np.asarray(velocity, dtype=np.float64).reshape(2)
    xy, vel, acc = _spline(pts, v0)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    return EgoStates(xy, vel, acc, _headings(vel, speed), speed)


def box_corners(xy: np.ndarray, heading: np.ndarray, size: np.ndarray = EGO_SIZE) -> np.ndarray:
    """Corners (N, 4, 2) of boxes (length along heading, width) centred at xy (N, 2): front-left, rear-left,
    rear-right, front-right."""
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    lx = np.array([0.5, -0.5, -0.5, 0.5])[None] * size[0]
    ly = np.array([0.5, 0.5, -0.5, -0.5])[None] * size[1]
    return np.stack([xy[:, 0:1] + c * lx - s * ly, xy[:, 1:2] + s * lx + c * ly], axis=-1)


def off_road(states: EgoStates, drivable: DrivableQuery | None, ego_pose: EgoPose | None = None,
             size: np.ndarray = EGO_SIZE) -> np.ndarray:
    """Per state (N,) bool: a corner of the ego box lies outside the drivable area. `drivable` answers for
    points (K, 2) in the map's frame; `ego_pose` (x, y, yaw) maps ego-frame points there (None: the query takes
    ego-frame points). No query: nothing is off the road."""
    if drivable is None:
        return np.zeros(len(states.xy), dtype=bool)
    pts = box_corners(states.xy, states.heading, size).reshape(-1, 2)
    if ego_pose is not None:
        x, y, yaw = (float(v) for v in ego_pose)
        c, s = np.cos(yaw), np.sin(yaw)
        pts = np.stack([x + c * pts[:, 0] - s * pts[:, 1], y + s * pts[:, 0] + c * pts[:, 1]], axis=1)
    inside = np.asarray(drivable(pts), dtype=bool).reshape(-1, 4)
    return np.logical_not(inside.all(axis=1))


# -- the expert's path ------------------------------------------------------------------------------------------

def expert_path(expert: npt.ArrayLike, final_heading: float = 0.0) -> np.ndarray:
    """The expert's path: the polyline from the origin through its waypoints (repeats dropped), continued
    straight for 1 km along `final_heading` (its heading at 3 s, which stays put while it stands; a standing
    expert's path is that ray from the origin)."""
    pts = [np.zeros(2)]
    for p in waypoints(expert, "expert"):
        if np.hypot(*(p - pts[-1])) > 1e-6:
            pts.append(p)
    ahead = EXTEND_M * np.array([np.cos(final_heading), np.sin(final_heading)])
    return np.vstack([pts, pts[-1] + ahead])


def path_distance(path: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Distance of points (K, 2) to a polyline (M, 2), its first and last segments continued straight.

    Written per coordinate (no (K, M, 2) temporaries, no reduction over a length-2 axis): the same sums in the
    same order as the dot product and `np.linalg.norm` over that axis it replaced, so the same bits
    (tests/unit/test_lanes_exact.py)."""
    ax, ay = path[:-1, 0], path[:-1, 1]
    bx, by = path[1:, 0] - ax, path[1:, 1] - ay
    px, py = pts[:, 0:1], pts[:, 1:2]
    t = ((px - ax) * bx + (py - ay) * by) / (bx * bx + by * by)
    lo, hi = np.zeros(len(ax)), np.ones(len(ax))
    lo[0], hi[-1] = -np.inf, np.inf
    t = np.clip(t, lo[None], hi[None])
    dx, dy = ax + t * bx - px, ay + t * by - py
    return np.sqrt(dx * dx + dy * dy).min(1)


def out_of_lane(states: EgoStates, path: np.ndarray, size: np.ndarray = EGO_SIZE) -> np.ndarray:
    """Per state (N,) bool: a corner of the ego box lies more than HALF_LANE_M from the expert's path, the
    stand-in for NAVSIM's "in multiple lanes" where the map has no lanes."""
    corners = box_corners(states.xy, states.heading, size).reshape(-1, 2)
    far = path_distance(path, corners) > HALF_LANE_M
    return np.asarray(far.reshape(-1, 4).any(axis=1), dtype=bool)


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


def savgol(y: np.ndarray, window: int, poly: int, deriv: int = 0) -> np.ndarray:
    """scipy's `savgol_filter(y, window, poly, deriv, delta=SIM_DT)` (mode 'interp'), without scipy."""
    return _savgol_operator(len(y), window, poly, deriv, SIM_DT) @ y


def _comfort_signals(states: EgoStates) -> dict[str, np.ndarray]:
    n = len(states.heading)
    lon, lat = states.lon_accel, states.lat_accel
    mag = np.hypot(states.accel[:, 0], states.accel[:, 1])
    return {
        "lon_accel": savgol(lon, n, 2),
        "lat_accel": savgol(lat, n, 2),
        "jerk": savgol(savgol(mag, 8, 2), n, 2, 1),
        "lon_jerk": savgol(savgol(lon, 8, 2), n, 2, 1),
        "yaw_accel": savgol(states.heading, 5, 3, 2),
        "yaw_rate": savgol(states.heading, 5, 2, 1),
    }


def comfort_terms(states: EgoStates) -> dict[str, np.ndarray]:
    """NAVSIM's comfort signals over the states (window sizes of pdm_comfort_metrics, capped at the 31 states):
    accelerations fitted over all states (order 2); jerks as the derivative (order 2, all states) of the
    accelerations smoothed over 8; yaw rate and yaw acceleration from the heading over 5 (orders 2 and 3),
    rounded to 1e-8."""
    return {k: np.round(v, 8) for k, v in _comfort_signals(states).items()}


#: COMFORT_BOUNDS as a (terms, 2) array, in its order.
_BOUNDS = np.array(list(COMFORT_BOUNDS.values()), dtype=np.float64)


def within_comfort(signals: dict[str, np.ndarray]) -> float:
    """1.0 when every signal (one per COMFORT_BOUNDS key, all of one length), rounded to 1e-8, stays strictly
    within its bounds at every state, else 0.0. The signals are rounded and compared stacked, in one call each:
    rounding is elementwise, so the same values as term by term."""
    rounded = np.round(np.stack([signals[k] for k in COMFORT_BOUNDS]), 8)
    return float(((rounded > _BOUNDS[:, :1]) & (rounded < _BOUNDS[:, 1:])).all())


def is_comfortable(states: EgoStates) -> float:
    """1.0 when every comfort signal (`comfort_terms`) stays strictly within its COMFORT_BOUNDS at every state,
    else 0.0."""
    return within_comfort(_comfort_signals(states))
