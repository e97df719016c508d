"""The nuScenes-format reader: one reader for real nuScenes (v1.0-mini, v1.0-trainval) and the embedded world.

Tables are loaded and indexed once; frames are built lazily in scene order and images are decoded only on
request (`load_image`), so memory does not grow with the number of frames iterated. Ego status comes from the
CAN bus expansion (`can_bus/<scene>_pose.json`) when present, else from ego_pose finite differences (past
keyframes only; the first keyframe of a scene falls back to the forward difference). Frames that cannot be
scored or built are skipped and counted in `skipped` (reason -> count), with messages in `problems`.

Maps: a frame's `location` is its log's; `drivable_area` reads `maps/expansion/<location>.json` (real nuScenes'
map expansion, or the world's own) once per location, and says None where the data root has no map for it.
"""

from __future__ import annotations

import copy
import hashlib
import os
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ..constants import CAMERAS, HORIZON_STEPS, PAST_STEPS, STEP_SECONDS
from ..errors import DataError
from . import geometry as geo
from .frame import AgentBoxes, CameraInfo, Command, EgoStatus, Frame, command_from_future
from .maps import DrivableArea, LaneMap, load_drivable_area, load_lane_map
from .tables import REQUIRED_TABLES, confined, load_can_bus, load_manifest, load_table

WORLD_MANIFEST = "drivedegrade_world.json"
#: The `skipped` reason of keyframes that are read but not scored (fewer than six future keyframes).
UNSCORED = "fewer than six future keyframes (not scored)"
#: ``junction``: a world's junction scenes (`world.junctionscenes`), in a world built with them only.
SPLITS = ("train", "val", "mini_train", "mini_val", "all", "junction")


def coarse_category(name: str) -> str:
    """nuScenes category name -> vehicle / pedestrian / cyclist / other."""
    if name.startswith("human.pedestrian"):
        return "pedestrian"
    if name.startswith(("vehicle.bicycle", "vehicle.motorcycle")):
        return "cyclist"
    if name.startswith("vehicle."):
        return "vehicle"
    return "other"


def official_split(split: str) -> set[str]:
    """Scene names of an official nuScenes split, from the devkit's lists shipped with the package."""
    import yaml

    data = yaml.safe_load((Path(__file__).with_name("nuscenes_splits.yaml")).read_text())
    names: set[str] = set()
    for part in data[split].split(","):
        a, _, b = part.strip().partition("-")
        names.update(f"scene-{i:04d}" for i in range(int(a), int(b or a) + 1))
    return names


def official_scene_names(split: str) -> list[str]:
    """Scene names of an official nuScenes split in scene-number order."""
    return sorted(official_split(split), key=lambda name: int(name.rpartition("-")[2]))


