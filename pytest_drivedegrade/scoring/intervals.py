"""Intervals on what the verdict rests on: one joint bootstrap of every cell, from which the thresholds, the axes
and the verdict get their 95 % intervals and the verdict its confidence (SPEC sections 12 and 17).

**The sampling unit is the scene** (SPEC section 17, issue 36). Frames of one scene share the road, the traffic
and the planner's state, so they are not independent draws; the estimand is the planner on scenes like these.
When the run knows each frame's scene, each resample draws the run's G scenes with replacement and keeps each
drawn scene's frames whole (a pairs cluster bootstrap; `Basis`); only without that knowledge (a caller that gives
no scenes) are frames resampled as if independent, and the certificate's ``settings.intervals.basis`` says which.
With few clusters the percentile interval is too narrow (the bootstrap's variance is (G-1)/G of the plug-in's,
and the t quantile with G-1 degrees of freedom exceeds the normal one), so the cluster intervals use Hesterberg's
*expanded* percentile levels (`expanded_tail`); under `MIN_SCENES_FOR_CONFIDENCE` scenes the verdict states no
confidence at all (`Basis.confidence_reason`).

One set of resamples (R x F counts) is drawn once and shared by every cell, so in each resample the whole
retention curve of a family, and both axes, are computed on the same scenes and frames (paired). Cells run under several
corruption seeds (``--drivedegrade-seeds``) add a first level: each resample also draws the seeds with
replacement, and a cell's retention in that resample is the mean over the drawn seeds of its per-seed retention
on the drawn frames (a two-level bootstrap: seeds, then frames).

Vectorised: the frame draws become a count matrix ``C`` (R x F), and every (cell, seed) column's resampled means
are one matrix product ``C @ V``; the thresholds are found for all resamples at once.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .clusters import (  # noqa: F401 - re-exported: the intervals' callers read them here
    CONFIDENCE,
    MIN_SCENES,
    MIN_SCENES_FOR_CONFIDENCE,
    Basis,
    cluster_counts,
    expanded_tail,
    percentile_interval,
    scene_clusters,
)
from .records import AXES, AxisIntervals, Interval
from .retention import THRESHOLD_LEVELS, retention, tolerance_threshold

#: Where the interval resamples' generator starts, apart from the per-cell CI's stream (seeded with `seed` alone).
STREAM = 15
#: Under this verdict confidence the verdict's text says "Borderline".
BORDERLINE = 0.95
@dataclass(frozen=True)
class Resamples:
    """Each cell's retention in every resample: cell id -> (R,) (NaN where a resample left it no frame)."""

    retention: dict[str, np.ndarray]
    n_resamples: int
    n_seeds: int  # the most seeds any cell ran under (1: no seed level)
    basis: Basis | None = None  #: None: frames, scenes unknown

    @property
    def clusters(self) -> int | None:
        return None if self.basis is None else self.basis.clusters


def frame_counts(rng: np.random.Generator, n_resamples: int, n_frames: int) -> np.ndarray:
    """(R, F) how often each frame is drawn in each resample: F draws with replacement per resample.

    One double per index (as `bootstrap_retention_ci`), so the draws do not depend on how they are chunked."""
    idx = (rng.random((n_resamples, n_frames)) * n_frames).astype(np.intp)
    flat = (idx + np.arange(n_resamples)[:, None] * n_frames).ravel()
    return np.bincount(flat, minlength=n_resamples * n_frames).reshape(n_resamples, n_frames).astype(float)


