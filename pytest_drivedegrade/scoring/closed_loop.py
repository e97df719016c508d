"""The closed-loop cells together (SPEC section 13): DS retention with bounds, the axes, the verdict under every
assignment of the unscored runs, the availability-versus-quality separation, the null, agreement with the open
loop; the certificate's ``closed_loop`` figures and their recomputation by `drivedegrade verify`.

The entry point takes per-cell run lists, so the plugin's cells and an import of CARLA leaderboard results go
through the same arithmetic (`closedloop.analysis` holds the per-cell figures):

    analyse_runs({"closed-clean": [RunResult, ...], "closed-blackout-s5": [...]}, reads_rear=False,
                 null_runs=(), flat=0.9, open_label=None, first_step=None) -> ClosedAnalysis
    ClosedAnalysis.figures() -> dict  (the caller adds the settings and seals it as ``closed_loop``)
    check_section(section, open_label) -> list of problems (empty: the figures follow from the run rows)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..closedloop.analysis import CLEAN, NULL, SWAP_CELL, CellFigures, NullFigures, RunRow, null_figures, swap_figures
from ..closedloop.cells import Json, as_float, as_list, as_map, parse_id
from ..closedloop.results import RunResult
from ..constants import DEFAULT_FLAT
from . import routestats as rs
from .records import Axes
from .verdict import VERDICT_LABELS, FamilyGroups, verdict

#: How far a recomputed figure may be off the certificate's (6 decimals; DS runs to 100).
TOLERANCE = 1e-5
#: Stands in for an unbounded retention (clean's low bound 0) when labelling the corners of the bounds.
UNBOUNDED = 1e9


def _mean(values: Sequence[float | None]) -> float | None:
    if not values or any(v is None for v in values):
        return None
    return float(sum(v for v in values if v is not None) / len(values))


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b <= 0 else a / b


@dataclass(frozen=True)
class ClosedAnalysis:
    """Every closed-loop figure of a run."""

    cells: tuple[CellFigures, ...]
    null: NullFigures | None
    axes: Mapping[str, float | None]
    label: str
    labels: tuple[str, ...]
    separation: Mapping[str, float | bool | None]
    flat: float
    open_label: str | None
    reason: str | None = None  #: why the label is undetermined (a failed null, unscored runs that sway it)
    command_swap: Mapping[str, Json] | None = None  #: the command swap's figures (`analysis.swap_figures`)

    @property
    def robust(self) -> bool:
        """The label stands at every corner of the axes' intervals and identification bounds (`labels`)."""
        return self.label in VERDICT_LABELS and set(self.labels) == {self.label}

    @property
    def agrees(self) -> bool | None:
        """Whether the closed-loop label equals the open loop's (None when either is undetermined or absent)."""
        if self.open_label not in VERDICT_LABELS or self.label not in VERDICT_LABELS:
            return None
        # the closed loop reads accuracy only: an open-loop planner whose plans move while both axes stay flat
        # (camera-sensitive) agrees with a closed loop flat on both
        opened = "not-shown-to-use-cameras" if self.open_label == "camera-sensitive" else self.open_label
        return opened == self.label

    def figures(self) -> dict[str, Json]:
        cells: list[Json] = [c.figures() for c in self.cells]
        labels: list[Json] = list(sorted(set(self.labels)))
        axes: dict[str, Json] = dict(self.axes)
        separation: dict[str, Json] = dict(self.separation)
        return {"cells": cells, "null_control": None if self.null is None else self.null.figures(), "axes": axes,
                "verdict": {"label": self.label, "labels_under_bounds": labels, "robust": self.robust,
                            "flat": self.flat, "reason": self.reason,
                            "basis": "paired route bootstrap (routes resampled, seeds averaged per route)"},
                "separation": separation, "open_loop": {"label": self.open_label, "agrees": self.agrees},
                "command_swap": None if self.command_swap is None else dict(self.command_swap)}


def _retentions(cells: Sequence[CellFigures], reads_rear: bool, null: NullFigures | None,
                draws: rs.RouteDraws) -> list[CellFigures]:
    """Each cell's retention (complete-case means), its identification bounds, its paired route-level
    intervals and whether it is separable from the null band (`routestats`)."""
    clean = next((c for c in cells if c.cell == CLEAN), None)
    if clean is None:
        return list(cells)
    kv = rs.route_values(clean.rows, draws.routes, None)
    out = []
    for c in cells:
        if c.cell == SWAP_CELL:  # other routes than clean's: no pairing, no retention (`swap_figures`)
            out.append(c)
            continue
        (lo, hi), (clo, chi) = c.bounds, clean.bounds
        p = rs.paired(draws, rs.route_values(c.rows, draws.routes, None), kv)
        diff = draws.interval(p.difference) if c.cell != CLEAN else None
        separable = None
        if null is not None and c.cell not in (CLEAN, NULL) or (reads_rear and c.cell == NULL and null is not None):
            assert null is not None
            separable = rs.separable(diff, null.band)
        out.append(replace(c, retention=_ratio(c.mean, clean.mean), retention_low=_ratio(lo, chi),
                           retention_high=_ratio(hi, clo), separable_from_null=separable,
                           retention_ci=draws.interval(p.retention) if c.cell != CLEAN else None,
                           difference_ci=diff))
    return out


