"""NAVSIM v2's two-stage (pseudo closed-loop) aggregation, the scoring half of the two-stage pseudo-simulation.

NAVSIM (v2.2, ``scene_aggregator.py`` and ``run_pdm_score.py``, read, not copied) scores a frame in two stages:
stage one is the logged frame (and the frame 0.5 s before it); stage two is a set of synthetic scenes that start
at the log time the stage-one plan ends (4 s later, and 3.5 s for the previous frame) from ego start states
perturbed around the logged one. Each stage-two scene is weighted by how close its start is to where the
stage-one plan ended: a Gaussian kernel ``exp(-d^2 / (2 sigma^2))`` with sigma^2 = 0.1 m^2 on the distance d
between the stage-one plan's simulated end point and the scene's start point, normalised to sum 1 (uniform when
every weight underflows to 0). The stage-two score is the weighted mean of the stage-two scenes' EPDMS; a group's
score is stage one's times stage two's; the frame's two-stage score is the mean of its two groups (now and the
frame before), and the run's the mean over frames.

Pure functions and constants; stage two's frames, rendered cameras and planner calls inside a cell are
`closedloop.twostage`'s (--drivedegrade-two-stage).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

#: NAVSIM's SceneAggregator.sigma_squared (m^2): the Gaussian kernel's variance.
SIGMA_SQUARED: float = 0.1
#: The stage-two start poses, (forward m, left m, yaw rad) from the logged ego pose in its own frame: the logged
#: pose, half a metre to each side, a metre ahead and behind, 5 degrees to each side. NAVSIM's come from its
#: synthetic-scene data set (navhard_two_stage), which the suite does not have: an adaptation.
STAGE_TWO_STARTS: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, -0.5, 0.0), (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0),
    (0.0, 0.0, math.radians(5.0)), (0.0, 0.0, -math.radians(5.0)))


def certificate_section() -> dict[str, object]:
    """The certificate's ``two_stage`` section: how a two-stage run (--drivedegrade-two-stage) scored its stage two
    (the start poses, forward m, left m, yaw rad; the kernel's variance; the aggregation; where the images came
    from)."""
    return {"starts": [list(s) for s in STAGE_TWO_STARTS], "sigma_squared": SIGMA_SQUARED,
            "aggregation": "per frame: stage one's EPDMS x the Gaussian-weighted mean of its stage-two starts' EPDMS "
                           "(NAVSIM v2); the cell's epdms2 is the mean over the frames with a stage two",
            "render": "the embedded world at each start pose, corrupted by the cell's operator"}


def stage_two_weights(endpoint: npt.ArrayLike, starts: npt.ArrayLike, sigma_squared: float = SIGMA_SQUARED
                      ) -> np.ndarray:
    """The stage-two scenes' weights (K,): ``exp(-|endpoint - start|^2 / (2 sigma^2))`` normalised to sum 1, each
    start (K, 2) against the stage-one plan's end point (2,) in the same (global) frame; 1/K each when the sum is
    0 (every start far off) or NaN, as NAVSIM's `calculate_pseudo_closed_loop_weights`."""
    end = np.asarray(endpoint, dtype=np.float64).reshape(2)
    pts = np.asarray(starts, dtype=np.float64).reshape(-1, 2)
    if not len(pts):
        return np.zeros(0)
    squared = (end[0] - pts[:, 0]) ** 2 + (end[1] - pts[:, 1]) ** 2
    weights = np.exp(-squared / (2.0 * sigma_squared))
    total = float(weights.sum())
    if np.isnan(total) or np.isclose(total, 0.0):
        return np.full(len(pts), 1.0 / len(pts))
    return weights / total


def weighted_average(scores: npt.ArrayLike, weights: npt.ArrayLike) -> float:
    """NAVSIM's `calculate_weighted_average_score` of one column: sum(w s) / sum(w); NaN without scenes or with a
    zero total weight (a NaN score makes it NaN, as pandas' sums there do not skip)."""
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if len(s) != len(w):
        raise ValueError(f"{len(s)} scores for {len(w)} weights")
    total = float(w.sum())
    if not len(s) or total == 0.0:
        return float("nan")
    return float((s * w).sum() / total)


def group_score(stage_one: float, stage_two: npt.ArrayLike, weights: npt.ArrayLike) -> float:
    """One group's two-stage score: stage one's EPDMS times the weighted mean of its stage-two scenes'."""
    return float(stage_one) * weighted_average(stage_two, weights)


def two_stage_score(now: tuple[float, npt.ArrayLike, npt.ArrayLike],
                    previous: tuple[float, npt.ArrayLike, npt.ArrayLike]) -> float:
    """A frame's two-stage score: the mean of its two groups' (`group_score`), the frame now and the one 0.5 s
    before, each (stage-one EPDMS, stage-two EPDMS (K,), stage-two weights (K,))."""
    return 0.5 * (group_score(*now) + group_score(*previous))
