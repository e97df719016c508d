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

from ..closedloop.analysis import CLEAN, NULL, CellFigures, NullFigures, RunRow, null_figures
from ..closedloop.cells import Json, as_float, as_list, as_map, parse_id
from ..closedloop.results import RunResult
from ..constants import DEFAULT_FLAT
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

    @property
    def robust(self) -> bool:
        return len(set(self.labels)) == 1

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
                            "flat": self.flat},
                "separation": separation, "open_loop": {"label": self.open_label, "agrees": self.agrees}}


def _retentions(cells: Sequence[CellFigures], reads_rear: bool, null: NullFigures | None) -> list[CellFigures]:
    clean = next((c for c in cells if c.cell == CLEAN), None)
    out = []
    for c in cells:
        if clean is None:
            out.append(c)
            continue
        (lo, hi), (clo, chi) = c.bounds, clean.bounds
        separable = None
        if null is not None and c.cell not in (CLEAN, NULL) or (reads_rear and c.cell == NULL and null is not None):
            assert null is not None
            separable = lo is not None and hi is not None and null.low is not None and null.high is not None and \
                (hi < null.low or lo > null.high)
        out.append(replace(c, retention=_ratio(c.mean, clean.mean), retention_low=_ratio(lo, chi),
                           retention_high=_ratio(hi, clo), separable_from_null=separable))
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


def analyse_rows(rows: Mapping[str, Sequence[RunRow]], *, reads_rear: bool = False,
                 null_rows: Sequence[RunRow] = (), flat: float = DEFAULT_FLAT, open_label: str | None = None,
                 first_step: int | None = None, groups: FamilyGroups | None = None) -> ClosedAnalysis:
    """The analysis of closed cells given as run rows by cell id (`closed-clean`, `closed-blackout-s5`, ...)."""
    groups = groups or FamilyGroups.from_registry()
    figures = [CellFigures(cell, *parse_id(cell), tuple(runs)) for cell, runs in rows.items()]
    by_id = {c.cell: c for c in figures}
    null = null_figures(by_id, reads_rear, null_rows, first_step)
    cells = _retentions(figures, reads_rear, null)
    axes = _axes(cells, groups)
    q, r = axes["quality"], axes["removal"]
    corners = [_label(UNBOUNDED if qq is None and q is not None else qq, UNBOUNDED if rr is None and r is not None
                      else rr, flat)
               for qq in (axes["quality_low"], axes["quality_high"]) for rr in (axes["removal_low"],
                                                                                  axes["removal_high"])]
    qlo, rhi = axes["quality_ds_low"], axes["removal_ds_high"]
    quality_cells = [c for c in cells if c.severity == 5 and c.family in groups.quality]
    quality_ds = _mean([c.mean for c in quality_cells]) if quality_cells else None
    removal_ds = next((c.mean for c in cells if c.severity == 5 and c.family == groups.removal), None)
    separation = {"holds": None if quality_ds is None or removal_ds is None else removal_ds < quality_ds,
                  "holds_under_every_assignment": None if qlo is None or rhi is None else rhi < qlo,
                  "quality_ds": quality_ds, "removal_ds": removal_ds, "quality_ds_low": qlo, "removal_ds_high": rhi}
    return ClosedAnalysis(tuple(cells), null, axes, _label(q, r, flat), tuple(corners), separation, flat,
                          open_label)


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
    for cell in as_list(got["cells"]):
        mine = as_map(cell)
        _diff(problems, f"closed_loop.cells.{mine['cell']}", by_cell.get(mine["cell"]), mine)
    for key in ("null_control", "axes", "verdict", "separation", "open_loop"):
        _diff(problems, f"closed_loop.{key}", section.get(key), got[key])
    return problems