def _axes(cells: Sequence[CellFigures], groups: FamilyGroups) -> dict[str, float | None]:
    s5 = {c.family: c for c in cells if c.severity == 5}
    quality = [s5[f] for f in groups.quality if f in s5]
    removal = s5.get(groups.removal)
    axes: dict[str, float | None] = {}
    for suffix in ("", "_low", "_high"):
        name = "retention" + suffix
        axes["quality" + suffix] = _mean([getattr(c, name) for c in quality]) if quality else None
        axes["removal" + suffix] = None if removal is None else getattr(removal, name)
    axes["quality_ds_low"] = _mean([c.bounds[0] for c in quality]) if quality else None
    axes["removal_ds_high"] = None if removal is None else removal.bounds[1]
    return axes


def _label(quality: float | None, removal: float | None, flat: float) -> str:
    gap = None if quality is None or removal is None else quality - removal
    return verdict(Axes(quality, removal, gap, None), flat).label


@dataclass(frozen=True)
class _AxisDraws:
    """Per resample, under each assignment of the unscored runs: the quality and removal axes (retention) and
    the quality-minus-removal DS gap; None where the cells are missing."""

    quality: dict[str, np.ndarray]
    removal: dict[str, np.ndarray]
    gap: dict[str, np.ndarray]


def _axis_draws(cells: Sequence[CellFigures], groups: FamilyGroups, draws: rs.RouteDraws) -> _AxisDraws:
    by = {c.cell: c for c in cells}
    s5 = {c.family: c for c in cells if c.severity == 5}
    quality, removal = [s5[f] for f in groups.quality if f in s5], s5.get(groups.removal)
    out: dict[str, dict[str, np.ndarray]] = {"quality": {}, "removal": {}, "gap": {}}
    if CLEAN not in by or not quality or removal is None:
        return _AxisDraws(**out)
    clean = rs.clean_values(by[CLEAN].rows, draws.routes)
    for a, (mine, _) in rs.ASSIGNMENTS.items():
        q = [rs.route_values(c.rows, draws.routes, mine) for c in quality]
        r = rs.route_values(removal.rows, draws.routes, mine)
        out["quality"][a] = np.mean([rs.paired(draws, v, clean[a]).retention for v in q], axis=0)
        out["removal"][a] = rs.paired(draws, r, clean[a]).retention
        worst = rs.route_values(removal.rows, draws.routes, 100.0 if a == "low" else 0.0 if a == "high" else None)
        qd = np.mean(q, axis=0)
        mask = np.isfinite(qd) & np.isfinite(worst)
        out["gap"][a] = draws.means(qd - worst, mask)
    return _AxisDraws(**out)


def _interval_axes(ax: _AxisDraws, draws: rs.RouteDraws) -> dict[str, float | None]:
    """The axes' paired route-level intervals (complete case): ``quality_ci_low`` ... ``gap_ds_ci_high``."""
    out: dict[str, float | None] = {}
    for name, got in (("quality", ax.quality.get("point")), ("removal", ax.removal.get("point")),
                      ("gap_ds", ax.gap.get("point"))):
        ci = None if got is None else draws.interval(got)
        out[name + "_ci_low"], out[name + "_ci_high"] = ci or (None, None)
    return out


def _interval_corners(ax: _AxisDraws, draws: rs.RouteDraws, flat: float) -> list[str]:
    """The labels at the corners of [quality's lower bound under 'low', its upper under 'high'] x the same for
    removal: the label is robust only when every corner gives it."""
    def bounds(d: dict[str, np.ndarray]) -> tuple[float | None, float | None]:
        lo = draws.interval(d["low"]) if "low" in d else None
        hi = draws.interval(d["high"]) if "high" in d else None
        return (None if lo is None else lo[0]), (None if hi is None else hi[1])

    if not ax.quality:
        return []
    return [_label(q, r, flat) for q in bounds(ax.quality) for r in bounds(ax.removal)]


