"""The expert driver: keeps its lane, slows for bends and turns, follows and brakes for what is ahead.

Longitudinal control is the Intelligent Driver Model (IDM) against the nearest obstacle in the ego lane
corridor (a vehicle, or a pedestrian / cyclist in or about to enter the corridor); the free-road target speed
is capped ahead of curves so that lateral acceleration stays under `A_LAT`. Also measures, per keyframe,
whether an event only the cameras can show changes the next 3 s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .agents import DT, EGO_START_S, SIM_STEPS, Agent, along
from .roads import Path

A_MAX, B_COMF, T_HEAD, S0, A_LAT, B_CURVE = 1.6, 2.5, 1.3, 3.0, 2.0, 1.6
EGO_LENGTH, EGO_WIDTH = 4.084, 1.85
KEY_EVERY = 5  # sim steps per keyframe (2 Hz)


@dataclass
class EgoLog:
    xy: np.ndarray  # (SIM_STEPS, 2)
    yaw: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    s: np.ndarray
    obstacle_brake: np.ndarray  # (SIM_STEPS,) bool: an obstacle holds the ego below its free-road acceleration


def allowed_speed(lane: Path, v_cruise: float) -> np.ndarray:
    """Per lane sample, the speed from which the ego can still slow down for every bend ahead."""
    kappa = np.abs(lane.curvature())
    kappa = np.convolve(kappa, np.ones(9) / 9, mode="same")
    v = np.minimum(v_cruise, np.sqrt(A_LAT / np.maximum(kappa, 1e-5)))
    ds = lane.s[1] - lane.s[0]
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * B_CURVE * ds))
    return v


def corridor_obstacles(lane: Path, agents: list[Agent]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per agent and step: arc length on the ego lane, speed along it, and whether it blocks the corridor."""
    n = len(agents)
    s_all, v_all, block = np.zeros((n, SIM_STEPS)), np.zeros((n, SIM_STEPS)), np.zeros((n, SIM_STEPS), bool)
    for i, a in enumerate(agents):
        s, d = lane.project(a.xy)
        inside = (np.abs(d) < EGO_WIDTH / 2 + a.size[1] / 2 + 0.4) & (s > 0) & (s < lane.length)
        if a.kind in ("pedestrian", "cyclist"):  # anticipate someone about to step into the lane
            soon = np.zeros_like(inside)
            for k in range(0, 25):
                soon[: SIM_STEPS - k] |= inside[k:]
            inside = soon
        s_all[i], v_all[i], block[i] = s, np.gradient(s, DT), inside
    return s_all, v_all, block


def idm(v: float, v0: float, gap: float | None, dv: float) -> float:
    """IDM acceleration for speed `v`, desired speed `v0`, bumper gap `gap` (None: free road), closing speed dv."""
    free = A_MAX * (1 - (v / max(v0, 0.1)) ** 4)
    if gap is None:
        return free
    s_star = S0 + max(0.0, v * T_HEAD + v * dv / (2 * np.sqrt(A_MAX * B_COMF)))
    return free - A_MAX * (s_star / max(gap, 0.2)) ** 2


def drive(lane: Path, agents: list[Agent], v_cruise: float, v_start: float, s_start: float) -> EgoLog:
    """Simulate the ego along `lane` on the sim clock; returns its log."""
    v_allow = allowed_speed(lane, v_cruise)
    s_obs, v_obs, block = corridor_obstacles(lane, agents)
    half_len = np.array([a.size[0] / 2 for a in agents]) + EGO_LENGTH / 2
    s, v = s_start, v_start
    log_s, log_v, log_a, log_b = (np.zeros(SIM_STEPS) for _ in range(4))
    for t in range(SIM_STEPS):
        v0 = float(np.interp(s, lane.s, v_allow))
        ahead = block[:, t] & (s_obs[:, t] > s)
        gap, dv = None, 0.0
        if ahead.any():
            gaps = np.where(ahead, s_obs[:, t] - s - half_len, np.inf)
            i = int(gaps.argmin())
            gap, dv = float(gaps[i]), v - max(float(v_obs[i, t]), 0.0)
        a = max(idm(v, v0, gap, dv), -8.0)
        log_b[t] = gap is not None and a < idm(v, v0, None, 0.0) - 0.7
        log_s[t], log_v[t], log_a[t] = s, v, a
        v_next = max(v + a * DT, 0.0)
        s += 0.5 * (v + v_next) * DT
        v = v_next
    x, y, yaw = lane.at(log_s)
    return EgoLog(np.stack([x, y], 1), yaw, log_v, np.gradient(log_v, DT), log_s, log_b.astype(bool))


def follower(rng, lane: Path, ego: EgoLog) -> Agent:
    """A car behind the ego that follows it with IDM (so it never runs into the ego when it stops)."""
    s0 = float(ego.s[0] - rng.uniform(12, 22))
    s, v, v0 = s0, float(ego.speed[0]), float(rng.uniform(10, 13))
    speeds = np.zeros(SIM_STEPS)
    for t in range(SIM_STEPS):
        speeds[t] = v
        a = max(idm(v, v0, ego.s[t] - s - 4.6, v - ego.speed[t]), -8.0)
        s += v * DT
        v = max(v + a * DT, 0.0)
    return along(lane, s0, speeds, "car", rng, "follower")


def keyframe_events(lane: Path, ego: EgoLog, n_keys: int, walker_block: np.ndarray) -> list[str]:
    """Per keyframe: the event ('brake', 'vru', 'bend') that bends the next 3 s away from what ego status
    alone predicts (constant speed and yaw rate, deviation over 1 m at 3 s), or '' when there is none."""
    kappa = np.abs(lane.curvature())
    out = []
    for k in range(n_keys):
        t0, t1 = k * KEY_EVERY, min(k * KEY_EVERY + 30, SIM_STEPS - 1)
        yaw_rate = (ego.yaw[t0] - ego.yaw[max(t0 - 1, 0)]) / DT if t0 else 0.0
        tt = np.arange(1, t1 - t0 + 1) * DT
        head = ego.yaw[t0] + yaw_rate * tt
        pred = ego.xy[t0] + np.cumsum(ego.speed[t0] * DT * np.stack([np.cos(head), np.sin(head)], 1), axis=0)
        deviation = float(np.linalg.norm(pred[-1] - ego.xy[t1]))
        seg = (lane.s >= ego.s[t0]) & (lane.s <= ego.s[t1] + 5.0)
        kind = ""
        if deviation > 1.0:
            if walker_block[t0:t1].any():
                kind = "vru"
            elif ego.obstacle_brake[t0:t1].any():
                kind = "brake"
            elif seg.any() and kappa[seg].max() > 1 / 150:
                kind = "bend"
        out.append(kind)
    return out


def start_state(rng, v_cruise: float) -> tuple[float, float]:
    """Initial (arc length, speed) of the ego."""
    return EGO_START_S, float(rng.uniform(0.5, 1.0) * v_cruise)
