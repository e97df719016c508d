"""CARLA leaderboard bridge: run any leaderboard agent with its camera images degraded by the suite's operators.

The leaderboard loads an agent file, calls its ``get_entry_point()`` for a class name and builds that class; the
class is ``setup(path_to_conf_file)``, asked for ``sensors()`` and called each tick through ``run_step(input_data,
timestamp)``, where ``input_data`` maps a sensor id to ``(frame, data)`` and a camera's data is an H x W x 4 BGRA
uint8 array. Point the leaderboard at this file and this file at your agent:

    export DRIVEDEGRADE_CARLA_AGENT=/path/to/my_agent.py     # optionally :ClassName (default: its get_entry_point())
    export DRIVEDEGRADE_FAMILY=gaussian_blur DRIVEDEGRADE_SEVERITY=5 DRIVEDEGRADE_SEED=0
    export TEAM_AGENT=/path/to/planners/examples/carla_agent.py   # the leaderboard's --agent
    ./scripts/run_evaluation.sh                                  # --checkpoint results/gaussian_blur-s5.json

or put the settings in a JSON file named by ``DRIVEDEGRADE_CARLA_CONFIG`` (``{"family": "blackout", "severity": 3,
"seed": 1, "cameras": {"Center": "CAM_FRONT"}, "route": ""}``; a variable set in the environment wins over the
file). ``--agent-config`` still goes to your agent unchanged.

The class the leaderboard gets is a subclass of your agent whose ``run_step`` replaces the camera arrays of
``input_data`` by their degraded copies and calls yours; everything else (sensors, ``set_global_plan``,
``destroy``, the leaderboard's own ``__call__``) is your agent's. Degrading follows the suite exactly:

- each RGB camera sensor stands for a suite camera (``CAM_FRONT`` ...): the one nearest in yaw (CARLA's yaw turns
  clockwise, nuScenes' counter-clockwise), or as the config's ``cameras`` names it; a blackout of the rear views
  then blacks out what your agent mounted at the back;
- the randomness is the suite's key (seed, frame, camera, family, severity) with frame ``<route>/<step>``: step
  counts ``run_step`` calls from 0, route is the config's ``route`` or, by default, ``carla-`` and a digest of the
  route's waypoints (``set_global_plan``), the same for every repetition of a route;
- a sample-level family (``blackout``, ``frame_dropout``) acts on all the agent's cameras together, as in the suite.

Other sensors (LiDAR, GNSS, IMU, speedometer) pass through untouched. The score comes from the leaderboard's own
results file, one per cell; ``drivedegrade closed-loop import`` turns those files into the closed-loop analysis.
Importable without CARLA: nothing here imports ``carla`` or ``leaderboard``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import cv2
import numpy as np

from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.corruptions.api import check_family, check_severity, corrupt_sample
from pytest_drivedegrade.data.world.rig import MOUNTS
from pytest_drivedegrade.errors import DriveDegradeError

ENV_AGENT, ENV_CONFIG = "DRIVEDEGRADE_CARLA_AGENT", "DRIVEDEGRADE_CARLA_CONFIG"
ENV_FAMILY, ENV_SEVERITY, ENV_SEED, ENV_ROUTE = ("DRIVEDEGRADE_FAMILY", "DRIVEDEGRADE_SEVERITY", "DRIVEDEGRADE_SEED",
                                                 "DRIVEDEGRADE_ROUTE")
#: The class name the leaderboard gets from get_entry_point().
ENTRY = "DriveDegradeAgent"
RGB_CAMERA = "sensor.camera.rgb"


class BridgeError(DriveDegradeError, ValueError):
    """A bad bridge setting: names the variable or file and what it accepts."""


@dataclass(frozen=True)
class BridgeConfig:
    """The cell the agent runs in (family, severity 0..5, corruption seed), the sensor id -> suite camera names
    that override the yaw rule, and the route key (empty: derived from the route's waypoints)."""

    family: str = "clean"
    severity: int = 0
    seed: int = 0
    cameras: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}))
    route: str = ""

    @property
    def cell(self) -> str:
        if self.family in ("clean", "blind"):
            return self.family
        return "clean" if self.severity == 0 else f"{self.family}-s{self.severity}"

    @staticmethod
    def load(environ: Mapping[str, str] = os.environ) -> BridgeConfig:
        """From the JSON file $DRIVEDEGRADE_CARLA_CONFIG (if set), then the single variables over it."""
        raw: dict[str, object] = {}
        path = environ.get(ENV_CONFIG)
        if path:
            try:
                loaded = json.loads(Path(path).read_text())
            except (OSError, ValueError) as exc:
                raise BridgeError(f"{ENV_CONFIG}={path}: cannot read a JSON object from it ({exc})") from None
            if not isinstance(loaded, dict):
                raise BridgeError(f"{ENV_CONFIG}={path}: expected a JSON object, got {type(loaded).__name__}")
            raw.update(loaded)
        for key, var in (("family", ENV_FAMILY), ("severity", ENV_SEVERITY), ("seed", ENV_SEED), ("route", ENV_ROUTE)):
            if environ.get(var):
                raw[key] = environ[var]
        return BridgeConfig.of(raw, path or "the environment")

    @staticmethod
    def of(raw: Mapping[str, object], where: str) -> BridgeConfig:
        unknown = sorted(set(raw) - {"family", "severity", "seed", "cameras", "route"})
        if unknown:
            raise BridgeError(f"{where}: unknown setting(s) {', '.join(unknown)}; known: family, severity, seed, "
                              "cameras, route")
        try:
            family = check_family(str(raw.get("family", "clean")), allow_diagnostic=True)
            severity = check_severity(int(str(raw.get("severity", 0 if family == "clean" else -1))))
            seed = int(str(raw.get("seed", 0)))
        except ValueError as exc:
            raise BridgeError(f"{where}: {exc} (variables {ENV_FAMILY}, {ENV_SEVERITY}, {ENV_SEED})") from None
        cameras = raw.get("cameras", {})
        if not isinstance(cameras, dict) or any(v not in CAMERAS for v in cameras.values()):
            raise BridgeError(f"{where}: cameras must map sensor ids to suite cameras ({', '.join(CAMERAS)}), "
                              f"got {cameras!r}")
        return BridgeConfig(family, severity, seed, MappingProxyType(dict(cameras)), str(raw.get("route", "")))


