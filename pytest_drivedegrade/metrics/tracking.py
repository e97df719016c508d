"""A plan as NAVSIM v1 scores it: interpolated to 10 Hz, tracked by an LQR controller, driven by a bicycle model.

NAVSIM does not score a plan's waypoints: it interpolates the poses linearly to 0.1 s, fits a velocity and a
curvature profile to them, and simulates a kinematic bicycle model (rear-axle reference) that a decoupled LQR
tracker steers along them (``pdm_simulator.py``, ``batch_lqr.py``, ``batch_lqr_utils.py``,
``batch_kinematic_bicycle.py``, after nuPlan's ``tracker/lqr.py``). The scored states then carry the model's
body-frame acceleration: longitudinal only after t = 0 (the bicycle model has no lateral acceleration), the
logged acceleration at t = 0. Written here in numpy from that published behaviour; every parameter below is
NAVSIM's default. Batched over plans as NAVSIM is: arrays are ``(B, N)`` with N = 31 states (0 .. 3 s).

Plans are ``(6, 2)`` waypoints at t = 0.5 .. 3.0 s in the current ego frame (x forward, y left); NAVSIM's plans
carry a heading per pose, the suite's do not, so a waypoint's heading is the direction of travel through it
(`waypoint_headings`). The tracked point is the plan's point (NAVSIM's rear axle).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..constants import HORIZON_STEPS, STEP_SECONDS
from ..data.frame import EgoStatus
from ..data.geometry import wrap_angle as _wrap
from .pdms.constants import SCORED_POSES, SIM_DT, SUBSTEPS
from .pdms.motion import EgoStates, is_comfortable

#: nuPlan's get_pacifica_parameters().wheel_base (m): NAVSIM's vehicle for both the tracker and the model.
WHEEL_BASE: float = 3.089
#: BatchKinematicBicycleModel: steering angle bound (rad) and the first-order lag (s) of acceleration and steering.
MAX_STEERING_ANGLE: float = math.pi / 3
ACCEL_TIME_CONSTANT: float = 0.2
STEERING_TIME_CONSTANT: float = 0.05
#: Below this chord (m) between a waypoint's neighbours the plan stands still there and the heading is held.
STANDING_CHORD_M: float = 0.1


@dataclass(frozen=True)
class LQRParams:
    """BatchLQRTracker's defaults: weights of the decoupled longitudinal (velocity / acceleration) and lateral
    (lateral error, heading error, steering angle / steering rate) one-step problems over a 10-step (1 s)
    look-ahead, the least-squares penalties of the profile fit, and the P controller used near standstill."""

    q_longitudinal: float = 10.0
    r_longitudinal: float = 1.0
    q_lateral: tuple[float, float, float] = (1.0, 10.0, 0.0)
    r_lateral: float = 1.0
    horizon: int = 10
    jerk_penalty: float = 1e-4
    curvature_rate_penalty: float = 1e-2
    initial_curvature_penalty: float = 1e-10
    stopping_gain: float = 0.5
    stopping_velocity: float = 0.2  # m/s: reference and ego both at or below it -> the P controller, no steering


NAVSIM_LQR = LQRParams()


@dataclass(frozen=True)
class InitialState:
    """The ego at t = 0 as NAVSIM's log state has it (body frame, rear axle at the origin with heading 0):
    speed and lateral velocity, logged acceleration, yaw rate, and the tyre steering angle (0 in nuPlan's logs)."""

    velocity_x: float = 0.0
    velocity_y: float = 0.0
    acceleration_x: float = 0.0
    acceleration_y: float = 0.0
    yaw_rate: float = 0.0
    steering_angle: float = 0.0

    @staticmethod
    def of(ego: EgoStatus) -> InitialState:
        """The suite's ego status (velocity, acceleration, yaw rate in the current ego frame)."""
        (vx, vy), (ax, ay) = ego.velocity, ego.acceleration
        return InitialState(float(vx), float(vy), float(ax), float(ay), float(ego.yaw_rate))


@dataclass(frozen=True)
class TrackedStates:
    """Simulated states, (B, N) each, at 0.1 s from t = 0, in the current ego frame; velocities and accelerations
    are body-frame (x along the heading, y to its left), headings unwrapped."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    velocity_x: np.ndarray
    velocity_y: np.ndarray
    acceleration_x: np.ndarray
    acceleration_y: np.ndarray
    yaw_rate: np.ndarray
    yaw_acceleration: np.ndarray
    steering_angle: np.ndarray
    steering_rate: np.ndarray

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def ego_states(self, b: int) -> EgoStates:
        """Plan `b` as the PDMS module's EgoStates (velocity and acceleration rotated into the ego frame)."""
        h = self.heading[b]
        c, s = np.cos(h), np.sin(h)

        def rotate(bx: np.ndarray, by: np.ndarray) -> np.ndarray:
            return np.stack([c * bx - s * by, s * bx + c * by], axis=-1)

        vel = rotate(self.velocity_x[b], self.velocity_y[b])
        return EgoStates(np.stack([self.x[b], self.y[b]], axis=-1), vel,
                         rotate(self.acceleration_x[b], self.acceleration_y[b]), h.copy(),
                         np.hypot(vel[:, 0], vel[:, 1]), self.yaw_rate[b].copy())


# -- the reference ---------------------------------------------------------------------------------------------

def _plans(plans: np.ndarray) -> np.ndarray:
    arr = np.asarray(plans, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[2] != 2 or arr.shape[1] not in SCORED_POSES:
        raise ValueError(f"plans must have shape ({HORIZON_STEPS}, 2) or (B, {HORIZON_STEPS}, 2) (8 for 4 s), got "
                         f"{arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("plans have non-finite waypoints")
    return arr


def waypoint_headings(points: np.ndarray) -> np.ndarray:
    """Headings (B, 7) of the origin (0: the ego's) and the six waypoints: the direction of the chord between a
    waypoint's neighbours; at the last waypoint its incoming segment's direction turned on by half the turn
    between the last two segments (both exact on a line or a circle); held where the plan stands (chord below
    STANDING_CHORD_M); a chord more than 90 degrees off the previous heading is driving backwards."""
    pts = np.concatenate([np.zeros((len(points), 1, 2)), points], axis=1)
    last = pts[:, -1] - pts[:, -2]
    chord = np.concatenate([pts[:, 2:] - pts[:, :-2], last[:, None]], axis=1)  # waypoints 1..6
    angle = np.arctan2(chord[..., 1], chord[..., 0])
    moving = np.hypot(chord[..., 0], chord[..., 1]) >= STANDING_CHORD_M
    before = pts[:, -2] - pts[:, -3]
    turn_on = 0.5 * _wrap(angle[:, -1] - np.arctan2(before[:, 1], before[:, 0]))
    angle[:, -1] += np.where(np.hypot(before[:, 0], before[:, 1]) >= STANDING_CHORD_M, turn_on, 0.0)
    out = np.zeros((len(points), points.shape[1] + 1))
    for k in range(points.shape[1]):
        turn = _wrap(angle[:, k] - out[:, k])
        turn = np.where(np.abs(turn) > np.pi / 2, _wrap(turn - np.pi), turn)  # backwards: heading opposite
        out[:, k + 1] = np.where(moving[:, k], out[:, k] + turn, out[:, k])
    return out


def interpolate_plan(plans: np.ndarray, headings: np.ndarray | None = None) -> np.ndarray:
    """NAVSIM's reference: the poses (origin at t = 0, then the waypoints with their `headings`, (6,) or (B, 6),
    by default `waypoint_headings`) interpolated linearly at 0.1 s (headings unwrapped, as nuPlan's
    InterpolatedTrajectory does). (B, N, 3) x, y, heading."""
    pts = _plans(plans)
    knots = np.concatenate([np.zeros((len(pts), 1, 2)), pts], axis=1)
    if headings is None:
        yaw = waypoint_headings(pts)
    else:
        given = np.broadcast_to(np.asarray(headings, dtype=np.float64), pts.shape[:2])
        yaw = np.unwrap(np.concatenate([np.zeros((len(pts), 1)), given], axis=1), axis=1)
    poses = np.concatenate([knots, yaw[..., None]], axis=-1)  # (B, 7, 3)
    poses_n = pts.shape[1]
    t = np.arange(poses_n * SUBSTEPS + 1) * SIM_DT
    seg = np.minimum((t / STEP_SECONDS + 1e-9).astype(int), poses_n - 1)
    u = (t - seg * STEP_SECONDS) / STEP_SECONDS
    return poses[:, seg] * (1.0 - u)[None, :, None] + poses[:, seg + 1] * u[None, :, None]


# -- the velocity and curvature profiles (batch_lqr_utils) -----------------------------------------------------

def _solve(a: np.ndarray, reg: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Regularised least squares per batch: argmin ||y - a x||^2 + x' reg x. One plan at a time, in 2-D
    products: a stacked product's rounding can depend on the batch's size, a plan's profile must not (the score
    is the same whichever plans share its batch)."""
    out = []
    for ai, ri, yi in zip(a, reg, y):
        ai, yi = np.ascontiguousarray(ai), np.ascontiguousarray(yi)  # a strided row takes another BLAS kernel
        out.append(np.linalg.solve(ai.T @ ai + ri, ai.T @ yi))  # positive definite: reg > 0
    return np.stack(out)


def fit_profiles(poses: np.ndarray, params: LQRParams = NAVSIM_LQR) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and curvature at each 0.1 s step, (B, N - 1) each, fitted to the reference poses: displacements
    are v_k dt along the pose heading with v_k = v_0 + dt * (a_0 + .. + a_{k-1}) and the "jerk" penalty as
    NAVSIM applies it; heading changes are v_k dt kappa_k with a penalty on the curvature rate.

    NAVSIM's batched `_make_banded_difference_matrix` (nuPlan's own, a loop, sets both bands) writes its +1
    band and then overwrites most of it with the -1 band, so the penalty is jerk_penalty * (a_0^2 + .. +
    a_{M-4}^2 + (a_{M-2} - a_{M-3})^2): a ridge on the accelerations with one difference at the end (spec
    4.2.0). Fitted with a true jerk penalty the speeds of a noisy plan are up to 1 m/s off NAVSIM's."""
    b, n = poses.shape[:2]
    m, dt = n - 1, SIM_DT
    disp = np.diff(poses, axis=1)
    dheading = _wrap(disp[..., 2])
    tri = np.tril(np.ones((m, m)))
    direction = np.stack([np.cos(poses[:, :-1, 2]), np.sin(poses[:, :-1, 2])], axis=-1)  # (B, M, 2)
    a_vel = np.empty((b, m, 2, m))  # displacement k uses v_0 and a_0 .. a_{k-1}
    a_vel[..., 0] = direction * dt
    a_vel[..., 1:] = direction[..., None] * (dt * dt * np.tril(np.ones((m, m - 1)), -1))[None, :, None, :]
    jerk = np.zeros((m - 2, m))  # NAVSIM's "difference" matrix: row k is -a_k, the last row a_{M-2} - a_{M-3}
    jerk[np.arange(m - 2), np.arange(1, m - 1)], jerk[m - 3, m - 1] = -1.0, 1.0
    x = _solve(a_vel.reshape(b, 2 * m, m), np.broadcast_to(params.jerk_penalty * jerk.T @ jerk, (b, m, m)),
               disp[..., :2].reshape(b, 2 * m))
    velocity = x[:, :1] + np.concatenate([np.zeros((b, 1)), np.cumsum(x[:, 1:] * dt, axis=1)], axis=1)
    a_curv = np.broadcast_to(tri, (b, m, m)).copy()
    a_curv[:, :, 0] = velocity * dt
    a_curv[:, 1:, 1:] *= velocity[:, 1:, None] * dt * dt
    reg = params.curvature_rate_penalty * np.eye(m)
    reg[0, 0] = params.initial_curvature_penalty
    k = _solve(a_curv, np.broadcast_to(reg, (b, m, m)), dheading)
    curvature = k[:, :1] + np.concatenate([np.zeros((b, 1)), np.cumsum(k[:, 1:] * dt, axis=1)], axis=1)
    return velocity, curvature


# -- the LQR tracker (batch_lqr) -------------------------------------------------------------------------------

def _lateral_command(error: np.ndarray, velocity: np.ndarray, curvature: np.ndarray,
                     params: LQRParams) -> np.ndarray:
    """Steering rate (B,) that, held over the look-ahead, minimises the weighted lateral state (lateral error,
    heading error, steering angle) at its end; dynamics linearised per step j (small angles, Euler, dt):
    e' = v h_e, h_e' = v (delta / L - kappa), delta' = rate.

    Each step's matrix is I + a_j E01 + b_j E12 (a_j = v_j dt, b_j = v_j dt / L), so their product over steps k..
    is I + (sum a) E01 + (sum b) E12 + (sum over i > j of a_i b_j) E02: the end state comes from suffix sums
    over the look-ahead, (B, H) arrays, rather than H matrix products."""
    dt = SIM_DT
    a, b = velocity * dt, velocity * dt / WHEEL_BASE
    c = -velocity * curvature * dt  # the heading error each step's reference curvature adds

    def suffix(x: np.ndarray) -> np.ndarray:  # (B, H + 1): sum over steps >= k, 0 after the last
        return np.concatenate([np.cumsum(x[:, ::-1], axis=1)[:, ::-1], np.zeros((len(x), 1))], axis=1)

    sa, sb = suffix(a), suffix(b)
    sab = suffix(b * sa[:, 1:])  # sum over i > j >= k of a_i b_j
    e, h, delta = error[:, 0], error[:, 1], error[:, 2]
    free = np.stack([e + sa[:, 0] * h + sab[:, 0] * delta + (c * sa[:, 1:]).sum(axis=1),
                     _wrap(h + sb[:, 0] * delta + c.sum(axis=1)), _wrap(delta)], axis=1)
    gain = dt * np.stack([sab[:, 1:].sum(axis=1), sb[:, 1:].sum(axis=1),
                          np.full(len(error), float(velocity.shape[1]))], axis=1)
    q = np.asarray(params.q_lateral)
    return -((gain * q) * free).sum(axis=1) / ((gain * q * gain).sum(axis=1) + params.r_lateral)


def _commands(states: TrackedStates, i: int, poses: np.ndarray, velocity: np.ndarray, curvature: np.ndarray,
              params: LQRParams) -> tuple[np.ndarray, np.ndarray]:
    """Acceleration and steering-rate commands (B,) at step i: near standstill (reference and ego at or below
    the stopping velocity) a P controller on speed and no steering; else the two one-step LQR problems against
    the reference speed `horizon` steps ahead and the curvature over the look-ahead."""
    m = velocity.shape[1]
    ref = min(i + params.horizon, m - 1)
    v0, v_ref = states.velocity_x[:, i], velocity[:, ref]
    stop = (v_ref <= params.stopping_velocity) & (v0 <= params.stopping_velocity)
    span = params.horizon * SIM_DT  # the acceleration is held over the look-ahead: v_N = v_0 + span * a
    accel = -span * params.q_longitudinal * (v0 - v_ref) / (span * span * params.q_longitudinal + params.r_longitudinal)
    accel = np.where(stop, -params.stopping_gain * (v0 - v_ref), accel)
    kappa = np.concatenate([curvature[:, i:ref], np.repeat(curvature[:, ref:ref + 1], params.horizon - (ref - i),
                                                            axis=1)], axis=1)
    v_lin = v0[:, None] + accel[:, None] * SIM_DT * np.arange(params.horizon)[None, :]
    dx, dy = states.x[:, i] - poses[:, i, 0], states.y[:, i] - poses[:, i, 1]
    h_ref = poses[:, i, 2]
    error = np.stack([-dx * np.sin(h_ref) + dy * np.cos(h_ref), _wrap(states.heading[:, i] - h_ref),
                      states.steering_angle[:, i]], axis=1)
    rate = np.where(stop, 0.0, _lateral_command(error, v_lin, kappa, params))
    return accel, rate


# -- the kinematic bicycle model (batch_kinematic_bicycle) -----------------------------------------------------

def _propagate(s: TrackedStates, i: int, accel_cmd: np.ndarray, rate_cmd: np.ndarray) -> None:
    """State i + 1 from state i: the commands pass a first-order lag (ACCEL_TIME_CONSTANT,
    STEERING_TIME_CONSTANT), then one Euler step of the rear-axle bicycle model; the steering angle is clipped
    to MAX_STEERING_ANGLE; no lateral velocity or acceleration."""
    dt = SIM_DT
    v, h, delta = s.velocity_x[:, i], s.heading[:, i], s.steering_angle[:, i]
    accel = s.acceleration_x[:, i] + dt / (dt + ACCEL_TIME_CONSTANT) * (accel_cmd - s.acceleration_x[:, i])
    rate = dt / (dt + STEERING_TIME_CONSTANT) * rate_cmd  # the lagged steering angle's change over dt, per second
    s.x[:, i + 1] = s.x[:, i] + v * np.cos(h) * dt
    s.y[:, i + 1] = s.y[:, i] + v * np.sin(h) * dt
    s.heading[:, i + 1] = h + v * np.tan(delta) / WHEEL_BASE * dt
    s.velocity_x[:, i + 1] = v + accel * dt
    s.acceleration_x[:, i + 1] = accel
    s.steering_angle[:, i + 1] = np.clip(delta + rate * dt, -MAX_STEERING_ANGLE, MAX_STEERING_ANGLE)
    s.steering_rate[:, i + 1] = rate
    s.yaw_rate[:, i + 1] = s.velocity_x[:, i + 1] * np.tan(s.steering_angle[:, i + 1]) / WHEEL_BASE
    s.yaw_acceleration[:, i + 1] = (s.yaw_rate[:, i + 1] - s.yaw_rate[:, i]) / dt


_INITIAL_FIELDS = ("velocity_x", "velocity_y", "acceleration_x", "acceleration_y", "yaw_rate", "steering_angle")


def track(poses: np.ndarray, initial: InitialState | Sequence[InitialState] = InitialState(),
          params: LQRParams = NAVSIM_LQR) -> TrackedStates:
    """Simulate the bicycle model tracking reference poses (B, N, 3) from `interpolate_plan`, as PDMSimulator
    does: state 0 is the initial state at the origin (one for all plans, or one per plan), each later state one
    controller and model step on."""
    ref = np.asarray(poses, dtype=np.float64)
    b, n = ref.shape[:2]
    starts = [initial] if isinstance(initial, InitialState) else list(initial)
    if len(starts) not in (1, b):
        raise ValueError(f"{len(starts)} initial states for {b} plans")
    velocity, curvature = fit_profiles(ref, params)
    s = TrackedStates(*(np.zeros((b, n)) for _ in range(11)))
    for name in _INITIAL_FIELDS:
        getattr(s, name)[:, 0] = [getattr(start, name) for start in starts]
    for i in range(n - 1):
        accel, rate = _commands(s, i, ref, velocity, curvature, params)
        _propagate(s, i, accel, rate)
    return s


def _initial(ego: EgoStatus | InitialState | None) -> InitialState:
    return ego if isinstance(ego, InitialState) else InitialState.of(ego) if ego is not None else InitialState()


def track_plans(plans: np.ndarray, ego: EgoStatus | InitialState | Sequence[EgoStatus | InitialState] | None = None,
                headings: np.ndarray | None = None) -> TrackedStates:
    """Plans (6, 2) or (B, 6, 2) interpolated and tracked from the ego's state, or one state per plan
    (NAVSIM's pipeline in one call)."""
    starts = _initial(ego) if ego is None or isinstance(ego, (EgoStatus, InitialState)) else [_initial(e) for e in ego]
    return track(interpolate_plan(plans, headings), starts)


# -- comfort on tracked states ---------------------------------------------------------------------------------

def tracked_comfort(states: TrackedStates) -> np.ndarray:
    """NAVSIM's comfort verdict (B,) in {0, 1} on tracked states: the PDMS module's six filtered signals and
    bounds (`pdms.is_comfortable`), on the model's body-frame accelerations and headings."""
    return np.array([is_comfortable(states.ego_states(b)) for b in range(len(states))])
