"""What the world says about the simulated ego at one 10 Hz step: its collisions (with the open-loop PDMS rule for
who is at fault, `metrics.pdms.rules.at_fault`, for the at-fault option), whether it is outside its route's lanes
(off the driving and parking lanes, or in an oncoming lane: the leaderboard's OutsideRouteLanesTest), the speed
the minimum-speed test compares with (MinimumSpeedRouteTest), and whether the road ahead is free (blocked end)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..constants import EGO_LENGTH, EGO_WIDTH
from ..data.frame import AgentBoxes
from ..data.nuscenes import coarse_category
from ..data.world.agents import DT
from ..data.world.lights import RED, segments_cross
from ..data.world.roads import LANE_WIDTH, distance_to_roads, in_junction
from ..metrics.pdms.agents import hits
from ..metrics.pdms.motion import EgoStates
from ..metrics.pdms.rules import Contact, at_fault
from .leaderboard import ALLOWED_OUT_M, BLOCKED_SPEED, RED_LIGHT_DISTANCE_M
from .routes import Route

__all__ = ["BLOCKED_SPEED", "Pose", "collisions", "outside_m", "outside_route_lanes", "red_lights_run",
           "road_ahead_free", "traffic_speed"]

EGO_SIZE = np.array([EGO_LENGTH, EGO_WIDTH])
#: Props (buildings, trees, poles) farther than this from the ego are not tested for contact (m).
PROP_REACH = 15.0
#: The corridor ahead that must be free of agents for a standstill to count as blocked: length, half width (m).
AHEAD_M, AHEAD_HALF_WIDTH = 20.0, 2.5


@dataclass(frozen=True)
class Pose:
    """The simulated ego at one step, world frame: box centre, heading, speed and acceleration along it."""

    x: float
    y: float
    yaw: float
    speed: float
    accel: float

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.x, self.y])


def footprint(pose: Pose) -> np.ndarray:
    """The ego box's four corners (4, 2), world frame."""
    c, s = np.cos(pose.yaw), np.sin(pose.yaw)
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * (EGO_SIZE / 2)
    return pose.xy + local @ np.array([[c, s], [-s, c]])


def outside_m(route: Route, pose: Pose) -> float:
    """How far (m) the ego box's farthest corner lies outside the drivable area (<= 0: inside)."""
    return float(distance_to_roads(route.scene.net, footprint(pose)).max())


def outside_route_lanes(route: Route, pose: Pose) -> bool:
    """The ego's centre outside every driving and parking lane by more than ALLOWED_OUT_M (the carriageway and
    junction squares are those lanes), or in an oncoming lane of the route's road (left of its centreline, outside
    junctions, where the leaderboard does not judge lanes either)."""
    net = route.scene.net
    if float(distance_to_roads(net, pose.xy)[0]) > ALLOWED_OUT_M:
        return True
    if bool(in_junction(net, pose.xy)[0]):
        return False
    _, d = net.route.center.project(pose.xy)
    return bool(0.0 < float(d[0]) <= net.route.half_width)


def traffic_speed(route: Route, step: int) -> float:
    """The speed (m/s) the minimum-speed test compares the ego's with at log `step`: the logged expert's on this
    route. The leaderboard compares with its background vehicles, which flow around the ego at the town's speed
    limits; the world's other vehicles do not (they drive other roads and the oncoming lanes, or are the scenario's
    own), so the flow the route allows is the expert's, who obeyed every event on it."""
    ego = route.scene.ego
    return abs(float(ego.speed[min(step, len(ego.speed) - 1)]))


def _states(pose: Pose) -> EgoStates:
    heading = np.array([pose.yaw])
    vel = pose.speed * np.array([[np.cos(pose.yaw), np.sin(pose.yaw)]])
    return EgoStates(pose.xy[None], vel, pose.accel * vel / max(pose.speed, 1e-9), heading, np.array([pose.speed]))


