"""NAVSIM v2.2's scorer on the neutral cases of `benchmarks/navsim_reference.py` (run inside NAVSIM's environment).

    <navsim python> benchmarks/navsim_driver.py cases.json navsim.json [keyframes|interpolated]

It imports NAVSIM and nuPlan's devkit only, never the project. The environment (not the project's): NAVSIM at
commit 359c7f7 (tag v2.2 with the 2025-09-29 human-filter fix), nuPlan's devkit at tag nuplan-devkit-v1.2, both
unpacked from their GitHub snapshots onto a path file of a fresh venv, plus the PyPI packages their import chain
asks for (docs/explanation/navsim.md, "Checked against NAVSIM v2.2's own scorer").

Per frame it builds, in the frame's ego frame (the ego's rear axle at the origin, heading 0):

- the ego: `EgoState.build_from_rear_axle` with the frame's velocity and acceleration (no yaw rate, no steering
  angle: NAVSIM's `ego_status_to_ego_state`), and
  `VehicleParameters` of the project's box (length, width) centred on the rear axle (front = rear length = half
  the length: the project tracks and boxes the same point) with the Pacifica's wheel base, which both trackers use;
- the expert and each plan: NAVSIM `Trajectory`s of six 0.5 s poses (the project's waypoint headings);
- the agents: `DetectionsTracks` at every 0.1 s step of 3 s, holding the frame's boxes at the six waypoint times
  (0.5 .. 3 s) and none between (the project scores agents where the data annotate them: this keeps the inputs
  the same), or (``interpolated``) NAVSIM's own 10 Hz interpolation of those annotations (`detections`); a box
  is an `Agent` (vehicle, pedestrian, bicycle) with the project's track id as its track token and its track's
  first-seen velocity, or a `StaticObject` (generic object) for the category "other";
- the map: a `PDMDrivableMap` of the drivable area's polygons (`DRIVABLE_AREA`), the lanes (`LANE`, connectors
  `LANE_CONNECTOR`) and intersections (`INTERSECTION`); the centreline a `PDMPath` through the project's route
  centreline (what PDM-Closed's `centerline` is in NAVSIM); the route lanes the lanes the case file names;
- the past: an `InterpolatedTrajectory` of the three past keyframes and this one (heading and acceleration).

Then NAVSIM's `pdm_score` (its simulator, `LogReplayTrafficAgents`, `PDMScorer` with the default v2 config and
the human filter on, the expert as `metric_cache.trajectory`, the progress reference) scores each plan, once with
the filter and once without; EC is `ego_is_two_frame_extended_comfort` on the same kind of plan's simulated states
of the previous frame, overlapped as `SceneAggregator` does. The EPDMS is the weighted sum without EC, as the
project's per-frame figure.
"""

from __future__ import annotations

import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np
from shapely.geometry import Polygon

warnings.filterwarnings("ignore")

from navsim.common.dataclasses import Trajectory  # noqa: E402
from navsim.common.enums import SceneFrameType  # noqa: E402
from navsim.evaluate.pdm_score import pdm_score, transform_trajectory  # noqa: E402
from navsim.planning.metric_caching.metric_cache import MetricCache  # noqa: E402
from navsim.planning.simulation.planner.pdm_planner.observation.pdm_observation import PDMObservation  # noqa: E402
from navsim.planning.simulation.planner.pdm_planner.observation.pdm_occupancy_map import PDMDrivableMap  # noqa: E402
from navsim.planning.simulation.planner.pdm_planner.scoring.pdm_comfort_metrics import (  # noqa: E402
    ego_is_two_frame_extended_comfort,
)
from navsim.planning.simulation.planner.pdm_planner.scoring.pdm_scorer import (  # noqa: E402
    PDMScorer,
    PDMScorerConfig,
)
from navsim.planning.simulation.planner.pdm_planner.simulation.pdm_simulator import PDMSimulator  # noqa: E402
from navsim.planning.simulation.planner.pdm_planner.utils.pdm_enums import StateIndex  # noqa: E402
from navsim.planning.simulation.planner.pdm_planner.utils.pdm_path import PDMPath  # noqa: E402
from navsim.traffic_agents_policies.log_replay_traffic_agents import LogReplayTrafficAgents  # noqa: E402
from nuplan.common.actor_state.agent import Agent  # noqa: E402
from nuplan.common.actor_state.ego_state import EgoState  # noqa: E402
from nuplan.common.actor_state.oriented_box import OrientedBox  # noqa: E402
from nuplan.common.actor_state.scene_object import SceneObjectMetadata  # noqa: E402
from nuplan.common.actor_state.state_representation import StateSE2, StateVector2D, TimePoint  # noqa: E402
from nuplan.common.actor_state.static_object import StaticObject  # noqa: E402
from nuplan.common.actor_state.tracked_objects import TrackedObjects  # noqa: E402
from nuplan.common.actor_state.tracked_objects_types import TrackedObjectType  # noqa: E402
from nuplan.common.actor_state.vehicle_parameters import VehicleParameters  # noqa: E402
from nuplan.common.maps.maps_datatypes import SemanticMapLayer  # noqa: E402
from nuplan.planning.simulation.observation.observation_type import DetectionsTracks  # noqa: E402
from nuplan.planning.simulation.trajectory.interpolated_trajectory import InterpolatedTrajectory  # noqa: E402
from nuplan.planning.simulation.trajectory.trajectory_sampling import TrajectorySampling  # noqa: E402