def resample_cells(clean: np.ndarray, cells: Mapping[str, Sequence[np.ndarray]], *, kind: str = "error",
                   n_resamples: int = 1000, seed: int = 0, scenes: Sequence[str] | None = None) -> Resamples:
    """Every cell's retention per resample from per-frame M values.

    `clean` is clean's per-frame M (F,); `cells` maps cell id -> one (F,) array per seed run. A frame counts for
    a (cell, seed) column only where both it and clean are finite (NaN frames drop out of that comparison only).
    `scenes` (each frame's scene) makes the draws a scene-cluster bootstrap (`scene_clusters`).
    """
    m_clean = np.asarray(clean, dtype=float)
    n = len(m_clean)
    rng = np.random.default_rng((int(seed), STREAM))
    labels, basis = scene_clusters(scenes, n)
    if labels is not None:
        counts = cluster_counts(rng, n_resamples, labels)
    else:
        counts = frame_counts(rng, n_resamples, n) if n else np.zeros((n_resamples, 0))
    names = list(cells)
    columns = [np.asarray(run, dtype=float) for name in names for run in cells[name]]
    if not columns:
        return Resamples({}, n_resamples, 1, basis)
    values = np.stack(columns, axis=1)  # (F, K)
    ok = np.isfinite(values) & np.isfinite(m_clean)[:, None]
    okf = ok.astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        den = counts @ okf  # (R, K) frames drawn that count for each column
        mean_clean = (counts @ np.where(ok, m_clean[:, None], 0.0)) / den
        mean_cell = (counts @ np.where(ok, values, 0.0)) / den
        per_column = np.where(den > 0, retention(mean_clean, mean_cell, kind), np.nan)
    n_seeds = max(len(cells[name]) for name in names)
    # Seed draws, one weight matrix per seed count (drawn in increasing order, after the frames): weight of each
    # seed run in each resample = how often it was drawn / the number of seeds.
    weights = {s: _seed_weights(rng, n_resamples, s) for s in sorted({len(cells[name]) for name in names}) if s > 1}
    out: dict[str, np.ndarray] = {}
    start = 0
    for name in names:
        k = len(cells[name])
        block = per_column[:, start:start + k]
        out[name] = block[:, 0] if k == 1 else np.einsum("rk,rk->r", block, weights[k])
        start += k
    return Resamples(out, n_resamples, n_seeds, basis)


def _seed_weights(rng: np.random.Generator, n_resamples: int, n_seeds: int) -> np.ndarray:
    idx = (rng.random((n_resamples, n_seeds)) * n_seeds).astype(np.intp)
    w = np.zeros((n_resamples, n_seeds))
    np.add.at(w, (np.arange(n_resamples)[:, None], idx), 1.0)
    return w / n_seeds


def thresholds_per_resample(severities: Sequence[int], curve: np.ndarray, level: float) -> np.ndarray:
    """`tolerance_threshold` for every row of `curve` (R, n) at once (columns in `severities`' increasing
    order); +inf where a row never falls below `level`. Rows with a non-finite retention take the scalar path
    (which skips such points), so every row equals `tolerance_threshold` exactly."""
    sev = np.asarray(severities, dtype=float)
    r = np.asarray(curve, dtype=float)
    out = np.full(len(r), math.inf)
    if r.shape[1] == 0:
        return out
    below = r < level
    hit = below.any(axis=1)
    first = np.argmax(below, axis=1)
    prev = np.maximum(first - 1, 0)
    rows = np.arange(len(r))
    s0, r0, s1, r1 = sev[prev], r[rows, prev], sev[first], r[rows, first]
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing = np.where(first == 0, s1, s0 + (r0 - level) / (r0 - r1) * (s1 - s0))
    out[hit] = crossing[hit]
    for i in np.flatnonzero(~np.isfinite(r).all(axis=1)):
        got = tolerance_threshold(dict(zip(severities, r[i].tolist())), level)
        out[i] = math.inf if got is None else got
    return out


