"""Write scenes as nuScenes tables (and the CAN bus pose expansion); render and write their JPEGs.

Tokens are derived from (seed, kind, ids) by hashing, timestamps from the scene index, and JSON is written with
sorted keys, so the same seed and options give byte-identical files.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np

from ...constants import CAMERAS
from ..geometry import yaw_to_quat
from ..maps import EXPANSION_VERSION
from . import models, render, sensing, texture
from .agents import DT, KINDS
from .expert import KEY_EVERY
from .lanemap import lane_layers
from .lights import map_layers
from .rig import Rig
from .roads import drivable_polygons
from .scene import Scene

BASE_TIME = 1_533_151_600_000_000  # microseconds; scene i starts 10^8 us (100 s) after scene i - 1
ANNOTATION_RANGE = 60.0  # m around the ego, as nuScenes annotates
ATTRIBUTES = ("vehicle.moving", "vehicle.stopped", "vehicle.parked", "pedestrian.moving",
              "pedestrian.standing", "cycle.with_rider")
VISIBILITY = (("1", "v0-40"), ("2", "v40-60"), ("3", "v60-80"), ("4", "v80-100"))
JPEG_QUALITY = 90
LIDAR = "LIDAR_TOP"
#: nuScenes v1.0's category `index` (the lidarseg class index) of the real taxonomy's names the world uses.
CATEGORY_INDEX = {"human.pedestrian.adult": 2, "vehicle.bicycle": 14, "vehicle.bus.rigid": 16, "vehicle.car": 17,
                  "vehicle.truck": 23}
MAP_TOLERANCE = 0.01  # m: the map's polygons stay this close to the painted carriageway edges
#: Map expansion layers written empty (the world has no road blocks, walkways or car parks; stop lines and traffic
#: lights only in its light scenes' maps), so the file has the full schema `NuScenesMap` loads.
EMPTY_MAP_LAYERS = ("road_block", "walkway", "stop_line", "carpark_area", "traffic_light")


def token(seed: int, *parts) -> str:
    return hashlib.blake2b("|".join(map(str, (seed, *parts))).encode(), digest_size=16).hexdigest()


def image_name(scene: Scene, cam: str, k: int) -> str:
    return f"samples/{cam}/ddworld-s{scene.seed}-{scene.name}__{cam}__{timestamp(scene, k)}.jpg"


def lidar_name(scene: Scene, k: int) -> str:
    return f"samples/{LIDAR}/ddworld-s{scene.seed}-{scene.name}__{LIDAR}__{timestamp(scene, k)}.pcd.bin"


def timestamp(scene: Scene, k: int) -> int:
    return BASE_TIME + scene.index * 100_000_000 + k * KEY_EVERY * int(DT * 1e6)


def location(scene: Scene, seed: int) -> str:
    """The log's `location`, naming its map: every scene has its own roads around the same origin, so its own map."""
    return f"ddworld-s{seed}-{scene.name}"


def static_tables(seed: int, rig: Rig) -> dict[str, list[dict]]:
    """Tables shared by every scene: sensors, calibration, categories, attributes, visibility."""
    t: dict[str, list[dict]] = {"sensor": [], "calibrated_sensor": []}
    for cam in CAMERAS:
        info = rig.cameras[cam]
        t["sensor"].append({"token": token(seed, "sensor", cam), "channel": cam, "modality": "camera"})
        t["calibrated_sensor"].append({"token": token(seed, "calib", cam), "sensor_token": token(seed, "sensor", cam),
                                       "translation": list(info.translation), "rotation": list(info.rotation),
                                       "camera_intrinsic": info.intrinsic.tolist()})
    t["sensor"].append({"token": token(seed, "sensor", LIDAR), "channel": LIDAR, "modality": "lidar"})
    t["calibrated_sensor"].append({"token": token(seed, "calib", LIDAR), "sensor_token": token(seed, "sensor", LIDAR),
                                   "translation": list(sensing.LIDAR_TRANSLATION),
                                   "rotation": list(sensing.LIDAR_ROTATION), "camera_intrinsic": []})
    t["category"] = [{"token": token(seed, "category", KINDS[k][0]), "name": KINDS[k][0],
                      "description": f"drivedegrade world {k}", "index": CATEGORY_INDEX[KINDS[k][0]]}
                     for k in KINDS]
    t["attribute"] = [{"token": token(seed, "attribute", a), "name": a, "description": a} for a in ATTRIBUTES]
    t["visibility"] = [{"token": tok, "level": lvl, "description": f"visibility of whole object {lvl}"}
                       for tok, lvl in VISIBILITY]
    return t


