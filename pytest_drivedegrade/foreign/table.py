"""The per-cell table (`docs/how-to/foreign-evaluator.md`): what a model's own evaluator computed, one row per
(model, cell, seed), read and checked here, with an error naming the file, the row, the column and what to do.

Columns (a header row; ``#`` lines are comments; an empty value, ``-``, ``--``, ``n/a`` or ``nan`` is "not
given"):

- ``model`` (required; ``planner`` is read when there is no ``model``, so a suite's cells.csv is a table) and
  ``cell`` (``clean``, ``blind``, ``gaussian_blur-s3``, ...) or ``family`` and ``severity``; ``seed`` (default
  0), ``frames`` (the frames the figures average over), ``frames_file`` (a per-frame CSV of this cell, relative
  to the table: ``frame`` and the same metric columns), ``note``.
- L2 under a named convention, as the suite's cells.csv names it: ``l2_1s_stp3``, ``l2_2s_stp3``,
  ``l2_3s_stp3`` and/or ``l2_avg_stp3`` (``_uniad`` for the at-the-horizon convention); collision rates
  (fractions 0..1) ``collision_1s_stp3`` ... and ``vru_1s_stp3`` ...; ``jerk``.
- PDMS and its sub-scores ``pdms, nc, dac, ttc, ep, comfort``; EPDMS ``epdms, ddc, tlc, lk, hc, ec`` (0..1).
- Retention where the source gives only that: ``retention`` (L2), ``pdms_retention``, ``epdms_retention``;
  the metric is then clean's times (reward) or over (error) the retention, and the outputs say it was derived.
"""

from __future__ import annotations

import csv
import difflib
import hashlib
import io
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..cells import DIAGNOSTIC, cell_id
from ..constants import EGO_BLIND, EGO_NOISE, REPORT_HORIZONS_S
from ..corruptions.ladder import FAMILIES
from ..errors import DataError
from ..metrics.trajectory import CONVENTIONS

KEY_COLUMNS: tuple[str, ...] = ("model", "cell", "family", "severity", "seed", "frames", "frames_file", "note")
PDMS_COLUMNS: tuple[str, ...] = ("pdms", "nc", "dac", "ttc", "ep", "comfort")
EPDMS_COLUMNS: tuple[str, ...] = ("epdms", "ddc", "tlc", "lk", "hc", "ec")
RETENTION_COLUMNS: tuple[str, ...] = ("retention", "pdms_retention", "epdms_retention")
#: The metric a given retention stands for, and whether it is an error (clean / cell) or a reward (cell / clean).
RETENTION_OF: dict[str, tuple[str, str]] = {"retention": ("l2_avg", "error"), "pdms_retention": ("pdms", "reward"),
                                            "epdms_retention": ("epdms", "reward")}
HORIZON_KINDS: tuple[str, ...] = ("l2", "collision", "vru")


def horizon_columns(kind: str, convention: str) -> tuple[str, ...]:
    """``<kind>_1s_<convention>``, ``_2s_``, ``_3s_``: the columns of one horizon metric under one convention."""
    return tuple(f"{kind}_{h}s_{convention}" for h in REPORT_HORIZONS_S)


#: Every per-frame metric column a table (or a per-frame file) may carry.
METRIC_COLUMNS: tuple[str, ...] = (
    *(c for conv in CONVENTIONS for kind in HORIZON_KINDS for c in horizon_columns(kind, conv)),
    *(f"l2_avg_{conv}" for conv in CONVENTIONS), "jerk", *PDMS_COLUMNS, *EPDMS_COLUMNS)
#: Metrics on 0..1 (a rate or a score), and what to do when a value is a percentage.
UNIT_COLUMNS: frozenset[str] = frozenset(
    {*(c for conv in CONVENTIONS for kind in ("collision", "vru") for c in horizon_columns(kind, conv)),
     *PDMS_COLUMNS, *EPDMS_COLUMNS})
_MISSING = frozenset({"", "-", "--", "n/a", "na", "nan", "none", "null"})
_CELL = re.compile(r"^(?P<family>[a-z_]+)-s(?P<severity>[0-9]+)$")


@dataclass(frozen=True)
class Value:
    """One given number and the half unit of its last printed decimal (the rounding it carries)."""

    value: float
    half_unit: float


@dataclass(frozen=True)
class Row:
    """One table row: where it is (`where`: file and line), its cell and seed and its given figures."""

    where: str
    model: str
    cell: str
    family: str
    severity: int
    seed: int
    frames: int | None
    frames_file: Path | None
    note: str
    values: Mapping[str, Value] = field(default_factory=dict)

    def get(self, name: str) -> float | None:
        got = self.values.get(name)
        return None if got is None else got.value