def threshold_intervals(res: Resamples, curves: Mapping[str, Mapping[int, str]]) \
        -> dict[str, dict[str, tuple[Interval | None, float]]]:
    """family -> level (s10, s25) -> (95 % interval, never) from the resampled curves.

    `curves` maps family -> severity -> cell id. ``never`` is the share of resamples whose curve never falls
    below the level (those count as +inf in the percentiles)."""
    out: dict[str, dict[str, tuple[Interval | None, float]]] = {}
    for fam, cells in curves.items():
        sev = sorted(s for s in cells if s > 0 and cells[s] in res.retention)
        if not sev:
            continue
        curve = np.stack([res.retention[cells[s]] for s in sev], axis=1)
        entry: dict[str, tuple[Interval | None, float]] = {}
        for key, level in THRESHOLD_LEVELS.items():
            t = thresholds_per_resample(sev, curve, level)
            entry[key] = (percentile_interval(t, clusters=res.clusters), float(np.isinf(t).mean()))
        out[fam] = entry
    return out


@dataclass(frozen=True)
class AxisResamples:
    """The four axes (`records.AXES`) in every resample; None where an axis's families were not all run."""

    quality: np.ndarray | None = None
    removal: np.ndarray | None = None
    gap: np.ndarray | None = None
    mean: np.ndarray | None = None
    clusters: int | None = None  #: the scene count of a cluster bootstrap (None: frames)

    def of(self, axis: str) -> np.ndarray | None:
        got: np.ndarray | None = getattr(self, axis)
        return got


def _mean_of(res: Resamples, s5: Mapping[str, str], names: Sequence[str]) -> np.ndarray | None:
    """Per resample, the mean S5 retention over `names`; None when any of them was not run at S5."""
    if not names or any(n not in s5 or s5[n] not in res.retention for n in names):
        return None
    return np.mean(np.stack([res.retention[s5[n]] for n in names], axis=1), axis=1)


def axes_per_resample(res: Resamples, s5: Mapping[str, str], quality: Sequence[str], removal: str,
                      core: Sequence[str]) -> AxisResamples:
    """quality, removal, gap and mean in every resample (`s5` maps family -> its S5 cell id)."""
    q, r = _mean_of(res, s5, quality), _mean_of(res, s5, (removal,))
    return AxisResamples(quality=q, removal=r, gap=None if q is None or r is None else q - r,
                         mean=_mean_of(res, s5, core), clusters=res.clusters)


def axis_intervals(per_resample: AxisResamples) -> AxisIntervals:
    """The axes' 95 % intervals (None for an axis without resamples)."""
    return AxisIntervals(**{name: None if (v := per_resample.of(name)) is None
                            else percentile_interval(v, clusters=per_resample.clusters) for name in AXES})


#: Label codes of the vectorised verdict; -1 is "undetermined".
_CODES = {"camera-reliant": 0, "quality-insensitive": 1, "not-shown-to-use-cameras": 2}


def labels_per_resample(quality: np.ndarray | None, removal: np.ndarray | None, flat: float) -> np.ndarray | None:
    """The verdict's label code in every resample, by `verdict`'s rule (axes rounded to 6 decimals first)."""
    if quality is None:
        return None
    q = np.round(quality, 6)
    r = np.round(removal, 6) if removal is not None else np.full_like(q, np.nan)
    code = np.where(q < flat, 0, np.where(r < flat, 1, 2))
    undetermined = np.isnan(q) | (~(q < flat) & np.isnan(r))
    return np.where(undetermined, -1, code)


def verdict_confidence(label: str, quality: np.ndarray | None, removal: np.ndarray | None,
                       flat: float) -> float | None:
    """Share of resamples whose label equals `label`; None when the label is undetermined."""
    codes = labels_per_resample(quality, removal, flat)
    if codes is None or label not in _CODES:
        return None
    return float((codes == _CODES[label]).mean())


def borderline_text(confidence: float) -> str:
    """The sentence appended to the verdict's text when its confidence is under `BORDERLINE`."""
    return (f" Borderline: only {100 * confidence:.1f} % of bootstrap resamples give this label (confidence "
            f"{confidence:.3f} < {BORDERLINE:.2f}); more frames (or seeds) would settle it.")