def suite_cameras(sensors: Sequence[Mapping[str, object]], named: Mapping[str, str]) -> dict[str, str]:
    """Sensor id -> suite camera for every RGB camera of `sensors()`: `named`'s entry, else the suite camera
    nearest in yaw (CARLA degrees, clockwise). Two sensors on one suite camera: an error asking to name them."""
    out: dict[str, str] = {}
    for sensor in sensors:
        if sensor.get("type") != RGB_CAMERA:
            continue
        sid = str(sensor["id"])
        if sid in named:
            out[sid] = named[sid]
            continue
        yaw = -float(str(sensor.get("yaw", 0.0)))  # the suite's yaw is counter-clockwise
        gap = {cam: abs((yaw - MOUNTS[cam][1] + 180.0) % 360.0 - 180.0) for cam in CAMERAS}
        out[sid] = min(CAMERAS, key=lambda cam: (gap[cam], CAMERAS.index(cam)))
    taken: dict[str, str] = {}
    for sid, cam in out.items():
        if cam in taken:
            raise BridgeError(f"camera sensors {taken[cam]!r} and {sid!r} both stand for {cam}: name each in the "
                              f"config's cameras ({ENV_CONFIG})")
        taken[cam] = sid
    return out


def route_key(plan: object) -> str:
    """`carla-` and 12 hex digits of the route's waypoints (x, y rounded to 0.1 m): the same route gives the same
    key in every repetition and on every machine. A plan without locations gives "route"."""
    try:
        points = [(round(float(p[0].location.x), 1), round(float(p[0].location.y), 1)) for p in plan]  # type: ignore
    except (TypeError, AttributeError, IndexError):
        return "route"
    return "carla-" + hashlib.sha256(repr(points).encode()).hexdigest()[:12] if points else "route"


