"""cells.csv: one row per cell with every metric, retention and its CI, and what makes the row traceable.

Written with the csv module (pandas is not needed to write a table). The columns come from `columns.CSV`
(names up to ``retention_ci_high`` are stable, SPEC section 6). Floats are rounded to six decimals like the
certificate; a missing or non-finite value is an empty field; booleans are ``true`` / ``false``.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Any

from ..atomic import atomic_write_text
from ..certificate.seal import DIGITS, Provenance
from ..constants import COMMAND_SWAP
from ..scoring.records import RunAnalysis
from .columns import CSV as CSV_COLUMNS

#: A spreadsheet reads a field starting with one of these as a formula (CSV injection), e.g. a planner name
#: ``=HYPERLINK(...)`` or a data path ``@SUM(...)``.
FORMULA_PREFIXES = ("=", "+", "-", "@")


def _neutralise(text: str) -> str:
    """A text field that a spreadsheet would run as a formula, with a leading apostrophe (numbers untouched)."""
    if not text.startswith(FORMULA_PREFIXES):
        return text
    try:
        float(text)
    except ValueError:
        return "'" + text
    return text


def _field(value: Any) -> str:
    """One CSV field: rounded floats, empty for missing / NaN, lower-case booleans, and text that would start a
    spreadsheet formula (=, +, -, @, unless it is a number) neutralised with a leading apostrophe."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(round(value, DIGITS) + 0.0) if math.isfinite(value) else ""
    if isinstance(value, int):
        return str(value)
    return _neutralise(str(value))


def cell_rows(analysis: RunAnalysis, provenance: Provenance) -> list[dict[str, str]]:
    """The CSV rows as string fields, in report order."""
    extra = {"planner": provenance.planner_name, "planner_fingerprint": provenance.planner_fingerprint,
             "dataset_fingerprint": provenance.dataset_fingerprint, "split": provenance.split,
             "spec_version": provenance.spec_version, "seed": provenance.seed,
             "convention": analysis.settings.get("convention", "")}
    command = command_columns(analysis)
    rows = ({**s.flat(), **extra, **(command if s.cell == COMMAND_SWAP else {})}  # each summary flattened once
            for s in analysis.summaries)
    return [{col: _field(row.get(col)) for col in CSV_COLUMNS} for row in rows]


def command_columns(analysis: RunAnalysis) -> dict[str, object]:
    """The command_swap row's following columns (`columns.COMMAND`); none when the cell did not run."""
    if analysis.command is None:
        return {}
    f = analysis.command.following
    return {"command_following": f.value, "command_following_ci_low": f.low, "command_following_ci_high": f.high,
            "command_label": f.label, "command_frames": f.frames, "junction_frames": analysis.command.junction_frames}


def cells_csv_text(analysis: RunAnalysis, provenance: Provenance) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(cell_rows(analysis, provenance))
    return buf.getvalue()


def write_cells_csv(path: str | os.PathLike[str], analysis: RunAnalysis, provenance: Provenance) -> Path:
    """Write cells.csv atomically."""
    return atomic_write_text(path, cells_csv_text(analysis, provenance))
