"""`drivedegrade estimate`: turn a planner's speed (and, from a certificate's cost ledger, the suite's own
per-frame overhead) into the wall time of a full certification, e.g. nuScenes val on G GPUs."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

#: The cells of a default run (clean, null, blind, the 16 x 5 ladder, ego_noise S1..S5, ego_blind, command_blind
#: and command_swap); tests/unit/test_scale.py checks it against `cells.run_order`.
DEFAULT_CELLS = 91


@dataclass(frozen=True)
class Estimate:
    gpus: int
    predictions: int
    planner_hours: float
    overhead_hours: float

    @property
    def wall_hours(self) -> float:
        """Shards run in parallel, one per GPU; the suite's decode, injection and scoring run beside them."""
        return (self.planner_hours + self.overhead_hours) / self.gpus


def overhead_per_prediction(cost: Mapping[str, Any] | None) -> float:
    """Seconds per prediction the planner waits for the suite, from a certificate's cost ledger; 0 without one.

    Where the ledger has the cells' wall time and ``planner_busy`` (`scoring.records.cost_ledger`), it is what
    was measured: the wall time the planner was not computing, per prediction (with --drivedegrade-prefetch the
    suite's decoding, injection and scoring hide behind the planner's calls, and only what did not hide counts).
    From an older ledger, the suite's own seconds (decode, inject, score, check) per prediction: all of it
    serial, as it was then."""
    if not cost or not cost.get("predictions"):
        return 0.0
    wall, busy = cost.get("wall"), cost.get("planner_busy")
    if isinstance(wall, (int, float)) and wall > 0 and isinstance(busy, (int, float)):
        return float(wall) * (1.0 - float(busy)) / float(cost["predictions"])
    sec = cost["seconds"]
    besides = sum(float(sec.get(k, 0.0)) for k in ("decode", "inject", "metrics", "pdms", "check"))
    return besides / float(cost["predictions"])


def estimate(fps: float, frames: int, gpus: Sequence[int], *, cells: int = DEFAULT_CELLS,
             overhead: float = 0.0) -> list[Estimate]:
    """The wall time of `cells` x `frames` predictions at `fps` frames/s per GPU, for each GPU count."""
    if fps <= 0 or frames <= 0 or cells <= 0 or any(g < 1 for g in gpus):
        raise ValueError("fps, frames, cells and every GPU count must be positive")
    predictions = cells * frames
    return [Estimate(g, predictions, predictions / fps / 3600.0, predictions * overhead / 3600.0) for g in gpus]


def estimate_lines(rows: Sequence[Estimate], fps: float, frames: int, cells: int, overhead: float) -> list[str]:
    head = f"{cells} cells x {frames} frames = {cells * frames:,} predictions at {fps:g} frames/s per GPU"
    if overhead:
        head += f", plus {overhead * 1000:.1f} ms per prediction the planner waits for decoding, injection and scoring"
    lines = [head, f"{'GPUs':>6} {'wall time':>12}"]
    for r in rows:
        hours = r.wall_hours
        text = f"{hours:.1f} h" if hours >= 1 else f"{hours * 60:.0f} min"
        lines.append(f"{r.gpus:>6} {text:>12}")
    return lines


#: The suite's own seconds per prediction (decoding, injection, the input check and scoring) on the embedded world
#: (800 x 450 images), from the cost ledger of `pytest --drivedegrade planners/camera_cnn.py -n 2
#: --drivedegrade-frames 24` on a 2-core machine (decode 0.4 + inject 5.9 + scoring 2.6 + check 0.6 s over 2,035
#: predictions). A pre-flight estimate adds it to the planner's own time per frame.
SUITE_SECONDS_PER_PREDICTION = 0.0047
#: The seconds a run spends outside its cells: starting the workers, the ego-only floor, the intervals and the
#: report at the end (the same run: 16.1 s of session, 7.4 s of cells per worker).
SUITE_FIXED_SECONDS = 9.0


@dataclass(frozen=True)
class RunCount:
    """What a run will compute, counted before it starts: open-loop cells and their predictions (an upper bound:
    frames whose inputs equal clean's may reuse its plan), and the closed-loop cells beside them."""

    cells: int
    predictions: int
    closed_cells: int = 0


def count_predictions(frames: int, seeds_per_cell: Sequence[int], *, processes: int = 1,
                      closed_cells: int = 0) -> RunCount:
    """`frames` predictions per seed of each open cell (`seeds_per_cell`: the seed count of each), plus the clean
    cell planned once more in each further process (every process plans clean first, `RunContext.prime_clean`)."""
    if frames < 0 or processes < 1 or any(s < 1 for s in seeds_per_cell):
        raise ValueError("frames must be >= 0, processes >= 1 and every cell's seed count >= 1")
    cells = len(seeds_per_cell)
    extra = frames * (processes - 1) if cells > 1 else 0
    return RunCount(cells, frames * sum(seeds_per_cell) + extra, closed_cells)


def run_wall_seconds(count: RunCount, planner_seconds: float, *, processes: int = 1, cores: int = 1,
                     load: float = 0.0, suite_seconds: float = SUITE_SECONDS_PER_PREDICTION,
                     fixed_seconds: float = SUITE_FIXED_SECONDS) -> float:
    """The wall time of the open cells: each prediction costs the planner's and the suite's seconds, spread over
    the processes that run cells (no more at once than the machine has cores), plus the run's fixed seconds; all
    of it stretched by `load`, the other jobs' runnable processes (a core shared with them is a core's share).
    One short call measures near a quiet machine's speed even under load (it fits in a time slice), so the load
    is applied here rather than read from that call."""
    if planner_seconds < 0 or suite_seconds < 0 or processes < 1 or cores < 1 or load < 0:
        raise ValueError("seconds and load must be >= 0, processes and cores >= 1")
    parallel = min(processes, cores)
    stretch = max(1.0, (load + parallel) / cores)
    return (fixed_seconds + count.predictions * (planner_seconds + suite_seconds) / parallel) * stretch


def duration_text(seconds: float) -> str:
    """'about 40 seconds', 'about 6 minutes', 'about 2.5 hours': as precise as an estimate deserves."""
    if seconds < 90:
        return f"about {max(10, round(seconds / 10) * 10):.0f} seconds"
    if seconds < 90 * 60:
        return f"about {round(seconds / 60):.0f} minutes"
    return f"about {seconds / 3600:.1f} hours"


def estimate_line(count: RunCount, seconds: float | None, *, processes: int) -> str:
    """The one line a run prints before its cells: '89 cells, 17,373 predictions, about 6 minutes with -n 2'."""
    if not count.cells:  # a closed-loop-only run: its cost (routes x steps x seeds) is not modelled here
        return f"{count.closed_cells} closed-loop cell(s) (time not estimated)"
    how = f"with -n {processes}" if processes > 1 else "in one process"
    text = f"{count.cells} cells, {count.predictions:,} predictions"
    text += f", {duration_text(seconds)} {how}" if seconds is not None else " (time not estimated)"
    if count.closed_cells:
        text += f"; plus {count.closed_cells} closed-loop cell(s), not in the estimate"
    return text
