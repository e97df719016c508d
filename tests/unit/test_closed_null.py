"""The closed null control on rendered runs (SPEC section 13): for camera_cnn, which reads the front three cameras,
blackout S3 (the rear three) reproduces clean run for run, bit for bit; a planner that declares the front camera
but reads CAM_BACK parts from clean, and the failure names the route and the step."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.closedloop import Corruption, Route, load_routes, run_route
from pytest_drivedegrade.closedloop.cells import ClosedRecord
from pytest_drivedegrade.data.frame import Command, EgoStatus
from pytest_drivedegrade.plugin.closed import null_failure

PLANNERS = Path(__file__).resolve().parents[2] / "planners"
STEPS = 4


@pytest.fixture(scope="module")
def route(tmp_path_factory: pytest.TempPathFactory) -> Route:
    from pytest_drivedegrade.data.world import write_world

    return load_routes(write_world(tmp_path_factory.mktemp("w"), scenes=3, seed=1))[0]


def camera_cnn() -> object:
    spec = importlib.util.spec_from_file_location("_closed_camera_cnn", PLANNERS / "camera_cnn.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module.CameraCNNPlanner()


def record(planner: object, route: Route, corruption: Corruption) -> ClosedRecord:
    runs = tuple(run_route(planner, route, corruption, seed, max_steps=STEPS) for seed in (0, 1))  # type: ignore[arg-type]
    return ClosedRecord(f"closed-{corruption.name}", corruption.family, corruption.severity, runs)


def test_blackout_s3_reproduces_clean_bit_for_bit_for_camera_cnn(route: Route) -> None:
    planner = camera_cnn()
    clean = record(planner, route, Corruption())
    null = record(planner, route, Corruption("blackout", 3))
    assert null_failure(clean, null, 5) is None
    for a, b in zip(clean.runs, null.runs):
        assert a.trace.tobytes() == b.trace.tobytes() and a.ds == b.ds and a.steps == STEPS
    assert record(planner, route, Corruption("blackout", 5)).runs[0].trace.tobytes() != clean.runs[0].trace.tobytes()


class SecretBack:
    """Declares the front camera, steers by the back one's brightness."""

    cameras = ("CAM_FRONT",)

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        light = float(images["CAM_BACK"][::16, ::16].mean()) / 255.0
        return np.arange(1, 7)[:, None] * 0.5 * np.array([max(ego.velocity[0], 2.0) * (0.5 + light), 0.0])


def test_a_secret_rear_reader_parts_from_clean_and_is_named_with_route_and_step(route: Route) -> None:
    clean = record(SecretBack(), route, Corruption())
    null = record(SecretBack(), route, Corruption("blackout", 3))
    message = null_failure(clean, null, 5)
    assert message is not None
    assert f"route {route.name} (seed 0) parts from closed-clean at step 0" in message
