"""The CARLA leaderboard bridge (planners/examples/carla_agent.py), without CARLA: a fake leaderboard agent gets
camera images equal to the suite's operator output for the same key (seed, "<route>/<step>", camera, family,
severity), BGRA in and out, other sensors untouched; cameras map by yaw or by name; bad settings name the
variable; the module-level entry point the leaderboard uses builds the degraded subclass."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType, SimpleNamespace

import cv2
import numpy as np
import pytest

from pytest_drivedegrade.corruptions.api import corrupt_sample

BRIDGE = Path(__file__).resolve().parents[2] / "planners" / "examples" / "carla_agent.py"

FAKE_AGENT = '''
def get_entry_point():
    return "FakeAgent"


class FakeAgent:
    """A leaderboard-shaped agent: three cameras (CARLA yaw, clockwise), a LiDAR and a speedometer."""

    def __init__(self, *args):
        self.args, self.seen, self.conf = args, [], None

    def setup(self, path_to_conf_file):
        self.conf = path_to_conf_file

    def set_global_plan(self, gps, world):
        self.plan = world

    def sensors(self):
        cam = {"type": "sensor.camera.rgb", "x": 1.3, "y": 0.0, "z": 2.3, "width": 64, "height": 48, "fov": 70}
        return [dict(cam, id="Left", yaw=-60.0), dict(cam, id="Center", yaw=0.0), dict(cam, id="Right", yaw=60.0),
                {"type": "sensor.lidar.ray_cast", "id": "LIDAR", "yaw": 0.0},
                {"type": "sensor.speedometer", "id": "SPEED"}]

    def run_step(self, input_data, timestamp):
        self.seen.append(input_data)
        return ("control", timestamp)

    def destroy(self):
        pass
'''


def _load(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def bridge() -> ModuleType:
    return _load("carla_agent_under_test", BRIDGE)


@pytest.fixture
def fake(tmp_path: Path) -> Path:
    path = tmp_path / "fake_agent.py"
    path.write_text(FAKE_AGENT)
    return path


def _input(step: int) -> dict[str, tuple[int, object]]:
    rng = np.random.default_rng(step)
    cams = {sid: rng.integers(0, 256, (48, 64, 4), dtype=np.uint8) for sid in ("Left", "Center", "Right")}
    for img in cams.values():
        img[..., 3] = 255
    return {**{sid: (100 + step, img) for sid, img in cams.items()}, "LIDAR": (100 + step, np.ones((10, 4))),
            "SPEED": (100 + step, {"speed": 3.0})}


def _expected(data: dict[str, tuple[int, object]], family: str, severity: int, seed: int, frame: str,
              previous: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    names = {"Left": "CAM_FRONT_LEFT", "Center": "CAM_FRONT", "Right": "CAM_FRONT_RIGHT"}
    rgb = {names[sid]: cv2.cvtColor(np.asarray(data[sid][1]), cv2.COLOR_BGRA2RGB) for sid in names}
    done = corrupt_sample(rgb, family, severity, seed=seed, frame=frame, previous=previous)
    return {sid: cv2.cvtColor(done[cam], cv2.COLOR_RGB2BGRA) for sid, cam in names.items()}


@pytest.mark.parametrize(("family", "severity"), [("gaussian_noise", 3), ("blackout", 5), ("motion_blur", 4)])
def test_the_agent_sees_the_suites_operator_output_for_the_same_key(
        bridge: ModuleType, fake: Path, monkeypatch: pytest.MonkeyPatch, family: str, severity: int) -> None:
    for var, value in ((bridge.ENV_AGENT, str(fake)), (bridge.ENV_FAMILY, family),
                       (bridge.ENV_SEVERITY, str(severity)), (bridge.ENV_SEED, "7"), (bridge.ENV_ROUTE, "r1")):
        monkeypatch.setenv(var, value)
    cls = getattr(bridge, bridge.get_entry_point())  # what the leaderboard does
    agent = cls("localhost", 2000, False)
    agent.setup("my_agent.yaml")
    assert agent.conf == "my_agent.yaml" and type(agent).__mro__[1].__name__ == "FakeAgent"
    previous = None
    for step in range(3):
        data = _input(step)
        before = {k: np.array(v[1]) for k, v in data.items() if k != "SPEED"}
        assert agent.run_step(data, 0.05 * step) == ("control", 0.05 * step)
        seen = agent.seen[-1]
        want = _expected(data, family, severity, 7, f"r1/{step}", previous)
        previous = {cam: cv2.cvtColor(img, cv2.COLOR_BGRA2RGB) for cam, img in
                    zip(("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"), want.values())}
        for sid, img in want.items():
            assert seen[sid][0] == 100 + step and np.array_equal(seen[sid][1], img), (sid, step)
        assert seen["LIDAR"] is data["LIDAR"] and seen["SPEED"] is data["SPEED"]
        assert all(np.array_equal(np.asarray(data[k][1]), v) for k, v in before.items())  # input left alone
    if family == "gaussian_noise":  # a different step is a different draw
        assert not np.array_equal(agent.seen[0]["Center"][1], _expected(_input(0), family, severity, 7, "r1/1")
                                  ["Center"])


def test_the_route_key_comes_from_the_waypoints_and_clean_passes_through(bridge: ModuleType, fake: Path) -> None:
    inner = bridge.load_agent_class(f"{fake}:FakeAgent")
    cls = bridge.degraded(inner, bridge.BridgeConfig("gaussian_noise", 2, 0))
    agent = cls()
    waypoint = SimpleNamespace(location=SimpleNamespace(x=10.04, y=-3.0))
    agent.set_global_plan([], [(waypoint, "LANEFOLLOW")] * 3)
    data = _input(0)
    agent.run_step(data, 0.0)
    key = bridge.route_key([(waypoint, "LANEFOLLOW")] * 3)
    assert key.startswith("carla-") and len(key) == 18
    assert np.array_equal(agent.seen[0]["Center"][1], _expected(data, "gaussian_noise", 2, 0, f"{key}/0")["Center"])
    clean = bridge.degraded(inner, bridge.BridgeConfig())()
    clean.run_step(data, 0.0)
    assert all(clean.seen[0][k] is data[k] for k in data)


def test_cameras_map_by_yaw_or_by_name(bridge: ModuleType) -> None:
    cam = {"type": "sensor.camera.rgb"}
    sensors = [dict(cam, id="a", yaw=-60.0), dict(cam, id="b", yaw=180.0), dict(cam, id="c", yaw=100.0),
               {"type": "sensor.other.gnss", "id": "GPS"}]
    assert bridge.suite_cameras(sensors, {}) == {"a": "CAM_FRONT_LEFT", "b": "CAM_BACK", "c": "CAM_BACK_RIGHT"}
    assert bridge.suite_cameras(sensors, {"c": "CAM_FRONT"})["c"] == "CAM_FRONT"
    with pytest.raises(bridge.BridgeError, match="'a' and 'd' both stand for CAM_FRONT_LEFT"):
        bridge.suite_cameras([*sensors, dict(cam, id="d", yaw=-50.0)], {})


def test_settings_from_a_file_the_environment_wins_and_bad_ones_are_named(bridge: ModuleType, tmp_path: Path) -> None:
    conf = tmp_path / "dd.json"
    conf.write_text(json.dumps({"family": "blackout", "severity": 3, "seed": 2, "cameras": {"Center": "CAM_FRONT"}}))
    got = bridge.BridgeConfig.load({bridge.ENV_CONFIG: str(conf), bridge.ENV_SEED: "5"})
    assert (got.family, got.severity, got.seed, dict(got.cameras), got.cell) == \
        ("blackout", 3, 5, {"Center": "CAM_FRONT"}, "blackout-s3")
    with pytest.raises(bridge.BridgeError, match="unknown corruption family 'smog'.*DRIVEDEGRADE_FAMILY"):
        bridge.BridgeConfig.load({bridge.ENV_FAMILY: "smog", bridge.ENV_SEVERITY: "3"})
    with pytest.raises(bridge.BridgeError, match="severity must be an integer"):
        bridge.BridgeConfig.load({bridge.ENV_FAMILY: "blackout"})  # a family needs its severity
    conf.write_text("{not json")
    with pytest.raises(bridge.BridgeError, match=f"{bridge.ENV_CONFIG}=.*dd.json"):
        bridge.BridgeConfig.load({bridge.ENV_CONFIG: str(conf)})
    with pytest.raises(bridge.BridgeError, match="no agent file"):
        bridge.load_agent_class(str(tmp_path / "missing.py"))
