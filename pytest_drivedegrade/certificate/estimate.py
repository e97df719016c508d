"""`drivedegrade estimate`: turn a planner's speed (and, from a certificate's cost ledger, the suite's own
per-frame overhead) into the wall time of a full certification, e.g. nuScenes val on G GPUs."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

#: The cells of a default run (clean, null, blind, the 16 x 5 ladder, ego_noise S1..S5 and ego_blind).
DEFAULT_CELLS = 89


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
    """Seconds the suite spends per prediction besides the planner (decode, inject, score, check), from a
    certificate's cost ledger; 0 without one."""
    if not cost or not cost.get("predictions"):
        return 0.0
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
        head += f", plus {overhead * 1000:.1f} ms per prediction of decoding, injection and scoring"
    lines = [head, f"{'GPUs':>6} {'wall time':>12}"]
    for r in rows:
        hours = r.wall_hours
        text = f"{hours:.1f} h" if hours >= 1 else f"{hours * 60:.0f} min"
        lines.append(f"{r.gpus:>6} {text:>12}")
    return lines
