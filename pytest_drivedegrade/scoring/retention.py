"""Retention and its paired frame bootstrap, one cell's summary, and the tolerance thresholds s*10 / s*25."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..cells import EPDMS_FIELDS, PDMS_FIELDS, TWO_STAGE_FIELDS, CellRecord, is_camera_ladder
from ..errors import InvalidInput
from .clusters import cluster_counts, percentile_interval, scene_clusters
from .records import CellSummary, finite_mean, horizon_metrics

#: Retention levels of the two tolerance thresholds s*10 and s*25.
THRESHOLD_LEVELS: dict[str, float] = {"s10": 0.90, "s25": 0.75}
DEFAULT_RESAMPLES = 1000


def retention(m_clean: ArrayLike, m_cell: ArrayLike, kind: str = "error") -> Any:
    """r = M(clean) / M(s) for an error metric, M(s) / M(clean) for a reward metric; vectorised.

    Higher is better and 1.0 means no measurable damage. Both zero -> 1.0 (nothing to lose); a zero
    denominator otherwise -> inf. Returns a float for scalar input.
    """
    if kind not in ("error", "reward"):
        raise InvalidInput(f"retention kind must be 'error' or 'reward', got {kind!r}")
    num, den = (m_clean, m_cell) if kind == "error" else (m_cell, m_clean)
    num, den = np.asarray(num, dtype=float), np.asarray(den, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where((num == 0) & (den == 0), 1.0, num / den)
    return float(r) if r.ndim == 0 else r


def bootstrap_retention_ci(clean: ArrayLike, cell: ArrayLike, *, kind: str = "error",
                           n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0, confidence: float = 0.95,
                           chunk_elems: int = 2_000_000, scenes: Sequence[str] | None = None) -> tuple[float, float]:
    """Paired percentile bootstrap CI of retention: over scenes when `scenes` (each frame's scene, two or more
    scenes) is given, else over frames.

    Each resample draws frame indices with replacement and applies the *same* indices to clean and the cell,
    so per-frame difficulty cancels. Frames not finite in both are dropped first. The generator is seeded
    with `seed` only, so every cell of a run sees the same resamples and the result is order-independent.
    Vectorised in chunks of about `chunk_elems` indices. (NaN, NaN) when no frame is usable. With scenes, each
    resample draws the scenes with replacement and takes their frames whole (`clusters.scene_clusters`), and
    the bounds are read at the expanded levels for that many scenes (`clusters.expanded_tail`).
    """
    a, b = np.asarray(clean, dtype=float), np.asarray(cell, dtype=float)
    if scenes is not None:
        return _cluster_ci(a, b, scenes, kind=kind, n_resamples=n_resamples, seed=seed, confidence=confidence)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    n = len(a)
    if n == 0 or n_resamples < 1:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    per_chunk = max(1, chunk_elems // n)
    ratios = []
    for start in range(0, n_resamples, per_chunk):
        # One double per index (not ``integers``, whose 32-bit buffering depends on the chunk shape), so the
        # resamples are the same whatever the chunk size.
        idx = (rng.random((min(per_chunk, n_resamples - start), n)) * n).astype(np.intp)
        ratios.append(retention(a[idx].mean(axis=1), b[idx].mean(axis=1), kind))
    r = np.concatenate(ratios)
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(r, [tail, 100.0 - tail])
    return float(low), float(high)


def _cluster_ci(a: np.ndarray, b: np.ndarray, scenes: Sequence[str], *, kind: str, n_resamples: int, seed: int,
                confidence: float) -> tuple[float, float]:
    """`bootstrap_retention_ci` over scenes (falls back to frames when the frames span fewer than two scenes)."""
    labels, basis = scene_clusters(scenes, len(a))
    ok = np.isfinite(a) & np.isfinite(b)
    if labels is None or not ok.any() or n_resamples < 1:
        return bootstrap_retention_ci(a, b, kind=kind, n_resamples=n_resamples, seed=seed, confidence=confidence)
    counts = cluster_counts(np.random.default_rng(seed), n_resamples, labels)
    with np.errstate(divide="ignore", invalid="ignore"):
        den = counts @ ok.astype(float)
        r = retention((counts @ np.where(ok, a, 0.0)) / den, (counts @ np.where(ok, b, 0.0)) / den, kind)
    got = percentile_interval(np.where(den > 0, r, np.nan), confidence, clusters=basis.clusters)
    if got is None:
        return math.nan, math.nan
    return (math.nan if got[0] is None else got[0]), (math.inf if got[1] is None else got[1])


def paired_retention(m_clean: np.ndarray, m_cell: np.ndarray, kind: str = "error") -> float:
    """Retention over the frames finite in both the cell and clean (the bootstrap's frames); NaN when none."""
    paired = np.isfinite(m_clean) & np.isfinite(m_cell)
    return float(retention(finite_mean(m_clean[paired]), finite_mean(m_cell[paired]), kind))


def record_retention(clean: CellRecord, record: CellRecord, convention: str = "stp3", kind: str = "error") -> float:
    """A cell's retention: `paired_retention` of each seed run against clean, averaged over the seeds (one run:
    exactly its paired retention)."""
    m_clean = clean.l2_avg_per_frame(convention)
    values = [paired_retention(m_clean, run.l2_avg_per_frame(convention), kind) for run in record.runs()]
    return values[0] if len(values) == 1 else finite_mean(values)


def _seed_mean(values: Iterable[dict[str, float]]) -> dict[str, float]:
    """Key-wise mean over seed runs (NaN runs left out)."""
    rows = list(values)
    return {k: finite_mean([row[k] for row in rows]) for k in rows[0]}


def summarise_cell(record: CellRecord, clean: CellRecord, *, convention: str = "stp3", kind: str = "error",
                   n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0,
                   ci: tuple[float, float] | None = None, scenes: Sequence[str] | None = None) -> CellSummary:
    """A cell's metrics, its retention against `clean` and the paired bootstrap CI.

    A cell run under several seeds reports the mean over its seed runs of every metric and of retention, and
    takes its CI from `ci` (the two-level bootstrap of ``intervals``); `scenes` (each frame's scene) makes the
    one-run CIs scene-cluster bootstraps; `frames` counts the frames finite in
    every run, `conformance_errors` and `data_errors` the failures of all runs. A cell with no scored frame has
    no retention (NaN), the clean cell included: 1.0 over 0 frames would claim what was never measured.
    """
    if record.frames != clean.frames:
        raise InvalidInput(f"cell {record.cell!r} was scored on other frames than the clean cell")
    m_clean, m_cell = clean.l2_avg_per_frame(convention), record.l2_avg_per_frame(convention)
    if record.seed_runs:
        runs = record.runs()
        per_run = [{**horizon_metrics(run), "endpoint_shift": finite_mean(run.endpoint_shift(clean)),
                    "energy": float(retention(finite_mean(clean.bit1), finite_mean(run.bit1), "reward")),
                    "l2_avg": finite_mean(run.l2_avg_per_frame(convention))} for run in runs]
        metrics = _seed_mean(per_run)
        l2 = metrics.pop("l2_avg")
        r = record_retention(clean, record, convention, kind)
        low, high = ci if ci is not None else (math.nan, math.nan)
        finite = np.all([np.isfinite(run.l2_avg_per_frame(convention)) for run in runs], axis=0)
        return CellSummary(record.cell, record.family, record.severity, int(finite.sum()), l2, r, low, high,
                           metrics, conformance_errors=sum(len(run.errors) for run in runs),
                           data_errors=sum(len(run.data_errors) for run in runs))
    metrics = horizon_metrics(record)
    metrics["endpoint_shift"] = finite_mean(record.endpoint_shift(clean))
    metrics["energy"] = float(retention(finite_mean(clean.bit1), finite_mean(record.bit1), "reward"))
    metrics.update(pdms_metrics(record, clean, n_resamples=n_resamples, seed=seed, scenes=scenes))
    if record.cell == clean.cell:
        r, ci = (1.0, (1.0, 1.0)) if np.isfinite(m_clean).any() else (math.nan, (math.nan, math.nan))
    else:
        r = paired_retention(m_clean, m_cell, kind)
        ci = bootstrap_retention_ci(m_clean, m_cell, kind=kind, n_resamples=n_resamples, seed=seed, scenes=scenes)
    return CellSummary(record.cell, record.family, record.severity, int(np.isfinite(m_cell).sum()),
                       finite_mean(m_cell), r, ci[0], ci[1], metrics, conformance_errors=len(record.errors),
                       data_errors=len(record.data_errors))


def pdms_metrics(record: CellRecord, clean: CellRecord, *, n_resamples: int = DEFAULT_RESAMPLES,
                 seed: int = 0, scenes: Sequence[str] | None = None) -> dict[str, float]:
    """A cell's mean PDMS-like score and sub-scores (spec 3), the share of frames scored with a map
    (``map_scored``), and PDMS retention M(cell) / M(clean) (a reward) with its paired bootstrap CI
    (``pdms_retention``, ``pdms_retention_ci_low``, ``pdms_retention_ci_high``); the same for the EPDMS (spec
    4.1: its terms' means, ``epdms_retention`` and its CI); in a two-stage run also the stage-two and two-stage
    EPDMS means (``epdms_stage2``, ``epdms2``), the frames with a stage two and ``epdms2_retention`` with its CI
    (absent from a one-stage run's); NaN where not scored."""
    out = {k: finite_mean(getattr(record, k)) for k in (*PDMS_FIELDS, *EPDMS_FIELDS)}
    out["map_scored"] = finite_mean(record.map_scored)
    two_stage = np.isfinite(clean.epdms2).any() or np.isfinite(record.epdms2).any()
    if two_stage:  # --drivedegrade-two-stage: the stage-two and two-stage EPDMS, on the frames that have them
        out.update({k: finite_mean(getattr(record, k)) for k in TWO_STAGE_FIELDS})
        out["epdms2_frames"] = int(np.isfinite(record.epdms2).sum())
    for name in ("pdms", "epdms", *(("epdms2",) if two_stage else ())):
        mine, theirs = getattr(record, name), getattr(clean, name)
        if record.cell == clean.cell:
            r, ci = (1.0, (1.0, 1.0)) if np.isfinite(theirs).any() else (math.nan, (math.nan, math.nan))
        else:
            r = paired_retention(theirs, mine, "reward")
            ci = bootstrap_retention_ci(theirs, mine, kind="reward", n_resamples=n_resamples, seed=seed,
                                        scenes=scenes)
        out.update({f"{name}_retention": r, f"{name}_retention_ci_low": ci[0], f"{name}_retention_ci_high": ci[1]})
    return out


def tolerance_threshold(curve: Mapping[int, float], level: float) -> float | None:
    """Severity at which retention first falls *below* `level`, linearly interpolated.

    `curve` maps severity (1..5, any subset) to retention. Retention exactly at `level` is not below. Walking
    up the measured severities, the first one below `level` is the crossing: interpolate between it and the
    measured severity just before it. When the lowest measured severity is already below (S1 normally), the
    value is that severity (1.0). None when no measured severity falls below. NaN retentions are skipped.
    """
    points = sorted((int(s), float(r)) for s, r in curve.items() if int(s) > 0 and math.isfinite(float(r)))
    prev: tuple[int, float] | None = None
    for s, r in points:
        if r < level:
            if prev is None:
                return float(s)
            s0, r0 = prev
            return float(s0 + (r0 - level) / (r0 - r) * (s - s0))
        prev = (s, r)
    return None


def thresholds(summaries: Iterable[CellSummary]) -> dict[str, dict[str, float | None]]:
    """family -> {"s10": x|None, "s25": x|None} for every camera ladder family among the summaries (not the ego
    cells)."""
    curves: dict[str, dict[int, float]] = {}
    for s in summaries:
        if is_camera_ladder(s.family):
            curves.setdefault(s.family, {})[s.severity] = s.retention
    return {fam: {k: tolerance_threshold(c, lvl) for k, lvl in THRESHOLD_LEVELS.items()} for fam, c in curves.items()}