def _separation(cells: Sequence[CellFigures], groups: FamilyGroups, axes: Mapping[str, float | None],
                ax: _AxisDraws, draws: rs.RouteDraws) -> dict[str, float | bool | None]:
    """The availability-versus-quality separation: removal's DS under quality's, held only when the paired
    route-level interval of the gap clears 0 (complete case; under every assignment: the worst one's); None
    where there is no interval (a cell missing, or fewer than two routes)."""
    quality_cells = [c for c in cells if c.severity == 5 and c.family in groups.quality]
    quality_ds = _mean([c.mean for c in quality_cells]) if quality_cells else None
    removal_ds = next((c.mean for c in cells if c.severity == 5 and c.family == groups.removal), None)
    gap = None if "point" not in ax.gap else draws.interval(ax.gap["point"])
    worst = None if "low" not in ax.gap else draws.interval(ax.gap["low"])
    return {"holds": None if quality_ds is None or removal_ds is None or gap is None else gap[0] > 0,
            "holds_under_every_assignment": None if axes["quality_ds_low"] is None or axes["removal_ds_high"] is None
            or worst is None else worst[0] > 0,
            "quality_ds": quality_ds, "removal_ds": removal_ds, "quality_ds_low": axes["quality_ds_low"],
            "removal_ds_high": axes["removal_ds_high"], "gap_ds_ci_low": None if gap is None else gap[0],
            "gap_ds_ci_high": None if gap is None else gap[1], "gap_ds_worst_ci_low": None if worst is None
            else worst[0]}


def _headline(label: str, bound_labels: Sequence[str], null: NullFigures | None,
              cells: Sequence[CellFigures], groups: FamilyGroups) -> tuple[str, str | None]:
    """The closed label and why it is undetermined: a failed null, or unscored runs in the cells the axes rest
    on whose identification bounds give another label."""
    if null is not None and null.passed is False:
        return "undetermined", (f"the closed-loop null control failed (route {null.first_route}, seed "
                                f"{null.first_seed}): the closed figures cannot be told from the planner's own "
                                "variation")
    used = [c for c in cells if c.cell == CLEAN or c.severity == 5 and
            (c.family in groups.quality or c.family == groups.removal)]
    unscored = sum(c.unscored for c in used)
    if unscored and set(bound_labels) != {label}:
        return "undetermined", (f"{unscored} unscored run(s) in the cells the axes rest on, and their bounds allow "
                                f"{', '.join(sorted(set(bound_labels)))}")
    return label, None


def analyse_rows(rows: Mapping[str, Sequence[RunRow]], *, reads_rear: bool = False,
                 null_rows: Sequence[RunRow] = (), flat: float = DEFAULT_FLAT, open_label: str | None = None,
                 first_step: int | None = None, groups: FamilyGroups | None = None) -> ClosedAnalysis:
    """The analysis of closed cells given as run rows by cell id (`closed-clean`, `closed-blackout-s5`, ...)."""
    groups = groups or FamilyGroups.from_registry()
    figures = [CellFigures(cell, *parse_id(cell), tuple(runs)) for cell, runs in rows.items()]
    by_id = {c.cell: c for c in figures}
    draws = rs.RouteDraws.of(list(dict.fromkeys(r.route for r in by_id[CLEAN].rows)) if CLEAN in by_id else [])
    null = _with_band(null_figures(by_id, reads_rear, null_rows, first_step), by_id, draws)
    cells = _retentions(figures, reads_rear, null, draws)
    axes = _axes(cells, groups)
    q, r = axes["quality"], axes["removal"]
    corners = [_label(UNBOUNDED if qq is None and q is not None else qq, UNBOUNDED if rr is None and r is not None
                      else rr, flat)
               for qq in (axes["quality_low"], axes["quality_high"]) for rr in (axes["removal_low"],
                                                                                  axes["removal_high"])]
    ax = _axis_draws(cells, groups, draws)
    axes.update(_interval_axes(ax, draws))
    label, reason = _headline(_label(q, r, flat), corners, null, cells, groups)
    labels = tuple(corners) + tuple(_interval_corners(ax, draws, flat))
    return ClosedAnalysis(tuple(cells), null, axes, label, labels, _separation(cells, groups, axes, ax, draws),
                          flat, open_label, reason, swap_figures(by_id))


def _with_band(null: NullFigures | None, cells: Mapping[str, CellFigures], draws: rs.RouteDraws) \
        -> NullFigures | None:
    """The null's figures with its band: the null's own per-route spread around clean (`routestats.band`)."""
    if null is None or CLEAN not in cells:
        return null
    rows = null.rows if null.mode == "wander" else cells[NULL].rows
    kv = rs.route_values(cells[CLEAN].rows, draws.routes, None)
    return replace(null, band=rs.band(draws, rs.route_values(rows, draws.routes, None), kv))