def agent_boxes(route: Route, step: int) -> tuple[AgentBoxes, np.ndarray]:
    """The agents' boxes at log `step` (world frame) and their velocities (N, 2)."""
    agents = route.scene.agents
    if not agents:
        return AgentBoxes.empty(), np.zeros((0, 2))
    yaw = np.array([a.yaw[step] for a in agents])
    speed = np.array([a.speed[step] for a in agents])
    boxes = AgentBoxes(np.array([a.xy[step] for a in agents]), np.array([a.size[:2] for a in agents]), yaw,
                       tuple(coarse_category(a.category) for a in agents))
    return boxes, speed[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)


def collisions(route: Route, pose: Pose, step: int, astray: bool) -> list[tuple[str, int, bool]]:
    """Contacts at log `step`: (kind, agent index, at fault) per agent touched; props as (collision_static, -1 - i,
    True). The caller judges an agent by its first contact only, as NAVSIM ignores a not-at-fault track after."""
    boxes, velocities = agent_boxes(route, step)
    states, out = _states(pose), []
    for j in hits(pose.xy, pose.yaw, boxes, EGO_SIZE):
        agent = route.scene.agents[int(j)]
        contact = Contact.of(0, boxes, int(j), np.arange(len(boxes)), velocities)
        kind = "collision_pedestrian" if agent.kind == "pedestrian" else "collision_vehicle"  # CARLA: a bicycle
        # is a vehicle.* actor
        out.append((kind, int(j), at_fault(states, contact, np.array([astray]), agent.parked)))
    props = route.scene.props
    near = [i for i, p in enumerate(props) if np.hypot(*(np.asarray(p.xy) - pose.xy)) < PROP_REACH]
    if near and pose.speed > 0.1:
        pb = AgentBoxes(np.array([props[i].xy for i in near], dtype=np.float64),
                        np.array([props[i].size[:2] for i in near], dtype=np.float64),
                        np.array([props[i].yaw for i in near], dtype=np.float64), ("other",) * len(near))
        out += [("collision_static", -1 - near[int(j)], True) for j in hits(pose.xy, pose.yaw, pb, EGO_SIZE)]
    return out


def road_ahead_free(route: Route, pose: Pose, step: int) -> bool:
    """No agent box centre in the corridor AHEAD_M ahead of the ego (a standstill there is the planner's)."""
    boxes, _ = agent_boxes(route, step)
    if not len(boxes):
        return True
    rel = np.asarray(boxes.center) - pose.xy
    c, s = np.cos(pose.yaw), np.sin(pose.yaw)
    fwd, side = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
    return not bool(((fwd > 0) & (fwd < AHEAD_M) & (np.abs(side) < AHEAD_HALF_WIDTH)).any())


def red_lights_run(route: Route, pose: Pose, step: int) -> list[int]:
    """The lights (indices into the scene's `lights`) the ego runs at sim `step`, as RunningRedLightTest judges:
    the light red, its stop line within RED_LIGHT_DISTANCE_M of the ego, the ego heading along the lane, and the
    segment behind the ego's centre from 0.8 x its half length to its half length + 1 m (its tail) crossing the
    stop line, which reaches 0.1 lane width beyond the outer lanes (CARLA: 0.6 lane width either side of each
    lane's waypoint). The caller counts a light once."""
    scene = route.scene
    out = []
    heading = np.array([np.cos(pose.yaw), np.sin(pose.yaw)])
    half = EGO_LENGTH / 2
    tail = np.stack([pose.xy - 0.8 * half * heading, pose.xy - (half + 1.0) * heading])
    for j, light in enumerate(scene.lights):
        if light.state_at(step * DT) != RED:
            continue
        line = light.stop_line(scene.net)
        if float(np.hypot(*(line.mean(0) - pose.xy))) > RED_LIGHT_DISTANCE_M:
            continue
        _, _, lane_yaw = scene.net.route.center.at(light.s_line)
        if float(np.cos(pose.yaw - lane_yaw)) <= 0:
            continue
        along = (line[1] - line[0]) / max(float(np.hypot(*(line[1] - line[0]))), 1e-9)
        wide = np.stack([line[0] - 0.1 * LANE_WIDTH * along, line[1] + 0.1 * LANE_WIDTH * along])
        if segments_cross(tail, wide):
            out.append(j)
    return out
