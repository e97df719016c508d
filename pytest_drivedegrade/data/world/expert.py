"""The expert driver: keeps its lane, slows for bends and turns, follows and brakes for what is ahead.

It reacts late, as a human does, so that its future depends on what only the cameras show at the current frame:
it keeps cruising toward an obstacle in its lane corridor (a vehicle, or a pedestrian / cyclist in or about to
enter the corridor) until stopping behind it (or matching its speed) needs `B_TRIGGER`, then brakes firmly and
follows it with the Intelligent Driver Model (IDM); it sees a vehicle's change of speed only `REACTION` steps
late (the brake lights show it at once); it brakes for a bend only when the bend's speed needs `B_CURVE`.
Also measures, per keyframe, whether the next 3 s leave what the ego status alone predicts, and why.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...constants import EGO_LENGTH, EGO_WIDTH
from .agents import DT, EGO_START_S, SIM_STEPS, Agent, along
from .roads import Path

A_MAX, B_COMF, T_HEAD, S0, A_LAT, B_CURVE = 1.6, 2.5, 1.3, 3.0, 2.0, 2.8
B_TRIGGER = 3.0  # m/s^2: the deceleration an obstacle must demand before the expert reacts to it
B_MAX = 6.0  # m/s^2: the firmest braking the expert uses
REACTION = 10  # sim steps (1 s): how late a vehicle's change of speed reaches the expert
VRU_LOOKAHEAD = 5  # sim steps (0.5 s): a pedestrian or cyclist this close to entering the corridor counts
KEY_EVERY = 5  # sim steps per keyframe (2 Hz)
#: Reasons the expert leaves its free-road acceleration, logged per step (EgoLog.react).
REACT_NONE, REACT_VEHICLE, REACT_VRU, REACT_BEND, REACT_LIGHT = 0, 1, 2, 3, 4
#: Traffic lights (`lights.TrafficLight`): the expert stops with its front bumper LIGHT_MARGIN (m) before the stop
#: line, braking once stopping needs B_LIGHT (m/s^2); at the onset of yellow it goes on when stopping would need
#: more than B_YELLOW (it then clears the line within the yellow), and stops otherwise.
LIGHT_MARGIN, B_LIGHT, B_YELLOW = 1.0, 2.0, 3.0


@dataclass
class EgoLog:
    xy: np.ndarray  # (SIM_STEPS, 2)
    yaw: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    s: np.ndarray
    react: np.ndarray  # (SIM_STEPS,) int: REACT_* that held the ego below its free-road acceleration
    min_gap: float = np.inf  # smallest bumper gap to anything in the corridor ahead (m)

    @property
    def obstacle_brake(self) -> np.ndarray:
        return (self.react == REACT_VEHICLE) | (self.react == REACT_VRU)


def allowed_speed(lane: Path, v_cruise: float) -> np.ndarray:
    """Per lane sample, the speed from which the ego can still slow down (at `B_CURVE`) for every bend ahead."""
    kappa = np.abs(lane.curvature())
    kappa = np.convolve(kappa, np.ones(9) / 9, mode="same")
    v = np.minimum(v_cruise, np.sqrt(A_LAT / np.maximum(kappa, 1e-5)))
    ds = lane.s[1] - lane.s[0]
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * B_CURVE * ds))
    return v


#: Agents' projections on one lane (`Path.project` of their track), by id; the agent is kept in the value so that its
#: id is not reused while the cache lives. A scene drives the expert up to 2 x MAX_TRIES times past the same
#: background traffic: each agent is projected once.
Projections = dict[int, tuple[Agent, np.ndarray, np.ndarray]]


def _projected(lane: Path, agent: Agent, cache: Projections | None) -> tuple[np.ndarray, np.ndarray]:
    if cache is None:
        return lane.project(agent.xy)
    hit = cache.get(id(agent))
    if hit is None or hit[0] is not agent:
        hit = cache[id(agent)] = (agent, *lane.project(agent.xy))
    return hit[1], hit[2]


def corridor_obstacles(lane: Path, agents: list[Agent], projections: Projections | None = None,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per agent and step: arc length on the ego lane, speed along it, and whether it blocks the corridor
    (`projections`: a cache for this `lane`, shared by calls on the same agents)."""
    n = len(agents)
    s_all, v_all, block = np.zeros((n, SIM_STEPS)), np.zeros((n, SIM_STEPS)), np.zeros((n, SIM_STEPS), bool)
    for i, a in enumerate(agents):
        s, d = _projected(lane, a, projections)
        inside = (np.abs(d) < EGO_WIDTH / 2 + a.size[1] / 2 + 0.4) & (s > 0) & (s < lane.length)
        if a.kind in ("pedestrian", "cyclist"):  # about to step into the lane: a short look ahead only
            soon = inside.copy()
            for k in range(1, VRU_LOOKAHEAD + 1):
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