def analyse_runs(runs: Mapping[str, Sequence[RunResult]], *, reads_rear: bool = False,
                 null_runs: Sequence[RunResult] = (), flat: float = DEFAULT_FLAT, open_label: str | None = None,
                 first_step: int | None = None) -> ClosedAnalysis:
    """`analyse_rows` on `RunResult`s (the plugin's cells, or CARLA results read into RunResults)."""
    return analyse_rows({c: [RunRow.of(r) for r in rs] for c, rs in runs.items()}, reads_rear=reads_rear,
                        null_rows=[RunRow.of(r) for r in null_runs], flat=flat, open_label=open_label,
                        first_step=first_step)


def _close(a: object, b: object) -> bool:
    if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None or isinstance(a, str) or \
            isinstance(b, str):
        return a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(float(a), float(b), rel_tol=TOLERANCE, abs_tol=TOLERANCE)
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return set(a) == set(b) and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    return a == b


def _diff(problems: list[str], where: str, recorded: object, recomputed: object) -> None:
    if isinstance(recorded, Mapping) and isinstance(recomputed, Mapping):
        for k in sorted(set(recorded) | set(recomputed)):
            _diff(problems, f"{where}.{k}", recorded.get(k), recomputed.get(k))
        return
    if not _close(recorded, recomputed):
        problems.append(f"{where}: certificate says {recorded!r:.80}, its run rows give {recomputed!r:.80}")


def _rows(value: object) -> list[RunRow]:
    return [RunRow.from_list(as_list(r, "run row")) for r in as_list(value, "run_rows")]


def check_section(section: Mapping[str, object], open_label: str | None) -> list[str]:
    """Recompute the ``closed_loop`` figures from the section's own run rows (per cell and the null's), its
    flat line and the open-loop label; every figure that disagrees, as ``closed_loop.<field>: ... gives ...``."""
    try:
        recorded = [as_map(c, "cell") for c in as_list(section["cells"], "cells")]
        cells = {str(c["cell"]): _rows(c["run_rows"]) for c in recorded}
        nc = as_map(section.get("null_control") or {}, "null_control")
        step = nc.get("first_step")
        got = analyse_rows(cells, reads_rear=nc.get("mode") == "wander", null_rows=_rows(nc.get("run_rows", [])),
                           flat=as_float(as_map(section["verdict"], "verdict")["flat"], "verdict.flat"),
                           open_label=open_label, first_step=step if isinstance(step, int) else None).figures()
    except (KeyError, TypeError, ValueError) as exc:
        return [f"closed_loop: malformed ({type(exc).__name__}: {exc})"]
    problems: list[str] = []
    by_cell = {c.get("cell"): c for c in recorded}
    legacy = "basis" not in as_map(section["verdict"], "verdict")
    for cell in as_list(got["cells"]):
        mine = as_map(cell)
        theirs = by_cell.get(mine["cell"])
        _diff(problems, f"closed_loop.cells.{mine['cell']}", _legacy(theirs, LEGACY_CELL) if legacy else theirs,
              _legacy(mine, LEGACY_CELL) if legacy else mine)
    for key in ("null_control", "axes", "verdict", "separation", "open_loop", "command_swap"):
        if legacy and key in LEGACY_SECTION:
            _diff(problems, f"closed_loop.{key}", _legacy(section.get(key), LEGACY_SECTION[key]),
                  _legacy(got[key], LEGACY_SECTION[key]))
        elif not legacy:
            _diff(problems, f"closed_loop.{key}", section.get(key), got[key])
    return problems


#: A section written before the route-level statistics (spec 4: no ``verdict.basis``): its separability, null
#: band, robustness, separation and label followed the older point rules, so only the figures both rules share
#: are recomputed (the DS means, bounds and retentions, the null's mode and wander, the point axes).
LEGACY_CELL = ("cell", "family", "severity", "runs", "unscored", "ds_mean", "ds_std", "ds_low", "ds_high",
               "completion", "infractions", "retention", "retention_low", "retention_high")
LEGACY_SECTION: dict[str, tuple[str, ...]] = {
    "null_control": ("mode", "passed", "first_route", "first_seed", "first_step", "wander", "low", "high"),
    "axes": ("quality", "quality_low", "quality_high", "removal", "removal_low", "removal_high", "quality_ds_low",
             "removal_ds_high")}


def _legacy(value: object, keys: Sequence[str]) -> object:
    """`value`'s entries under `keys` (a mapping; anything else unchanged)."""
    if not isinstance(value, Mapping):
        return value
    return {k: value.get(k) for k in keys}
