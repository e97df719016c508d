"""Scenario scenes for the closed loop (spec 5, section 18): routes where seeing matters.

Each scenario scene is generated from (world seed, scenario number) on a random stream of its own, so the world's
open-loop scenes, their tables and images and the floor trained on them are untouched (scene.py is not changed;
tests/unit/test_scenarios.py checks a world's tables byte for byte). A scene stacks two events of the kinds the
CARLA leaderboard's and Bench2Drive's scenario families use, the second an obstacle that stays in the ego's lane
until the scene ends, so a driver that does not see it runs into it:

- `crossing`: a pedestrian crossing the route about when the ego arrives, visible on the curb first; then a
  vehicle standing in the lane (queued, delivering).
- `braking`: a crossing pedestrian, and a lead vehicle that brakes hard to a stop.
- `blocked`: a crossing cyclist, then a broken-down truck or bus standing in the lane, beyond a bend where there
  is one (the past path and the command do not show it).

The logged expert (`expert.drive`) yields to the crossing and stops behind the standing vehicle, which pulls away
2-5 s after it stopped; a draw where the expert does not stop for it, or cannot drive safely, is redrawn.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...constants import EGO_LENGTH
from .agents import (
    DT,
    EGO_START_S,
    SIM_STEPS,
    Agent,
    along,
    crossing_walker,
    speed_profile,
)
from .expert import REACT_LIGHT, REACT_VEHICLE, LightStops, drive, follower, keyframe_events
from .lights import TrafficLight
from .scene import KEYFRAMES, MIN_GAP, Scene, draw_ground

#: The scenario kinds, drawn in turn (scenario i has kind i mod 3).
SCENARIO_KINDS = ("crossing", "braking", "blocked")
#: Scenario scenes are numbered from here in the scene index space (no world has this many open-loop scenes),
#: and their random stream is keyed apart from `scene.make_scene`'s.
SCENARIO_BASE, SCENARIO_KEY = 100_000, 0x5CE7A
#: Draws of a scenario before giving up on one the expert cannot drive safely.
SCENARIO_TRIES = 12


def scenario_name(i: int) -> str:
    return f"scenario-{i:04d}-{SCENARIO_KINDS[i % len(SCENARIO_KINDS)]}"


def _standing(rng, lane, s_at: float, kinds: tuple[str, ...]) -> Agent:
    """A vehicle standing in the ego's lane at arc length `s_at` (until `_release` lets it go)."""
    return along(lane, s_at, np.zeros(SIM_STEPS), str(rng.choice(kinds)), rng, "stopped")


def _braking(rng, lane, v_cruise: float) -> Agent:
    """A lead vehicle 15-30 m ahead that brakes hard (3.5-6 m/s²) to a stop 2-7 s in (role "stopped": it stays
    until `_release` lets it go)."""
    v, tb, b = rng.uniform(0.7, 1.0) * v_cruise, rng.uniform(2.0, 7.0), rng.uniform(3.5, 6.0)
    kind = str(rng.choice(["car", "car", "truck", "bus"]))
    return along(lane, EGO_START_S + rng.uniform(15, 30), speed_profile(v, [(tb, -b, 0.0)]), kind, rng, "stopped")


def _events(rng, kind: str, net, lane, lane_d: float, v_cruise: float) -> tuple[list[Agent], list[float]]:
    """The scenario's agents and crosswalks (arc lengths on the route centreline)."""
    walker_kind = "cyclist" if kind == "blocked" else "pedestrian"
    walker, s_c = crossing_walker(rng, net, lane_d, v_cruise, walker_kind)
    agents = [walker] if walker is not None else []
    crosswalks = [float(s_c)] if walker is not None and walker_kind == "pedestrian" else []
    far = max(float(s_c) + 25.0 if s_c is not None else EGO_START_S + 40.0, EGO_START_S + 40.0)
    if kind == "braking":
        agents.append(_braking(rng, lane, v_cruise))
    elif kind == "blocked":
        kappa = np.abs(lane.curvature())
        bends = lane.s[(kappa > 1 / 120) & (lane.s > far) & (lane.s < EGO_START_S + 120.0)]
        at = float(bends[0] + rng.uniform(10.0, 25.0)) if len(bends) else far + float(rng.uniform(5.0, 30.0))
        agents.append(_standing(rng, lane, at, ("truck", "bus")))
    else:
        agents.append(_standing(rng, lane, far + float(rng.uniform(5.0, 30.0)), ("car", "car", "truck")))
    return agents, crosswalks


def _pull_away(agent: Agent, lane, t_go: float, v_go: float = 9.0, accel: float = 1.8) -> Agent:
    """The same vehicle, driving its own speed profile (standing, or braking to a stop) until `t_go` (s), then
    pulling away along `lane`."""
    speed = agent.speed.copy()
    for t in range(int(np.ceil(t_go / DT)), SIM_STEPS):
        speed[t] = min(speed[t - 1] + accel * DT, v_go)
    s = float(lane.project(agent.xy[:1])[0][0]) + np.concatenate([[0.0], np.cumsum(speed[:-1] * DT)])
    x, y, yaw = lane.at(s)
    return replace(agent, xy=np.stack([x, y], 1), yaw=yaw, speed=speed)