def _attribute(agent, step: int) -> str:
    moving = abs(float(agent.speed[step])) > 0.3
    if agent.kind == "pedestrian":
        return "pedestrian.moving" if moving else "pedestrian.standing"
    if agent.kind == "cyclist":
        return "cycle.with_rider"
    return "vehicle.parked" if agent.parked else ("vehicle.moving" if moving else "vehicle.stopped")


def scene_tables(scene: Scene, seed: int, t: dict[str, list[dict]], rig: Rig) -> dict[str, bytes]:
    """Append one scene's records (log, scene, samples, poses, sample_data, annotations, instances); returns
    the LIDAR_TOP point clouds to write (file name -> ``.pcd.bin`` bytes)."""
    clouds: dict[str, bytes] = {}
    log_tok, scene_tok = token(seed, "log", scene.index), token(seed, "scene", scene.index)
    t["log"].append({"token": log_tok, "logfile": f"ddworld-s{seed}-{scene.name}", "vehicle": "ddworld-ego",
                     "date_captured": "2018-08-01", "location": location(scene, seed)})
    samples = [token(seed, "sample", scene.index, k) for k in range(scene.keyframes)]
    t["scene"].append({"token": scene_tok, "log_token": log_tok, "nbr_samples": scene.keyframes,
                       "first_sample_token": samples[0], "last_sample_token": samples[-1], "name": scene.name,
                       "description": describe(scene)})
    ann_tokens: dict[int, list[str]] = {}
    # tokens used more than once (a sample_data's is its neighbours' prev/next too) are hashed once
    channels = (*CAMERAS, LIDAR)
    sd_tokens = {ch: [token(seed, "sd", scene.index, ch, j) for j in range(scene.keyframes)] + [""] for ch in channels}
    calib = {ch: token(seed, "calib", ch) for ch in channels}
    inst = [token(seed, "inst", scene.index, i) for i in range(len(scene.agents))]
    attribute = {a: token(seed, "attribute", a) for a in ATTRIBUTES}
    for k, st in enumerate(samples):
        step, ts = k * KEY_EVERY, timestamp(scene, k)
        t["sample"].append({"token": st, "timestamp": ts, "prev": samples[k - 1] if k else "",
                            "next": samples[k + 1] if k + 1 < scene.keyframes else "", "scene_token": scene_tok})
        pose_tok = token(seed, "pose", scene.index, k)
        t["ego_pose"].append({"token": pose_tok, "timestamp": ts, "rotation": list(yaw_to_quat(scene.ego.yaw[step])),
                              "translation": [float(scene.ego.xy[step, 0]), float(scene.ego.xy[step, 1]), 0.0]})
        for cam in CAMERAS:
            sd = sd_tokens[cam]  # sd[-1] is "": no previous at k = 0, no next at the last keyframe
            t["sample_data"].append({"token": sd[k], "sample_token": st, "ego_pose_token": pose_tok,
                                     "calibrated_sensor_token": calib[cam], "timestamp": ts,
                                     "fileformat": "jpg", "is_key_frame": True, "height": rig.cameras[cam].height,
                                     "width": rig.cameras[cam].width, "filename": image_name(scene, cam, k),
                                     "prev": sd[k - 1], "next": sd[k + 1]})
        sd = sd_tokens[LIDAR]
        t["sample_data"].append({"token": sd[k], "sample_token": st, "ego_pose_token": pose_tok,
                                 "calibrated_sensor_token": calib[LIDAR], "timestamp": ts,
                                 "fileformat": "pcd", "is_key_frame": True, "height": 0, "width": 0,
                                 "filename": lidar_name(scene, k), "prev": sd[k - 1], "next": sd[k + 1]})
        pose = (float(scene.ego.xy[step, 0]), float(scene.ego.xy[step, 1]), float(scene.ego.yaw[step]))
        boxes = sensing.boxes_at(scene.agents, step, pose)
        cloud, n_points = sensing.lidar_scan(boxes)
        clouds[lidar_name(scene, k)] = cloud.tobytes()
        annotated = [i for i, a in enumerate(scene.agents)
                     if np.linalg.norm(a.xy[step] - scene.ego.xy[step]) <= ANNOTATION_RANGE]
        visible = dict(zip(annotated, sensing.visible_fractions(boxes, annotated, rig)))
        for i in annotated:
            a = scene.agents[i]
            at = token(seed, "ann", scene.index, i, k)
            ann_tokens.setdefault(i, []).append(at)
            t["sample_annotation"].append({
                "token": at, "sample_token": st, "instance_token": inst[i],
                "visibility_token": sensing.visibility_token(float(visible[i])),
                "attribute_tokens": [attribute[_attribute(a, step)]],
                "translation": [float(a.xy[step, 0]), float(a.xy[step, 1]), a.size[2] / 2],
                "size": [a.size[1], a.size[0], a.size[2]], "rotation": list(yaw_to_quat(float(a.yaw[step]))),
                "prev": "", "next": "", "num_lidar_pts": int(n_points[i]), "num_radar_pts": 0})
    _link_instances(scene, seed, t, ann_tokens)
    t["map"][0]["log_tokens"].append(log_tok)
    return clouds


