"""`drivedegrade closed-loop import` end to end (SPEC section 13, "CARLA"): leaderboard results files read into
cells (`closedloop.carla_import`), put through the closed-loop analysis the plugin's cells go through
(`scoring.closed_loop.analyse_runs`: retention with bounds, axes, the verdict at every corner of the bounds, the
separation under every assignment of the unscored runs), and written as closed_loop.csv, closed_loop_summary.json
(per cell, and under "closed_loop" the analysis as a certificate's section holds it) and report.html (the
closed-loop section), with the plugin's terminal lines.

CARLA is not deterministic, so its null control is never "identical": it is "wander" mode with
`closed-blackout-s3` (the rear views a front-camera agent never reads) as the null; its distance from clean is
the wander, and a cell whose bounds overlap the null's band is "not separable from the null".
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from ..atomic import atomic_write_text
from ..closedloop.analysis import CLEAN, NULL
from ..closedloop.carla_import import CSV_NAME, SUMMARY_NAME, ImportedCell, csv_text, gather, run_lists, summary
from ..constants import DEFAULT_FLAT
from ..errors import DataError
from ..scoring.closed_loop import ClosedAnalysis, analyse_runs
from .closed_html import write_imported_report
from .closed_outputs import closed_lines

REPORT_NAME = "report.html"


def analyse_import(cells: Sequence[ImportedCell], flat: float = DEFAULT_FLAT) -> ClosedAnalysis:
    """The closed-loop analysis of imported cells; DataError when clean is missing (retention is over clean)."""
    runs = run_lists(cells)
    if CLEAN not in runs:
        raise DataError(f"closed-loop import: no clean cell among {', '.join(runs)}: retention is a cell's DS over "
                        "clean's, so give the clean run's results file too (clean=FILE)")
    return analyse_runs(runs, reads_rear=True, null_runs=runs.get(NULL, ()), flat=flat)


def import_results(sources: Sequence[str], out: Path, flat: float = DEFAULT_FLAT) -> list[str]:
    """Read the sources, analyse them, write the CSV, the summary and report.html into `out`; the lines to
    print (the plugin's closed-loop summary, then where the cells came from and what was written)."""
    cells = gather(sources)
    analysis = analyse_import(cells, flat)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = atomic_write_text(out / CSV_NAME, csv_text(cells))
    data = {**summary(cells), "closed_loop": analysis.figures()}
    json_path = atomic_write_text(out / SUMMARY_NAME, json.dumps(data, indent=2, sort_keys=True) + "\n")
    files = [(cell.cell, f.path) for cell in cells for f in cell.files]
    report = write_imported_report(out / REPORT_NAME, analysis, files)
    lines = closed_lines(analysis, None)
    lines += [f"{cell.cell}: {len(cell.runs)} runs from {', '.join(f.path for f in cell.files)}" for cell in cells]
    lines.append(f"wrote {csv_path}, {json_path} and {report}")
    return lines