class Degrader:
    """One route's camera stream through the cell's corruption: `__call__(input_data)` gives a new input_data
    whose camera arrays are degraded copies (BGRA in, BGRA out, alpha kept; other entries the same objects)."""

    def __init__(self, config: BridgeConfig, cameras: Mapping[str, str], route: str) -> None:
        self.config, self.cameras, self.route = config, dict(cameras), route
        self.step = 0
        self.previous: dict[str, np.ndarray] | None = None

    def __call__(self, input_data: Mapping[str, tuple[object, object]]) -> dict[str, tuple[object, object]]:
        out = dict(input_data)
        present = {sid: cam for sid, cam in self.cameras.items() if sid in input_data}
        step, self.step = self.step, self.step + 1
        if self.config.cell == "clean" or not present:
            return out
        images = {}
        for sid, cam in present.items():
            data = np.asarray(input_data[sid][1])
            if data.dtype != np.uint8 or data.ndim != 3 or data.shape[2] not in (3, 4):
                raise BridgeError(f"sensor {sid!r}: expected an H x W x 4 BGRA (or x 3 BGR) uint8 image, got "
                                  f"{data.dtype} {data.shape}")
            images[cam] = np.ascontiguousarray(data[..., 2::-1])  # BGR(A) -> RGB
        done = corrupt_sample(images, self.config.family, self.config.severity, seed=self.config.seed,
                              frame=f"{self.route}/{step}", previous=self.previous)
        self.previous = done
        for sid, cam in present.items():
            frame, payload = input_data[sid]
            original = np.asarray(payload)
            bgr = cv2.cvtColor(done[cam], cv2.COLOR_RGB2BGR)
            out[sid] = (frame, np.dstack([bgr, original[..., 3:]]) if original.shape[2] == 4 else bgr)
        return out


def degraded(agent_class: type, config: BridgeConfig | None = None) -> type:
    """A subclass of the leaderboard agent class `agent_class` whose `run_step` sees degraded camera images."""

    class DriveDegradeAgent(agent_class):
        drivedegrade_config = config

        def set_global_plan(self, global_plan_gps: object, global_plan_world_coord: object) -> None:
            self._drivedegrade_route = route_key(global_plan_world_coord)
            super().set_global_plan(global_plan_gps, global_plan_world_coord)

        def run_step(self, input_data: Mapping[str, tuple[object, object]], timestamp: float) -> object:
            degrader = getattr(self, "_drivedegrade", None)
            if degrader is None:  # built at the first tick: sensors() may need setup() and the route
                cfg = self.drivedegrade_config or BridgeConfig.load()
                route = cfg.route or getattr(self, "_drivedegrade_route", "route")
                degrader = self._drivedegrade = Degrader(cfg, suite_cameras(self.sensors(), cfg.cameras), route)
            return super().run_step(degrader(input_data), timestamp)

    DriveDegradeAgent.__qualname__ = DriveDegradeAgent.__name__ = ENTRY
    return DriveDegradeAgent


def load_agent_class(spec: str) -> type:
    """The class of `path/to/agent.py[:ClassName]` (default: the file's get_entry_point())."""
    path, name = spec.rsplit(":", 1) if ":" in spec and not spec.endswith(".py") else (spec, "")
    if not Path(path).is_file():
        raise BridgeError(f"{ENV_AGENT}={spec}: no agent file {path} (set it to path/to/agent.py[:ClassName])")
    module_spec = importlib.util.spec_from_file_location(f"drivedegrade_inner_{Path(path).stem}", path)
    assert module_spec is not None and module_spec.loader is not None
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[module_spec.name] = module
    module_spec.loader.exec_module(module)
    if not name and hasattr(module, "get_entry_point"):
        name = str(module.get_entry_point())
    if not name or not isinstance(getattr(module, name, None), type):
        raise BridgeError(f"{ENV_AGENT}={spec}: no agent class {name or '(no get_entry_point())'} in {path}")
    return getattr(module, name)


def get_entry_point() -> str:
    """What the leaderboard asks first: the name of the class to build."""
    return ENTRY


def __getattr__(name: str) -> type:
    """`DriveDegradeAgent`: the agent named by $DRIVEDEGRADE_CARLA_AGENT, degraded (built on first access)."""
    if name != ENTRY:
        raise AttributeError(name)
    spec = os.environ.get(ENV_AGENT)
    if not spec:
        raise BridgeError(f"set {ENV_AGENT}=path/to/agent.py[:ClassName]: the leaderboard agent to degrade")
    cls = degraded(load_agent_class(spec))
    globals()[ENTRY] = cls
    return cls