def _link_instances(scene, seed, t, ann_tokens) -> None:
    by_token = {r["token"]: r for r in t["sample_annotation"][-sum(map(len, ann_tokens.values())):]}
    for i, toks in ann_tokens.items():
        for a, b in zip(toks[:-1], toks[1:]):
            by_token[a]["next"], by_token[b]["prev"] = b, a
        t["instance"].append({"token": token(seed, "inst", scene.index, i),
                              "category_token": token(seed, "category", scene.agents[i].category),
                              "nbr_annotations": len(toks), "first_annotation_token": toks[0],
                              "last_annotation_token": toks[-1]})


def map_expansion(scene: Scene, seed: int) -> dict:
    """The scene's map in nuScenes map-expansion form: its carriageways and junctions as `drivable_area`, and the
    lane-level layers of `lanemap.lane_layers` (lanes, connectors, dividers, crossings, road segments).

    Drivable polygons come from `roads.drivable_polygons` (what the renderer paints as asphalt), simplified by
    Douglas-Peucker within `MAP_TOLERANCE`, counter-clockwise, without holes; coordinates in the scene's world
    frame (the frame of ego_pose and sample_annotation), rounded to 0.1 mm. `canvas_edge` (the devkit's bitmap
    extent) covers the nodes' largest coordinates.
    """
    nodes, polygons = [], []
    for i, ring in enumerate(drivable_polygons(scene.net)):
        o = ring[0]
        ring = cv2.approxPolyDP((ring - o).astype(np.float32).reshape(-1, 1, 2), MAP_TOLERANCE, True)
        ring = ring.reshape(-1, 2).astype(np.float64) + o
        toks = [token(seed, "map-node", scene.index, i, k) for k in range(len(ring))]
        nodes += [{"token": t, "x": round(x, 4), "y": round(y, 4)} for t, (x, y) in zip(toks, ring.tolist())]
        polygons.append({"token": token(seed, "map-polygon", scene.index, i), "exterior_node_tokens": toks,
                         "holes": []})
    lanes = lane_layers(scene.net, scene.crosswalks, token, seed, scene.index, scene.style.yellow_centre)
    out: dict = {name: [] for name in EMPTY_MAP_LAYERS}
    out.update(lanes.layers)
    out["node"] = nodes + out["node"]
    out["polygon"] = polygons + out["polygon"]
    if scene.lights:  # the light scenes' stop lines and lights (`lights.map_layers`); other maps keep them empty
        for name, rows in map_layers(scene.lights, scene.net, token, seed, scene.index, timestamp(scene, 0)).items():
            out[name] = out.get(name, []) + rows
    far = np.array([[n["x"], n["y"]] for n in out["node"]]).max(0)
    out.update({"version": EXPANSION_VERSION, "canvas_edge": [float(np.ceil(far[0])), float(np.ceil(far[1]))],
                "arcline_path_3": lanes.arcline_path_3, "connectivity": lanes.connectivity,
                "drivable_area": [{"token": token(seed, "map-drivable", scene.index),
                                   "polygon_tokens": [p["token"] for p in polygons]}]})
    return out


def can_bus(scene: Scene) -> list[dict]:
    """The CAN bus pose expansion at 10 Hz: speed, acceleration and yaw rate in the ego frame."""
    yaw_rate = np.gradient(np.unwrap(scene.ego.yaw), DT)
    out = []
    for step in range(scene.keyframes * KEY_EVERY):
        v = float(scene.ego.speed[step])
        out.append({"utime": timestamp(scene, 0) + step * int(DT * 1e6),
                    "pos": [float(scene.ego.xy[step, 0]), float(scene.ego.xy[step, 1]), 0.0],
                    "orientation": list(yaw_to_quat(float(scene.ego.yaw[step]))), "vel": [v, 0.0, 0.0],
                    "accel": [float(scene.ego.accel[step]), v * float(yaw_rate[step]), 9.81],
                    "rotation_rate": [0.0, 0.0, float(yaw_rate[step])]})
    return out


