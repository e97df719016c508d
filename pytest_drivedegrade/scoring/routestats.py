"""Paired route-level intervals for the closed loop (SPEC section 17, issue 36): the route is the sampling unit.

A closed cell's runs are (route, seed); runs of one route share the road, the traffic and the scenario, and a
deterministic cell's seeds replay one another, so neither runs nor seeds are independent draws. Every figure
here is first reduced to one value per route (the mean DS over that route's runs), then compared with clean
**on the same routes** (paired), and its interval comes from resampling the routes with replacement, one set of
route draws shared by every cell (so the axes, the separation and the null band are paired across cells too),
read at the expanded percentile levels for that many routes (`clusters.expanded_tail`: as wide as a t
interval with G - 1 degrees of freedom for a mean).

Unscored runs are handled by assignment: ``point`` leaves them out (complete case; a route none of whose runs
scored drops out of that comparison), ``low`` puts a cell's at 0 and clean's at 100, ``high`` the other way
round, so a retention under ``low`` is the least and under ``high`` the most the unscored runs could make it.

**The null band** is the null's own spread: per route, the null run's DS minus clean's (the clean rerun of a
planner that reads the rear cameras, or blackout S3 of one that does not: 0 on every route when it reproduces
clean). The farthest bound of its interval from 0, either way, is the band (`band`); a cell is separable from
the null only when its own paired interval (cell minus clean, per route) lies wholly outside the band.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..closedloop.analysis import RunRow
from .clusters import cluster_counts, percentile_interval

#: Route resamples drawn (one set for the whole closed-loop analysis), and the stream they are drawn from.
ROUTE_RESAMPLES = 2000
STREAM = (36, 13)
#: The assignments of the unscored runs: (value of a cell's unscored run, value of clean's).
ASSIGNMENTS: dict[str, tuple[float | None, float | None]] = {"point": (None, None), "low": (0.0, 100.0),
                                                             "high": (100.0, 0.0)}

Interval = tuple[float, float] | None


def route_values(rows: Sequence[RunRow], routes: Sequence[str], unscored: float | None) -> np.ndarray:
    """(G,) mean DS per route over the route's runs (unscored ones at `unscored`, or left out when None); NaN
    for a route without a (scored) run."""
    out = np.full(len(routes), np.nan)
    at = {r: i for i, r in enumerate(routes)}
    sums, counts = np.zeros(len(routes)), np.zeros(len(routes))
    for row in rows:
        if row.route not in at:
            continue
        value = row.ds if row.ds is not None else unscored
        if value is None:
            continue
        sums[at[row.route]] += value
        counts[at[row.route]] += 1
    np.divide(sums, counts, out=out, where=counts > 0)
    return out


@dataclass(frozen=True)
class RouteDraws:
    """The routes (clean's, in run order) and how often each is drawn in each resample (R, G)."""

    routes: tuple[str, ...]
    counts: np.ndarray

    @classmethod
    def of(cls, routes: Sequence[str], n_resamples: int = ROUTE_RESAMPLES) -> RouteDraws:
        labels = np.arange(len(routes), dtype=np.intp)
        counts = cluster_counts(np.random.default_rng(STREAM), n_resamples, labels) if len(routes) \
            else np.zeros((n_resamples, 0))
        return cls(tuple(routes), counts)

    @property
    def clusters(self) -> int:
        return len(self.routes)

    def means(self, values: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(R,) the mean of `values` over the drawn routes where `mask` holds (NaN where none was drawn)."""
        w = self.counts * mask[None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            return (w @ np.where(mask, values, 0.0)) / w.sum(axis=1)

    def interval(self, per_resample: np.ndarray) -> Interval:
        """The expanded-percentile interval of a statistic's resamples (None without a finite resample)."""
        v = np.asarray(per_resample, dtype=float)
        got = percentile_interval(np.where(np.isfinite(v), v, np.nan), clusters=self.clusters) \
            if self.clusters >= 2 else None
        if got is None or got[0] is None or got[1] is None:
            return None
        return float(got[0]), float(got[1])


@dataclass(frozen=True)
class Paired:
    """One cell against clean on the routes both have: the per-resample retention (mean cell / mean clean) and
    DS difference (mean of cell - clean), and the point figures."""

    retention: np.ndarray
    difference: np.ndarray
    point_retention: float | None
    point_difference: float | None


def paired(draws: RouteDraws, cell: np.ndarray, clean: np.ndarray) -> Paired:
    """`cell` against `clean` (per-route values, NaN where absent), paired on the routes finite in both."""
    mask = np.isfinite(cell) & np.isfinite(clean)
    mc, mk = draws.means(cell, mask), draws.means(clean, mask)
    with np.errstate(divide="ignore", invalid="ignore"):
        ret = np.where(mk > 0, mc / mk, np.nan)
    if not mask.any():
        return Paired(ret, mc - mk, None, None)
    c, k = float(cell[mask].mean()), float(clean[mask].mean())
    return Paired(ret, mc - mk, c / k if k > 0 else None, c - k)


def band(draws: RouteDraws, null: np.ndarray | None, clean: np.ndarray) -> Interval:
    """The null band in DS: [-h, h], h the farthest bound from 0 of the interval of the null's mean paired
    difference from clean (None without a null; [0, 0] for a null that equals clean on every route).

    Symmetric because under the null a cell minus clean is distributed as the rerun minus clean, two draws of
    the same noise: a drift of the null one way says as much about noise the other way."""
    if null is None:
        return None
    got = draws.interval(paired(draws, null, clean).difference)
    if got is None:
        return None
    h = max(abs(got[0]), abs(got[1]))
    return (-h if h else 0.0), h


def separable(difference: Interval, null_band: Interval) -> bool | None:
    """Whether the cell's paired DS-difference interval lies wholly outside the null band (None: either
    missing)."""
    if difference is None or null_band is None:
        return None
    return difference[0] > null_band[1] or difference[1] < null_band[0]


def per_route(cells: Mapping[str, Sequence[RunRow]], routes: Sequence[str]) -> dict[str, dict[str, np.ndarray]]:
    """cell -> assignment -> (G,) per-route DS (`ASSIGNMENTS`: clean takes the second value of each pair)."""
    return {cell: {a: route_values(rows, routes, v[0]) for a, v in ASSIGNMENTS.items()}
            for cell, rows in cells.items()}


def clean_values(rows: Sequence[RunRow], routes: Sequence[str]) -> dict[str, np.ndarray]:
    """Clean's per-route DS under each assignment (its unscored runs at the pair's second value)."""
    return {a: route_values(rows, routes, v[1]) for a, v in ASSIGNMENTS.items()}
