"""The percept bound: the world expert's rule driven from a few numbers a camera could tell, read from the world.

A driver that perceives, at each planner call (2 Hz), the lane ahead, the bend speeds, the free corridor, the lead's
speed and the next red or yellow stop line, and plans with the expert's own rule (`data.world.expert`: IDM to the
cruise speed, braking for bends, obstacles and lights) from its own speed, through the same tracker as any planner.
`PerceptExpert` reads those numbers from the world (privileged): its Driving Score is what a camera driver that
perceived them exactly would score, the bound of the modular design in docs/how-to/closed-loop.md, where a network
predicts the `Percept` and `plan` drives it.

Where the world expert's log and this bound differ: it replans every 0.5 s, not every 0.1 s; it sees where each
agent is now (no reaction delay) and assumes it keeps its speed for 3 s; it counts a pedestrian or cyclist
`VRU_EARLY_S` before it enters the corridor; it stops `STOP_MARGIN` before a red line and holds there; its cruise
speed is inferred once per route from the first ego status (`cruise_from_status`), not known. Like the expert it
decides once whether to go on at a yellow line and keeps to it (`YellowDecision`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..constants import EGO_LENGTH, HORIZON_STEPS
from ..data.context import FrameContext
from ..data.frame import Command, EgoStatus
from ..data.world.agents import DT
from ..data.world.expert import (
    A_MAX,
    B_LIGHT,
    B_MAX,
    B_TRIGGER,
    B_YELLOW,
    S0,
    ExpertRule,
    LightStops,
    allowed_speed,
    idm,
    required_decel,
)
from ..data.world.lights import RED, YELLOW
from .expert import WorldExpert
from .loop_io import to_ego
from .routes import Route
from .simulate import PLAN_EVERY

#: Arc offsets (m) ahead of the ego's projection on its lane at which the lane is perceived, and the bend speeds.
LANE_AHEAD = (0.0, 3.0, 6.0, 10.0, 15.0, 21.0, 28.0, 36.0, 45.0)
BEND_AHEAD = (0.0, 5.0, 10.0, 20.0, 30.0, 45.0)
#: Farther than this (m) nothing is perceived: a free corridor or no stop line reads FAR_M.
FAR_M = 60.0
#: Bend speeds are capped here (m/s): a straight road reads V_TOP.
V_TOP = 20.0
#: A pedestrian or cyclist counts this long (s) before it enters the corridor (the world expert: 0.5 s).
VRU_EARLY_S = 1.5
#: The driver stops its front bumper STOP_MARGIN (m) before a red or yellow line (the expert: 1 m), and keeps a
#: line it has passed by less than PAST_LINE_M in view (so that a stop a little past the line holds).
STOP_MARGIN, PAST_LINE_M = 2.0, 3.0
#: The IDM desired speed's range in the world (`data.world.scene`: the cruise speed is drawn in 8 .. 14 m/s).
CRUISE_RANGE = (8.0, 14.0)


@dataclass(frozen=True)
class Percept:
    """What the driver knows at one call, in its own frame: the lane at `LANE_AHEAD` (x, y) m, the bend speeds at
    `BEND_AHEAD` (m/s), the bumper gap to the nearest obstacle in the corridor and its speed along the lane (FAR_M
    and V_TOP: none), the front bumper's distance to the next stop line (FAR_M: none) and its state."""

    lane: np.ndarray  # (len(LANE_AHEAD), 2)
    bend: np.ndarray  # (len(BEND_AHEAD),)
    gap: float = FAR_M
    lead_speed: float = V_TOP
    line: float = FAR_M
    red: bool = False
    yellow: bool = False


