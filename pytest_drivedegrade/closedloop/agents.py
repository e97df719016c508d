"""The other agents of a closed-loop run: replayed from their logs (`log`, the default: non-reactive) or
`reactive`: every agent that moves follows its logged path, keeps to its logged speed profile, and brakes for the
ego in its way by the Intelligent Driver Model (IDM).

An agent the ego never gets in front of replays its log exactly (the log's own numbers, copied); once IDM slows it,
it drives its own progress along the logged path and may never be ahead of where its log was at the same time
(its speed is capped by the log's). Deterministic: plain float arithmetic in a fixed order.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..data.world.agents import DT, Agent
from ..errors import DriveDegradeError
from .judge import Pose, footprint
from .routes import Route

#: What `agents=` accepts: replay the logs, or IDM along the logged paths.
AGENT_MODES = ("log", "reactive")
#: The ego is looked for this far (m) ahead of an agent's front, and within this lateral margin (m) of its sides.
LOOKAHEAD_M, SIDE_MARGIN_M = 40.0, 0.5


@dataclass(frozen=True)
class IDM:
    """The Intelligent Driver Model (Treiber, Hennecke and Helbing, "Congested traffic states in empirical
    observations and microscopic simulations", Phys. Rev. E 62, 1805, 2000) with the city-traffic parameters of
    Treiber and Kesting, "Traffic Flow Dynamics" (Springer 2013), table 11.2: maximum acceleration a 1.0 m/s²,
    comfortable deceleration b 1.5 m/s², time headway T 1.0 s, minimum gap s0 2 m, exponent 4. IDM's braking is
    unbounded as the gap closes; `max_brake` caps it at what tyres give (8 m/s², not part of the model)."""

    accel: float = 1.0
    decel: float = 1.5
    headway: float = 1.0
    min_gap: float = 2.0
    delta: float = 4.0
    max_brake: float = 8.0

    def acceleration(self, v: float, v0: float, gap: float, dv: float) -> float:
        """IDM acceleration (m/s²) at speed `v` with desired speed `v0`, bumper gap `gap` (m) to the leader and
        approach rate `dv` = v - v_leader (m/s)."""
        s_star = self.min_gap + max(0.0, v * self.headway + v * dv / (2.0 * np.sqrt(self.accel * self.decel)))
        free = 1.0 - (v / max(v0, 0.1)) ** self.delta
        return max(self.accel * (free - (s_star / max(gap, 0.01)) ** 2), -self.max_brake)


def check_mode(agents: str) -> str:
    """`agents` if it is an AGENT_MODES value, else an error naming the valid ones."""
    if agents not in AGENT_MODES:
        raise DriveDegradeError(f"agents={agents!r}: the other agents are 'log' (replayed, the default) or "
                                "'reactive' (IDM along their logged paths)")
    return agents


def leader_gap(agent: Agent, t: int, ego: Pose) -> tuple[float, float] | None:
    """(bumper gap m, the ego's speed along the agent's heading) when a corner of the ego's box lies ahead of
    `agent` at step `t`, within its half width plus SIDE_MARGIN_M of its axis and LOOKAHEAD_M of its front (gap 0
    when already touching); None otherwise. A straight look ahead along its heading: paths bend little in 40 m."""
    yaw = float(agent.yaw[t])
    c, s = np.cos(yaw), np.sin(yaw)
    rel = footprint(ego) - agent.xy[t]
    fwd, side = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
    in_way = (fwd > 0) & (np.abs(side) < agent.size[1] / 2.0 + SIDE_MARGIN_M)
    if not in_way.any():
        return None
    gap = max(float(fwd[in_way].min()) - agent.size[0] / 2.0, 0.0)
    return (gap, ego.speed * float(np.cos(ego.yaw - yaw))) if gap <= LOOKAHEAD_M else None


class PathAgent:
    """One reactive agent: its logged path as a polyline parameterised by distance driven, and its state."""

    def __init__(self, agent: Agent) -> None:
        self.agent = agent
        self.log_xy, self.log_yaw = agent.xy.copy(), agent.yaw.copy()
        self.s_path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(self.log_xy, axis=0).T))])
        self.v_path = np.append(np.diff(self.s_path) / DT, 0.0)  # the log's speed along its path
        self.on_log = True
        self.s, self.v = 0.0, float(self.v_path[0])  # at the start it drives at its log's first speed

    def place(self, t: int) -> None:
        """Write the agent's pose at step `t` from its progress along the logged path."""
        i = int(np.clip(np.searchsorted(self.s_path, self.s, side="right") - 1, 0, len(self.s_path) - 2))
        seg = self.s_path[i + 1] - self.s_path[i]
        frac = 0.0 if seg <= 0 else min((self.s - self.s_path[i]) / seg, 1.0)
        self.agent.xy[t] = self.log_xy[i] + frac * (self.log_xy[i + 1] - self.log_xy[i])
        self.agent.yaw[t] = self.log_yaw[i]
        self.agent.speed[t] = self.v

    def advance(self, t: int, ego: Pose, idm: IDM) -> None:
        """From step t - 1 to t: the log's speed over the step (reached at most at IDM's `accel` once off the
        log), lowered by IDM when the ego is in the way; then the pose. `v` is the speed over the last step."""
        prev = t - 1
        wanted = float(self.v_path[prev])
        free = (wanted - self.v) / DT if self.on_log else min((wanted - self.v) / DT, idm.accel)
        accel = free
        found = leader_gap(self.agent, prev, ego)
        if found is not None:
            gap, v_ego = found
            accel = min(free, idm.acceleration(self.v, wanted, gap, self.v - v_ego))
        if self.on_log and accel == free:
            self.s, self.v = float(self.s_path[t]), wanted
            return  # still its log: the logged numbers stay in place
        self.on_log = False
        self.v = min(max(self.v + accel * DT, 0.0), wanted)  # never faster than the log: never ahead of it
        self.s += self.v * DT
        self.place(t)


class ReactiveAgents:
    """The moving agents of one run, reactive: `advance(t, ego)` moves each from step t - 1 to t given the ego's
    pose at t - 1 (agents and ego update together from the same instant). Parked agents stay put."""

    def __init__(self, route: Route, idm: IDM = IDM()) -> None:
        self.idm = idm
        self.moving = [PathAgent(a) for a in route.scene.agents if not a.parked]

    def advance(self, t: int, ego: Pose) -> None:
        if t <= 0:
            return
        for agent in self.moving:
            if t < len(agent.s_path):
                agent.advance(t, ego, self.idm)


def run_world(route: Route, agents: str) -> tuple[Route, ReactiveAgents | None]:
    """The route a run drives and its reactive agents: `log` gives the route itself and None; `reactive` a copy
    whose agents' arrays the run may rewrite (the scene's own logs are shared and never written)."""
    if check_mode(agents) == "log":
        return route, None
    copies = [replace(a, xy=a.xy.copy(), yaw=a.yaw.copy(), speed=a.speed.copy()) for a in route.scene.agents]
    mine = replace(route, scene=replace(route.scene, agents=copies))
    return mine, ReactiveAgents(mine)


__all__ = ["AGENT_MODES", "IDM", "ReactiveAgents", "check_mode", "run_world"]