class NuScenesReader:
    """Frames of one split of a nuScenes-format data root."""

    def __init__(self, root: str | os.PathLike[str], version: str | None = None, split: str = "val",
                 strict: bool = False):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataError(f"nuScenes data root {self.root} does not exist or is not a folder")
        self.version = version or self._detect_version()
        self.table_dir = self.root / self.version
        if not self.table_dir.is_dir():
            raise DataError(f"no version folder {self.table_dir}: pass the nuScenes root that holds it")
        if split not in SPLITS:
            raise DataError(f"unknown split {split!r}: choose one of {', '.join(SPLITS)}")
        self.split, self.strict = split, strict
        self.skipped: Counter[str] = Counter()
        self.problems: list[str] = []
        self.manifest = load_manifest(self.root / WORLD_MANIFEST)
        self.future_poses = future_poses(self.manifest, self.root)
        self._index()

    def _detect_version(self) -> str:
        found = sorted(p.name for p in self.root.iterdir() if p.is_dir() and p.name.startswith("v1.0-"))
        if len(found) != 1:
            what = "no v1.0-* version folder" if not found else f"several version folders ({', '.join(found)})"
            raise DataError(f"nuScenes data root {self.root} has {what}: pass the version explicitly")
        return found[0]

    def _index(self) -> None:
        t = {name: load_table(self.table_dir / f"{name}.json") for name in REQUIRED_TABLES}
        self.scenes = t["scene"]
        self.samples = {r["token"]: r for r in t["sample"]}
        self.poses = {r["token"]: r for r in t["ego_pose"]}
        sensors = {r["token"]: r for r in t["sensor"]}
        self.calib = {r["token"]: dict(r, channel=sensors.get(r["sensor_token"], {}).get("channel", ""))
                      for r in t["calibrated_sensor"]}
        self.key_data: dict[str, dict[str, dict]] = defaultdict(dict)
        for r in t["sample_data"]:
            if r.get("is_key_frame", True):
                channel = self.calib.get(r["calibrated_sensor_token"], {}).get("channel", "")
                self.key_data[r["sample_token"]][channel] = r
        categories = {r["token"]: coarse_category(r["name"]) for r in t["category"]}
        inst = {r["token"]: categories.get(r["category_token"], "other") for r in t["instance"]}
        logs = {}
        if (self.table_dir / "log.json").is_file():
            logs = {r["token"]: r.get("location", "") for r in load_table(self.table_dir / "log.json")}
        self.locations = {s["token"]: logs.get(s.get("log_token", ""), "") for s in self.scenes}
        self._maps: dict[str, DrivableArea | None] = {}
        self._lane_maps: dict[str, LaneMap | None] = {}
        self.annotations: dict[str, list[tuple]] = defaultdict(list)
        for r in t["sample_annotation"]:
            self.annotations[r["sample_token"]].append(
                (r["translation"], r["size"], r["rotation"], inst.get(r["instance_token"], "other")))
        self.split_scenes = self._select_scenes()

    def with_split(self, split: str) -> NuScenesReader:
        """The same data root read as another split, sharing the indexed tables (no second read)."""
        if split not in SPLITS:
            raise DataError(f"unknown split {split!r}: choose one of {', '.join(SPLITS)}")
        other = copy.copy(self)
        other.split, other.skipped, other.problems = split, Counter(), []
        other.split_scenes = other._select_scenes()
        return other

    def _select_scenes(self) -> list[dict]:
        if self.split == "all":
            return list(self.scenes)
        if self.manifest is not None and self.split in self.manifest.get("splits", {}):
            names = set(self.manifest["splits"][self.split])
        elif self.split == "junction":
            raise DataError(f"{self.root}: no junction split: only a world built with junction scenes has one "
                            f"(drivedegrade world --out DIR --junction-scenes N, then --drivedegrade-data DIR)")
        else:
            names = official_split(self.split)
        return [s for s in self.scenes if s["name"] in names]

    # -- public API ---------------------------------------------------------------------------------
    def frames(self, *, agents: bool = True) -> Iterator[Frame]:
        """Every keyframe of the split's scenes, in scene order (scorable or not). Each pass recounts
        `skipped` and `problems`. `agents=False` reads no annotation: each future step's boxes are empty (the
        ego-only floor trains on ego status, command and logged future alone; the boxes were over a third of its
        read)."""
        self.skipped, self.problems = Counter(), []
        for scene in self.split_scenes:
            tokens = self._scene_samples(scene)
            if not tokens:
                continue
            poses, problem = self._poses(tokens)
            if problem:
                self._skip("sample points at a missing record", problem, len(tokens))
                continue
            can = self._can_bus(scene["name"])
            for k in range(len(tokens)):
                frame = self._frame(scene, tokens, poses, k, can, agents)
                if frame is not None:
                    yield frame

    def scorable_frames(self, limit: int | None = None, *, agents: bool = True) -> list[Frame]:
        """Frames with six future keyframes, scene by scene in timestamp order; with `limit`, a deterministic
        subset of `limit` frames made of one contiguous run per scene (see `contiguous_subset`); `agents` as
        in `frames`."""
        frames = [f for f in self.frames(agents=agents) if f.scorable]
        if limit is not None and 0 < limit < len(frames):
            frames = contiguous_subset(frames, limit)
        return frames

    def fingerprint(self) -> str:
        """A stable hex id of the data content and split."""
        h = hashlib.blake2b(digest_size=16)
        if self.manifest is not None:
            h.update(f"{self.manifest['fingerprint']}|{self.split}".encode())
        else:
            h.update(f"{self.version}|{self.split}".encode())
            for scene in self.split_scenes:
                h.update(f"|{scene['name']}|{scene['first_sample_token']}|{scene.get('nbr_samples')}".encode())
        return h.hexdigest()

    def drivable_area(self, where: Frame | str) -> DrivableArea | None:
        """The drivable area of a frame's location (or of a location by name): polygons in global metres and a
        vectorised point query (`contains`, or call it). None when there is no map: no log location, or no
        `maps/expansion/<location>.json` under the data root. Read once per location."""
        location = where if isinstance(where, str) else where.location
        if location not in self._maps:
            self._maps[location] = load_drivable_area(self.root, location) if location else None
        return self._maps[location]

    def lane_map(self, where: Frame | str) -> LaneMap | None:
        """The lane-level map of a frame's location (or of a location by name), or None when the map expansion
        has no lane layers there (then the EPDMS's ddc and lk are not scored). Read once per location."""
        location = where if isinstance(where, str) else where.location
        if location not in self._lane_maps:
            found = load_lane_map(self.root, location) if location else None
            self._lane_maps[location] = found if found is not None and found.lanes else None
        return self._lane_maps[location]

    @staticmethod
    def load_image(camera: CameraInfo) -> np.ndarray:
        """Decode one camera image to H x W x 3 uint8 RGB; DataError names the file and the frame for a missing,
        empty, truncated, undecodable or wrong-size image (size from sample_data's width and height)."""
        from .images import decode_rgb

        return decode_rgb(camera.path, camera.sample_token, (camera.width, camera.height))

    # -- building frames ----------------------------------------------------------------------------
    def _skip(self, reason: str, detail: str, count: int = 1) -> None:
        if self.strict:
            raise DataError(detail)
        self.skipped[reason] += count
        self.problems.append(detail)

    def _scene_samples(self, scene: dict) -> list[str]:
        tokens: list[str] = []
        token, seen = scene.get("first_sample_token", ""), set()
        while token and token not in seen:
            if token not in self.samples:
                self._skip("sample points at a missing record",
                           f"scene {scene['name']} ({scene['token']}) links to missing sample {token} in "
                           f"{self.table_dir / 'sample.json'}", max(len(tokens), 1))
                return []
            seen.add(token)
            tokens.append(token)
            token = self.samples[token].get("next", "")
        if not tokens:
            self._skip("scene without keyframes", f"scene {scene.get('name')} ({scene['token']}) has no "
                                                   f"keyframes in {self.table_dir / 'sample.json'}")
        return tokens

    def _poses(self, tokens: list[str]) -> tuple[Sequence[np.ndarray], str]:
        """The ego pose of every keyframe (of its LIDAR_TOP record when present, else CAM_FRONT)."""
        out = []
        for tok in tokens:
            data = self.key_data.get(tok, {})
            ref = data.get("LIDAR_TOP") or data.get("CAM_FRONT") or next(iter(data.values()), None)
            if ref is None:
                return [], f"sample {tok} has no key-frame sample_data in {self.table_dir / 'sample_data.json'}"
            pose = self.poses.get(ref["ego_pose_token"])
            if pose is None:
                return [], (f"sample_data {ref['token']} of sample {tok} points at missing ego_pose "
                            f"{ref['ego_pose_token']} in {self.table_dir / 'ego_pose.json'}")
            out.append(pose)
        xy = np.array([p["translation"][:2] for p in out], dtype=float)
        yaw = geo.quat_yaws(np.array([p["rotation"] for p in out]))
        full = np.array([[*p["rotation"], *p["translation"]] for p in out], dtype=float)  # (K, 7) w x y z tx ty tz
        return (xy, yaw, np.array([p["timestamp"] for p in out]), full), ""

    def _can_bus(self, scene_name: str) -> list[dict] | None:
        path = self.root / "can_bus" / f"{scene_name}_pose.json"
        if not path.is_file():
            return None
        return load_can_bus(path) or None

    def _frame(self, scene: dict, tokens: list[str], poses: Sequence[np.ndarray], k: int,
               can: list[dict] | None, with_agents: bool = True) -> Frame | None:
        token = tokens[k]
        cameras, problem = self._cameras(token)
        if problem:
            self._skip("sample points at a missing record", problem)
            return None
        xy, yaw, stamps, full = poses
        ego = _ego_status(xy, yaw, stamps, k, can)
        beyond = list(range(k + 1 + HORIZON_STEPS, min(k + 1 + self.future_poses, len(tokens))))
        ahead = list(range(k + 1, min(k + 1 + HORIZON_STEPS, len(tokens))))  # the future keyframes there are
        valid = np.arange(HORIZON_STEPS) < len(ahead)  # the steps they fill, the first ones
        future = np.zeros((HORIZON_STEPS, 2))
        if ahead:  # every step in one call: each row is its own point's arithmetic, the same bits
            future[: len(ahead)] = geo.se2_to_ego(xy[ahead], xy[k], yaw[k])
        agents = [self._agents(tokens[i], xy[k], yaw[k]) if with_agents else AgentBoxes.empty() for i in ahead]
        command = command_from_future(future[valid]) if valid.any() else Command.STRAIGHT
        if not valid.all() or len(beyond) < self.future_poses - HORIZON_STEPS:
            self.skipped[UNSCORED] += 1
        tail = geo.se2_to_ego(xy[beyond], xy[k], yaw[k]) if beyond else None
        tail_agents = tuple(self._agents(tokens[i], xy[k], yaw[k]) if with_agents else AgentBoxes.empty()
                            for i in beyond)
        pose = (tuple(float(v) for v in full[k, :4]), tuple(float(v) for v in full[k, 4:]))
        can_record = None
        if can is not None:
            rec = _nearest(can, int(stamps[k]))
            can_record = {key: tuple(float(v) for v in rec[key][:3]) for key in ("accel", "rotation_rate", "vel")}
        return Frame(token, scene["token"], int(self.samples[token]["timestamp"]), cameras, ego, command,
                     future, valid, tuple(agents), scene["name"], index=k, ego_pose=pose,
                     lidar=self._lidar(token), can=can_record, location=self.locations.get(scene["token"], ""),
                     pose=(float(xy[k, 0]), float(xy[k, 1]), float(yaw[k])), lidar_file=self._lidar_file(token),
                     past_motion=_past_motion(yaw, stamps, k, lambda i: _ego_status(xy, yaw, stamps, i, can)),
                     future_tail=tail, agents_tail=tail_agents, future_needed=self.future_poses)

    def _lidar(self, token: str) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
        """LIDAR_TOP's calibrated_sensor (rotation, translation) at keyframe `token`, or None without one."""
        rec = self.key_data.get(token, {}).get("LIDAR_TOP")
        cal = self.calib.get(rec["calibrated_sensor_token"]) if rec is not None else None
        if cal is None:
            return None
        return tuple(float(v) for v in cal["rotation"]), tuple(float(v) for v in cal["translation"])

    def _lidar_file(self, token: str) -> str:
        """The path of keyframe `token`'s LIDAR_TOP sweep, or "" without one (read only when a planner asks)."""
        rec = self.key_data.get(token, {}).get("LIDAR_TOP")
        if rec is None or not rec.get("filename"):
            return ""
        where = f"{self.table_dir / 'sample_data.json'}: the record with token {rec['token']!r}"
        return str(confined(self.root, rec["filename"], where))

    def _cameras(self, token: str) -> tuple[dict[str, CameraInfo], str]:
        data = self.key_data.get(token, {})
        out = {}
        for name in CAMERAS:
            rec = data.get(name)
            if rec is None:
                return {}, f"sample {token} has no {name} key-frame image in {self.table_dir / 'sample_data.json'}"
            cal = self.calib.get(rec["calibrated_sensor_token"])
            if cal is None:
                return {}, (f"sample_data {rec['token']} points at missing calibrated_sensor "
                            f"{rec['calibrated_sensor_token']} in {self.table_dir / 'calibrated_sensor.json'}")
            where = f"{self.table_dir / 'sample_data.json'}: the record with token {rec['token']!r}"
            out[name] = CameraInfo(name, str(confined(self.root, rec["filename"], where)), int(rec["width"]),
                                   int(rec["height"]),
                                   np.asarray(cal["camera_intrinsic"], dtype=float),
                                   tuple(cal["rotation"]), tuple(cal["translation"]), token)
        return out, ""

    def _agents(self, sample_token: str, origin_xy: np.ndarray, origin_yaw: float) -> AgentBoxes:
        anns = self.annotations.get(sample_token, [])
        if not anns:
            return AgentBoxes.empty()
        centre = geo.se2_to_ego(np.array([a[0][:2] for a in anns], dtype=float), origin_xy, origin_yaw)
        size = np.array([[a[1][1], a[1][0]] for a in anns], dtype=float)  # nuScenes size is (w, l, h)
        yaw = geo.wrap_angle(geo.quat_yaws(np.array([a[2] for a in anns])) - origin_yaw)
        return AgentBoxes(centre, size, yaw, tuple(a[3] for a in anns))


