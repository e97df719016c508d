"""The null control's culprit search (issue 20, "False accusation"): a camera is named only when a replay that
reproduces the recorded plans proves it; a planner whose plans depend on its call history is told so instead;
frames that failed in clean are neither compared nor searched (M11).

The fake context below runs a real call sequence: each camera of frame i delivers a known value (0 when the cell
blacks it out), and every cell, replay included, calls the planner frame by frame as `RunContext.run_cell` does
(``reset`` before each scene for a planner that has it), so a planner's state carries across cells and replays.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from pytest_drivedegrade.cells import CellRecord, cell_id
from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.plugin import checks
from pytest_drivedegrade.run import unread_cameras
from pytest_drivedegrade.settings import RunSettings
from pytest_drivedegrade.store import ResultStore

FRAMES = 4
SCENES = ("s0", "s0", "s1", "s1")


def images(family: str, unread: tuple[str, ...], i: int) -> dict[str, float]:
    """What each camera of frame `i` shows in a cell: the front camera 10 * (i + 1), every other camera i + 1,
    the null cell's `unread` and every camera of blind black (0)."""
    out = {c: float(10 * (i + 1) if c == "CAM_FRONT" else i + 1) for c in CAMERAS}
    for cam in out:
        if family == "blind" or (family == "null" and cam in unread):
            out[cam] = 0.0
    return out


class FakeContext:
    """The part of `RunContext` a cell check uses, over `images`: every cell is computed by calling the planner."""

    planner_path = None
    seed = 0
    settings = RunSettings()

    def __init__(self) -> None:
        self.frames = [SimpleNamespace(token=f"tok{i}", scene_token=SCENES[i]) for i in range(FRAMES)]
        self._clean: CellRecord | None = None
        self.replays: list[str] = []

    def run_key(self, planner: Any) -> dict[str, Any]:
        return {"planner_fingerprint": "fake"}

    def planner_info(self, planner: Any) -> Any:
        return SimpleNamespace(unread=unread_cameras(planner.cameras))

    def reuses_clean(self, planner: Any, family: str, severity: int) -> bool:
        return False

    def run_seeded_cell(self, planner: Any, family: str, severity: int, clean: Any = None) -> CellRecord:
        return self.run_cell(planner, family, severity)

    def clean_record(self, planner: Any, stored: Any = lambda: None) -> CellRecord:
        if self._clean is None:
            self._clean = self.run_cell(planner, "clean", 0)
        return self._clean

    def prime_clean(self, planner: Any) -> None:
        """Clean first in this process, as `RunContext.prime_clean` (M12)."""
        self.clean_record(planner)

    def run_cell(self, planner: Any, family: str, severity: int, *, unread: tuple[str, ...] | None = None,
                 span: tuple[int, int] | None = None) -> CellRecord:
        unread = unread_cameras(planner.cameras) if unread is None else unread
        if span is not None:
            self.replays.append(f"{cell_id(family, severity)} {'+'.join(unread) if family == 'null' else ''}")
        a, b = span or (0, FRAMES)
        plans, errors, scene = np.full((b - a, 6, 2), np.nan), [], None
        for k, i in enumerate(range(a, b)):
            if hasattr(planner, "reset") and SCENES[i] != scene:
                planner.reset(SCENES[i])
            scene = SCENES[i]
            try:
                plans[k] = planner.predict(images(family, unread, i), family)
            except RuntimeError as exc:
                errors.append(f"frame 'tok{i}': {exc}")
        n = b - a
        return CellRecord(cell_id(family, severity), family, severity, [f"tok{i}" for i in range(a, b)], plans,
                          np.zeros((n, 6)), np.zeros((n, 6)), np.zeros((n, 6)), np.ones(n), np.ones(n),
                          errors=errors)


def plan(value: float) -> np.ndarray:
    return np.full((6, 2), value)


class FrontDiff:
    """Reads only CAM_FRONT and plans from its change since the previous call, with no ``reset``: the state a BEV
    planner fuses from its previous frame, never cleared."""

    cameras = ("CAM_FRONT",)

    def __init__(self) -> None:
        self.previous: float | None = None

    def predict(self, images: dict[str, float], family: str) -> np.ndarray:
        change = 0.0 if self.previous is None else images["CAM_FRONT"] - self.previous
        self.previous = images["CAM_FRONT"]
        return plan(change)


class FrontDiffWithReset(FrontDiff):
    """The same planner with ``reset``: its state is the scene's, so a replay from the scene's start is exact."""

    def reset(self, scene: str) -> None:
        self.previous = None


class ReadsBack:
    """Declares CAM_FRONT, reads CAM_BACK too: stateless, so every replay reproduces."""

    cameras = ("CAM_FRONT",)

    def predict(self, images: dict[str, float], family: str) -> np.ndarray:
        return plan(images["CAM_FRONT"] + images["CAM_BACK"])


class Glitchy:
    """Reads CAM_FRONT only; its plan moves by 1 on the calls numbered in `glitches` (counted from its first):
    a history that the first replays of a frame happen to reproduce, and a later one does not."""

    cameras = ("CAM_FRONT",)

    def __init__(self, glitches: set[int]) -> None:
        self.calls, self.glitches = 0, glitches

    def predict(self, images: dict[str, float], family: str) -> np.ndarray:
        self.calls += 1
        return plan(images["CAM_FRONT"] + (self.calls in self.glitches))


def null_failures(planner: Any, context: FakeContext | None = None, *cells: str) -> tuple[list[str], FakeContext]:
    """Run clean, then `cells` (default: the blind cell, as in a run's order), then check the null cell."""
    context = context or FakeContext()
    context.clean_record(planner)
    for cell in cells or ("blind",):
        context.run_cell(planner, cell, 0)
    _, failures = checks.certify(context, planner, "null", 0, store=ResultStore(context_dir()), baseline=None,
                                 tolerance=0.02)
    return failures, context


