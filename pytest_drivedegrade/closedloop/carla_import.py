"""`drivedegrade closed-loop import`: CARLA leaderboard results files (one per cell) into the closed loop's
cells: `closed_loop.csv` (one row per run) and the per-cell part of `closed_loop_summary.json` (DS mean and
standard deviation over the scored runs, the identification bounds with the unscored runs at 0 and at 100, mean
completion, infractions by kind), the same numbers `results.CellResult` gives the embedded world's runs; the
cells' run lists (`run_lists`) go through the closed-loop analysis in `report.closed_import`.

Files of one cell are that cell's seeds: a file's "drivedegrade".seed, else its place among the cell's files
(0, 1, ...). The same (cell, route id, seed) twice is an error naming both files. Cells are paired by route
(issue 37): every cell must have run the clean cell's routes, as many times (a route the leaderboard planned but
did not run counts, unscored); a cell missing one, or with a route clean lacks, is an error naming both, since
a retention over other routes than clean's compares other drives.
"""

from __future__ import annotations

import csv
import io
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

from ..atomic import neutralise as quote
from ..errors import DataError
from .carla_results import LeaderboardRun, ResultsFile, parse_source, read_results
from .results import CellResult, RunResult

CSV_NAME, SUMMARY_NAME = "closed_loop.csv", "closed_loop_summary.json"
CSV_COLUMNS = ("cell", "route_id", "route", "repetition", "seed", "ds", "completion", "penalty", "end", "status",
               "infractions", "reported_ds", "length_m", "source")


@dataclass(frozen=True)
class ImportedCell:
    """One cell's files and runs, and the cell result the analysis reads (`cell` with the "closed-" prefix)."""

    cell: str
    files: tuple[ResultsFile, ...]

    @property
    def runs(self) -> tuple[LeaderboardRun, ...]:
        return tuple(run for f in self.files for run in f.runs)

    @property
    def result(self) -> CellResult:
        return CellResult.of(self.cell, [run.run_result() for run in self.runs])  # the cell's DS, bounds


def gather(sources: Sequence[str]) -> list[ImportedCell]:
    """Read every source (`FILE` or `CELL=FILE`) and group the files by cell: clean first, then in the order
    the cells first appear."""
    if not sources:
        raise DataError("closed-loop import: no results files given")
    by_cell: dict[str, list[ResultsFile]] = {}
    for source in sources:
        name, path = parse_source(source)
        probe = read_results(path, name)  # small files: read once for the cell, again with its next seed
        found = read_results(path, name, seed=len(by_cell.get(probe.cell, [])))
        by_cell.setdefault(found.cell, []).append(found)
    seen: dict[tuple[str, str, int], str] = {}
    for cell, files in by_cell.items():
        for f in files:
            for run in f.runs:
                key = (cell, run.route_id, run.seed)
                if key in seen:
                    raise DataError(f"{f.path}: route {run.route_id} of cell {cell} under seed {run.seed} is also in "
                                    f"{seen[key]}: give each file of a cell its own \"drivedegrade\".seed")
                seen[key] = f.path
    order = sorted(by_cell, key=lambda c: (c != "clean", list(by_cell).index(c)))
    cells = [ImportedCell(f"closed-{cell}", tuple(by_cell[cell])) for cell in order]
    check_paired(cells)
    return cells


def _routes(cell: ImportedCell) -> tuple[Counter[str], int]:
    """(the named route ids run, how often each; the planned routes the leaderboard did not run)."""
    unrun = [run for run in cell.runs if run.route_id.startswith("unrun_") and run.ds is None]
    return Counter(run.route_id for run in cell.runs if run not in unrun), len(unrun)


def check_paired(cells: Sequence[ImportedCell]) -> None:
    """Every cell ran the clean cell's routes, as often (see the module docstring); a DataError naming the cell,
    its files and the route otherwise. Without a clean cell there is nothing to pair (the analysis says so)."""
    clean = next((c for c in cells if c.cell == "closed-clean"), None)
    if clean is None:
        return
    base, _ = _routes(clean)
    for cell in cells:
        if cell is clean:
            continue
        named, unrun = _routes(cell)
        files = ", ".join(f.path for f in cell.files)
        extra = sorted((named - base).elements())
        if extra:
            raise DataError(f"{files}: cell {cell.cell} ran route {extra[0]}, which the clean cell did not "
                            f"({len(extra)} run(s) not in clean): cells are compared route by route, so every cell "
                            "must run the clean cell's routes")
        missing = sorted((base - named).elements())
        if len(missing) > unrun:
            raise DataError(f"{files}: cell {cell.cell} has no run of route {missing[0]}, which the clean cell ran "
                            f"({len(missing)} run(s) missing): cells are compared route by route; rerun the missing "
                            "route(s), or give the leaderboard's progress so they count as unscored")


def run_lists(cells: Sequence[ImportedCell]) -> dict[str, list[RunResult]]:
    """Cell id -> its runs as the suite's `RunResult`s (no traces): the per-cell run lists the closed-loop
    analysis takes (`scoring.closed_loop.analyse_runs`), as the plugin's closed cells give them."""
    return {cell.cell: [run.run_result() for run in cell.runs] for cell in cells}


def _cell(value: float | None) -> str:
    return "" if value is None else repr(float(value))


def neutralise(value: object) -> object:
    """A text the file gave (a route id, a status, a path) that a spreadsheet would run as a formula, with a
    leading apostrophe (issue 37, low: formula injection); numbers, written by this module, unchanged."""
    return value if isinstance(value, (int, float)) or _numeric(value) else quote(value)


def _numeric(value: object) -> bool:
    try:
        float(str(value))
    except ValueError:
        return False
    return True


def csv_text(cells: Sequence[ImportedCell]) -> str:
    """One row per run, cells in order, runs in file and record order; text cells neutralised."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for cell in cells:
        for f in cell.files:
            for run in f.runs:
                kinds = ";".join(f"{kind}:{n}" for kind, n in run.infractions)
                writer.writerow([neutralise(v) for v in (
                    cell.cell, run.route_id, run.route, run.repetition, run.seed, _cell(run.ds),
                    _cell(run.completion), _cell(run.penalty), run.end, run.status, kinds, _cell(run.reported_ds),
                    repr(run.length_m), f.path)])
    return buf.getvalue()


def summary(cells: Sequence[ImportedCell]) -> dict[str, object]:
    """Per cell: runs, scored, unscored, DS mean and std (scored runs), bounds, completion, infractions."""
    out: dict[str, object] = {}
    for cell in cells:
        result = cell.result
        lo, hi = result.bounds
        out[cell.cell] = {"files": [f.path for f in cell.files], "seeds": sorted({f.seed for f in cell.files}),
                          "runs": len(result.runs), "scored": len(result.scored), "unscored": result.unscored,
                          "ds_mean": result.mean, "ds_std": result.std, "ds_bounds": [lo, hi],
                          "completion": result.completion, "infractions": result.infractions}
    return {"source": "carla-leaderboard", "cells": out}
