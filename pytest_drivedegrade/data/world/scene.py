"""One scene of the world, generated from (seed, index): roads, appearance, agents, scenery, the expert's drive."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .agents import DT, Agent, Prop, background_traffic, crossing_walker, depart, lead_vehicle, scenery
from .expert import (
    KEY_EVERY,
    REACT_VEHICLE,
    EgoLog,
    Projections,
    allowed_speed,
    drive,
    follower,
    keyframe_events,
    start_state,
)
from .roads import LANE_WIDTH, Path, RoadNet, build_roads

KEYFRAMES = 40  # 20 s at 2 Hz, as a nuScenes scene
#: The seconds of future every scored keyframe holds: 3 (nuScenes' convention, the default world) or 4 (NAVSIM's
#: eight poses): a world with 4 s exports each scene's KEYFRAMES plus the two keyframes after it (the simulation
#: runs SIM_STEPS, past both), so its first KEYFRAMES are the default world's, the same records and images.
FUTURE_SECONDS = (3, 4)


def scene_keyframes(future_s: int = 3) -> int:
    """The keyframes a scene exports when its scored frames hold `future_s` seconds of future."""
    if future_s not in FUTURE_SECONDS:
        raise ValueError(f"future_s must be one of {FUTURE_SECONDS}, got {future_s!r}")
    return KEYFRAMES + 2 * (future_s - 3)


@dataclass
class Style:
    """Appearance of a scene: light, sky, surfaces. Drawn from the seed so that scenes look different."""

    sky_top: np.ndarray
    sky_horizon: np.ndarray
    clouds: float
    sun: np.ndarray  # unit vector towards the sun, world frame
    light: float  # global exposure factor
    asphalt: float  # asphalt grey level
    sidewalk: np.ndarray
    verge: np.ndarray  # ground beyond the sidewalk (grass or dirt)
    yellow_centre: bool
    haze_m: float  # distance at which haze reaches 63 %
    urban: float

    @staticmethod
    def draw(rng: np.random.Generator) -> Style:
        overcast = rng.random() < 0.35
        top = np.array([150, 160, 170]) if overcast else np.array([60, 110, 200]) + rng.normal(0, 12, 3)
        horizon = np.array([200, 205, 210]) if overcast else np.array([185, 205, 230]) + rng.normal(0, 8, 3)
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(0.3, 1.1)
        grass = rng.random() < 0.6
        verge = np.array([70, 110, 45]) if grass else np.array([150, 130, 100])
        return Style(np.clip(top, 0, 255), np.clip(horizon, 0, 255), float(rng.uniform(0.1, 0.9)),
                     np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)]),
                     float(rng.uniform(0.8, 1.1) * (0.85 if overcast else 1.0)), float(rng.uniform(70, 115)),
                     np.array([165, 160, 150]) + rng.normal(0, 10, 3), verge + rng.normal(0, 10, 3),
                     bool(rng.random() < 0.5), float(rng.uniform(250, 700) * (0.6 if overcast else 1.0)),
                     float(rng.uniform(0.35, 1.0)))


@dataclass
class Scene:
    index: int
    seed: int
    name: str
    net: RoadNet
    lane: Path
    agents: list[Agent]
    ego: EgoLog
    style: Style
    events: list[str]
    crosswalks: list[float]  # arc lengths on the route centreline with a zebra crossing
    v_cruise: float
    keyframes: int = KEYFRAMES  # the keyframes it exports (`scene_keyframes`)
    lights: tuple = ()  # its traffic lights (`lights.TrafficLight`): only the light scenes (`scenarios`) have any

    @functools.cached_property
    def props(self) -> list[Prop]:
        """Static scenery, drawn only when rendering (its own random stream keeps tables-only runs fast)."""
        return scenery(np.random.default_rng([self.seed, self.index, 0x9C0B]), self.net, self.style.urban)

    @property
    def key_steps(self) -> np.ndarray:
        return np.arange(self.keyframes) * KEY_EVERY


MAX_TRIES = 8  # draws of a scene's scenario before it falls back to background traffic only
MIN_GAP = 0.5  # m: the expert must keep at least this bumper gap to everything in its corridor


def draw_ground(rng: np.random.Generator, cruise: tuple[float, float]):
    """One draw of a scene's ground, in this order (the world's bytes depend on it): the roads, the ego's lane (the
    turning lane at a junction), the cruise speed in `cruise` (m/s), the style, the background traffic, the start
    state. Returns (roads, the lane's offset, the lane, cruise speed, style, background, s0, v0)."""
    net = build_roads(rng)
    turn, lanes = (net.junctions[0].turn if net.junctions else "straight"), net.route.lanes
    k = lanes - 1 if turn == "right" else (0 if turn == "left" else int(rng.integers(lanes)))
    lane_d = -(k + 0.5) * LANE_WIDTH
    lane = net.route.center.offset(lane_d)
    v_cruise = float(rng.uniform(*cruise))
    style = Style.draw(rng)
    background = background_traffic(rng, net, k)
    s0, v0 = start_state(rng, v_cruise)
    return net, lane_d, lane, v_cruise, style, background, s0, v0


def make_scene(seed: int, index: int, name: str, keyframes: int = KEYFRAMES) -> Scene:
    """Generate scene `index` of the world with `seed`: deterministic for a given (seed, index); `keyframes`
    (`scene_keyframes`) changes only how many of its keyframes are exported, never the drive."""
    rng = np.random.default_rng([seed, index, 0x5EED])
    net, lane_d, lane, v_cruise, style, background, s0, v0 = draw_ground(rng, (8.0, 14.0))
    v0 = min(v0, float(np.interp(s0, lane.s, allowed_speed(lane, v_cruise))))  # not already too fast for a bend
    seen: Projections = {}  # the background's projections on the lane, computed once for every try
    for _ in range(MAX_TRIES):  # redraw a scenario the expert cannot drive safely (too late to stop)
        scenario, crosswalks = _scenario(rng, net, lane, lane_d, v_cruise)
        agents, ego = _drive_and_release(rng, lane, scenario + background, v_cruise, v0, s0, seen)
        if ego.min_gap >= MIN_GAP:
            break
    else:
        crosswalks = []
        agents, ego = _drive_and_release(rng, lane, background, v_cruise, v0, s0, seen)
    if rng.random() < 0.5:
        agents.append(follower(rng, lane, ego))
    events = keyframe_events(lane, ego, keyframes)
    return Scene(index, seed, name, net, lane, agents, ego, style, events, crosswalks, v_cruise, keyframes)


def _scenario(rng, net: RoadNet, lane: Path, lane_d: float, v_cruise: float) -> tuple[list[Agent], list[float]]:
    """The agents the expert must react to: a lead or standing vehicle, crossing pedestrians and cyclists."""
    agents: list[Agent] = []
    if rng.random() < 0.85:
        agents.append(lead_vehicle(rng, lane, v_cruise))
    crosswalks: list[float] = []
    for kind, p in (("pedestrian", 0.6), ("pedestrian", 0.3), ("cyclist", 0.25)):
        if rng.random() < p:
            walker, s_c = crossing_walker(rng, net, lane_d, v_cruise, kind)
            if walker is not None:
                agents.append(walker)
                if kind == "pedestrian" and rng.random() < 0.7:
                    crosswalks.append(float(s_c))
    return agents, crosswalks


def _drive_and_release(rng, lane: Path, agents: list[Agent], v_cruise: float, v0: float, s0: float,
                       seen: Projections):
    """Drive the expert; a standing vehicle it has stopped behind pulls away a few seconds later (drive again)."""
    ego = drive(lane, agents, v_cruise, v0, s0, seen)
    stopped = [i for i, a in enumerate(agents) if a.role == "stopped"]
    if not stopped:
        return agents, ego
    agents = list(agents)
    halted = np.flatnonzero((ego.speed < 0.3) & (ego.react == REACT_VEHICLE))
    t_go = (halted[0] * DT if len(halted) else float(rng.uniform(4.0, 14.0))) + float(rng.uniform(1.0, 6.0))
    for i in stopped:
        agents[i] = depart(agents[i], lane, t_go)
    return agents, drive(lane, agents, v_cruise, v0, s0, seen)
