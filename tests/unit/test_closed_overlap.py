"""Overlap in closed-loop runs (issue 23 in closed-loop cells): with a thread pool a step's cameras render and
are corrupted at once and the last plan's steps are judged while the next cameras render; every run is the serial
run bit for bit (images the planner saw, trace, DS, ends, infractions), for image- and sample-scope corruptions,
and for a run that ends early (the images rendered ahead for a step that never comes are never shown)."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from pytest_drivedegrade.closedloop import Corruption, Route, route_of, run_route
from pytest_drivedegrade.closedloop.results import END_DEVIATED
from pytest_drivedegrade.data.frame import Command, EgoStatus
from pytest_drivedegrade.data.world.scene import make_scene

CAMERAS = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT")


class ThreeCameras:
    """Reads three cameras: speed from the front image's brightness, a swerve of `swerve` m a step; records a
    digest of every image it was given."""

    cameras = CAMERAS

    def __init__(self, swerve: float = 0.0) -> None:
        self.swerve, self.seen = swerve, []

    def reset(self, route: str) -> None:
        self.seen.append(f"reset {route}")

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        self.seen.append(hashlib.sha256(b"".join(images[c].tobytes() for c in CAMERAS)).hexdigest())
        light = float(np.mean([images[c][::16, ::16].mean() for c in CAMERAS])) / 255.0
        steps = np.arange(1, 7)[:, None]
        return steps * 0.5 * np.array([max(ego.velocity[0], 2.0) * (0.5 + light), 0.0]) + \
            np.array([0.0, self.swerve]) * steps ** 2


@pytest.fixture(scope="module")
def route() -> Route:
    return route_of(make_scene(1, 6, "scene-6"))


def both(route: Route, corruption: Corruption, swerve: float = 0.0, max_steps: int | None = 6):
    serial, threaded = ThreeCameras(swerve), ThreeCameras(swerve)
    a = run_route(serial, route, corruption, seed=3, max_steps=max_steps)
    with ThreadPoolExecutor(3) as pool:
        b = run_route(threaded, route, corruption, seed=3, max_steps=max_steps, pool=pool)
    return (a, serial.seen), (b, threaded.seen)


@pytest.mark.parametrize("corruption", [Corruption(), Corruption("gaussian_noise", 3), Corruption("frame_dropout", 5),
                                        Corruption("motion_blur", 5)])
def test_a_run_on_threads_is_the_serial_run_bit_for_bit(route: Route, corruption: Corruption) -> None:
    (a, seen_a), (b, seen_b) = both(route, corruption)
    assert seen_a == seen_b and len(seen_a) == 7  # the reset, then six steps of the same images
    assert (a.ds, a.completion, a.end, a.infractions, a.steps, a.error) == \
        (b.ds, b.completion, b.end, b.infractions, b.steps, b.error)
    assert a.trace.tobytes() == b.trace.tobytes() and len(a.trace) == 31


def test_a_run_that_ends_early_on_threads_ends_where_the_serial_one_does(route: Route) -> None:
    (a, seen_a), (b, seen_b) = both(route, Corruption("gaussian_blur", 3), swerve=0.6, max_steps=None)
    assert a.end == b.end == END_DEVIATED and a.steps == b.steps < 30
    assert seen_a == seen_b and len(seen_a) == a.steps + 1  # no plan asked for after the end
    assert a.trace.tobytes() == b.trace.tobytes() and (a.ds, a.infractions) == (b.ds, b.infractions)
