"""The scene-cluster bootstrap's parts, shared by the full run's intervals (`intervals`, `retention`) and the
closed loop's route intervals (`routestats`): each frame's cluster, the cluster draws, the expanded percentile
levels for a cluster count, and the basis a certificate names (SPEC section 17, issue 36).

Why scenes: frames of one scene share the road, the traffic and the planner's state, so they are not
independent draws; the estimand is the planner on scenes like these. See docs/explanation/intervals.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInput
from .records import Interval

CONFIDENCE = 0.95
#: The fewest scenes on which the verdict states a confidence (a share of scene resamples giving the label).
#: Why 10: a label probability from G scenes can say no more than the scenes' own agreement. With every one of
#: G scenes on the same side, a sign test's two-sided p is 2 ** (1 - G): 0.031 at 6 scenes, 0.002 at 10. Below
#: 10 the cluster bootstrap has at most C(2G-1, G) distinct resamples (462 at 6) and routinely prints 1.000 when
#: each scene agrees, a figure 6 scenes cannot support; at 10 and above the share is reported, with the
#: borderline flag under 0.95. (The intervals are still given below 10, on the expanded levels.)
MIN_SCENES_FOR_CONFIDENCE = 10
#: The fewest scenes a cluster bootstrap is drawn over; with one scene there is nothing between scenes to draw.
MIN_SCENES = 2
#: t quantiles at 0.975 for 1..30 degrees of freedom (beyond: the normal's), for the expanded percentile levels.
_T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
         2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042)
_Z975 = 1.959964


def expanded_tail(units: int | None, confidence: float = CONFIDENCE) -> float:
    """The tail probability each bound of a percentile interval is read at, for a bootstrap over `units` clusters.

    None (a frame bootstrap): (1 - confidence) / 2. Otherwise Hesterberg's expanded percentile interval (The
    American Statistician 69(4), 2015): the bound is read at Phi(-sqrt(G / (G - 1)) t_{G-1}), so that for a mean
    it is as wide as the t interval with G - 1 degrees of freedom: 0.0024 at 6 scenes, 0.0086 at 10, 0.0246 at
    150. Defined for the default 95 % only (other confidences take the plain tail)."""
    tail = (1.0 - confidence) / 2.0
    if units is None or units < MIN_SCENES or not math.isclose(confidence, CONFIDENCE):
        return tail
    t = _T975[units - 2] if units - 1 <= len(_T975) else _Z975
    z = math.sqrt(units / (units - 1)) * t
    return 0.5 * math.erfc(z / math.sqrt(2.0))


@dataclass(frozen=True)
class Basis:
    """What the resamples draw: ``scenes`` (a cluster bootstrap over `n_units` scenes) or ``frames`` (`n_units`
    frames treated as independent, `why` says why not scenes)."""

    units: str
    n_units: int
    why: str = ""

    @property
    def clusters(self) -> int | None:
        """The cluster count the expanded levels use (None for a frame bootstrap)."""
        return self.n_units if self.units == "scenes" else None

    @property
    def text(self) -> str:
        if self.units == "scenes":
            return f"scene-cluster bootstrap, {self.n_units} scene{'s' if self.n_units != 1 else ''}"
        return f"frame bootstrap, {self.n_units} frames ({self.why})"

    @property
    def confidence_reason(self) -> str | None:
        """Why the verdict states no confidence on this basis (None: it states one)."""
        if self.units == "scenes" and self.n_units < MIN_SCENES_FOR_CONFIDENCE:
            return (f"the intervals rest on {self.n_units} scenes, too few for a label probability (it needs "
                    f"{MIN_SCENES_FOR_CONFIDENCE}); more scenes would give one")
        if self.units == "frames" and self.why.startswith("one scene"):
            return "every frame is from one scene, so nothing measures how the label varies between scenes"
        return None

    def to_builtins(self) -> dict[str, object]:
        return {"basis": self.text, "units": self.units, "n_units": self.n_units,
                "tail": expanded_tail(self.clusters), "confidence_stated": self.confidence_reason is None,
                "confidence_reason": self.confidence_reason}


def scene_clusters(scenes: Sequence[str] | None, n_frames: int) -> tuple[np.ndarray | None, Basis]:
    """Each frame's scene as a cluster index 0..G-1 (in order of first appearance) and the basis; (None, frame
    basis) when the scenes are unknown or fewer than `MIN_SCENES`."""
    if scenes is None:
        return None, Basis("frames", n_frames, "scenes unknown: frames treated as independent")
    if len(scenes) != n_frames:
        raise InvalidInput(f"{len(scenes)} scene labels for {n_frames} frames: one scene per scored frame needed")
    index: dict[str, int] = {}
    labels = np.array([index.setdefault(str(s), len(index)) for s in scenes], dtype=np.intp)
    if len(index) < MIN_SCENES:
        return None, Basis("frames", n_frames, "one scene: frames treated as independent, which understates the "
                                               "spread")
    return labels, Basis("scenes", len(index))


def cluster_counts(rng: np.random.Generator, n_resamples: int, labels: np.ndarray) -> np.ndarray:
    """(R, F) how often each frame is drawn: G scenes drawn with replacement per resample (one double per draw,
    as `frame_counts`), each drawn scene's frames all taken (label -1: a frame left out)."""
    g = int(labels.max()) + 1 if len(labels) else 0
    idx = (rng.random((n_resamples, g)) * g).astype(np.intp)
    flat = (idx + np.arange(n_resamples)[:, None] * g).ravel()
    per_scene = np.bincount(flat, minlength=n_resamples * g).reshape(n_resamples, g).astype(float)
    per_scene = np.concatenate([per_scene, np.zeros((n_resamples, 1))], axis=1)  # column -1: left out
    return per_scene[:, labels]


def percentile_interval(values: np.ndarray, confidence: float = CONFIDENCE, clusters: int | None = None) \
        -> Interval | None:
    """[low, high]: linear-interpolated percentiles (numpy's default) at (1 - confidence)/2 and its mirror, or at
    the expanded levels of a bootstrap over `clusters` scenes (`expanded_tail`).

    +inf ("never") sorts above every number; a bound that touches an infinite order statistic is +inf and is
    written None. NaN resamples are left out; None when no resample is left."""
    v = np.sort(np.asarray(values, dtype=float)[~np.isnan(values)])
    if len(v) == 0:
        return None
    tail = expanded_tail(clusters, confidence)
    out: list[float | None] = []
    for q in (tail, 1.0 - tail):
        pos = q * (len(v) - 1)
        lo, hi = math.floor(pos), math.ceil(pos)
        if not math.isfinite(v[hi]):
            out.append(None)
        else:
            out.append(float(v[lo] + (v[hi] - v[lo]) * (pos - lo)))
    return out[0], out[1]