def required_decel(v: float, gap: float, v_obs: float) -> float:
    """Constant deceleration that brings speed `v` down to `v_obs` at the desired gap behind the obstacle."""
    if v <= v_obs:
        return 0.0
    room = gap - S0 - T_HEAD * max(v_obs, 0.0)
    return (v - v_obs) ** 2 / (2 * max(room, 0.1))


def perceived(s_obs: np.ndarray, v_obs: np.ndarray, vehicle: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Where the expert believes each agent is at step t: vehicles as seen `REACTION` steps ago, extrapolated at
    the speed seen then (a driver who has not yet reacted to brake lights); pedestrians and cyclists as they are."""
    t_seen = max(t - REACTION, 0)
    s_seen = s_obs[:, t_seen] + v_obs[:, t_seen] * (t - t_seen) * DT
    s = np.where(vehicle, s_seen, s_obs[:, t])
    v = np.where(vehicle, v_obs[:, t_seen], v_obs[:, t])
    return s, np.maximum(v, 0.0)


@dataclass
class LightStops:
    """The lights on the expert's lane: each one's stop position (arc length on the lane), and per light whether
    the expert is braking for it, or decided at the onset of yellow to go on."""

    s_stop: np.ndarray
    lights: tuple
    braking: np.ndarray
    going: np.ndarray

    @staticmethod
    def on(lane: Path, lights, net) -> LightStops:
        mids = np.array([light.stop_line(net).mean(0) for light in lights]).reshape(-1, 2)
        s_stop = lane.project(mids)[0] if len(mids) else np.zeros(0)
        n = len(s_stop)
        return LightStops(s_stop, tuple(lights), np.zeros(n, bool), np.zeros(n, bool))

    def accel(self, t: int, s: float, v: float, v_cruise: float) -> float | None:
        """The acceleration the lights ahead demand at step `t` (None: none)."""
        out = None
        for j, light in enumerate(self.lights):
            front = s + EGO_LENGTH / 2
            state = light.state_at(t * DT)
            if state == "green":
                self.braking[j] = self.going[j] = False
            if state == "green" or front > self.s_stop[j]:
                continue
            gap = self.s_stop[j] - LIGHT_MARGIN - front
            need = v * v / (2 * max(gap, 0.1))
            if state == "yellow" and not self.braking[j] and not self.going[j]:
                self.going[j] = need > B_YELLOW
            if self.going[j] and state == "yellow":
                continue
            self.braking[j] |= need > B_LIGHT or gap < 1.0 or state == "yellow"
            if self.braking[j]:
                a = -need if v > 0.5 else idm(v, v_cruise, max(gap, 0.0) + S0, v)
                out = a if out is None else min(out, a)
        return out


@dataclass
class ExpertRule:
    """The expert's driving rule on one lane among one set of agents: what `accel` asks at a step, from any state.
    `drive` rolls it out from the scene's start; the reference driver's training labels roll it out from the states
    the driver reaches (planners/train_closed_driver.py)."""

    lane: Path
    v_cruise: float
    v_allow: np.ndarray
    s_obs: np.ndarray
    v_obs: np.ndarray
    block: np.ndarray
    vehicle: np.ndarray
    half_len: np.ndarray
    lights: LightStops | None

    @staticmethod
    def of(lane: Path, agents: list[Agent], v_cruise: float, projections: Projections | None = None,
           lights: LightStops | None = None) -> ExpertRule:
        s_obs, v_obs, block = corridor_obstacles(lane, agents, projections)
        vehicle = np.array([a.kind not in ("pedestrian", "cyclist") for a in agents], bool)
        half_len = np.array([a.size[0] / 2 for a in agents]) + EGO_LENGTH / 2
        return ExpertRule(lane, v_cruise, allowed_speed(lane, v_cruise), s_obs, v_obs, block, vehicle, half_len,
                          lights)

    def fresh(self) -> np.ndarray:
        """A fresh start: no light braked for or passed yet; returns the engaged flags (none yet)."""
        if self.lights is not None:
            self.lights.braking[:] = False
            self.lights.going[:] = False
        return np.zeros(len(self.vehicle), bool)

    def accel(self, t: int, s: float, v: float, engaged: np.ndarray, v_cruise: float | None = None,
              ) -> tuple[float, int, float]:
        """(acceleration, REACT_* that set it, the free-road acceleration) at step `t` from (s, v); `engaged`
        (updated in place) holds the agents the expert is braking for; `v_cruise` overrides the scene's."""
        v0 = self.v_cruise if v_cruise is None else v_cruise
        free = idm(v, v0, None, 0.0)
        a, why = free, REACT_NONE
        v_next_allowed = float(np.interp(s + v * DT, self.lane.s, self.v_allow))
        if v > v_next_allowed + 1e-3:  # a bend ahead needs it now: brake along the allowed profile
            a, why = (v_next_allowed - v) / DT, REACT_BEND
        ahead = self.block[:, t] & (self.s_obs[:, t] > s)
        s_seen, v_seen = perceived(self.s_obs, self.v_obs, self.vehicle, t)
        engaged &= ahead
        for i in np.flatnonzero(ahead):
            gap = float(s_seen[i] - s - self.half_len[i])
            need = required_decel(v, gap, float(v_seen[i]))
            if not engaged[i] and (need > B_TRIGGER or gap < S0 + 0.5 * v):
                engaged[i] = True
            if engaged[i]:
                a_i = -need if v > v_seen[i] + 0.5 else idm(v, v0, gap, v - float(v_seen[i]))
                if a_i < a:
                    a, why = a_i, (REACT_VEHICLE if self.vehicle[i] else REACT_VRU)
        a_light = self.lights.accel(t, s, v, v0) if self.lights is not None else None
        if a_light is not None and a_light < a:
            a, why = a_light, REACT_LIGHT
        return max(a, -B_MAX), why, free


def drive(lane: Path, agents: list[Agent], v_cruise: float, v_start: float, s_start: float,
          projections: Projections | None = None, lights: LightStops | None = None) -> EgoLog:
    """Simulate the ego along `lane` on the sim clock; returns its log (`projections`: see `corridor_obstacles`;
    `lights`: the traffic lights it obeys)."""
    rule = ExpertRule.of(lane, agents, v_cruise, projections, lights)
    engaged = rule.fresh()
    s, v, min_gap = s_start, v_start, np.inf
    log_s, log_v, log_r = np.zeros(SIM_STEPS), np.zeros(SIM_STEPS), np.zeros(SIM_STEPS, int)
    for t in range(SIM_STEPS):
        ahead = rule.block[:, t] & (rule.s_obs[:, t] > s)
        if ahead.any():
            min_gap = min(min_gap, float((rule.s_obs[:, t] - s - rule.half_len)[ahead].min()))
        a, why, free = rule.accel(t, s, v, engaged)
        log_r[t] = why if a < free - 0.3 else REACT_NONE
        log_s[t], log_v[t] = s, v
        v_next = max(v + a * DT, 0.0)
        s += 0.5 * (v + v_next) * DT
        v = v_next
    x, y, yaw = lane.at(log_s)
    return EgoLog(np.stack([x, y], 1), yaw, log_v, np.gradient(log_v, DT), log_s, log_r, min_gap)


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


def status_extrapolation(ego: EgoLog, t0: int, n: int) -> np.ndarray:
    """What the ego status at step t0 alone predicts for the next `n` steps: constant acceleration (never below
    standstill) and constant yaw rate. (n, 2) world positions."""
    yaw_rate = (ego.yaw[t0] - ego.yaw[max(t0 - 1, 0)]) / DT if t0 else 0.0
    tt = np.arange(1, n + 1) * DT
    speed = np.maximum(ego.speed[t0] + ego.accel[t0] * tt, 0.0)
    head = ego.yaw[t0] + yaw_rate * tt
    return ego.xy[t0] + np.cumsum(speed[:, None] * DT * np.stack([np.cos(head), np.sin(head)], 1), axis=0)


def keyframe_events(lane: Path, ego: EgoLog, n_keys: int) -> list[str]:
    """Per keyframe: the event ('brake', 'vru', 'bend') that takes the next 3 s more than 1 m away from what the
    ego status predicts (constant acceleration and yaw rate), or '' when there is none."""
    kappa = np.abs(lane.curvature())
    out = []
    for k in range(n_keys):
        t0, t1 = k * KEY_EVERY, min(k * KEY_EVERY + 30, SIM_STEPS - 1)
        pred = status_extrapolation(ego, t0, t1 - t0)
        deviation = float(np.linalg.norm(pred[-1] - ego.xy[t1]))
        seg = (lane.s >= ego.s[t0]) & (lane.s <= ego.s[t1] + 5.0)
        why = ego.react[t0:t1 + 1]
        kind = ""
        if deviation > 1.0:
            if (why == REACT_VRU).any():
                kind = "vru"
            elif (why == REACT_VEHICLE).any():
                kind = "brake"
            elif (why == REACT_BEND).any() or (seg.any() and kappa[seg].max() > 1 / 300):
                kind = "bend"
            else:
                kind = "other"  # e.g. pulling away after a stop
        out.append(kind)
    return out


def start_state(rng, v_cruise: float) -> tuple[float, float]:
    """Initial (arc length, speed) of the ego."""
    return EGO_START_S, float(rng.uniform(0.5, 1.0) * v_cruise)