def describe(scene: Scene) -> str:
    turn = scene.net.junctions[0].turn if scene.net.junctions else "none"
    roles = sorted({a.role for a in scene.agents})
    return f"junction: {turn}; lanes: {scene.net.route.lanes}; agents: {', '.join(roles)}"


def dump(path: Path, records) -> bytes:
    """Write JSON deterministically; returns the bytes written (for the content fingerprint)."""
    data = json.dumps(records, sort_keys=True, separators=(",", ":")).encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return data


def items_json(records: list) -> str:
    """The items of `records` as `dump` writes them inside its list: joined by "," they are that list's text."""
    return json.dumps(records, sort_keys=True, separators=(",", ":"))[1:-1]


def dump_items(path: Path, fragments: list[str]) -> bytes:
    """Write a list given as `items_json` fragments (of its parts, in order); the same bytes `dump` writes."""
    data = ("[" + ",".join(f for f in fragments if f) + "]").encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return data


def scene_backdrop(scene: Scene) -> tuple[texture.GroundMap, np.ndarray, models.Parts]:
    """What every render of a scene starts from, logged or at a simulated pose (`closedloop.camera`): the ground
    texture, the sky panorama and the static scenery, drawn from the scene's own random stream in this order."""
    rng = np.random.default_rng([scene.seed, scene.index, 0x7E27])
    lines = [(*light.stop_line(scene.net), light.along(scene.net)) for light in scene.lights]
    ground = texture.ground_map(scene.net, scene.ego.xy, scene.style, scene.crosswalks, rng, lines)
    sky = texture.sky_panorama(scene.style, rng)
    static = models.Parts()
    for prop in scene.props:
        getattr(models, prop.kind)(static, prop, rng)
    return ground, sky, static


def camera_jpeg(scene: Scene, rig: Rig, cam: str, pre: render.CameraPrecomp,
                backdrop: tuple[texture.GroundMap, np.ndarray, models.Parts], parts: models.Parts,
                pose: tuple[float, float, float], step: int, shadow_reach: float | None = None) -> np.ndarray:
    """One camera's image at world `pose` with the agents at log `step` (`parts`: the scenery and the agents'
    parts), JPEG-encoded as the data's images are. `shadow_reach`: only agents that near the camera cast a shadow
    (the renderer draws none farther; None: every agent of the scene is tried)."""
    ground, sky, _ = backdrop
    info = rig.cameras[cam]
    img = render.draw_background(pre, (info.height, info.width), ground, sky, pose, scene.style)
    w2c, centre = render.world_to_camera(rig, cam, pose)
    agents = scene.agents if shadow_reach is None else \
        [a for a in scene.agents if np.hypot(*(a.xy[step] - centre[:2])) < shadow_reach]
    render.draw_shadows(img, agents, step, info, w2c, scene.style)
    render.draw_solids(img, parts, info, w2c, centre, scene.style)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    return buf


def render_scene(scene: Scene, rig: Rig, root: Path, keys=None) -> list[bytes]:
    """Render and write the six JPEGs of every keyframe (or of `keys`); returns their bytes' digests."""
    backdrop = scene_backdrop(scene)
    static = backdrop[2]
    pre = {cam: render.precompute(rig, cam, scene.style.haze_m) for cam in CAMERAS}
    digests = []
    for k in range(scene.keyframes) if keys is None else keys:
        step = k * KEY_EVERY
        pose = (float(scene.ego.xy[step, 0]), float(scene.ego.xy[step, 1]), float(scene.ego.yaw[step]))
        parts = models.Parts(list(static.boxes), list(static.colours), dict(static.decals))
        render.agent_parts(parts, scene.agents, step)
        if scene.lights:
            models.light_parts(parts, scene.net, scene.lights, step, DT)
        for cam in CAMERAS:
            buf = camera_jpeg(scene, rig, cam, pre[cam], backdrop, parts, pose, step)
            path = root / image_name(scene, cam, k)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(buf.tobytes())
            digests.append(hashlib.blake2b(buf.tobytes(), digest_size=16).digest())
    return digests
