"""The pieces of NAVSIM's two-stage pseudo-simulation built so far (issue 39): its aggregation (known answers
worked from NAVSIM v2.2's scene_aggregator.py / run_pdm_score.py) and the second stage's cameras, rendered by the
world at a start pose off the logged one."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.metrics.pdms.two_stage import (
    SIGMA_SQUARED,
    group_score,
    stage_two_weights,
    two_stage_score,
    weighted_average,
)


def test_weights_are_navsims_gaussian_kernel_normalised():
    d = math.sqrt(SIGMA_SQUARED)  # d^2 = sigma^2: exp(-1/2) before normalising
    w = stage_two_weights((10.0, 5.0), [(10.0, 5.0), (10.0 + d, 5.0), (10.0, 5.0 - d)])
    k = math.exp(-0.5)
    assert w == pytest.approx([1 / (1 + 2 * k), k / (1 + 2 * k), k / (1 + 2 * k)], abs=1e-15)
    assert w.sum() == pytest.approx(1.0)


def test_weights_fall_back_to_uniform_when_every_start_is_far():
    assert stage_two_weights((0.0, 0.0), [(100.0, 0.0), (0.0, -80.0)]).tolist() == [0.5, 0.5]
    assert stage_two_weights((0.0, 0.0), [(np.nan, 0.0)]).tolist() == [1.0]
    assert stage_two_weights((0.0, 0.0), np.zeros((0, 2))).shape == (0,)


def test_group_and_two_stage_scores_known_answers():
    assert weighted_average([1.0, 0.5], [3.0, 1.0]) == pytest.approx(0.875)
    assert math.isnan(weighted_average([], [])) and math.isnan(weighted_average([1.0], [0.0]))
    assert group_score(0.9, [1.0, 0.5], [0.75, 0.25]) == pytest.approx(0.7875)
    assert two_stage_score((0.9, [1.0, 0.5], [0.75, 0.25]), (1.0, [0.0], [1.0])) == pytest.approx(0.39375)
    with pytest.raises(ValueError, match="2 scores for 1 weights"):
        weighted_average([1.0, 0.5], [1.0])


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    from pytest_drivedegrade.data.world import write_world

    return write_world(tmp_path_factory.mktemp("two-stage") / "w", scenes=2, workers=1)


FRONT = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT")


def test_stage_two_images_differ_from_the_logged_ones_and_equal_a_fresh_render(world):
    from pytest_drivedegrade.closedloop import camera
    from pytest_drivedegrade.closedloop.routes import load_routes
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    route = load_routes(world)[0]
    keyframe = 6  # where a plan made at keyframe 0 ends (3 s)
    frame = next(f for f in NuScenesReader(world).frames() if f.scene_name == route.name and f.index == keyframe)
    logged = {cam: NuScenesReader.load_image(frame.cameras[cam]) for cam in FRONT}
    assert frame.pose is not None
    x, y, yaw = frame.pose
    assert camera.images_at(route, FRONT, (x, y, yaw), keyframe).keys() == logged.keys()
    at_log = camera.images_at(route, FRONT, (x, y, yaw), keyframe)
    assert all(np.array_equal(at_log[c], logged[c]) for c in FRONT)  # the renderer is the data's
    # a start 0.5 m to the left of the logged ego, turned 3 degrees (a NAVSIM-style perturbed start state)
    moved = (x - 0.5 * math.sin(yaw), y + 0.5 * math.cos(yaw), yaw + math.radians(3.0))
    stage_two = camera.images_at(route, FRONT, moved, keyframe)
    for cam in FRONT:
        assert stage_two[cam].shape == logged[cam].shape
        assert np.abs(stage_two[cam].astype(int) - logged[cam]).mean() > 1.0, cam
    camera._BACKDROPS.clear()  # nothing kept from the first render: built again from the scene
    fresh = camera.images_at(route, FRONT, moved, keyframe)
    assert all(np.array_equal(fresh[c], stage_two[c]) for c in FRONT)
