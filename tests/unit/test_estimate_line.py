"""The pre-flight's count and estimate (issue 41): predictions counted before a run, its wall time from one frame's
time and the suite's measured per-prediction cost, in one line; the progress line's time left."""

from __future__ import annotations

import pytest

from pytest_drivedegrade.certificate.estimate import (
    SUITE_FIXED_SECONDS,
    SUITE_SECONDS_PER_PREDICTION,
    RunCount,
    count_predictions,
    duration_text,
    estimate_line,
    run_wall_seconds,
)
from pytest_drivedegrade.progress import Progress, Sink


def test_predictions_are_frames_times_seeds_plus_clean_again_in_each_further_process():
    # the default run: 89 cells on 204 frames, one seed; with -n 2 the second worker plans clean once more
    assert count_predictions(204, [1] * 89) == RunCount(89, 89 * 204)
    assert count_predictions(204, [1] * 89, processes=2).predictions == 90 * 204
    # three seeds on the random families' cells only
    assert count_predictions(10, [1, 3, 3, 1]).predictions == 80
    assert count_predictions(10, [1], processes=4).predictions == 10  # clean alone: nothing to prime
    with pytest.raises(ValueError):
        count_predictions(10, [0])


def test_the_wall_is_the_predictions_cost_over_the_cores_used_stretched_by_the_other_jobs():
    count = RunCount(89, 1000)
    per = 0.002 + SUITE_SECONDS_PER_PREDICTION
    quiet = run_wall_seconds(count, 0.002, processes=2, cores=2)
    assert quiet == pytest.approx(SUITE_FIXED_SECONDS + 1000 * per / 2)
    assert run_wall_seconds(count, 0.002, processes=8, cores=2) == pytest.approx(quiet)  # no more than the cores
    # 13 other runnable processes on 2 cores: our 2 get 2 / 15 of the machine
    assert run_wall_seconds(count, 0.002, processes=2, cores=2, load=13) == pytest.approx(quiet * 15 / 2)
    assert run_wall_seconds(count, 0.002, processes=1, cores=16, load=3) == \
        pytest.approx(SUITE_FIXED_SECONDS + 1000 * per)  # idle cores absorb the load


@pytest.mark.parametrize("seconds, text", [(4, "about 10 seconds"), (44, "about 40 seconds"),
                                           (360, "about 6 minutes"), (82.7 * 3600, "about 82.7 hours")])
def test_durations_read_as_precise_as_an_estimate_deserves(seconds, text):
    assert duration_text(seconds) == text


def test_the_one_line():
    count = RunCount(89, 17373)
    assert estimate_line(count, 360, processes=2) == "89 cells, 17,373 predictions, about 6 minutes with -n 2"
    assert estimate_line(count, None, processes=1) == "89 cells, 17,373 predictions (time not estimated)"
    assert estimate_line(RunCount(9, 36, 7), 30, processes=1) == \
        "9 cells, 36 predictions, about 30 seconds in one process; plus 7 closed-loop cell(s), not in the estimate"
    assert estimate_line(RunCount(0, 0, 3), 50, processes=1) == "3 closed-loop cell(s) (time not estimated)"


class Lines(Sink):
    def __init__(self) -> None:
        super().__init__(tty=False)
        self.lines: list[str] = []

    def line(self, text: str) -> None:
        self.lines.append(text)


def test_the_cells_progress_line_says_what_is_left_at_the_pace_so_far_and_what_runs():
    now = [0.0]
    sink = Lines()
    bar = Progress("drivedegrade cells", 10, unit="cells", sink=sink, milestones=10, eta=True, clock=lambda: now[0])
    for i in range(10):
        now[0] += 3.0
        bar.advance(note=f"c{i} done; running c{i + 1}")
    bar.finish()
    assert sink.lines[0] == "drivedegrade cells: 1/10 cells (10 %) 3.0 s, about 27 s left, c0 done; running c1"
    assert sink.lines[4] == "drivedegrade cells: 5/10 cells (50 %) 15.0 s, about 15 s left, c4 done; running c5"
    assert sink.lines[-1] == "drivedegrade cells: 10 cells in 30.0 s"
    plain = Progress("world", 4, sink=Lines(), clock=lambda: 0.0)
    plain.advance(note="scene-1")
    assert plain.text("x") == "world: 1/4 (25 %) 0.0 s, x"  # no estimate unless asked


def test_the_floor_shows_its_training_steps_and_trains_the_same_weights():
    import numpy as np
    import torch

    from pytest_drivedegrade.floor import SETTINGS, fit_arrays

    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(40, 16)), rng.normal(size=(40, 12))
    settings = {**SETTINGS, "steps": 20}
    sink = Lines()
    shown = fit_arrays(x, y, settings=settings,
                       progress=lambda steps: Progress("floor", steps, unit="steps", sink=sink, clock=lambda: 0.0))
    quiet = fit_arrays(x, y, settings=settings)
    assert sink.lines == ["floor: 5/20 steps (25 %) 0.0 s", "floor: 10/20 steps (50 %) 0.0 s",
                          "floor: 15/20 steps (75 %) 0.0 s", "floor: 20 steps in 0.0 s"]
    assert all(torch.equal(a, b) for a, b in zip(shown.state_dict().values(), quiet.state_dict().values()))