class WorldPercept:
    """Reads a route's `Percept` at any sim step and ego pose from the world (privileged)."""

    def __init__(self, route: Route) -> None:
        scene = route.scene
        self.lane = scene.lane
        self.rule = ExpertRule.of(scene.lane, scene.agents, V_TOP)
        self.lights = LightStops.on(scene.lane, list(scene.lights), scene.net) if scene.lights else None
        self.bend = allowed_speed(scene.lane, V_TOP)  # the bend speeds alone: a cruise speed no bend reaches
        early, vru = int(round(VRU_EARLY_S / DT)), ~self.rule.vehicle
        block = self.rule.block.copy()  # already 0.5 s early for pedestrians and cyclists: add the rest
        for k in range(1, early - 4):
            block[vru, : block.shape[1] - k] |= self.rule.block[vru, k:]
        self.block = block

    def at(self, t: int, s: float, pose: tuple[float, float, float]) -> Percept:
        """The percept at sim step `t` of an ego at arc length `s` on the lane and world `pose` (x, y, yaw)."""
        x, y, _ = self.lane.at(s + np.asarray(LANE_AHEAD))
        lane = to_ego(np.stack([x, y], axis=1), pose)
        bend = np.interp(s + np.asarray(BEND_AHEAD), self.lane.s, self.bend)
        rule, t = self.rule, min(t, self.rule.block.shape[1] - 1)
        gap, lead_speed = FAR_M, V_TOP
        ahead = self.block[:, t] & (rule.s_obs[:, t] > s)
        if ahead.any():
            gaps = rule.s_obs[:, t] - s - rule.half_len
            i = int(np.flatnonzero(ahead)[np.argmin(gaps[ahead])])
            if gaps[i] < FAR_M:
                gap = float(max(gaps[i], 0.0))
                lead_speed = float(max(rule.v_obs[i, t], 0.0)) if rule.vehicle[i] else 0.0
        line, state = FAR_M, ""
        if self.lights is not None:
            front = s + EGO_LENGTH / 2
            for j, light in enumerate(self.lights.lights):
                d = float(self.lights.s_stop[j] - front)
                if -PAST_LINE_M < d < line:
                    line, state = d, light.state_at(t * DT)
        return Percept(lane, bend, gap, lead_speed, line, state == RED, state == YELLOW)


def yellow_going(p: Percept, speed: float) -> bool:
    """The expert's choice at a yellow line: go on when stopping before it would need more than `B_YELLOW`."""
    return p.yellow and p.line < FAR_M and speed * speed / (2 * max(p.line - STOP_MARGIN, 0.1)) > B_YELLOW


class YellowDecision:
    """Whether to go on at the yellow line ahead, decided once, as the expert decides at the onset of yellow
    (`data.world.expert.LightStops`): at the first call that reads a red or yellow line (going on only if that line
    is yellow and `yellow_going`), kept while a red or yellow line is read, forgotten at a call that reads none.
    Deciding again at each call lets a line read a few metres nearer turn a begun stop into a run through the
    yellow, which then turns red before the ego clears it."""

    def __init__(self) -> None:
        self.going: bool | None = None

    def update(self, p: Percept, speed: float) -> bool:
        if not ((p.red or p.yellow) and p.line < FAR_M):
            self.going = None
            return False
        if self.going is None:
            self.going = yellow_going(p, speed)
        return self.going


def plan_arcs(p: Percept, speed: float, cruise: float, going: bool | None = None) -> np.ndarray:
    """Arc lengths (m) at +0.5 .. +3 s of the expert's rule driven from `speed` with percept `p`: IDM to `cruise`,
    the bend speeds, the obstacle (assumed to keep its speed; followed once stopping for it needs `B_TRIGGER` or it
    is closer than S0 + 0.5 s), the red or yellow line (braking once stopping needs `B_LIGHT`; at yellow going on
    when `going`, a `YellowDecision`, or when None, `yellow_going` now)."""
    v, s, out = max(speed, 0.0), 0.0, []
    bend = np.minimum(p.bend, cruise)
    stop = (p.red or p.yellow) and p.line < FAR_M
    going = p.yellow and stop and (yellow_going(p, v) if going is None else going)
    lead, engaged, braking = p.gap < FAR_M, False, False
    for k in range(PLAN_EVERY * HORIZON_STEPS):
        a = idm(v, cruise, None, 0.0)
        allowed = float(np.interp(s + v * DT, BEND_AHEAD, bend))
        if v > allowed + 1e-3:
            a = (allowed - v) / DT
        if lead:
            gap = p.gap + p.lead_speed * k * DT - s
            need = required_decel(v, gap, p.lead_speed)
            engaged = engaged or need > B_TRIGGER or gap < S0 + 0.5 * v
            if engaged:
                a = min(a, -need if v > p.lead_speed + 0.5 else idm(v, cruise, gap, v - p.lead_speed))
        if stop and not going:
            room = p.line - STOP_MARGIN - s
            need = v * v / (2 * max(room, 0.1))
            braking = braking or need > B_LIGHT or room < 1.0 or p.yellow
            if braking:
                a = min(a, -need if v > 0.5 and room > 0.1 else -B_MAX)
        v_next = max(v + max(a, -B_MAX) * DT, 0.0)
        s += 0.5 * (v + v_next) * DT
        v = v_next
        if k % PLAN_EVERY == PLAN_EVERY - 1:
            out.append(s)
    return np.array(out)


