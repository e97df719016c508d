"""A per-cell table's rows as the suite's cell records, so the one analysis (`scoring.analyse.analyse_run`) reads
them: each row's figures become per-frame arrays (one pseudo-frame per cell, or the frames of its per-frame
file) whose means under the table's L2 convention are exactly the given figures. Plans are not seen: they stay
NaN, and the null control, endpoint shift and energy are not computed.

L2 at 1/2/3 s under ``uniad`` (at the horizon) is the per-step array (v1, v1, v2, v2, v3, v3); under ``stp3`` (the
mean of the steps up to the horizon) it is (a, a, b, b, c, c) with a = v1, b = 2 v2 - v1, c = 3 v3 - 2 v2, whose
running means at 1, 2 and 3 s are v1, v2 and v3. Collision rates the same way. A given ``l2_avg`` alone fills
every step with it. A metric given only as a retention is clean's metric times (a reward) or over (an error)
that retention, and is listed as derived.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..cells import FRAME_ARRAYS, CellRecord
from ..constants import HORIZON_STEPS
from ..corruptions.ladder import FAMILIES
from ..errors import DataError
from ..metrics.trajectory import CONVENTIONS
from .table import (
    EPDMS_COLUMNS,
    PDMS_COLUMNS,
    RETENTION_OF,
    FrameFile,
    Row,
    Table,
    horizon_columns,
    read_frame_file,
)

#: The pseudo-frame of a cell given without per-frame figures.
TABLE_FRAME = "table"


def per_step(values: Sequence[float], convention: str) -> np.ndarray:
    """A (6,) per-step array whose 1/2/3 s aggregates under `convention` are `values` (see the module)."""
    v1, v2, v3 = (float(v) for v in values)
    pairs = (v1, v2, v3) if convention == "uniad" else (v1, 2.0 * v2 - v1, 3.0 * v3 - 2.0 * v2)
    return np.repeat(np.asarray(pairs, dtype=float), HORIZON_STEPS // 3)


@dataclass
class ModelCells:
    """One model's records by cell id, what its rows gave (`given`: output metric names per cell), the metrics
    derived from a retention (`derived`, as 'cell: metric from retention'), the rows by cell and seed, and
    whether per-frame figures were given (`per_frame`)."""

    model: str
    convention: str
    records: dict[str, CellRecord]
    given: dict[str, set[str]] = field(default_factory=dict)
    derived: list[str] = field(default_factory=list)
    rows: dict[str, list[Row]] = field(default_factory=dict)
    per_frame: bool = False


def choose_convention(rows: Sequence[Row], asked: str | None) -> str:
    """`asked` when given, else stp3 when any row gives stp3 L2, else uniad when one gives uniad L2, else stp3."""
    if asked is not None:
        if asked not in CONVENTIONS:
            raise DataError(f"--convention {asked}: one of {', '.join(CONVENTIONS)}")
        return asked
    for conv in CONVENTIONS:
        if any(any(c in r.values for c in (*horizon_columns("l2", conv), f"l2_avg_{conv}")) for r in rows):
            return conv
    return CONVENTIONS[0]


def _horizons(values: Mapping[str, float], kind: str, conv: str, where: str) -> list[float] | None:
    cols = horizon_columns(kind, conv)
    got = [values.get(c) for c in cols]
    if all(v is None for v in got):
        return None
    if any(v is None for v in got):
        raise DataError(f"{where}: {', '.join(c for c, v in zip(cols, got) if v is None)} not given while "
                        f"{', '.join(c for c, v in zip(cols, got) if v is not None)} is: give all three horizons "
                        "or none")
    return [float(v) for v in got if v is not None]


def frame_arrays(values: Mapping[str, float], conv: str, where: str) -> tuple[dict[str, float | np.ndarray], set[str]]:
    """One frame's arrays (by `FRAME_ARRAYS` name) from its figures, and the output metrics they give."""
    out: dict[str, float | np.ndarray] = {}
    given: set[str] = set()
    l2 = _horizons(values, "l2", conv, where)
    if l2 is not None:
        out["l2"] = per_step(l2, conv)
        given |= {*horizon_columns("l2", conv), f"l2_avg_{conv}"}
    elif values.get(f"l2_avg_{conv}") is not None:
        out["l2"] = np.full(HORIZON_STEPS, float(values[f"l2_avg_{conv}"]))
        given.add(f"l2_avg_{conv}")
    for kind, name in (("collision", "collision"), ("vru", "collision_vru")):
        got = _horizons(values, kind, conv, where)
        if got is not None:
            out[name] = per_step(got, conv)
            given |= set(horizon_columns(kind, conv))
    for name in ("jerk", *PDMS_COLUMNS, *EPDMS_COLUMNS):
        if values.get(name) is not None:
            out[name] = float(values[name])
            given.add(name)
    return out, given


