"""Trust (SPEC section 11): what the planner sees, partial results, data faults.

Each test names the case of the "Trust" issue it covers.
"""

from __future__ import annotations

import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import by_cell, load_json, no_traceback, read_csv, verify_cli  # noqa: E402

from pytest_drivedegrade.data.frame import Frame  # noqa: E402
from pytest_drivedegrade.loader import CellSample, samples  # noqa: E402
from pytest_drivedegrade.run import RunContext  # noqa: E402
from pytest_drivedegrade.settings import RunSettings  # noqa: E402

pytest_plugins = ["plugin_support"]

#: Attribute names a cheating planner tries on the images mapping.
CHEATS = ("frame", "family", "severity", "seed", "_sample", "sample", "_decode", "decode", "_frame", "_made",
          "_cache", "_dropout", "_read", "_mapping", "mapping", "__dict__", "__wrapped__", "cell")


def _reachable(root: Any, limit: int = 4000) -> list[Any]:
    """Every object a planner reaches from `root` by attributes (dir()), views, values and items, breadth
    first (no gc, no closure cells of functions it never receives); images themselves are leaves."""
    seen: dict[int, Any] = {}
    queue = [root]
    while queue and len(seen) < limit:
        obj = queue.pop(0)
        if id(obj) in seen:
            continue
        seen[id(obj)] = obj
        leaf = isinstance(obj, (np.ndarray, str, bytes, int, float, type, type(None)))
        if leaf or type(obj).__module__ == "builtins" and callable(obj) and not hasattr(obj, "__self__"):
            continue
        if isinstance(obj, Mapping):
            queue += [*obj.keys(), *obj.values(), obj.keys(), obj.values(), obj.items()]
        for name in dir(obj):
            try:
                queue.append(getattr(obj, name))
            except Exception:  # noqa: BLE001,S112 - an attribute that cannot be read leads nowhere
                continue
    return list(seen.values())


class Cheater:
    """Trust case 7's cheating planner: tries every route from `images` to the frame, its ground truth and the
    corruption, and plans the ground truth when it finds it."""

    cameras = ("CAM_FRONT",)

    def __init__(self) -> None:
        self.found: list[str] = []
        self.types: set[str] = set()

    def look(self, images: Any) -> np.ndarray:
        for name in CHEATS:
            try:
                getattr(images, name)
                self.found.append(name)
            except AttributeError:
                pass
        try:
            vars(images)
            self.found.append("vars()")
        except TypeError:
            pass
        for view in (images.keys(), images.values(), images.items()):
            if any(hasattr(view, n) for n in ("_mapping", "mapping")) and \
                    not isinstance(getattr(view, "mapping", None), type(images)):
                inner = getattr(view, "_mapping", None) or getattr(view, "mapping", None)
                if not all(v is None for v in dict(inner).values()):
                    self.found.append(f"{type(view).__name__}.mapping")
        for obj in _reachable(images):
            if isinstance(obj, (CellSample, Frame)) or type(obj).__name__ in ("CellSample", "Frame", "_Cameras"):
                self.types.add(type(obj).__name__)
        try:
            pickle.dumps(images)
            self.found.append("pickle")
        except (TypeError, pickle.PicklingError):
            pass
        plan = getattr(getattr(images, "frame", None), "gt_future", None)
        return np.array(plan, dtype=float) if plan is not None else np.full((6, 2), 1.0)

    def predict(self, images: Any, ego: Any, cmd: Any) -> np.ndarray:
        return self.look(images)

    def predict_batch(self, images: list, egos: list, cmds: list, contexts: list) -> np.ndarray:
        return np.stack([self.look(i) for i in images])


