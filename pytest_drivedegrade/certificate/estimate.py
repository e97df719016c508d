"""`drivedegrade estimate`: turn a planner's speed (and, from a certificate's cost ledger, the suite's own
per-frame overhead) into the wall time of a full certification, e.g. nuScenes val on G GPUs."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

#: The cells of a default run (clean, null, blind, the 16 x 5 ladder, ego_noise S1..S5, ego_blind and
#: command_blind).
DEFAULT_CELLS = 90


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