T0_US = 10_000_000  # this keyframe's time (nuPlan's TimePoint is not negative; the past lies 1.5 s before it)
PROPOSAL = TrajectorySampling(num_poses=30, interval_length=0.1)  # 3 s at 10 Hz: the project's six poses
PLAN = TrajectorySampling(num_poses=6, interval_length=0.5)
TYPES = {"vehicle": TrackedObjectType.VEHICLE, "pedestrian": TrackedObjectType.PEDESTRIAN,
         "cyclist": TrackedObjectType.BICYCLE, "other": TrackedObjectType.GENERIC_OBJECT}
COLUMNS = {"nc": "no_at_fault_collisions", "dac": "drivable_area_compliance", "ddc": "driving_direction_compliance",
           "tlc": "traffic_light_compliance", "ep": "ego_progress", "ttc": "time_to_collision_within_bound",
           "lk": "lane_keeping", "hc": "history_comfort"}


def vehicle(frame: dict) -> VehicleParameters:
    length, width = frame["ego_size"]
    return VehicleParameters(width=width, front_length=0.5 * length, rear_length=0.5 * length,
                             cog_position_from_rear_axle=1.67, wheel_base=frame["wheel_base"],
                             vehicle_name="project_box", vehicle_type="gen1", height=1.777)


def ego_state(pose, velocity, accel, time_us: int, params: VehicleParameters) -> EgoState:
    return EgoState.build_from_rear_axle(StateSE2(*pose), StateVector2D(*velocity), StateVector2D(*accel), 0.0,
                                         TimePoint(int(time_us)), params)


def _box(b: dict, x: float, y: float, yaw: float, t_us: int):
    """A box of the case file as nuPlan's tracked object (an `Agent`, or a `StaticObject` for "other")."""
    box = OrientedBox(StateSE2(x, y, yaw), b["length"], b["width"], 1.5)
    token = f"track_{b['id']}"
    meta = SceneObjectMetadata(t_us, token, b["id"], token)
    kind = TYPES[b["category"]]
    return StaticObject(kind, box, meta) if b["category"] == "other" else \
        Agent(kind, box, StateVector2D(b["vx"], b["vy"]), meta)


def detections(frame: dict, agents: str = "keyframes") -> list[DetectionsTracks]:
    """The agents at 0.1 s steps 0 .. 30. "keyframes": the boxes at steps 5, 10, .., 30 and none elsewhere (the
    project's inputs). "interpolated": as NAVSIM's metric cache builds them from 2 Hz annotations
    (`MetricCacheProcessor._interpolate_gt_observation`): each track's boxes interpolated linearly (heading
    unwrapped) at every step between its first and last keyframe, a track seen once kept at every step."""
    if agents not in ("keyframes", "interpolated"):
        raise ValueError(f"agents {agents!r}: 'keyframes' or 'interpolated'")
    steps: list[list] = [[] for _ in range(PROPOSAL.num_poses + 1)]
    tracks: dict[int, list[tuple[int, dict]]] = {}
    for k, boxes in enumerate(frame["agents"]):
        for b in boxes:
            tracks.setdefault(b["id"], []).append((5 * (k + 1), b))
    for seen in tracks.values():
        first = seen[0][1]
        if agents == "keyframes":
            for step, b in seen:
                steps[step].append(_box(b, b["x"], b["y"], b["yaw"], T0_US + step * 100_000))
            continue
        if len(seen) == 1:
            for step in range(len(steps)):
                steps[step].append(_box(first, first["x"], first["y"], first["yaw"], T0_US))
            continue
        t = np.array([s for s, _ in seen], dtype=np.float64)
        xyh = np.array([[b["x"], b["y"], b["yaw"]] for _, b in seen])
        xyh[:, 2] = np.unwrap(xyh[:, 2])
        for step in range(int(t[0]), int(t[-1]) + 1):
            x, y, h = (float(np.interp(step, t, xyh[:, j])) for j in range(3))
            steps[step].append(_box(first, x, y, h, T0_US))
    return [DetectionsTracks(TrackedObjects(objs)) for objs in steps]


def polygon(ring, holes=()) -> Polygon:
    return Polygon(np.asarray(ring)[:, :2], [np.asarray(h)[:, :2] for h in holes])


