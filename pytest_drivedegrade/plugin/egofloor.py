"""The ego-only floor of a run (the controller's end, `controller.finished_run`): its clean and ego_blind cells on
the scored frames, worked out at the end or, on an xdist controller, on a thread beside the workers' cells
(`FloorAhead`)."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import pytest

from ..certificate.finished import FloorFigures
from ..errors import DriveDegradeError
from ..run import RunContext
from .context import cache_root
from .options import RunOptions


@dataclass(frozen=True)
class FloorFrames:
    """The ego-only floor's clean l2_avg per scored frame and, when the ego cells run, its ego_blind one."""

    clean: np.ndarray
    ego_blind: np.ndarray | None = None

    def figures(self) -> FloorFigures:
        return FloorFigures.of(self.clean, self.ego_blind)

    def blind_list(self) -> list[float] | None:
        return None if self.ego_blind is None else [float(v) for v in self.ego_blind]


def floor_frames(config: pytest.Config, context: RunContext, split: str, lines: list[str],
                 ego: bool = False) -> FloorFrames | None:
    """The ego-only floor on the scored frames (trained on the train split once, cached), with its ego_blind
    cell when `ego`; None with a line saying why when there is no floor."""
    from ..floor import load_or_train_floor, train_split_for
    from ..progress import Progress, Sink

    try:
        train = context.reader.with_split(train_split_for(split))
        if not any(f.scorable for f in train.frames(agents=False)):  # lazily: stops at the first scorable one
            lines.append(f"ego-only floor: skipped, split {train.split!r} has no scorable frames")
            return None
        model = load_or_train_floor(train, cache_root(config) / "floor", progress=lambda steps: Progress(
            "drivedegrade ego-only floor, training", steps, unit="steps", sink=Sink.log_for_pytest(config), eta=True))
    except DriveDegradeError as exc:
        lines.append(f"ego-only floor: skipped ({exc})")
        return None
    clean = context.run_cell(model, "clean", 0, pdms=False).l2_avg_per_frame()
    blind = context.run_cell(model, "ego_blind", 0, pdms=False).l2_avg_per_frame() if ego else None
    return FloorFrames(clean, blind)


class FloorAhead:
    """The floor (`floor_frames`) worked out on a thread of the xdist controller while its workers run the cells:
    the controller is idle then, and the floor (trained on the first run, then its two cells) was a serial tail
    after the last cell. The same figures and lines as at the end: the floor reads no image and no cell's result,
    and the controller runs no planner. `take` waits for it and adds its lines where the end would have."""

    def __init__(self, config: pytest.Config, context: RunContext, split: str, ego: bool) -> None:
        self.lines: list[str] = []
        self.frames: FloorFrames | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._work, args=(config, context, split, ego), daemon=True,
                                       name="drivedegrade-floor")
        self.thread.start()

    def _work(self, config: pytest.Config, context: RunContext, split: str, ego: bool) -> None:
        try:
            self.frames = floor_frames(config, context, split, self.lines, ego)
        except BaseException as exc:  # noqa: BLE001 - raised again in the controller's thread, by `take`
            self.error = exc

    def close(self) -> None:
        """Wait for the thread (the session's end: a run without clean never takes the floor, and a thread still
        training torch while the interpreter shuts down may crash it or cut the floor's cache file short)."""
        self.thread.join()

    def take(self, notes: list[str]) -> FloorFrames | None:
        self.close()
        if self.error is not None:
            raise self.error
        notes += self.lines
        return self.frames


def start_floor(config: pytest.Config, options: RunOptions, context: RunContext) -> FloorAhead | None:
    """The floor started beside the cells where this process is an xdist controller (which runs no cell), else
    None: the end computes it, as a single process, whose thread runs the planner, must."""
    if not config.pluginmanager.has_plugin("dsession") or options.ray is not None:
        return None
    return FloorAhead(config, context, options.settings.split, bool(options.ego))


def floor_of_run(config: pytest.Config, options: RunOptions, context: RunContext, notes: list[str],
                 ahead: FloorAhead | None) -> FloorFrames | None:
    """The floor of the run: taken from `ahead` when it was started beside the cells, else worked out now."""
    if ahead is not None:
        return ahead.take(notes)
    return floor_frames(config, context, options.settings.split, notes, bool(options.ego))
