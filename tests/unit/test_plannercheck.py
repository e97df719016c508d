"""The pre-flight's checks of what a planner declares against what the data and the run serve (issue 41), on
stand-in frames and settings: each mismatch is named, a valid planner passes."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pytest_drivedegrade.plugin.plannercheck import declared_problems


def context(*, frames: int = 3, cameras=("CAM_FRONT", "CAM_BACK"), future: int = 6, lidar: str = "sweep.bin",
            batch: int = 1, device: str = "cpu"):
    made = [SimpleNamespace(cameras=dict.fromkeys(cameras), gt_future=np.zeros((future, 2)), lidar_file=lidar)
            for _ in range(frames)]
    return SimpleNamespace(frames=made, settings=SimpleNamespace(batch=batch, device=device))


class Plain:
    cameras = ("CAM_FRONT",)

    def predict(self, images, ego, cmd):
        return np.zeros((6, 2))


def planner(base=Plain, **attrs):
    return type("P", (base,), attrs)()


def test_a_valid_planner_has_no_problem_and_no_note():
    assert declared_problems(Plain(), context()) == ([], [])


@pytest.mark.parametrize("attrs, ctx, expected", [
    ({"cameras": ("CAM_FRONT", "CAM_FRONT_LEFT")}, {}, "planner.cameras declares CAM_FRONT_LEFT, which some scored "
                                                       "frames do not have"),
    ({"poses": 8}, {}, "the planner declares poses = 8 (4 s) but the data holds 3 s of future per scored frame"),
    ({"poses": 8.0}, {}, "planner.poses must be 6 or 8 (waypoints at 0.5 s: nuScenes' 3 s or NAVSIM's 4 s), got 8.0"),
    ({"poses": True}, {}, "planner.poses must be 6 or 8"),
    ({"lidar": True}, {}, "planner.lidar is set but predict() takes no `context` parameter"),
    ({"lidar": True, "predict": lambda self, images, ego, cmd, context=None: None}, {"lidar": ""},
     "planner.lidar is set but 3 of 3 scored frames have no LIDAR_TOP sweep"),
    ({"reset": lambda self: None}, {}, "planner.reset must take one argument, the scene token"),
    ({"cameras": "CAM_FRONT"}, {}, "planner.cameras must be a collection of camera names, got the string"),
], ids=["camera-not-served", "8-poses-on-3s", "poses-float", "poses-bool", "lidar-no-context", "lidar-no-sweeps",
        "reset-arity", "cameras-string"])
def test_each_mismatch_is_named(attrs, ctx, expected):
    problems, _ = declared_problems(planner(**attrs), context(**ctx))
    assert len(problems) == 1 and problems[0].startswith(expected), problems


def test_8_poses_on_data_with_4_s_of_future_is_fine():
    assert declared_problems(planner(poses=8), context(future=8)) == ([], [])


def test_a_batch_without_predict_batch_or_with_reset_is_a_note_not_a_stop():
    assert declared_problems(Plain(), context(batch=4))[1] == [
        "--drivedegrade-batch 4 has no effect: the planner has no predict_batch()"]
    both = planner(predict_batch=lambda self, *a: None, reset=lambda self, token: None)
    assert declared_problems(both, context(batch=4)) == (
        [], ["--drivedegrade-batch 4 has no effect: a planner with reset() is called frame by frame"])


class Weights:
    def __init__(self, device: str) -> None:
        self.device = device


@pytest.mark.parametrize("run, weights, stops", [("cuda", "cpu", True), ("cpu", "cuda:0", True),
                                                 ("cuda", "cuda:0", False), ("cuda:1", "cuda:0", True),
                                                 ("cuda:1", "cuda:1", False), ("cpu", "cpu", False)])
def test_weights_on_another_device_than_the_run_asks_stop_it(run, weights, stops):
    model = SimpleNamespace(parameters=lambda: iter([Weights(weights)]))
    problems, _ = declared_problems(planner(model=model), context(device=run))
    assert bool(problems) == stops, problems
    if stops:
        assert problems[0] == (f"the run asks for --drivedegrade-device {run} but the planner's weights are on "
                               f"{weights}: build it on planner_device() (or drivedegrade_context.device)")