def future_poses(manifest: dict | None, root: Path) -> int:
    """The future keyframes every scored frame of the data holds: 2 x a world manifest's ``future_s`` (a world
    generated with ``--future 4``: 8), else nuScenes' convention of 3 s (6)."""
    seconds = 3 if manifest is None else manifest.get("future_s", 3)
    if isinstance(seconds, bool) or seconds not in (3, 4):
        raise DataError(f"{root / WORLD_MANIFEST}: future_s must be 3 or 4 (seconds of future per scored frame), "
                        f"found {seconds!r}")
    return round(seconds / STEP_SECONDS)


def _ego_status(xy: np.ndarray, yaw: np.ndarray, stamps: np.ndarray, k: int, can: list[dict] | None) -> EgoStatus:
    """Ego status at keyframe k: past positions in the current frame (oldest first) and motion terms."""
    dt = np.maximum(np.diff(stamps) * 1e-6, 1e-3)
    # backward difference in the frame of keyframe i; forward difference at the first keyframe
    def vel(i: int) -> np.ndarray:
        j0, j1 = (i - 1, i) if i > 0 else (0, min(1, len(xy) - 1))
        if j0 == j1:
            return np.zeros(2)
        return geo.se2_to_ego(xy[j1], xy[j0], yaw[i])[0] / dt[j0]
    v = vel(k)
    if can is not None:
        rec = _nearest(can, stamps[k])
        velocity, accel = tuple(rec["vel"][:2]), tuple(rec["accel"][:2])
        yaw_rate = float(rec["rotation_rate"][2])
    else:
        yaw_rate = float(geo.wrap_angle(yaw[k] - yaw[k - 1]) / dt[k - 1]) if k > 0 else 0.0
        if k > 1:
            c, s = np.cos(yaw[k - 1] - yaw[k]), np.sin(yaw[k - 1] - yaw[k])
            vp = vel(k - 1)
            accel = tuple((v - np.array([c * vp[0] - s * vp[1], s * vp[0] + c * vp[1]])) / dt[k - 1])
        else:
            accel = (0.0, 0.0)
        velocity = tuple(v)
    past = np.zeros((PAST_STEPS, 2))
    for n in range(1, PAST_STEPS + 1):
        row = PAST_STEPS - n  # oldest first
        past[row] = geo.se2_to_ego(xy[k - n], xy[k], yaw[k])[0] if k - n >= 0 else \
            -np.asarray(velocity, dtype=float) * n * STEP_SECONDS
    return EgoStatus((float(velocity[0]), float(velocity[1])), (float(accel[0]), float(accel[1])),
                     float(yaw_rate), past)


