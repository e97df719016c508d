"""Temporal planners and the frame context (SPEC section 8), end to end on the small world: the stream order,
reset per scene per cell, bit-identical cells whatever the layout or selection, a null control that blames only
a camera the state really read, the frame context's values, and inputs that cannot be changed."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import by_cell, read_csv  # noqa: E402

from pytest_drivedegrade.data import geometry as geo  # noqa: E402
from pytest_drivedegrade.data.context import CAN_BUS_SIZE, FrameContext  # noqa: E402
from pytest_drivedegrade.run import RunContext  # noqa: E402
from pytest_drivedegrade.settings import RunSettings  # noqa: E402

pytest_plugins = ["plugin_support"]

TEMPORAL = '''
import numpy as np
import pytest

T = 0.5 * np.arange(1, 7)


class Temporal:
    """Keeps an exponential memory of the front camera's brightness (as a BEV planner keeps prev_bev) and
    drives straight at its speed, drifting sideways by the memory. `leak` adds CAM_BACK to the memory from a
    scene's second frame on: the state carries it, which the pre-flight (one frame after a reset) cannot see and
    the null control's replays must find."""

    cameras = ("CAM_FRONT",)
    name = "temporal"
    leak = {leak!r}

    def __init__(self):
        self.memory = None

    def reset(self, scene_token):
        self.memory = None

    def predict(self, images, ego, cmd, context):
        seen = float(images["CAM_FRONT"][::8, ::8].mean()) / 255.0
        if self.leak and self.memory is not None:
            seen += float(images["CAM_BACK"][::8, ::8].mean()) / 255.0
        self.memory = seen if self.memory is None else 0.7 * self.memory + 0.3 * seen
        plan = np.zeros((6, 2))
        plan[:, 0] = max(ego.velocity[0], 0.0) * T
        plan[:, 1] = self.memory + 0.001 * context.index
        return plan


@pytest.fixture(scope="session")
def planner():
    return Temporal()
