"""`plugin.childplanner` (--drivedegrade-isolate) piece by piece: the clean environment, what crosses the socket
(the frame context, the planner's exceptions, the images through the memfd), and a real child's calls: the plan
it returns, an exception it raises, a write into its input image, a reset, and a child that ends."""

from __future__ import annotations

import os
import textwrap
from functools import partial
from pathlib import Path
from types import MappingProxyType

import numpy as np
import pytest

from pytest_drivedegrade.data.context import FrameContext
from pytest_drivedegrade.errors import DataError
from pytest_drivedegrade.plugin.childplanner import (
    ChildEnded,
    SharedImages,
    _exception,
    clean_environment,
    pack_context,
    spawn,
    start_child_planner,
    unpack_context,
)


def test_the_clean_environment_holds_no_pytest_or_suite_variable(monkeypatch):
    monkeypatch.setenv("PYTEST_CURRENT_TEST", "planner.py::fog-s5 (call)")
    monkeypatch.setenv("DRIVEDEGRADE_SIGNING_KEY", "-----BEGIN PRIVATE KEY-----")
    monkeypatch.setenv("pytest_xdist_worker", "gw0")
    env = clean_environment()
    assert not [k for k in env if k.upper().startswith(("PYTEST_", "DRIVEDEGRADE_"))]
    assert env["PATH"] == os.environ["PATH"]


def _context(small_world: Path) -> FrameContext:
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    frame = next(iter(NuScenesReader(small_world, split="val").scorable_frames(limit=1)))
    return FrameContext.of(frame).private()


def test_the_context_crosses_as_it_is_read_only_on_arrival(small_world):
    import pickle

    context = _context(small_world)
    back = unpack_context(pickle.loads(pickle.dumps(pack_context(context))))
    assert back is not None and back.token == context.token and back.calibration.keys() == context.calibration.keys()
    assert isinstance(back.calibration, MappingProxyType)
    assert np.array_equal(back.ego2global, context.ego2global) and not back.ego2global.flags.writeable
    cal = next(iter(back.calibration.values()))
    assert not cal.intrinsic.flags.writeable and not back.can_bus.flags.writeable
    assert unpack_context(pack_context(None)) is None


@pytest.mark.parametrize("name, data, base", [("ValueError", False, ValueError), ("KeyError", False, KeyError),
                                              ("CustomPlannerError", False, Exception), ("DataError", True, DataError)])
def test_the_planners_exception_reads_as_raised(name, data, base):
    exc = _exception(name, "'CAM_X' is broken", data)
    assert type(exc).__name__ == name and str(exc) == "'CAM_X' is broken" and isinstance(exc, base)


def test_shared_images_cross_bit_for_bit_and_grow():
    parent = SharedImages()
    child = SharedImages(os.dup(parent.fd))
    rng = np.random.default_rng(0)
    small, big = rng.integers(0, 255, (9, 16, 3), np.uint8), rng.integers(0, 255, (900, 1600, 3), np.uint8)
    placed = [parent.put(small), parent.put(big)]  # the second grows the memfd past its first size
    for image, where in zip((small, big), placed):
        sent, copy = child.get(where[0], tuple(where[1]), where[2])
        assert np.array_equal(copy, image) and not copy.flags.writeable and np.array_equal(sent, image)
    del sent, copy  # the child's arrays view its map, which cannot close while they do
    parent.close()
    child.close()


PLANNER = textwrap.dedent('''
    import os

    import numpy as np
    import pytest


    class Probe:
        cameras = ("CAM_FRONT",)
        name = "probe"

        def __init__(self):
            self.scenes = []

        def reset(self, scene_token):
            self.scenes.append(scene_token)

        def predict(self, images, ego, cmd, context=None):
            if cmd == 0:
                raise KeyError("no right turns")
            front = images["CAM_FRONT"]
            if cmd == 1:  # LEFT: write into its input
                front.setflags(write=True)
                front[0, 0, 0] ^= 1
            if ego.yaw_rate == 123.0:
                os._exit(3)
            plan = np.zeros((6, 2))
            plan[:, 0] = float(front.mean()) + len(self.scenes)
            plan[:, 1] = context.can_bus[0] if context is not None else -1.0
            return plan


    @pytest.fixture(scope="session")
    def planner():
        return Probe()
''')


def test_a_child_plans_raises_tells_a_write_and_ends(small_world, tmp_path):
    from dataclasses import replace

    from pytest_drivedegrade.data.frame import Command
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.settings import RunSettings

    path = tmp_path / "probe.py"
    path.write_text(PLANNER)
    request = {"run": {"settings": RunSettings(frames=2).to_builtins(), "root": str(small_world),
                       "planner_path": str(path), "digest_cache": None},
               "collect_path": str(path), "module": None, "default_name": "probe", "opencv_threads": 1}
    child = start_child_planner(partial(spawn, request), 30.0)
    try:
        assert type(child).__name__ == "IsolatedPlanner" and child.cameras == ("CAM_FRONT",)
        assert child.pid != os.getpid() and len(child.apart_fingerprint) == 64
        frame = next(iter(NuScenesReader(small_world, split="val").scorable_frames(limit=1)))
        image = np.full((4, 5, 3), 10, np.uint8)
        image.setflags(write=False)
        context = FrameContext.of(frame).private()
        plan = child.predict(MappingProxyType({"CAM_FRONT": image}), frame.ego, Command.STRAIGHT, context=context)
        assert np.array_equal(plan[:, 0], np.full(6, 10.0)) and plan[0, 1] == context.can_bus[0]
        child.reset("scene-a")
        plan = child.predict(MappingProxyType({"CAM_FRONT": image}), frame.ego, Command.STRAIGHT, context=None)
        assert plan[0, 0] == 11.0 and plan[0, 1] == -1.0  # its state lives in the child; no context given
        with pytest.raises(KeyError) as raised:
            child.predict(MappingProxyType({"CAM_FRONT": image}), frame.ego, Command.RIGHT, context=None)
        assert str(raised.value) == "'no right turns'"
        mine = image.copy()
        mine.setflags(write=False)
        child.predict(MappingProxyType({"CAM_FRONT": mine}), frame.ego, Command.LEFT, context=None)
        assert not np.array_equal(mine, image)  # the write in the child shows in this process's copy
        ended = replace(frame.ego, yaw_rate=123.0)
        with pytest.raises(ChildEnded, match=r"ended during predict\(\) \(exit status 3\)"):
            child.predict(MappingProxyType({"CAM_FRONT": image}), ended, Command.STRAIGHT, context=None)
        plan = child.predict(MappingProxyType({"CAM_FRONT": image}), frame.ego, Command.STRAIGHT, context=None)
        assert plan[0, 0] == 10.0  # a new child: a new planner, its state fresh
    finally:
        assert child.close() == []
