"""The project's EPDMS terms against NAVSIM v2.2's own scorer on the same inputs (issue 39), term by term.

The cases are built here with the project's own code: the world's scorable frames (their start states, the
expert, the agent boxes, the lane map and the drivable area), and per frame the expert with N(0, sigma^2) noise
(sigma 0, 0.3, 1 m) and hand-made plans (stop, reverse, off-road, shoulder, oncoming lane, lane changes left and
right, wrong way). The project scores each (`PreparedFrame`: the tracked states, the EPDMS terms, the human filter;
EC between the same kind of plan on consecutive frames of a scene). The inputs go to a neutral JSON file, which
`benchmarks/navsim_driver.py` reads in a separate Python environment holding NAVSIM v2.2 and nuPlan's devkit
(never the project's), builds NAVSIM's objects from it and scores every plan with NAVSIM's `pdm_score` (PDMScorer,
v2 EPDMS config, the human filter on, the expert as the progress reference), then the table compares the two:

    python benchmarks/navsim_reference.py --navsim-python /tmp/navsim-venv/bin/python [--scenes 2 --seed 7]
        [--agents keyframes|interpolated]

Quick mode: the defaults (2 scenes). Without --navsim-python the cases are built and scored by the project only
(`--out cases.json` keeps the neutral file). How the NAVSIM side's environment is made, and what the adapter
chooses where nuScenes-style data lack a nuPlan concept (roadblocks, track tokens), is in the driver's docstring.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from typing import Any

import numpy as np

SIGMAS: tuple[float, ...] = (0.0, 0.3, 1.0)
TERMS: tuple[str, ...] = ("nc", "dac", "ddc", "tlc", "ep", "ttc", "lk", "hc")
#: Table rows: each term before the filter, after it (f_), EC, the EPDMS without EC (both sides) and the states.
ROWS: tuple[str, ...] = TERMS + tuple("f_" + k for k in TERMS) + ("ec", "epdms")
#: Lanes, intersections and drivable polygons whose points come within this of the ego go to NAVSIM (m).
RADIUS_M = 80.0
#: A lane is on the route (NAVSIM's route roadblocks' lanes, which nuScenes maps lack) when of its centreline's
#: segments starting within this of the route centreline (m) at least half run within ROUTE_ANGLE of the route's
#: direction there (half, not one: the route's joints between lanes and a lane's own kinks point anywhere).
ROUTE_NEAR_M, ROUTE_ANGLE = 5.5, math.pi / 4


def _plans(expert: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The plans of one frame (6, 2), by kind."""
    t = np.arange(1, 7) * 0.5
    ramp = np.clip(t / 2.0, 0.0, 1.0)[:, None]
    side = np.array([0.0, 1.0])
    out = {f"expert{s:g}": expert + (rng.normal(0.0, s, expert.shape) if s else 0.0) for s in SIGMAS}
    out["stop"] = np.zeros((6, 2))
    out["reverse"] = np.stack([-1.0 * t, np.zeros(6)], axis=1)
    out["off_road"] = expert + 9.0 * ramp * -side
    out["shoulder"] = expert + 2.6 * ramp * -side
    out["oncoming"] = expert + 3.5 * ramp * side
    out["lane_change_left"] = expert + 3.5 * np.clip(t / 3.0, 0, 1)[:, None] * side
    out["lane_change_right"] = expert + 3.5 * np.clip(t / 3.0, 0, 1)[:, None] * -side
    a = np.linspace(np.pi / 6, np.pi, 6)  # a U-turn to the left, radius 5 m
    out["wrong_way"] = np.stack([5.0 * np.sin(a), 5.0 * (1.0 - np.cos(a))], axis=1)
    return out


def _local(pose: tuple[float, float, float], xy: np.ndarray) -> list[list[float]]:
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    d = np.asarray(xy, dtype=np.float64)[:, :2] - [x, y]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1).tolist()


def _near(ring: np.ndarray, pose: tuple[float, float, float]) -> bool:
    return bool(len(ring)) and float(np.hypot(*(np.asarray(ring)[:, :2] - pose[:2]).T).min()) <= RADIUS_M


