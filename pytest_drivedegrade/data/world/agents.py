"""Who is in a scene: scripted agents (traffic, parked cars, pedestrians, cyclists) and static scenery.

Agents are scripted along lane or sidewalk paths on the simulation clock (`DT`, `SIM_STEPS`); only the ego
(and a follower behind it) react, in `expert.py`. Sizes are (length, width, height) in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .roads import LANE_WIDTH, SIDEWALK, Path, RoadNet, distance_to_roads, in_junction

DT = 0.1  # s, simulation step
SIM_STEPS = 245  # 24.5 s: a 20 s scene plus margin
EGO_START_S = 70.0  # m along the route centreline

#: kind -> (nuScenes category, length range, width range, height range)
KINDS = {
    "car": ("vehicle.car", (4.2, 4.9), (1.75, 1.95), (1.45, 1.75)),
    "truck": ("vehicle.truck", (6.5, 8.5), (2.3, 2.5), (2.8, 3.4)),
    "bus": ("vehicle.bus.rigid", (10.5, 12.0), (2.5, 2.6), (3.1, 3.4)),
    "pedestrian": ("human.pedestrian.adult", (0.5, 0.7), (0.5, 0.7), (1.55, 1.9)),
    "cyclist": ("vehicle.bicycle", (1.7, 1.9), (0.55, 0.7), (1.6, 1.8)),
}
VEHICLE_COLOURS = np.array([[200, 200, 205], [30, 30, 35], [150, 20, 25], [20, 50, 130], [235, 235, 230],
                            [90, 95, 100], [160, 150, 120], [25, 90, 60], [220, 170, 20], [120, 60, 30]])


@dataclass
class Agent:
    kind: str
    size: tuple[float, float, float]
    colour: tuple[int, int, int]
    xy: np.ndarray  # (SIM_STEPS, 2)
    yaw: np.ndarray  # (SIM_STEPS,)
    speed: np.ndarray  # (SIM_STEPS,) m/s, signed along the heading
    role: str = "traffic"  # lead, stopped, follower, oncoming, parked, waiting, walker, crossing, cyclist
    parked: bool = False

    @property
    def category(self) -> str:
        return KINDS[self.kind][0]

    @property
    def braking(self) -> np.ndarray:
        """Brake lights: decelerating, or standing still in traffic (not parked)."""
        acc = np.gradient(self.speed, DT)
        return ((acc < -0.6) | (np.abs(self.speed) < 0.2)) & (not self.parked)


@dataclass
class Prop:
    kind: str  # building, tree, pole
    xy: np.ndarray
    size: tuple[float, float, float]
    yaw: float
    colour: tuple[int, int, int]
    extra: dict = field(default_factory=dict)


def _size(rng, kind):
    _, lr, wr, hr = KINDS[kind]
    return (float(rng.uniform(*lr)), float(rng.uniform(*wr)), float(rng.uniform(*hr)))


def _colour(rng):
    return tuple(int(c) for c in np.clip(VEHICLE_COLOURS[rng.integers(len(VEHICLE_COLOURS))]
                                         + rng.normal(0, 8, 3), 0, 255))


def speed_profile(v0: float, events: list[tuple[float, float, float]]) -> np.ndarray:
    """Speeds on the sim clock: start at v0; from each event's t_start (the latest started one rules) the speed
    ramps with `accel` toward `target`."""
    v = np.empty(SIM_STEPS)
    cur = v0
    for i in range(SIM_STEPS):
        started = [e for e in events if i * DT >= e[0]]
        if started:
            _, acc, target = started[-1]
            cur = max(cur + acc * DT, target) if acc < 0 else min(cur + acc * DT, target)
        v[i] = cur
    return v


def along(path: Path, s0: float, speed: np.ndarray, kind: str, rng, role: str, **kw) -> Agent:
    """An agent that travels `path` from arc length `s0` with the given speed profile."""
    s = s0 + np.concatenate([[0.0], np.cumsum(speed[:-1] * DT)])
    x, y, yaw = path.at(s)
    return Agent(kind, _size(rng, kind), _colour(rng), np.stack([x, y], 1), yaw, speed, role, **kw)


def lead_vehicle(rng, lane: Path, v_cruise: float) -> Agent:
    """The vehicle ahead in the ego lane: slower, braking to a stop (and going again), or standing in the lane
    (queued, broken down, delivering: role "stopped") until the scene releases it with `depart`."""
    mode = rng.choice(["follow", "brake", "stopped"], p=[0.2, 0.35, 0.45])
    if mode == "follow":
        kind = str(rng.choice(["car", "car", "car", "truck", "bus"]))
        v = rng.uniform(3.0, 0.75 * v_cruise)
        return along(lane, EGO_START_S + rng.uniform(18, 35), speed_profile(v, []), kind, rng, "lead")
    if mode == "brake":
        kind = str(rng.choice(["car", "car", "car", "truck", "bus"]))
        v, tb, b = rng.uniform(0.7, 1.0) * v_cruise, rng.uniform(1.5, 11.0), rng.uniform(2.5, 5.0)
        go = tb + v / b + rng.uniform(2.0, 6.0)
        prof = speed_profile(v, [(tb, -b, 0.0), (go, 1.6, v)])
        return along(lane, EGO_START_S + rng.uniform(15, 30), prof, kind, rng, "lead")
    kind = str(rng.choice(["car", "truck", "truck", "bus"]))
    s_q = EGO_START_S + 20.0 + v_cruise * rng.uniform(2.5, 11.0)
    return along(lane, s_q, np.zeros(SIM_STEPS), kind, rng, "stopped")


def depart(agent: Agent, lane: Path, t_go: float, v_go: float = 9.0, accel: float = 1.8) -> Agent:
    """The same standing agent, pulling away along `lane` from time `t_go` (s)."""
    s0 = float(lane.project(agent.xy[:1])[0][0])
    speed = speed_profile(0.0, [(t_go, accel, v_go)])
    s = s0 + np.concatenate([[0.0], np.cumsum(speed[:-1] * DT)])
    x, y, yaw = lane.at(s)
    return replace(agent, xy=np.stack([x, y], 1), yaw=yaw, speed=speed)


def crossing_walker(rng, net: RoadNet, lane_d: float, v_cruise: float, kind: str = "pedestrian"):
    """A pedestrian (or cyclist) that crosses the route about when the ego arrives; None if no room."""
    route = net.route.center
    for _ in range(6):
        s_c = EGO_START_S + v_cruise * rng.uniform(4.0, 14.0)
        x, y, yaw = route.at(s_c)
        if s_c < route.length - 60 and not in_junction(net, np.array([[x, y]]), 6.0)[0]:
            break
    else:
        return None, None
    hw = net.route.half_width
    side = rng.choice([-1.0, 1.0])
    start, end = side * (hw + 1.0), -side * (hw + 1.5)
    v = rng.uniform(1.1, 1.6) if kind == "pedestrian" else rng.uniform(3.0, 4.5)
    t_arrive = (s_c - EGO_START_S) / v_cruise
    t0 = max(0.0, t_arrive - abs(start - lane_d) / v + rng.uniform(-2.0, 1.5))
    t = np.arange(SIM_STEPS) * DT
    d = start + np.clip(t - t0, 0.0, None) * v * np.sign(end - start)
    d = np.clip(d, min(start, end), max(start, end))
    n = np.array([-np.sin(yaw), np.cos(yaw)])
    xy = np.array([x, y]) + d[:, None] * n
    heading = yaw + np.pi / 2 * np.sign(end - start)
    speed = np.abs(np.gradient(d, DT))
    agent = Agent(kind, _size(rng, kind), _colour(rng), xy, np.full(SIM_STEPS, heading), speed, "crossing")
    return agent, s_c


def background_traffic(rng, net: RoadNet, ego_lane: int) -> list[Agent]:
    """Oncoming traffic, parked cars, cars waiting at the junction, walkers and cyclists on the side."""
    road, out = net.route, []
    c = road.center
    for _ in range(int(rng.integers(2, 7))):
        lane = c.offset((int(rng.integers(road.lanes)) + 0.5) * LANE_WIDTH).reversed()
        kind = str(rng.choice(["car", "car", "car", "truck", "bus"]))
        out.append(along(lane, rng.uniform(0, lane.length - 150), speed_profile(rng.uniform(6, 13), []),
                         kind, rng, "oncoming"))
    for _ in range(int(rng.integers(4, 15))):
        side = rng.choice([-1.0, 1.0])
        path = c.offset(side * (road.lanes * LANE_WIDTH + 1.1))
        path = path if side < 0 else path.reversed()
        a = along(path, rng.uniform(0, path.length), np.zeros(SIM_STEPS), "car", rng, "parked", parked=True)
        if not in_junction(net, a.xy[:1], 6.0)[0]:
            out.append(a)
    for j in net.junctions:
        for sign in (-1.0, 1.0):
            if rng.random() < 0.6:
                arm = np.array([-np.sin(j.heading), np.cos(j.heading)]) * sign
                right = np.array([arm[1], -arm[0]])  # the right side of a car driving towards the junction
                pos = j.center + arm * (j.half + 3.0) - right * 0.5 * LANE_WIDTH
                yaw = np.arctan2(-arm[1], -arm[0])
                out.append(Agent("car", _size(rng, "car"), _colour(rng), np.tile(pos, (SIM_STEPS, 1)),
                                 np.full(SIM_STEPS, yaw), np.zeros(SIM_STEPS), "waiting"))
    for _ in range(int(rng.integers(4, 13))):
        side = rng.choice([-1.0, 1.0])
        path = c.offset(side * (road.half_width + rng.uniform(0.8, 2.2)))
        v = 0.0 if rng.random() < 0.3 else rng.uniform(0.9, 1.5)
        path = path if rng.random() < 0.5 else path.reversed()
        out.append(along(path, rng.uniform(0, path.length), np.full(SIM_STEPS, v), "pedestrian", rng, "walker"))
    for _ in range(int(rng.integers(0, 3))):
        path = c.offset(-(road.lanes * LANE_WIDTH + 0.9))
        out.append(along(path, EGO_START_S + rng.uniform(-30, 150), np.full(SIM_STEPS, rng.uniform(3, 5.5)),
                         "cyclist", rng, "cyclist"))
    return out


def scenery(rng, net: RoadNet, urban: float) -> list[Prop]:
    """Buildings, trees and street lights along every road, kept off carriageways, sidewalks and each other."""
    props: list[Prop] = []
    taken: list[tuple[np.ndarray, float]] = []
    palette = rng.uniform(60, 220, size=(5, 3))
    for road in net.roads:
        hw, c = road.half_width, road.center
        for side in (-1.0, 1.0):
            s = rng.uniform(0, 10)
            while s < c.length:
                front, depth = rng.uniform(8, 22), rng.uniform(8, 16)
                if rng.random() < urban:
                    lat = hw + SIDEWALK + rng.uniform(0.5, 5.0) + depth / 2
                    height = rng.uniform(5, 12) + urban * rng.uniform(0, 20)
                    col = np.clip(palette[rng.integers(5)] + rng.normal(0, 12, 3), 0, 255)
                    _place(props, taken, net, c, s + front / 2, side * lat, (front, depth, height), "building",
                           tuple(int(v) for v in col), SIDEWALK + 0.5, rng)
                s += front + rng.uniform(1, 8)
            for s in np.arange(rng.uniform(0, 10), c.length, rng.uniform(9, 20)):
                if rng.random() < 0.75:
                    _place(props, taken, net, c, s, side * (hw + rng.uniform(0.7, 1.3)),
                           (0.4, 0.4, rng.uniform(4, 8)), "tree", (70, 52, 35), 0.3, rng)
            for s in np.arange(rng.uniform(0, 20), c.length, rng.uniform(25, 40)):
                _place(props, taken, net, c, s, side * (hw + 0.4), (0.2, 0.2, 7.5), "pole", (120, 120, 125),
                       0.2, rng)
    return props


def _place(props, taken, net, path: Path, s, d, size, kind, colour, clearance, rng) -> None:
    x, y, yaw = path.at(s)
    n = np.array([-np.sin(yaw), np.cos(yaw)])
    xy = np.array([x, y]) + d * n
    radius = 0.5 * float(np.hypot(size[0], size[1])) if kind == "building" else 0.5 + (2.0 if kind == "tree" else 0)
    if kind == "building":
        u, v = np.array([np.cos(yaw), np.sin(yaw)]), n
        probe = xy + np.array([[a * size[0] / 2 * u + b * size[1] / 2 * v] for a in (-1, 1) for b in (-1, 1)])[:, 0]
        probe = np.vstack([xy, probe])
    else:
        probe = xy[None]
    if distance_to_roads(net, probe).min() < clearance:
        return
    if any(np.linalg.norm(xy - p) < r + radius for p, r in taken):
        return
    taken.append((xy, radius))
    extra = {"floors": max(1, int(size[2] / 3.2)), "crown": float(rng.uniform(1.6, 3.0))}
    props.append(Prop(kind, xy, size, float(yaw), colour, extra))