@dataclass(frozen=True)
class Table:
    """A read table: its rows in file order, its path and digest, and the columns it ignored."""

    path: Path
    sha256: str
    rows: tuple[Row, ...]
    ignored: tuple[str, ...] = ()

    def models(self) -> list[str]:
        return list(dict.fromkeys(r.model for r in self.rows))

    def of(self, model: str) -> list[Row]:
        return [r for r in self.rows if r.model == model]


def parse_number(text: str, where: str, column: str) -> Value | None:
    """A given number with its rounding; None when not given; DataError naming the place otherwise."""
    raw = text.strip()
    if raw.lower() in _MISSING:
        return None
    try:
        value = float(raw)
    except ValueError:
        raise DataError(f"{where}: column {column}: {raw!r} is not a number: give a number (a dot for the "
                        "decimal point) or leave it empty") from None
    if not math.isfinite(value):
        raise DataError(f"{where}: column {column}: {raw!r} is not a finite number: leave it empty when not given")
    mantissa = raw.lower().split("e")[0]
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    exponent = int(raw.lower().split("e")[1]) if "e" in raw.lower() else 0
    return Value(value, 0.5 * 10.0 ** (exponent - decimals))


def check_range(name: str, value: float, where: str) -> None:
    """A metric out of its range is a DataError saying what the column holds."""
    if name in UNIT_COLUMNS and not 0.0 <= value <= 1.0:
        hint = " (a percentage? divide by 100)" if 1.0 < value <= 100.0 else ""
        raise DataError(f"{where}: column {name}: {value:g} is outside 0..1: rates and scores are fractions{hint}")
    if name in RETENTION_COLUMNS and value <= 0.0:
        raise DataError(f"{where}: column {name}: {value:g}: a retention is a positive ratio (1.0 = no damage)")
    if name not in UNIT_COLUMNS and value < 0.0:
        raise DataError(f"{where}: column {name}: {value:g} is negative: L2 and jerk are non-negative")


def resolve_cell(cell: str, family: str, severity: str, where: str) -> tuple[str, str, int]:
    """(cell id, family, severity) from a ``cell`` and/or ``family`` + ``severity``; DataError when unknown or
    when the two disagree."""
    known = (*DIAGNOSTIC, *FAMILIES, EGO_NOISE, EGO_BLIND)
    if cell:
        m = _CELL.match(cell)
        fam, sev = (m.group("family"), int(m.group("severity"))) if m else (cell, 0)
        if family and family != fam or severity and _integer(severity, where, "severity") != sev:
            raise DataError(f"{where}: cell {cell!r} disagrees with family {family!r} / severity {severity!r}: "
                            "give one of the two, or make them agree")
    elif family:
        fam, sev = family, _integer(severity, where, "severity") if severity else 0
    else:
        raise DataError(f"{where}: no cell: give a cell (clean, gaussian_blur-s3, ...) or a family and a severity")
    if fam not in known:
        close = difflib.get_close_matches(fam, known, n=1)
        raise DataError(f"{where}: unknown family {fam!r}" + (f" (did you mean {close[0]!r}?)" if close else "")
                        + f": one of {', '.join(known)}")
    ladder = fam in FAMILIES or fam == EGO_NOISE
    if ladder and not 1 <= sev <= 5 or not ladder and sev != 0:
        raise DataError(f"{where}: {fam} at severity {sev}: ladder families run at 1..5, {', '.join(DIAGNOSTIC)} "
                        f"and {EGO_BLIND} at 0")
    return cell_id(fam, sev), fam, sev


def _integer(text: str, where: str, column: str) -> int:
    try:
        return int(text.strip())
    except ValueError:
        raise DataError(f"{where}: column {column}: {text.strip()!r} is not a whole number") from None


#: Columns only the suite's own cells.csv carries (its provenance): a table with them is one the suite wrote.
SUITE_MARKS = ("planner_fingerprint", "dataset_fingerprint", "spec_version")


def _ignored(header: Sequence[str], where: str) -> list[str]:
    """Columns the table has that no reader takes: ignored when they are no near miss of a known one (a
    suite's own cells.csv carries many), a DataError naming the column it probably meant otherwise."""
    known = (*KEY_COLUMNS, *METRIC_COLUMNS, *RETENTION_COLUMNS)
    suites = set(SUITE_MARKS) <= set(header)  # the suite's own cells.csv: its other columns are its own, no typos
    out = []
    for name in header:
        if name in known:
            continue
        close = None if suites else difflib.get_close_matches(name, known, n=1, cutoff=0.85)
        if close and not name.startswith(close[0]):
            raise DataError(f"{where}: column {name!r} is not one the table format knows; did you mean "
                            f"{close[0]!r}? (docs/how-to/foreign-evaluator.md lists the columns)")
        out.append(name)
    return out