@pytest.mark.parametrize("batch", [1, 3])
def test_cheating_planner_learns_nothing_from_the_images_mapping(small_world: Path, batch: int):
    """Trust case 7: `images` (predict and predict_batch) is a read-only mapping of the six cameras and nothing
    else: no attribute, vars(), view object, pickle or attribute walk reaches the frame (ground truth, agent
    boxes), the family or the severity; its repr names neither. A cheater that plans the ground truth when it
    finds it scores the same constant plan in every cell."""
    context = RunContext.open(RunSettings(data=small_world, frames=4, timeout=0.0, batch=batch))
    cheater = Cheater()
    records = [context.run_cell(cheater, family, severity) for family, severity in
               (("clean", 0), ("jpeg", 5), ("blackout", 5))]
    assert cheater.found == [] and cheater.types == set()
    for record in records:
        assert record.errors == []
        assert (record.plans == 1.0).all()  # never the ground truth
    sample = next(iter(samples(context.frames[:1], "jpeg", 5, seed=0, decode=context.decode)))
    assert any(isinstance(o, Frame) for o in _reachable(sample))  # the walk does find what the sample holds
    images = sample.view
    assert sorted(images) == sorted(sample) and len(images) == 6 and "CAM_FRONT" in images
    assert "jpeg" not in repr(images) and sample.frame.token not in repr(images)
    with pytest.raises(TypeError):
        images["CAM_FRONT"] = np.zeros(1)  # type: ignore[index]
    assert images["CAM_FRONT"] is sample["CAM_FRONT"]


def test_a_camera_is_decoded_only_when_read(small_world: Path):
    """Trust case 7: the planner's mapping stays lazy: keys, `in` and len decode nothing; one read, one decode."""
    context = RunContext.open(RunSettings(data=small_world, frames=1, timeout=0.0))
    decoded: list[str] = []

    def decode(frame: Frame, camera: str) -> np.ndarray:
        decoded.append(camera)
        return context.decode(frame, camera)

    images = next(iter(samples(context.frames, "jpeg", 3, seed=0, decode=decode))).view
    assert list(images.keys()) == list(images) and "CAM_BACK" in images and len(images) == 6
    assert decoded == []
    assert images.get("CAM_BACK").shape[2] == 3 and images.get("NOPE") is None
    assert decoded == ["CAM_BACK"]


class InputWriter:
    """Flips every array of its ego status and context writable and overwrites it, on every frame; records
    what it was given before writing."""

    cameras = ()

    def __init__(self, write: bool) -> None:
        self.write, self.seen = write, []

    def predict(self, images: Any, ego: Any, cmd: Any, context: Any) -> np.ndarray:
        arrays = [ego.past_xy, context.ego2global, context.can_bus,
                  *(c.intrinsic for c in context.calibration.values()),
                  *(c.sensor2ego for c in context.calibration.values()), *(context.lidar2img or {}).values()]
        assert all(not a.flags.writeable for a in arrays)
        self.seen.append([a.copy() for a in arrays])
        if self.write:
            for a in arrays:
                a.setflags(write=True)
                a[...] = 1e6
        return np.zeros((6, 2))


def test_ego_and_context_arrays_are_read_only_and_private_to_the_call(small_world: Path):
    """Trust case 7: every array of the ego status and the context is read-only and a copy private to the call:
    a planner that flips the flag and writes changes nothing the next call, cell or process sees."""
    context = RunContext.open(RunSettings(data=small_world, frames=4, timeout=0.0))
    fresh = RunContext.open(RunSettings(data=small_world, frames=4, timeout=0.0))
    vandal, honest, reference = InputWriter(True), InputWriter(False), InputWriter(False)
    for planner, ctx in ((vandal, context), (honest, context), (reference, fresh)):
        for family, severity in (("clean", 0), ("ego_noise", 3)):
            assert ctx.run_cell(planner, family, severity).errors == []
    assert len(honest.seen) == len(reference.seen) == 8
    for got, want in zip(honest.seen, reference.seen):
        assert all(np.array_equal(a, b) for a, b in zip(got, want))
    assert all(np.array_equal(a, b) for a, b in zip(vandal.seen[0], reference.seen[0]))
    assert np.abs(context.frames[0].ego.past_xy).max() < 1e3


