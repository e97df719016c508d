"""Scenario scenes for the closed loop (spec 5, section 18): deterministic, generated apart from the open-loop
world (its scenes are the same objects they were), the privileged expert completes every one of the default slice's
scenario routes at DS >= 95, and a driver that ignores what is ahead (constant velocity) scores far below it."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.closedloop import route_of, run_route
from pytest_drivedegrade.closedloop.camera import RouteCameras
from pytest_drivedegrade.closedloop.expert import WorldExpert
from pytest_drivedegrade.closedloop.routes import SCENARIO_ROUTES, Route
from pytest_drivedegrade.data.world.scenarios import SCENARIO_KINDS, scenario_name, scenario_scene
from pytest_drivedegrade.data.world.scene import make_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "planners"))
from constant_velocity import ConstantVelocity  # noqa: E402

#: The default world's seed: its scenario routes are the default closed slice's.
SEED = 0


@pytest.fixture(scope="module")
def routes() -> list[Route]:
    return [route_of(scenario_scene(SEED, i)) for i in range(6)]


def _digest(scene) -> str:
    import hashlib

    h = hashlib.sha256()
    for a in scene.agents:
        h.update(np.ascontiguousarray(a.xy).tobytes() + np.ascontiguousarray(a.speed).tobytes())
    h.update(np.ascontiguousarray(scene.ego.xy).tobytes())
    return h.hexdigest()


def test_a_scenario_scene_is_deterministic_and_named_by_its_kind() -> None:
    a, b = scenario_scene(SEED, 4), scenario_scene(SEED, 4)
    assert _digest(a) == _digest(b) and a.name == b.name == scenario_name(4) == "scenario-0004-braking"
    assert [scenario_name(i).rsplit("-", 1)[1] for i in range(3)] == list(SCENARIO_KINDS)
    assert SCENARIO_ROUTES >= 18  # with the default world's 6 val scenes: 24 distinct routes


def test_generating_scenarios_leaves_the_open_loop_scenes_as_they_were() -> None:
    before = _digest(make_scene(SEED, 3, "scene-0003"))
    scenario_scene(SEED, 0)
    assert _digest(make_scene(SEED, 3, "scene-0003")) == before


def test_every_scenario_has_a_vehicle_the_expert_stops_for(routes: list[Route]) -> None:
    for route in routes:
        stopped = [a for a in route.scene.agents if a.role == "stopped"]
        assert len(stopped) == 1 and (np.abs(stopped[0].speed) < 0.1).any()
        assert (route.scene.ego.speed < 0.3).any(), route.name  # the expert halts behind it
        assert "brake" in route.scene.events, route.name


def test_the_expert_completes_and_a_blind_driver_does_not(routes: list[Route]) -> None:
    expert = WorldExpert(routes)
    blind = []
    for route in routes:
        run = run_route(expert, route)
        assert run.ds is not None and run.ds >= 95.0 and run.end == "complete", route.name
        cv = run_route(ConstantVelocity(), route)
        assert cv.ds is not None
        blind.append(cv.ds)
    assert float(np.mean(blind)) < 60.0


def test_a_scenario_route_renders(routes: list[Route]) -> None:
    route = routes[0]
    ego = route.scene.ego
    image = RouteCameras(route, ("CAM_FRONT",)).images((float(ego.xy[0, 0]), float(ego.xy[0, 1]),
                                                        float(ego.yaw[0])), 0)["CAM_FRONT"]
    assert image.ndim == 3 and image.std() > 5.0