def _route_lanes(lanes: list[dict[str, Any]], route: np.ndarray | None) -> list[str]:
    """The tokens of the lanes on the route (ROUTE_NEAR_M, ROUTE_ANGLE), in the ego frame."""
    if route is None or len(route) < 2:
        return []
    a, b = route[:-1], route[1:]
    ab = b - a
    yaw = np.arctan2(ab[:, 1], ab[:, 0])
    on = []
    for lane in lanes:
        c = np.asarray(lane["centreline"])
        if len(c) < 2:
            continue
        pts = c[:, :2]
        seg = np.diff(pts, axis=0)
        lane_yaw = np.arctan2(seg[:, 1], seg[:, 0])
        t = np.clip(((pts[:-1, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
        d = np.hypot(*(a[None] + t[..., None] * ab[None] - pts[:-1, None]).transpose(2, 0, 1))
        k = d.argmin(axis=1)
        turn = np.abs((lane_yaw - yaw[k] + np.pi) % (2 * np.pi) - np.pi)
        near = d[np.arange(len(k)), k] <= ROUTE_NEAR_M
        if near.any() and 2 * int((near & (turn < ROUTE_ANGLE)).sum()) >= int(near.sum()):
            on.append(lane["token"])
    return on


def _map_inputs(reader: Any, frame: Any, prepared: Any) -> dict[str, Any]:
    """The frame's map in its ego frame: drivable polygons (with holes), lanes, intersections, route, route lanes."""
    pose = frame.pose
    area, lane_map = reader.drivable_area(frame), reader.lane_map(frame)
    drivable = [{"exterior": _local(pose, p.exterior), "holes": [_local(pose, h) for h in p.holes]}
                for p in area.polygons if _near(p.exterior, pose)]
    lanes = [{"token": lane.token, "connector": bool(lane.connector),
              "polygon": _local(pose, lane.polygon.exterior) if lane.polygon is not None else None,
              "centreline": _local(pose, lane.centreline)}
             for lane in lane_map.lanes if len(lane.centreline) >= 2 and _near(lane.centreline, pose)]
    junctions = [_local(pose, j.polygon.exterior) for j in lane_map.intersections if _near(j.polygon.exterior, pose)]
    route = prepared.lanes.route if prepared.lanes is not None else None
    return {"drivable": drivable, "lanes": [lane for lane in lanes if lane["polygon"] is not None],
            "intersections": junctions, "route": None if route is None else route.tolist(),
            "route_lanes": _route_lanes(lanes, route)}


def _agents(prepared: Any) -> list[list[dict[str, Any]]]:
    """Per waypoint time the agent boxes with the project's track ids and first-seen velocities."""
    out = []
    for k, boxes in enumerate(prepared.steps):
        out.append([{"id": int(prepared.ids[k][i]), "x": float(boxes.center[i, 0]), "y": float(boxes.center[i, 1]),
                     "length": float(boxes.size[i, 0]), "width": float(boxes.size[i, 1]), "yaw": float(boxes.yaw[i]),
                     "category": boxes.category[i], "vx": float(prepared.velocities[k][i, 0]),
                     "vy": float(prepared.velocities[k][i, 1])} for i in range(len(boxes))])
    return out


def build(scenes: int, seed: int) -> dict[str, Any]:
    """The cases, the project's scores and the neutral inputs."""
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import write_world
    from pytest_drivedegrade.metrics import pdms, tracking
    from pytest_drivedegrade.metrics.pdms import extended

    reader = NuScenesReader(write_world(tempfile.mkdtemp(prefix="ddnavref-"), scenes=scenes, seed=seed,
                                       val_images=False), split="all")
    frames = reader.scorable_frames()
    rng = np.random.default_rng(0)
    out_frames, previous = [], {}
    for f in frames:
        p = pdms.PreparedFrame.of(f, reader.drivable_area(f), lane_map=reader.lane_map(f))
        assert p.human is not None
        cases = []
        for kind, plan in _plans(f.gt_future, rng).items():
            ps = pdms.tracked_states(plan[None], [p.initial])[0]
            result = p.score_tracked(plan, ps)
            terms = p.extended(ps, result)
            kept = terms.filtered(p.human)
            prev = previous.get((f.scene_token, f.index - 1, kind))
            ec = extended.extended_comfort(ps, prev) if prev is not None else math.nan
            previous[(f.scene_token, f.index, kind)] = ps
            headings = tracking.waypoint_headings(plan[None])[0, 1:]
            cases.append({"kind": kind, "poses": np.concatenate([plan, headings[:, None]], axis=1).tolist(),
                          "ec_previous": prev is not None,
                          "project": {**{k: getattr(terms, k) for k in TERMS},
                                      **{"f_" + k: getattr(kept, k) for k in TERMS},
                                      "ec": ec, "epdms": extended.epdms_score(kept, math.nan),
                                      "xy": ps.xy.tolist(), "heading": ps.heading.tolist()}})
        expert_headings = tracking.waypoint_headings(f.gt_future[None])[0, 1:]
        out_frames.append({
            "token": f.token, "scene": f.scene_token, "index": f.index,
            "ego": {"vx": p.initial.velocity_x, "vy": p.initial.velocity_y, "ax": p.initial.acceleration_x,
                    "ay": p.initial.acceleration_y, "yaw_rate": p.initial.yaw_rate},
            "ego_size": p.ego_size.tolist(), "wheel_base": tracking.WHEEL_BASE,
            "expert": np.concatenate([f.gt_future, expert_headings[:, None]], axis=1).tolist(),
            "past": None if f.past_motion is None else np.asarray(f.past_motion)[-extended.PAST_HC:].tolist(),
            "agents": _agents(p), "map": _map_inputs(reader, f, p), "cases": cases})
    return {"frames": out_frames}


def _table(data: dict[str, Any], navsim: dict[str, Any]) -> None:
    """Per row: the cases compared, the largest |difference| and the cases differing beyond 1e-9."""
    pairs: dict[str, list[tuple[float, float]]] = {k: [] for k in ROWS}
    states: list[float] = []
    for frame in data["frames"]:
        for case in frame["cases"]:
            theirs = navsim[frame["token"]][case["kind"]]
            for k in ROWS:
                a, b = case["project"][k], theirs.get(k, math.nan)
                if k == "ec" and not case["ec_previous"]:
                    continue
                if k == "tlc":
                    a = 1.0 if math.isnan(a) else a  # not scored by the project (no lights): NAVSIM's 1
                if k == "f_tlc":
                    a = 1.0 if math.isnan(a) else a
                pairs[k].append((a, b))
            states.append(float(np.abs(np.asarray(case["project"]["xy"]) - np.asarray(theirs["xy"])).max()))
    print("| term | cases | max abs difference | cases differing > 1e-9 | project mean | NAVSIM mean |")
    print("|---|---|---|---|---|---|")
    for k in ROWS:
        a, b = np.array(pairs[k]).reshape(-1, 2).T
        diff = np.where(np.isnan(a) & np.isnan(b), 0.0, np.abs(a - b))
        diff = np.where(np.isnan(diff), np.inf, diff)
        print(f"| {k} | {len(a)} | {diff.max() if len(a) else 0:.3g} | {int((diff > 1e-9).sum())} | "
              f"{np.nanmean(a):.4f} | {np.nanmean(b):.4f} |")
    print(f"| tracked xy (m) | {len(states)} | {max(states):.3g} | {sum(s > 1e-9 for s in states)} | | |")


def _by_kind(data: dict[str, Any], navsim: dict[str, Any]) -> None:
    kinds = [c["kind"] for c in data["frames"][0]["cases"]]
    print("\n| plans | cases | project EPDMS | NAVSIM EPDMS | terms differing (cases) |")
    print("|---|---|---|---|---|")
    for kind in kinds:
        mine, theirs, differ = [], [], {}
        for frame in data["frames"]:
            case = next(c for c in frame["cases"] if c["kind"] == kind)
            other = navsim[frame["token"]][kind]
            mine.append(case["project"]["epdms"])
            theirs.append(other["epdms"])
            for k in TERMS + ("epdms",):
                a = case["project"]["f_" + k] if k != "epdms" else case["project"][k]
                b = other["f_" + k] if k != "epdms" else other[k]
                a = 1.0 if k == "tlc" and math.isnan(a) else a
                if not (math.isnan(a) and math.isnan(b)) and not abs(a - b) <= 1e-9:
                    differ[k] = differ.get(k, 0) + 1
        print(f"| {kind} | {len(mine)} | {np.mean(mine):.4f} | {np.mean(theirs):.4f} | "
              f"{', '.join(f'{k} {v}' for k, v in differ.items()) or 'none'} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--navsim-python", default="", help="the Python of an environment holding NAVSIM v2.2")
    ap.add_argument("--out", default="", help="keep the neutral cases file here")
    ap.add_argument("--agents", choices=("keyframes", "interpolated"), default="keyframes",
                    help="NAVSIM's agents: the project's (boxes at the six waypoint times only) or NAVSIM's own "
                         "10 Hz interpolation of them (what the keyframe grid adaptation moves)")
    args = ap.parse_args()
    data = build(args.scenes, args.seed)
    workdir = tempfile.mkdtemp(prefix="ddnavref-io-")
    cases = args.out or os.path.join(workdir, "cases.json")
    with open(cases, "w") as fh:
        json.dump(data, fh)
    n = sum(len(f["cases"]) for f in data["frames"])
    print(f"{len(data['frames'])} frames, {n} cases -> {cases}")
    if not args.navsim_python:
        return
    result = os.path.join(workdir, "navsim.json")
    driver = os.path.join(os.path.dirname(os.path.abspath(__file__)), "navsim_driver.py")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # NAVSIM's environment only
    subprocess.run([args.navsim_python, driver, cases, result, args.agents], check=True, env=env)
    with open(result) as fh:
        navsim = json.load(fh)
    print(f"NAVSIM v2.2's pdm_score, agents: {args.agents}")
    _table(data, navsim)
    _by_kind(data, navsim)


if __name__ == "__main__":
    sys.exit(main())