def _derive(row_values: dict[str, float], clean: Mapping[str, float], conv: str, where: str) -> list[str]:
    """Fill a metric given only as a retention from clean's (in place); the names of those derived."""
    derived = []
    for col, (metric, kind) in RETENTION_OF.items():
        name = f"l2_avg_{conv}" if metric == "l2_avg" else metric
        r = row_values.get(col)
        has = row_values.get(name) is not None or (metric == "l2_avg" and row_values.get(f"l2_3s_{conv}") is not None)
        if r is None or has:
            continue
        base = clean.get(name)
        if base is None:
            raise DataError(f"{where}: {col} given without {name}, and clean has no {name} to apply it to: give "
                            f"clean's {name} (the retention is relative to it)")
        row_values[name] = base / r if kind == "error" else base * r
        derived.append(f"{name} from {col}")
    return derived


def _clean_average(clean: Row, conv: str) -> dict[str, float]:
    """Clean's figures a retention applies to: its L2 average (from the horizons when given), PDMS, EPDMS."""
    vals = {k: v.value for k, v in clean.values.items()}
    l2 = _horizons(vals, "l2", conv, clean.where)
    if l2 is not None:
        vals[f"l2_avg_{conv}"] = math.fsum(l2) / 3.0
    return vals


def _run_record(row: Row, frames: list[str], ff: FrameFile | None, conv: str,
                clean: Mapping[str, float]) -> tuple[CellRecord, set[str], list[str]]:
    """One (cell, seed) run's record, the metrics it gives and those derived from a retention."""
    n = len(frames)
    arrays = {a.name: a.empty(n) for a in FRAME_ARRAYS}
    vals = {k: v.value for k, v in row.values.items()}
    derived = [] if row.cell == "clean" else _derive(vals, clean, conv, row.where)
    if ff is None:
        got, given = frame_arrays(vals, conv, row.where)
        for name, value in got.items():
            arrays[name][0] = value
    else:
        given = set()
        order = {f: i for i, f in enumerate(ff.frames)}
        if set(order) != set(frames):
            extra, lacking = sorted(set(order) - set(frames)), sorted(set(frames) - set(order))
            raise DataError(f"{ff.path}: its frames differ from clean's ({len(lacking)} missing, e.g. "
                            f"{lacking[:2]}; {len(extra)} not in clean, e.g. {extra[:2]}): every cell of a model is "
                            "scored on the same frames")
        for i, token in enumerate(frames):
            j = order[token]
            got, g = frame_arrays({c: v[j] for c, v in ff.columns.items() if math.isfinite(v[j])}, conv,
                                  f"{ff.path} frame {token}")
            given |= g
            for name, value in got.items():
                arrays[name][i] = value
    record = CellRecord.of_arrays(row.cell, row.family, row.severity, frames, arrays)
    return record, given, [f"{row.cell} (seed {row.seed}): {d}" for d in derived]


def model_cells(table: Table, model: str, convention: str | None = None) -> ModelCells:
    """One model's rows as cell records (seed runs joined, in seed order); DataError for a model without a
    clean row, a deterministic cell under several seeds, or per-frame files on some cells only."""
    rows = table.of(model)
    by_cell: dict[str, list[Row]] = {}
    for r in rows:
        by_cell.setdefault(r.cell, []).append(r)
    if "clean" not in by_cell:
        raise DataError(f"{table.path}: model {model!r} has no clean row: retention is each cell against clean")
    for cell, runs in by_cell.items():
        fam = runs[0].family
        if len(runs) > 1 and not (fam in FAMILIES and FAMILIES[fam].random):
            raise DataError(f"{runs[1].where}: model {model!r}, cell {cell} under seeds "
                            f"{', '.join(str(r.seed) for r in runs)}: {fam} is deterministic, so the suite runs it "
                            "once: keep one row")
        runs.sort(key=lambda r: r.seed)
    with_file = [r for r in rows if r.frames_file is not None]
    if with_file and len(with_file) != len(rows):
        lacking = next(r for r in rows if r.frames_file is None)
        raise DataError(f"{lacking.where}: model {model!r} gives frames_file on {len(with_file)} of {len(rows)} "
                        "rows: give a per-frame file for every row of the model, or for none")
    conv = choose_convention(rows, convention)
    clean_row = by_cell["clean"][0]
    files = {id(r): read_frame_file(r.frames_file, r.where) for r in with_file if r.frames_file is not None}
    frames = list(files[id(clean_row)].frames) if with_file else [TABLE_FRAME]
    out = ModelCells(model, conv, {}, per_frame=bool(with_file), rows=by_cell)
    clean = _clean_average(clean_row, conv)
    for cell, runs in by_cell.items():
        recs = []
        given: set[str] = set()
        for r in runs:
            rec, g, d = _run_record(r, frames, files.get(id(r)), conv, clean)
            recs.append(rec)
            given |= g
            out.derived += d
        first = recs[0]
        if len(recs) > 1:
            first.seed_runs, first.seeds = recs[1:], [r.seed for r in runs]
        out.records[cell], out.given[cell] = first, given
    return out