def test_partial_results_are_undetermined_end_to_end(dd, scored_tokens):
    """Trust case 9 end to end: a 1e200 plan on one jpeg-s5 frame is a contract failure naming the frame and the
    value (no longer a silent overflow); the certificate's verdict is `undetermined` with the reason, the
    terminal summary and the HTML report say so, and `drivedegrade verify` agrees."""
    frame = scored_tokens[2]
    dd.write_planner(faults={"jpeg-s5": ("huge", frame)})
    result = dd.run(families="jpeg,blackout", severities="5")
    result.assert_outcomes(passed=4, failed=1)
    no_traceback(result)
    reason = "1 cell with failed frames: jpeg-s5 (1 of 4 frames: 1 planner contract failure)"
    result.stdout.fnmatch_lines([
        "cell jpeg-s5: 1 of 4 frames failed the planner contract",
        f"*frame '{frame}' has a waypoint 1e+200 m from the ego at step 5*beyond the physical bound of 1000 m*",
        "verdict: undetermined - Undetermined: 1 cell with failed frames*",
        f"UNDETERMINED by failed frames: {reason}",
    ], consecutive=False)
    cert = load_json(dd.folder() / "certificate.json")
    assert cert["verdict"]["label"] == "undetermined" and cert["verdict"]["reason"] == reason
    assert cert["verdict"]["failed_cells"] == {"jpeg-s5": {"frames": 4, "conformance_errors": 1, "data_errors": 0}}
    assert cert["axes"]["partial"] == ["jpeg-s5"] and cert["thresholds"]["jpeg"]["partial"] is True
    rows = by_cell(read_csv(dd.folder() / "cells.csv"))
    assert (rows["jpeg-s5"]["conformance_errors"], rows["jpeg-s5"]["data_errors"], rows["jpeg-s5"]["frames"]) == \
        ("1", "0", "3")
    html = (dd.folder() / "report.html").read_text()
    assert f"Undetermined by failed frames: {reason}" in html
    check = verify_cli(dd.folder() / "certificate.json")
    assert check.returncode == 0, check.stderr


def test_nothing_compared_is_not_a_passed_null_control_and_clean_has_no_retention(dd):
    """Trust case 9 end to end: when no frame produced a plan in clean and null, the null control is `not run`
    (not `passed`), clean shows no retention over its 0 frames (not 1.0), and the verdict is undetermined."""
    dd.write_planner(faults={"clean": ("raise", None), "null": ("raise", None)})
    result = dd.run(families="jpeg", severities="5")
    no_traceback(result)
    assert "null control: not run (no frame produced a plan in both clean and null)" in result.stdout.str()
    cert = load_json(dd.folder() / "certificate.json")
    assert cert["null_control"]["passed"] is None and cert["null_control"]["ran"] is False
    clean = next(c for c in cert["cells"] if c["cell"] == "clean")
    assert clean["frames"] == 0 and clean["retention"] is None and clean["conformance_errors"] == 4
    assert by_cell(read_csv(dd.folder() / "cells.csv"))["clean"]["retention"] in ("", "nan")
    assert cert["verdict"]["label"] == "undetermined" and "clean (4 of 4 frames" in cert["verdict"]["reason"]
    assert "not run" in (dd.folder() / "report.html").read_text()


def test_an_empty_jpeg_is_a_data_error_not_the_planners(dd, small_world, scored_tokens, tmp_path):
    """Trust case 10 end to end: a 0-byte JPEG was reported as "predict() raised" an OpenCV assertion with no
    file name, and counted against the planner; now it is a data error naming the file and the frame, counted
    in `data_errors` (cells.csv, certificate) apart from the contract failures, and the verdict is undetermined."""
    import shutil

    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    data = tmp_path / "world"
    shutil.copytree(small_world, data)
    frame = next(f for f in NuScenesReader(data, split="val").scorable_frames(limit=4) if f.token == scored_tokens[0])
    image = Path(frame.cameras["CAM_FRONT"].path)
    image.write_bytes(b"")
    dd.write_planner()
    result = dd.run(data=data, families="jpeg", severities="5")
    no_traceback(result)
    out = result.stdout.str()
    assert "predict() raised" not in out and "failed the planner contract" not in out
    result.stdout.fnmatch_lines([
        "cell clean: 1 of 4 frames had data errors (the data set's fault, not the planner's)",
        f"  frame '{frame.token}': empty image file {image} (frame {frame.token}) (0 bytes)*"], consecutive=False)
    rows = by_cell(read_csv(dd.folder() / "cells.csv"))
    assert (rows["jpeg-s5"]["data_errors"], rows["jpeg-s5"]["conformance_errors"]) == ("1", "0")
    assert rows["blind"]["data_errors"] == "0"  # blind decodes nothing
    cert = load_json(dd.folder() / "certificate.json")
    assert next(c for c in cert["cells"] if c["cell"] == "clean")["data_errors"] == 1
    assert cert["verdict"]["label"] == "undetermined" and "1 data error" in cert["verdict"]["reason"]