def csv_rows(path: Path) -> tuple[list[str], list[tuple[int, dict[str, str]]]]:
    """The header and the (line number, row) pairs of a CSV file, ``#`` lines skipped; DataError when the file
    is missing, unreadable, empty or has a ragged row."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read it ({exc})") from None
    lines = [(n, line) for n, line in enumerate(text.splitlines(), 1) if line.strip() and
             not line.lstrip().startswith("#")]
    if not lines:
        raise DataError(f"{path}: empty: a header row and one row per (model, cell, seed) are expected")
    reader = csv.reader(io.StringIO("\n".join(line for _, line in lines)))
    parsed = list(reader)
    header = [h.strip() for h in parsed[0]]
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise DataError(f"{path}:{lines[0][0]}: column {dup!r} appears twice in the header")
    rows = []
    for (n, _), values in zip(lines[1:], parsed[1:]):
        if len(values) != len(header):
            raise DataError(f"{path}:{n}: {len(values)} values for {len(header)} columns: quote a value that "
                            "holds a comma")
        rows.append((n, dict(zip(header, values))))
    return header, rows


def read_values(raw: Mapping[str, str], where: str, columns: Sequence[str]) -> dict[str, Value]:
    """The given numbers of `columns` in one row, range-checked."""
    out = {}
    for name in columns:
        if name in raw:
            got = parse_number(raw[name], where, name)
            if got is not None:
                check_range(name, got.value, where)
                out[name] = got
    return out


def read_table(path: str | Path) -> Table:
    """Read and check a per-cell table (module docstring); DataError naming file, row and column otherwise."""
    path = Path(path)
    header, raw_rows = csv_rows(path)
    model_col = "model" if "model" in header else "planner"  # a suite's own cells.csv names it planner
    if model_col not in header:
        raise DataError(f"{path}: no model column: each row names the model it measured (one table may hold "
                        "several)")
    if "cell" not in header and "family" not in header:
        raise DataError(f"{path}: no cell column (nor family and severity): each row names its cell")
    ignored = _ignored(header, str(path))
    rows: list[Row] = []
    seen: dict[tuple[str, str, int], str] = {}
    for n, raw in raw_rows:
        where = f"{path}:{n}"
        model = raw.get(model_col, "").strip()
        if not model:
            raise DataError(f"{where}: column {model_col}: empty: name the model the row measured")
        cell, fam, sev = resolve_cell(raw.get("cell", "").strip(), raw.get("family", "").strip(),
                                      raw.get("severity", "").strip(), where)
        seed = _integer(raw["seed"], where, "seed") if raw.get("seed", "").strip() else 0
        key = (model, cell, seed)
        if key in seen:
            raise DataError(f"{where}: model {model!r}, cell {cell}, seed {seed} is also at {seen[key]}: one row per "
                            "(model, cell, seed)")
        seen[key] = where
        frames = _integer(raw["frames"], where, "frames") if raw.get("frames", "").strip() else None
        ffile = raw.get("frames_file", "").strip()
        rows.append(Row(where, model, cell, fam, sev, seed, frames, (path.parent / ffile) if ffile else None,
                        raw.get("note", "").strip(), read_values(raw, where, (*METRIC_COLUMNS, *RETENTION_COLUMNS))))
    if not rows:
        raise DataError(f"{path}: a header but no rows: one row per (model, cell, seed) is expected")
    return Table(path, hashlib.sha256(path.read_bytes()).hexdigest(), tuple(rows), tuple(ignored))


@dataclass(frozen=True)
class FrameFile:
    """A cell's per-frame figures: frame tokens in file order and each metric column's values (NaN: not given)."""

    path: Path
    frames: tuple[str, ...]
    columns: Mapping[str, tuple[float, ...]]


def read_frame_file(path: Path, where: str) -> FrameFile:
    """A per-frame CSV (``frame`` and metric columns); DataError naming the file, line and column otherwise."""
    if not path.is_file():
        raise DataError(f"{where}: frames_file {path}: no such file (the path is relative to the table's folder)")
    header, raw_rows = csv_rows(path)
    if "frame" not in header:
        raise DataError(f"{path}: no frame column: each row names its frame (sample token or file stem)")
    names = [c for c in header if c in METRIC_COLUMNS]
    if not names:
        raise DataError(f"{path}: no metric column ({', '.join(METRIC_COLUMNS[:4])}, ...)")
    frames: list[str] = []
    cols: dict[str, list[float]] = {c: [] for c in names}
    for n, raw in raw_rows:
        token = raw["frame"].strip()
        if not token or token in frames:
            raise DataError(f"{path}:{n}: frame {token!r} is empty or repeated: one row per frame")
        frames.append(token)
        got = read_values(raw, f"{path}:{n}", names)
        for c in names:
            cols[c].append(got[c].value if c in got else math.nan)
    return FrameFile(path, tuple(frames), {c: tuple(v) for c, v in cols.items()})