def on_lane(lane: np.ndarray, arcs: np.ndarray) -> np.ndarray:
    """Points (N, 2) at arc offsets `arcs` along the perceived lane (LANE_AHEAD points; straight on past the last)."""
    ahead = np.asarray(LANE_AHEAD)
    x, y = np.interp(arcs, ahead, lane[:, 0]), np.interp(arcs, ahead, lane[:, 1])
    far = arcs > ahead[-1]
    if far.any():
        k = (arcs[far] - ahead[-1]) / (ahead[-1] - ahead[-2])
        x[far] = lane[-1, 0] + k * (lane[-1, 0] - lane[-2, 0])
        y[far] = lane[-1, 1] + k * (lane[-1, 1] - lane[-2, 1])
    return np.stack([x, y], axis=1)


def tracked_lead_speed(gap: float, gap_before: float, speed: float, speed_before: float,
                       dt: float = PLAN_EVERY * DT) -> float:
    """The lead's speed (m/s, at least 0) that the bumper gap's change over the last `dt` s implies, with the ego's
    mean speed over it: v_lead = v_ego + d(gap)/dt. A new, nearer obstacle reads slow; one that left reads fast."""
    return max(0.5 * (speed + speed_before) + (gap - gap_before) / dt, 0.0)


def cruise_from_status(ego: EgoStatus) -> float:
    """The IDM desired speed that the ego status's speed and acceleration imply on a free road (a = A_MAX (1 -
    (v / v0)^4) solved for v0), in CRUISE_RANGE; the speed itself when the ego is not speeding up."""
    v, a = max(float(ego.velocity[0]), 0.0), float(ego.acceleration[0])
    v0 = v / max(1.0 - a / A_MAX, 1e-3) ** 0.25 if a > 0.02 else v
    return float(np.clip(v0, *CRUISE_RANGE))


class RulePlanner:
    """The expert's rule as a planner of percepts, with what it keeps within a route: the cruise speed read from the
    route's first status (`cruise_from_status`) and the yellow decision (`YellowDecision`). `reset()` at each new
    route or scene; `plan(p, ego)` at each call."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.cruise: float | None = None
        self.yellow = YellowDecision()

    def plan(self, p: Percept, ego: EgoStatus) -> np.ndarray:
        """Waypoints (6, 2) in the ego frame: `plan_arcs` from the ego's speed, placed on the perceived lane."""
        if self.cruise is None:
            self.cruise = cruise_from_status(ego)
        v = float(ego.velocity[0])
        return on_lane(p.lane, plan_arcs(p, v, self.cruise, self.yellow.update(p, v)))


class PerceptExpert(WorldExpert):
    """The percept bound as a planner (privileged: reads no camera; needs reset(route) and the frame context)."""

    name = "percept_expert"

    def __init__(self, routes: Sequence[Route]) -> None:
        super().__init__(routes)
        self._world: WorldPercept | None = None
        self._rule = RulePlanner()

    def reset(self, route: str) -> None:
        super().reset(route)
        assert self._route is not None
        self._world = WorldPercept(self._route)
        self._rule.reset()

    def percept(self, context: FrameContext) -> Percept:
        """The world's percept at the context's step and pose."""
        if self._route is None or self._world is None:
            raise RuntimeError("the percept expert needs reset(route) and the frame context")
        pose = (float(context.ego2global[0, 3]), float(context.ego2global[1, 3]),
                float(np.arctan2(context.ego2global[1, 0], context.ego2global[0, 0])))
        s = float(self._route.lane.project(np.array([pose[:2]]))[0][0])
        return self._world.at(self._route.start_step + PLAN_EVERY * context.index, s, pose)

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command,
                context: FrameContext | None = None) -> np.ndarray:
        if context is None:
            raise RuntimeError("the percept expert needs reset(route) and the frame context")
        return self.plan(self.percept(context), ego)

    def plan(self, p: Percept, ego: EgoStatus) -> np.ndarray:
        """The rule's waypoints from percept `p` (`RulePlanner`)."""
        return self._rule.plan(p, ego)