def _release(rng, lane, agents: list[Agent], v_cruise: float, v0: float, s0: float):
    """Drive the expert; the standing vehicle pulls away 2-5 s after the expert has stopped behind it (then drive
    again). None when the expert never stopped for it or cannot drive the scene safely."""
    ego = drive(lane, agents, v_cruise, v0, s0)
    halted = np.flatnonzero((ego.speed < 0.3) & (ego.react == REACT_VEHICLE))
    if not len(halted) or ego.min_gap < MIN_GAP:
        return None
    t_go = halted[0] * DT + float(rng.uniform(2.0, 5.0))
    out = [_pull_away(a, lane, t_go) if a.role == "stopped" else a for a in agents]
    ego = drive(lane, out, v_cruise, v0, s0)
    return (out, ego) if ego.min_gap >= MIN_GAP else None


def scenario_scene(seed: int, i: int) -> Scene:
    """Scenario scene `i` of the world with `seed` (deterministic in (seed, i)); kind SCENARIO_KINDS[i mod 3].
    Roads, lane choice and background traffic are drawn as `scene.make_scene` draws them."""
    kind = SCENARIO_KINDS[i % len(SCENARIO_KINDS)]
    index = SCENARIO_BASE + i
    rng = np.random.default_rng([seed, index, SCENARIO_KEY])
    for _ in range(SCENARIO_TRIES):
        net, lane_d, lane, v_cruise, style, background, s0, v0 = draw_ground(rng, (8.0, 12.0))
        scenario, crosswalks = _events(rng, kind, net, lane, lane_d, v_cruise)
        got = _release(rng, lane, scenario + background, v_cruise, v0, s0) if len(scenario) == 2 else None
        if got is not None:
            break
    else:
        raise RuntimeError(f"scenario {i} of world seed {seed}: no drivable draw in {SCENARIO_TRIES} tries")
    agents, ego = got
    agents = [*agents, follower(rng, lane, ego)]
    events = keyframe_events(lane, ego, KEYFRAMES)
    return Scene(index, seed, scenario_name(i), net, lane, agents, ego, style, events, crosswalks, v_cruise)


#: Light scenes (`light_scene`) are numbered from here, on a random stream of their own.
LIGHT_BASE, LIGHT_KEY = 200_000, 0x119B7
#: The stop line lies this far (m of route centreline) past the ego's start; a junction square that close to it
#: moves it to the junction's painted stop line (`texture._paint_markings`: its bar from 0.75 to 0.25 m before
#: the square).
LIGHT_AHEAD_M = (45.0, 85.0)


def light_name(i: int) -> str:
    return f"lights-{i:04d}"


def _light(rng, net, s0: float, v0: float) -> TrafficLight:
    """A light whose red meets the ego: yellow 3-6 s before a free-driving ego would reach the line, green again
    4-9 s after it would have."""
    s_line = EGO_START_S + float(rng.uniform(*LIGHT_AHEAD_M))
    for j in net.junctions:
        if abs(j.s_route - s_line) < j.half + 12.0:
            s_line = float(j.s_route - j.half - 0.75)
    t_arrive = max(s_line - s0, 0.0) / max(v0, 1.0)
    t_yellow = max(t_arrive - float(rng.uniform(3.0, 6.0)), 0.5)
    return TrafficLight(s_line, net.route.lanes, t_yellow, t_arrive + float(rng.uniform(4.0, 9.0)))


def ran_red(lane, light: TrafficLight, net, ego) -> bool:
    """Whether the logged ego's front crosses the light's stop line while it is red."""
    s_stop = float(lane.project(light.stop_line(net).mean(0)[None])[0][0])
    front = ego.s + EGO_LENGTH / 2
    crossed = np.flatnonzero((front[:-1] <= s_stop) & (front[1:] > s_stop))
    return any(light.state_at((t + 1) * DT) == "red" for t in crossed)


def light_scene(seed: int, i: int) -> Scene:
    """Light scene `i` of the world with `seed` (deterministic in (seed, i)): roads, lane, background traffic and a
    traffic light whose red the expert stops at; redrawn when the expert does not stop for it, runs it, or cannot
    drive the scene safely."""
    index = LIGHT_BASE + i
    rng = np.random.default_rng([seed, index, LIGHT_KEY])
    for _ in range(SCENARIO_TRIES):
        net, _, lane, v_cruise, style, background, s0, v0 = draw_ground(rng, (8.0, 12.0))
        light = _light(rng, net, s0, v0)
        ego = drive(lane, background, v_cruise, v0, s0, lights=LightStops.on(lane, [light], net))
        stopped = bool(((ego.speed < 0.3) & (ego.react == REACT_LIGHT)).any())
        if stopped and ego.min_gap >= MIN_GAP and not ran_red(lane, light, net, ego):
            break
    else:
        raise RuntimeError(f"light scene {i} of world seed {seed}: no drivable draw in {SCENARIO_TRIES} tries")
    agents = [*background, follower(rng, lane, ego)]
    events = keyframe_events(lane, ego, KEYFRAMES)
    return Scene(index, seed, light_name(i), net, lane, agents, ego, style, events, [], v_cruise,
                 lights=(light,))


__all__ = ["DT", "SCENARIO_KINDS", "light_name", "light_scene", "scenario_name", "scenario_scene"]