'''


def temporal_rows(dd: Any, *extra: str, report: str, leak: bool = False, name: str = "temporal.py"):
    dd.pytester.makepyfile(**{name[:-3]: TEMPORAL.format(leak=leak)})
    result = dd.run(*extra, planner=name, report=report)
    return result, dd.pytester.path / report / "temporal"


def test_temporal_planner_is_bit_identical_under_any_layout_and_selection(dd):
    serial, folder0 = temporal_rows(dd, "-p", "no:xdist", report="r0")
    serial.assert_outcomes(passed=9)
    parallel, folder2 = temporal_rows(dd, "-n", "2", report="r2")
    parallel.assert_outcomes(passed=9)
    picked, folderk = temporal_rows(dd, "-p", "no:xdist", "-k", "null or jpeg-s5 or clean", report="rk")
    picked.assert_outcomes(passed=3, deselected=6)
    rows0, rows2 = read_csv(folder0 / "cells.csv"), read_csv(folder2 / "cells.csv")
    assert rows0 == rows2  # every cell, bit for bit, whatever ran before it in a worker
    chosen = by_cell(read_csv(folderk / "cells.csv"))
    for cell in ("clean", "null", "jpeg-s5"):
        assert chosen[cell]["l2_avg"] == by_cell(rows0)[cell]["l2_avg"], cell
    assert "null control: passed" in serial.stdout.str()


def test_temporal_planner_whose_state_reads_an_unread_camera_is_caught_naming_it(dd):
    result, _ = temporal_rows(dd, "-p", "no:xdist", "-k", "clean or null", report="rl", leak=True)
    result.assert_outcomes(passed=1, failed=1, deselected=7)
    text = result.stdout.str()
    assert "declared-unread camera(s) that change the plan: CAM_BACK;" in text
    assert "CAM_BACK_LEFT" not in text.split("declared-unread camera(s) that change the plan:")[1].split("\n")[0]


# --- the runtime directly ------------------------------------------------------------------------------------


class Recorder:
    """Records what the suite hands it; plans depend on the frame index within the scene only."""

    cameras = ("CAM_FRONT",)

    def __init__(self) -> None:
        self.calls: list[tuple[str, ...]] = []
        self.contexts: list[FrameContext] = []

    def reset(self, scene_token: str) -> None:
        self.calls.append(("reset", scene_token))

    def predict(self, images: Any, ego: Any, cmd: Any, context: FrameContext) -> np.ndarray:
        self.calls.append(("predict", context.scene_token, context.token))
        self.contexts.append(context)
        return np.full((6, 2), float(context.index))


@pytest.fixture
def run_context(small_world: Path) -> RunContext:
    return RunContext.open(RunSettings(data=small_world, timeout=0.0))


def test_stream_is_scene_ordered_with_a_reset_before_each_scene_of_each_cell(small_world):
    context = RunContext.open(RunSettings(data=small_world, split="all", timeout=0.0))
    planner = Recorder()
    planner.cameras = ()  # train scenes have tables only: read no image
    context.run_cell(planner, "clean", 0)
    context.run_cell(planner, "blind", 0)
    scenes = list(dict.fromkeys(f.scene_token for f in context.frames))
    assert len(scenes) == 3
    expected: list[tuple[str, ...]] = []
    for _cell in range(2):
        for scene in scenes:
            expected.append(("reset", scene))
            expected += [("predict", scene, f.token) for f in context.frames if f.scene_token == scene]
    assert planner.calls == expected
    stamps = [f.timestamp for f in context.frames]
    for scene in scenes:
        mine = [s for s, f in zip(stamps, context.frames) if f.scene_token == scene]
        assert mine == sorted(mine)


def test_frame_context_values(run_context: RunContext):
    planner = Recorder()
    run_context.run_cell(planner, "jpeg", 5)
    frame, ctx = run_context.frames[3], planner.contexts[3]
    assert (ctx.token, ctx.scene_token, ctx.scene_name, ctx.timestamp) == \
        (frame.token, frame.scene_token, frame.scene_name, frame.timestamp)
    assert ctx.index == frame.index == 3  # the val scene's scored stream starts at its first keyframe
    np.testing.assert_allclose(ctx.ego2global[:2, 3], frame.pose[:2], atol=1e-9)  # type: ignore[index]
    np.testing.assert_allclose(np.arctan2(ctx.ego2global[1, 0], ctx.ego2global[0, 0]), frame.pose[2], atol=1e-9)  # type: ignore[index]
    cam = frame.cameras["CAM_FRONT"]
    cal = ctx.calibration["CAM_FRONT"]
    assert cal.image_size == (cam.width, cam.height) == (800, 450)
    np.testing.assert_array_equal(cal.intrinsic, cam.intrinsic)
    # a point 20 m ahead on the ground projects below the image centre of the front camera
    ahead = geo.apply(geo.invert(cal.sensor2ego), np.array([[20.0, 0.0, 0.0]]))
    pix, _ = geo.project(ahead, cal.intrinsic)
    assert abs(pix[0, 0] - 400) < 40 and pix[0, 1] > 225
    assert ctx.can_bus is not None and ctx.can_bus.shape == (CAN_BUS_SIZE,)
    np.testing.assert_allclose(ctx.can_bus[:3], ctx.ego2global[:3, 3])
    heading = np.degrees(frame.pose[2]) % 360  # type: ignore[index]
    assert ctx.can_bus[17] == pytest.approx(heading) and ctx.can_bus[16] == pytest.approx(np.radians(heading))
    assert ctx.can_bus[13] == pytest.approx(np.hypot(*frame.ego.velocity), abs=0.3)  # CAN speed ~ pose speed
    for array in (ctx.ego2global, cal.intrinsic, cal.sensor2ego, ctx.can_bus):
        assert not array.flags.writeable
    with pytest.raises(TypeError):
        ctx.calibration["CAM_FRONT"] = cal  # type: ignore[index]
    assert not any(hasattr(ctx, k) for k in ("family", "severity", "cell"))  # never names the corruption


class Writer:
    """Writes into its input image by one of three routes, on one frame, then plans from the clean mean."""

    cameras = ("CAM_FRONT",)

    def __init__(self, how: str, token: str) -> None:
        self.how, self.token = how, token

    def predict(self, images: Any, ego: Any, cmd: Any, context: FrameContext) -> np.ndarray:
        img = images["CAM_FRONT"]
        if context.token == self.token:
            if self.how == "setflags":
                img.setflags(write=True)
                img[10:20, 10:20] = 255
            elif self.how == "torch":
                import warnings

                import torch

                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)  # "The given NumPy array is not writable"
                    torch.from_numpy(img).add_(1)
            elif self.how == "raw":
                import ctypes

                ctypes.memset(img.ctypes.data, 7, 64)  # 7 nowhere in a row of a black or real frame
        return np.full((6, 2), float(images["CAM_FRONT"][::16, ::16].mean()) / 255.0)


@pytest.mark.parametrize("prefetch", [0, 2])
@pytest.mark.parametrize("how", ["setflags", "torch", "raw"])
def test_writes_into_inputs_fail_the_frame_naming_camera_and_frame_and_reach_nothing_else(small_world, how,
                                                                                           prefetch):
    """Serially and with the write check beside the next frame's loading (`stream._WriteChecks`)."""
    context = RunContext.open(RunSettings(data=small_world, frames=4, timeout=0.0, prefetch=prefetch))
    fresh = RunContext.open(RunSettings(data=small_world, frames=4, timeout=0.0))
    target = context.frames[1].token
    honest = Writer("none", "")
    for family, severity in (("clean", 0), ("jpeg", 3), ("frame_dropout", 5)):
        bad = context.run_cell(Writer(how, target), family, severity)
        assert len(bad.errors) == 1 and f"frame {target!r}: predict() wrote into its input image of CAM_FRONT" \
            in bad.errors[0]
        assert np.isnan(bad.plans[1]).all() and np.isfinite(np.delete(bad.plans, 1, axis=0)).all()
        after = context.run_cell(honest, family, severity)  # the same process: the decode cache is warm
        reference = fresh.run_cell(honest, family, severity)
        assert after.plans.tobytes() == reference.plans.tobytes()  # the write reached no later cell


class LateWriter:
    """Keeps the front image it was given and writes into it during its next call: a write after the call that
    received the image returned, which no check right after that call can see."""

    cameras = ("CAM_FRONT",)

    def __init__(self) -> None:
        self.kept: np.ndarray | None = None

    def predict(self, images: Any, ego: Any, cmd: Any) -> np.ndarray:
        import ctypes
        import time

        if self.kept is not None:
            ctypes.memset(self.kept.ctypes.data, 7, 4096)  # the last frame's image, as soon as this call starts
            time.sleep(0.002)  # long enough for a check of the last frame running beside this call to see it
        self.kept = images["CAM_FRONT"]
        return np.full((6, 2), float(self.kept[::16, ::16].mean()) / 255.0)


def test_a_write_into_an_earlier_frames_image_is_judged_the_same_with_the_check_beside_the_loader(small_world):
    """With --drivedegrade-prefetch the last frame's write check runs beside the next frame's loading, and is
    settled before the planner runs again: a planner writing into the image it kept from the last frame, in its
    next call, meets the serial path's verdict (no frame fails: each frame's check saw its own images as the
    call left them) whatever the threads' timing; a check still running during the next call would fail frames
    at random."""
    records = {}
    for prefetch in (0, 2):
        context = RunContext.open(RunSettings(data=small_world, frames=8, timeout=0.0, prefetch=prefetch))
        records[prefetch] = [context.run_cell(LateWriter(), family, severity)
                             for family, severity in (("clean", 0), ("jpeg", 3), ("frame_dropout", 5))]
    for serial, beside in zip(records[0], records[2]):
        assert serial.errors == beside.errors == []
        assert serial.plans.tobytes() == beside.plans.tobytes() and np.isfinite(serial.plans).all()


def test_ego_status_is_private_and_read_only(run_context: RunContext):
    class EgoWriter:
        cameras = ()

        def predict(self, images: Any, ego: Any, cmd: Any) -> np.ndarray:
            ego.past_xy[:] = 0.0  # raises: read-only
            return np.zeros((6, 2))

    record = run_context.run_cell(EgoWriter(), "clean", 0)
    assert len(record.errors) == len(run_context.frames)
    assert "read-only" in record.errors[0]
    assert np.abs(run_context.frames[0].ego.past_xy).sum() > 0  # the shared frame was not touched