def context_dir() -> Any:
    import tempfile
    from pathlib import Path

    return Path(tempfile.mkdtemp())


def named(failures: list[str]) -> list[str]:
    """The cameras the failures blame."""
    blamed = [f.split("change the plan:")[1] for f in failures if "declared-unread camera(s)" in f]
    return [c for c in CAMERAS if any(c + ";" in b or c + "," in b for b in blamed)]


def test_false_accusation_a_stateful_planner_without_reset_is_told_its_plans_depend_on_call_history():
    """The issue's planner: its null plan of frame 0 differs from clean's because blind ran before (its previous
    front image was black), not because of a camera. Today CAM_BACK was named; now the replay of frame 0 as in
    clean does not reproduce clean's plan, so the failure names the call history and no camera."""
    failures, context = null_failures(FrontDiff())
    assert failures[0].startswith("null control failed in cell null") and "first at frame 'tok0'" in failures[0]
    assert failures[1] == (f"  {checks.HISTORY} (frame 'tok0' replayed as in clean did not reproduce its plan)")
    assert named(failures) == []
    assert context.replays == ["clean "]  # stopped at the first replay that did not reproduce


def test_false_accusation_a_later_replay_that_does_not_reproduce_names_no_camera():
    """A planner whose history the first replays happen to reproduce: clean, blind, null are calls 1-12, the
    glitch at call 9 moves null's frame 0; the replays of frame 0 as in clean (13) and as in null (14, glitched
    as the recorded plan was) reproduce, the first camera's (15) moves, and clean's replay after it (16) does not
    reproduce: no camera, not even the one that "moved", is named."""
    failures, context = null_failures(Glitchy({9, 14, 15, 16}))
    assert "first at frame 'tok0'" in failures[0]
    assert failures[1] == f"  {checks.HISTORY} (frame 'tok0' replayed as in clean, after another replay, did not " \
                          "reproduce its plan)"
    assert named(failures) == [] and len(context.replays) == 4


def test_false_accusation_the_same_planner_with_reset_passes_and_replays_nothing():
    failures, context = null_failures(FrontDiffWithReset())
    assert failures == [] and context.replays == []


def test_false_accusation_an_undeclared_read_is_still_proved_and_named():
    """The planner that truly reads CAM_BACK: the replays as in clean and as in the null cell reproduce, then
    blacking out CAM_BACK alone moves the plan and no other camera does."""
    failures, context = null_failures(ReadsBack())
    assert failures[1] == "  declared-unread camera(s) that change the plan: CAM_BACK; add them to planner.cameras"
    unread = unread_cameras(ReadsBack.cameras)
    assert context.replays[:2] == ["clean ", f"null {'+'.join(unread)}"]
    assert context.replays[2:] == [r for cam in unread for r in (f"null {cam}", "clean ")]


class FailsInClean(ReadsBack):
    """Reads only what it declares, but raises on frame `fail` of the clean cell."""

    cameras = CAMERAS[:1]

    def __init__(self, fail: int) -> None:
        self.fail = fail

    def predict(self, images: dict[str, float], family: str) -> np.ndarray:
        if family == "clean" and images["CAM_FRONT"] == 10 * (self.fail + 1):
            raise RuntimeError("boom")
        return plan(images["CAM_FRONT"])


def test_clean_failed_on_a_frame_blames_no_camera_and_compares_only_frames_with_a_plan_in_both():
    """M11: clean failed on frame 1, the null cell planned it. Today every unread camera was blamed; now only the
    frames with a plan in both are compared (bit-identical here: the null item passes, clean's failure is clean's),
    and no culprit search runs."""
    failures, context = null_failures(FailsInClean(1))
    assert failures == [] and context.replays == []
    assert np.isnan(context.clean_record(None).plans[1]).all()


class FailsInCleanReadsBack(FailsInClean):
    def predict(self, images: dict[str, float], family: str) -> np.ndarray:
        return super().predict(images, family) + images["CAM_BACK"] * (images["CAM_FRONT"] == 30.0)


def test_clean_failed_on_a_frame_the_search_runs_on_a_frame_planned_in_both():
    """M11: clean failed on frame 0 and CAM_BACK moves frame 2: the search skips frame 0 and proves CAM_BACK on
    frame 2 (the replays run frame 2 alone)."""
    failures, context = null_failures(FailsInCleanReadsBack(0))
    assert "first at frame 'tok2'" in failures[0]
    assert failures[1] == "  declared-unread camera(s) that change the plan: CAM_BACK; add them to planner.cameras"


class Batched(ReadsBack):
    def predict_batch(self, images: list, egos: list, cmds: list, contexts: list) -> np.ndarray:
        raise AssertionError("not called here")


def test_a_replay_runs_where_the_planner_was():
    """A planner with reset replays its scene from the first scored frame; a batched one the batch the frame
    shared (a batch of one may round differently); any other the frame alone."""
    context = FakeContext()
    assert checks._replay_span(context, FrontDiffWithReset(), 3) == (2, 4)  # scene s1 starts at frame 2
    assert checks._replay_span(context, FrontDiffWithReset(), 1) == (0, 2)
    assert checks._replay_span(context, ReadsBack(), 3) == (3, 4)
    context.settings = RunSettings(batch=3)
    assert checks._replay_span(context, Batched(), 1) == (0, 3)
    assert checks._replay_span(context, Batched(), 3) == (3, 4)  # the last batch is short
    assert checks._replay_span(context, ReadsBack(), 1) == (1, 2)  # no predict_batch: one frame per call