def drivable_map(m: dict) -> PDMDrivableMap:
    tokens, types, geoms = [], [], []
    for i, p in enumerate(m["drivable"]):
        tokens.append(f"drivable_{i}")
        types.append(SemanticMapLayer.DRIVABLE_AREA)
        geoms.append(polygon(p["exterior"], p["holes"]))
    for lane in m["lanes"]:
        tokens.append(lane["token"])
        types.append(SemanticMapLayer.LANE_CONNECTOR if lane["connector"] else SemanticMapLayer.LANE)
        geoms.append(polygon(lane["polygon"]))
    for i, ring in enumerate(m["intersections"]):
        tokens.append(f"intersection_{i}")
        types.append(SemanticMapLayer.INTERSECTION)
        geoms.append(polygon(ring))
    arr = np.empty(len(geoms), dtype=object)
    arr[:] = geoms
    return PDMDrivableMap(tokens, types, arr)


def centreline(route) -> PDMPath:
    pts = np.asarray(route, dtype=np.float64)
    keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9])
    pts = pts[keep]
    d = np.diff(pts, axis=0)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    yaw = np.concatenate([yaw, yaw[-1:]])
    return PDMPath([StateSE2(x, y, h) for (x, y), h in zip(pts, yaw)])


def past(frame: dict, params: VehicleParameters, now: EgoState) -> InterpolatedTrajectory | None:
    if frame["past"] is None:
        return None
    states = [ego_state((0.0, 0.0, h), (0.0, 0.0), (ax, ay), T0_US + int(t), params) for t, h, ax, ay in frame["past"]]
    return InterpolatedTrajectory(states + [now])


def metric_cache(frame: dict, agents: str) -> MetricCache:
    params = vehicle(frame)
    e = frame["ego"]
    # as NAVSIM's `ego_status_to_ego_state` builds it: no yaw rate, no steering angle
    now = ego_state((0.0, 0.0, 0.0), (e["vx"], e["vy"]), (e["ax"], e["ay"]), T0_US, params)
    expert = Trajectory(np.asarray(frame["expert"], dtype=np.float64), PLAN)
    tracks = detections(frame, agents)
    observation = PDMObservation(PROPOSAL, PROPOSAL, 100.0, observation_sample_res=1, extend_observation_for_ttc=False)
    observation.update_detections_tracks(tracks)
    m = frame["map"]
    return MetricCache(file_path=Path("unused"), log_name="world", timepoint=now.time_point,
                       scene_type=SceneFrameType.ORIGINAL, trajectory=transform_trajectory(expert, now),
                       human_trajectory=expert, past_human_trajectory=past(frame, params, now), ego_state=now,
                       observation=observation, centerline=centreline(m["route"]), route_lane_ids=m["route_lanes"],
                       drivable_area_map=drivable_map(m), past_detections_tracks=[], current_tracked_objects=[],
                       future_tracked_objects=tracks, map_parameters=None)


def epdms(row: dict) -> float:
    mult = row["f_nc"] * row["f_dac"] * row["f_ddc"] * row["f_tlc"]
    return mult * (5 * row["f_ep"] + 5 * row["f_ttc"] + 2 * row["f_lk"] + 2 * row["f_hc"]) / 14


def score_frame(frame: dict, previous: dict, agents: str) -> dict:
    params = vehicle(frame)
    scorers = {"": PDMScorer(PROPOSAL, PDMScorerConfig(human_penalty_filter=False), params),
               "f_": PDMScorer(PROPOSAL, PDMScorerConfig(human_penalty_filter=True), params)}
    simulator = PDMSimulator(PROPOSAL)
    policy = LogReplayTrafficAgents(PROPOSAL)
    out = {}
    for case in frame["cases"]:
        plan = Trajectory(np.asarray(case["poses"], dtype=np.float64), PLAN)
        row: dict = {}
        for prefix, scorer in scorers.items():
            result, states = pdm_score(metric_cache(frame, agents), plan, PROPOSAL, simulator, scorer, policy)
            row.update({prefix + k: float(result[c].iloc[0]) for k, c in COLUMNS.items()})
        row["epdms"] = epdms(row)
        row["xy"] = states[:, StateIndex.POINT].tolist()
        prev = previous.get((frame["scene"], frame["index"] - 1, case["kind"]))
        row["ec"] = math.nan
        if prev is not None:
            row["ec"] = float(ego_is_two_frame_extended_comfort(states[None, :-5], prev[None, 5:],
                                                                np.arange(len(states) - 5) * 0.1)[0])
        previous[(frame["scene"], frame["index"], case["kind"])] = states
        out[case["kind"]] = row
    return out


def main() -> None:
    cases, result = sys.argv[1], sys.argv[2]
    agents = sys.argv[3] if len(sys.argv) > 3 else "keyframes"
    with open(cases) as fh:
        data = json.load(fh)
    previous: dict = {}
    out = {f["token"]: score_frame(f, previous, agents) for f in data["frames"]}
    with open(result, "w") as fh:
        json.dump(out, fh)


if __name__ == "__main__":
    main()