def _past_motion(yaw: np.ndarray, stamps: np.ndarray, k: int, status: Callable[[int], EgoStatus]) -> np.ndarray:
    """`Frame.past_motion` of keyframe k: each past keyframe's time (us) and heading relative to k and its own
    logged acceleration (`status(i)`, the keyframe's `EgoStatus`); before the scene's first keyframe, the first
    keyframe's motion repeated 0.5 s further back per missing keyframe (NAVSIM never scores such a frame)."""
    out = np.zeros((PAST_STEPS, 4))
    for n in range(1, PAST_STEPS + 1):
        i = max(k - n, 0)
        missing = n - (k - i)
        out[PAST_STEPS - n] = (float(stamps[i] - stamps[k]) - missing * STEP_SECONDS * 1e6,
                               float(geo.wrap_angle(yaw[i] - yaw[k])), *status(i).acceleration)
    out.setflags(write=False)
    return out


def _nearest(records: list[dict], utime: int) -> dict:
    """The CAN bus record nearest in time at or before `utime` (the first record when none is before)."""
    times = np.array([r["utime"] for r in records])
    i = int(np.searchsorted(times, utime, side="right")) - 1
    return records[max(i, 0)]


def contiguous_subset(frames: list[Frame], limit: int) -> list[Frame]:
    """`limit` of `frames` (scene by scene, in order) as one contiguous run per scene, so a temporal planner never
    sees a stream with silent holes (SPEC section 8).

    Each scene gets a share of `limit` proportional to its frame count (largest remainders, ties to the earlier
    scene); its run is the middle `share` frames of the scene. Scenes whose share is 0 are left out.
    """
    scenes: dict[str, list[Frame]] = {}
    for f in frames:
        scenes.setdefault(f.scene_token, []).append(f)
    runs = list(scenes.values())
    quotas = [limit * len(r) / len(frames) for r in runs]
    shares = [int(q) for q in quotas]
    for i in sorted(range(len(runs)), key=lambda i: (-(quotas[i] - shares[i]), i))[:limit - sum(shares)]:
        shares[i] += 1
    out: list[Frame] = []
    for run, share in zip(runs, shares):
        begin = (len(run) - share) // 2
        out += run[begin:begin + share]
    return out