#: The issue's false accusation: a planner that reads only CAM_FRONT and plans from the change of the front image
#: since its previous call (state across calls, as a BEV planner fuses its previous frame), with no reset().
FRONT_CHANGE = '''
import numpy as np
import pytest


class FrontChange:
    cameras = ("CAM_FRONT",)
    name = "frontchange"

    def __init__(self):
        self.previous = None

    def predict(self, images, ego, cmd):
        front = images["CAM_FRONT"][::4, ::4].astype(np.float32)
        change = 0.0 if self.previous is None else float(np.abs(front - self.previous).mean()) / 255.0
        self.previous = front
        plan = np.zeros((6, 2))
        plan[:, 0] = 2.0 * np.arange(1, 7)
        plan[:, 1] = change
        return plan


@pytest.fixture(scope="session")
def planner():
    return FrontChange()
'''

HISTORY_LINE = "*plans depend on call history: give the planner a reset(), or declare deterministic = False*"


def no_camera_named(text: str) -> None:
    """No line blames a camera: the culprit sentence never appears."""
    assert "declared-unread camera(s) that change the plan" not in text, text
    assert "add them to planner.cameras" not in text, text


@pytest.mark.parametrize("layout", [("-n", "0"), ("-n", "2")])
def test_false_accusation_a_stateful_planner_without_reset_is_never_blamed_for_a_camera(dd, layout):
    """Issue 20, "False accusation": the front-only planner with state and no reset() was told "declared-unread
    camera(s) that change the plan: CAM_BACK". Its null cell (and blackout S3, the rear cameras' null control)
    may fail, since its plans depend on what ran before, but the failure says so and names no camera, under
    -n 0 and -n 2."""
    dd.pytester.makepyfile(frontchange=FRONT_CHANGE)
    result = dd.run(*layout, planner="frontchange.py", families="jpeg,blackout", severities="3")
    no_traceback(result)
    text = result.stdout.str()
    no_camera_named(text)
    if layout == ("-n", "0"):  # one process: null follows blind, so its first frame's history differs from clean's
        result.assert_outcomes(passed=3, failed=2)
        for cell in ("null", "blackout-s3"):
            result.stdout.fnmatch_lines([f"null control failed in cell {cell}:*", HISTORY_LINE], consecutive=True)
    else:  # any failed null control says why, and the why is the history
        lines = text.splitlines()
        failed = [i for i, line in enumerate(lines) if line.startswith("null control failed in cell")]
        assert all(lines[i + 1].startswith("  plans depend on call history: give the planner a reset()")
                   for i in failed), text
    assert (dd.folder("frontchange") / "certificate.json").exists()


def test_false_accusation_a_planner_that_reads_an_undeclared_camera_is_still_named(dd):
    """The other side of the fix: the planner that reads CAM_BACK undeclared is proved by replays that reproduce
    its plans, and named with CAM_BACK alone."""
    dd.write_planner(read_back=True)
    result = dd.run("-n", "0", families="blackout", severities="3")
    result.stdout.fnmatch_lines(["*null control failed in cell null*",
                                 "*declared-unread camera(s) that change the plan: CAM_BACK; add them to "
                                 "planner.cameras"], consecutive=False)
    assert "plans depend on call history" not in result.stdout.str()


def test_clean_failed_on_a_frame_blames_no_camera_end_to_end(dd, scored_tokens):
    """M11: the planner raises on one frame of clean only. Today the null control named every unread camera; now
    the frames with a plan in both are compared (identical), so the null cell passes and the certificate's null
    control passed over 3 frames, while clean fails its own conformance and the verdict is undetermined."""
    dd.write_planner(faults={"clean": ("raise", scored_tokens[1])})
    result = dd.run("-n", "0", families="jpeg", severities="5")
    no_traceback(result)
    no_camera_named(result.stdout.str())
    result.stdout.fnmatch_lines(["*cell clean: 1 of 4 frames failed the planner contract*"], consecutive=False)
    assert "null control failed" not in result.stdout.str()
    cert = load_json(dd.folder() / "certificate.json")
    assert cert["null_control"]["passed"] is True and cert["null_control"]["frames_compared"] == 3
    assert cert["verdict"]["label"] == "undetermined"
