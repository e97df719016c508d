"""`drivedegrade closed-loop import` end to end (SPEC section 13, "CARLA"): leaderboard results files read into
cells (`closedloop.carla_import`), put through the closed-loop analysis the plugin's cells go through
(`scoring.closed_loop.analyse_runs`: retention with bounds, axes, the verdict at every corner of the bounds, the
separation under every assignment of the unscored runs), and written as closed_loop.csv, closed_loop_summary.json
(per cell, and under "closed_loop" the analysis as a certificate's section holds it) and report.html (the
closed-loop section), with the plugin's terminal lines.

The null control (`NullChoice`, ``--null`` and ``--null-identical``): by default CARLA is taken as not
deterministic, so the null is "wander" mode with `closed-blackout-s3` (the rear views a front-camera agent never
reads); its distance from clean is the wander, and a cell whose bounds overlap the null's band is "not separable
from the null". ``--null clean-rerun`` names a second clean run (``clean-rerun=FILE``) as the null instead, for an
agent that reads its rear cameras (blackout S3 is then an ordinary cell), as the plugin reruns clean for such a
planner. ``--null-identical`` reads the blackout-S3 null as the plugin does a front-only planner's: on a
deterministic CARLA setup it must reproduce clean run for run (route, seed, DS and end: `RunRow.same` on runs
without traces), else the import exits 1 naming the first route that differs. ``--flat`` is the plugin's
``--drivedegrade-flat``: the retention at or above which an axis counts as flat.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from ..atomic import atomic_write_text
from ..closedloop.analysis import CLEAN, NULL
from ..closedloop.carla_import import CSV_NAME, SUMMARY_NAME, ImportedCell, csv_text, gather, run_lists, summary
from ..closedloop.carla_results import CLEAN_RERUN
from ..closedloop.results import RunResult
from ..constants import DEFAULT_FLAT
from ..errors import DataError
from ..scoring.closed_loop import ClosedAnalysis, analyse_runs
from .closed_html import write_imported_report
from .closed_outputs import closed_lines

REPORT_NAME = "report.html"
#: The null controls `--null` can name: blackout S3 (the default) or a second clean run.
NULL_CELLS = ("blackout-s3", CLEAN_RERUN)


@dataclass(frozen=True)
class NullChoice:
    """Which results are the null control: `cell` (None: a clean rerun when one was given, else blackout S3),
    and whether it must reproduce clean run for run (`identical`, a front-only agent on a deterministic setup)."""

    cell: str | None = None
    identical: bool = False

    def pick(self, runs: Mapping[str, Sequence[RunResult]]) -> str:
        """The null's cell id among `runs`; DataError when the named one was not given, or cannot be identical."""
        rerun = f"closed-{CLEAN_RERUN}"
        cell = f"closed-{self.cell}" if self.cell is not None else rerun if rerun in runs else NULL
        if self.cell is not None and self.cell not in NULL_CELLS:
            raise DataError(f"--null {self.cell}: expected one of {', '.join(NULL_CELLS)}")
        if self.cell == "blackout-s3" and rerun in runs:
            raise DataError(f"--null blackout-s3: a {CLEAN_RERUN} file was given too, and would be read for nothing: "
                            f"drop it, or name it the null with --null {CLEAN_RERUN}")
        if self.cell is not None and cell not in runs:
            raise DataError(f"--null {self.cell}: no results file of cell {self.cell} among {', '.join(runs)}: give "
                            f"it as {self.cell}=FILE")
        if self.identical and cell != NULL:
            raise DataError("--null-identical: only blackout S3 (the rear views a front-only agent never reads) can "
                            "reproduce clean run for run; a clean rerun is the null of an agent that reads its rear "
                            "cameras, and its null is how far it wanders")
        if self.identical and cell not in runs:
            raise DataError(f"--null-identical: no results file of cell blackout-s3 among {', '.join(runs)}: give "
                            "it as blackout-s3=FILE")
        return cell


def analyse_import(cells: Sequence[ImportedCell], flat: float = DEFAULT_FLAT,
                   null: NullChoice = NullChoice()) -> ClosedAnalysis:
    """The closed-loop analysis of imported cells with the `null` control and the `flat` line; DataError when
    clean is missing (retention is over clean) or the null named is not among them."""
    runs = run_lists(cells)
    if CLEAN not in runs:
        raise DataError(f"closed-loop import: no clean cell among {', '.join(runs)}: retention is a cell's DS over "
                        "clean's, so give the clean run's results file too (clean=FILE)")
    if not 0.0 <= flat <= 1.0:
        raise DataError(f"--flat {flat!r}: expected a retention in [0, 1] (the plugin's --drivedegrade-flat)")
    cell = null.pick(runs)
    if null.identical:
        return analyse_runs(runs, reads_rear=False, flat=flat)
    rerun = runs.pop(f"closed-{CLEAN_RERUN}", None)  # not a cell of the ladder: the null only
    return analyse_runs(runs, reads_rear=True, null_runs=rerun if cell != NULL and rerun else runs.get(NULL, ()),
                        flat=flat)


def import_results(sources: Sequence[str], out: Path, flat: float = DEFAULT_FLAT,
                   null: NullChoice = NullChoice()) -> tuple[list[str], bool]:
    """Read the sources, analyse them, write the CSV, the summary and report.html into `out`; the lines to
    print (the plugin's closed-loop summary, then where the cells came from and what was written), and False
    when an identical null control failed."""
    cells = gather(sources)
    analysis = analyse_import(cells, flat, null)
    cell = null.pick(run_lists(cells))
    what = "a clean rerun" if cell == f"closed-{CLEAN_RERUN}" else "blackout S3"
    out.mkdir(parents=True, exist_ok=True)
    csv_path = atomic_write_text(out / CSV_NAME, csv_text(cells))
    chosen = {"cell": cell, "mode": "identical" if null.identical else "wander"}
    data = {**summary(cells), "null": chosen, "closed_loop": analysis.figures()}
    json_path = atomic_write_text(out / SUMMARY_NAME, json.dumps(data, indent=2, sort_keys=True) + "\n")
    files = [(cell.cell, f.path) for cell in cells for f in cell.files]
    report = write_imported_report(out / REPORT_NAME, analysis, files, what)
    lines = closed_lines(analysis, None, what)
    lines += [f"{cell.cell}: {len(cell.runs)} runs from {', '.join(f.path for f in cell.files)}" for cell in cells]
    lines.append(f"wrote {csv_path}, {json_path} and {report}")
    return lines, analysis.null is None or analysis.null.passed is not False
