"""`drivedegrade analyse TABLE --out DIR` end to end: a per-cell table (`foreign.table`) read into cell records
(`foreign.records`), put through the analysis the plugin's runs go through (`scoring.analyse.analyse_run`:
retention, thresholds, axes, verdict, floor; intervals from the per-frame files where every cell has one), and
written per model as ``<out>/<model>/`` cells.csv, report.html and a sealed certificate.json whose
``provenance`` says what it proves: ``imported: metrics as given, arithmetic recomputed, plans not seen``.

`verify` checks such a certificate's arithmetic as any other's; `reproduce` refuses it (no plans to rerun
against); `compare` compares it and marks it imported. Where the table gives a figure the suite also computes
(a retention beside its metric, a row's figure beside its per-frame file's mean), the two are compared within
the rounding of the given figures and each disagreement is a note, in the terminal lines and the certificate.
"""

from __future__ import annotations

import hashlib
import html
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from ..certificate.fields import IMPORTED_KIND, IMPORTED_TEXT
from ..certificate.seal import Provenance
from ..constants import DEFAULT_FLAT
from ..errors import DataError
from ..foreign.records import ModelCells, model_cells
from ..foreign.table import RETENTION_OF, Table, Value, read_table
from ..scoring.records import Builtins, RunAnalysis, format_value

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

#: The figures the analysis puts beside a table's, for the agreement notes: table column -> summary key.
_COMPARED = {"retention": "retention", "pdms_retention": "pdms_retention", "epdms_retention": "epdms_retention",
             "pdms": "pdms", "epdms": "epdms"}
RESAMPLES = 1000


@dataclass
class ImportedRun:
    """One model's analysis of an imported table, its provenance and the notes on it."""

    cells: ModelCells
    analysis: RunAnalysis
    provenance: Provenance
    notes: list[str] = field(default_factory=list)


def choose_metric(mc: ModelCells, asked: str | None) -> str:
    """The figure the verdict is put on: `asked`, else L2 when clean has it, else PDMS, else EPDMS."""
    if asked is not None:
        return asked
    clean = mc.given.get("clean", set())
    if f"l2_avg_{mc.convention}" in clean:
        return "l2"
    return "pdms" if "pdms" in clean else "epdms" if "epdms" in clean else "l2"


def blank_not_given(analysis: RunAnalysis, mc: ModelCells) -> None:
    """Each summary's horizon metrics, jerk and sub-scores the table did not give set to NaN (the records hold
    stand-ins there), the frames set to the table's count (0: not given), and no cell marked (in)separable from
    the null: without plans there is no null wander."""
    from ..foreign.table import METRIC_COLUMNS

    for s in analysis.summaries:
        given = mc.given.get(s.cell, set())
        for key in METRIC_COLUMNS:
            if key in s.metrics and key not in given:
                s.metrics[key] = math.nan
        for key in ("endpoint_shift", "energy"):
            s.metrics[key] = math.nan
        s.separable_from_null = None
        if not mc.per_frame:
            row = mc.rows[s.cell][0]
            s.frames = int(row.frames) if row.frames is not None else 0


def agreement_notes(analysis: RunAnalysis, mc: ModelCells) -> list[str]:
    """Each given figure the analysis recomputes (a retention beside its metric, a row's figure beside its
    per-frame file's mean) that differs from it by more than its own rounding plus 1e-9: 'beyond the rounding'
    when the rounding of the figures it is computed from cannot explain it either, else 'within the rounding of
    the inputs' (consistent with the printed figures, and not checkable further from them)."""
    notes = []
    by_cell = {s.cell: s for s in analysis.summaries}
    for cell, rows in mc.rows.items():
        s = by_cell.get(cell)
        if s is None or len(rows) > 1:
            continue
        for col, key in (*_COMPARED.items(), *((c, c) for c in _row_figures(mc))):
            given = rows[0].values.get(col)
            if given is None or (col in RETENTION_OF and RETENTION_OF[col][0] not in _have(mc, cell)):
                continue
            got = s.retention if key == "retention" else s.metrics.get(key, math.nan)
            off = abs(got - given.value)
            if not math.isfinite(got) or off <= given.half_unit + 1e-9:
                continue
            spread = _input_rounding(mc, cell, col, got)
            how = (f"within the rounding of the figures it is computed from (+-{spread:.2g}): consistent with them, "
                   "not checkable further" if off <= given.half_unit + spread + 1e-9 else
                   f"beyond the rounding of the given figures (+-{given.half_unit:g}) and of those it is computed "
                   f"from (+-{spread:.2g})")
            notes.append(f"{cell}: {col} given {given.value:g}, the suite computes {got:.6f} from the table's "
                         f"figures: {how}")
    return notes


def _input_rounding(mc: ModelCells, cell: str, col: str, value: float) -> float:
    """How far a retention recomputed from printed figures can move within their rounding: r (h_a / a + h_b / b)
    for a ratio of a cell's and clean's figures (0 for a figure that is not a retention, or from per-frame files)."""
    if col not in RETENTION_OF or mc.per_frame:
        return 0.0
    metric = RETENTION_OF[col][0]
    name = f"l2_avg_{mc.convention}" if metric == "l2_avg" else metric
    total = 0.0
    for c in (cell, "clean"):
        row = mc.rows[c][0]
        cols = [name] if name in row.values else [f"l2_{h}s_{mc.convention}" for h in (1, 2, 3)]
        got = [row.values[k] for k in cols if k in row.values]
        if got:
            mean = math.fsum(v.value for v in got) / len(got)
            total += max(v.half_unit for v in got) / mean if mean > 0 else 0.0
    return abs(value) * total


def _row_figures(mc: ModelCells) -> tuple[str, ...]:
    """The row figures checked against the per-frame files' means (none without per-frame files)."""
    if not mc.per_frame:
        return ()
    return (f"l2_avg_{mc.convention}", "jerk", "nc", "dac", "ttc", "ep", "comfort", "ddc", "tlc", "lk", "hc", "ec")


def _have(mc: ModelCells, cell: str) -> set[str]:
    """Which metrics a cell's row gave itself (so its retention can be checked against them)."""
    got = mc.given.get(cell, set())
    derived = {d.split(": ", 1)[1].split(" from ")[0] for d in mc.derived if d.startswith(f"{cell} ")}
    out = {"l2_avg" if k == f"l2_avg_{mc.convention}" else k for k in got}
    return out - {"l2_avg" if d.startswith("l2_avg") else d for d in derived}


def identical_null(analysis: RunAnalysis, mc: ModelCells) -> None:
    """``--null-identical``: the null cell (the table's ``null`` row, else blackout S3: the rear views a
    front-only model never reads) must give every figure clean gives, equal; a difference fails the null control
    and makes the verdict undetermined, as the plugin's bit-identity check does with plans. DataError when the
    table has neither row."""
    from ..scoring.records import NullControl
    from ..scoring.verdict import undetermined_by_null_control

    null_cell = "null" if "null" in mc.rows else "blackout-s3"

    if null_cell not in mc.rows:
        raise DataError(f"--null-identical: model {mc.model!r} has no null or blackout-s3 row to compare with clean")
    clean, null = mc.rows["clean"][0].values, mc.rows[null_cell][0].values
    shared = sorted(set(clean) & set(null))
    if not shared:
        raise DataError(f"--null-identical: model {mc.model!r}: {null_cell} and clean give no figure in common")
    differ = [(k, null[k], clean[k]) for k in shared if null[k].value != clean[k].value]
    nc = NullControl(passed=not differ, max_abs_diff=max((abs(a.value - b.value) for _, a, b in differ), default=0.0),
                     max_l2_change=0.0, frames_changed=int(bool(differ)), frames_compared=1)
    analysis.null_control = nc
    if differ:
        what = ", ".join(f"{k} {_printed(a)} against clean's {_printed(b)}" for k, a, b in differ)
        reason = (f"the null control failed: {null_cell}, which the model cannot tell from clean, gives other "
                  f"figures ({what})")
        v = undetermined_by_null_control(analysis.verdict, nc)
        analysis.verdict = replace(v, reason=reason, text=f"Undetermined: {reason}. The axes give "
                                   f"{v.computed_label}, but a verdict is not sealed on figures that move with no "
                                   "corruption the model can see.")


def _printed(v: Value) -> str:
    """A given figure as it was printed (its decimals recovered from its rounding)."""
    return f"{v.value:.{max(0, round(-math.log10(2 * v.half_unit)))}f}"


def fingerprint(table: Table, model: str) -> str:
    """The model's fingerprint: a digest of its rows' given figures (what it was certified on)."""
    rows = [(r.cell, r.seed, r.frames, sorted((k, v.value) for k, v in r.values.items())) for r in table.of(model)]
    return "imported-" + hashlib.sha256(json.dumps(rows, sort_keys=True).encode()).hexdigest()


def analyse_model(table: Table, model: str, *, convention: str | None = None, flat: float = DEFAULT_FLAT,
                  metric: str | None = None, floor_l2: float | None = None, seed: int = 0,
                  split: str = "as given", null_identical: bool = False) -> ImportedRun:
    """One model's imported analysis (the module docstring)."""
    from ..corruptions.ladder import SPEC_VERSION
    from ..scoring.analyse import analyse_run

    if not 0.0 <= flat <= 1.0:
        raise DataError(f"--flat {flat}: a retention between 0 and 1")
    mc = model_cells(table, model, convention)
    n_seeds = max(len(runs) for runs in mc.rows.values())
    analysis = analyse_run(mc.records.values(), convention=mc.convention, flat=flat, seed=seed,
                           n_resamples=RESAMPLES if mc.per_frame else 0, intervals=mc.per_frame,
                           metric=choose_metric(mc, metric), floor_l2=floor_l2, seeds=n_seeds)
    analysis.null_control = None
    if null_identical:
        identical_null(analysis, mc)
    blank_not_given(analysis, mc)
    analysis.settings["seed_values"] = sorted({r.seed for runs in mc.rows.values() for r in runs})
    clean = mc.rows["clean"][0]
    frames = len(mc.records["clean"].frames) if mc.per_frame else (clean.frames or 0)
    prov = Provenance(planner_name=model, planner_fingerprint=fingerprint(table, model),
                      dataset_fingerprint="imported-" + hashlib.sha256(f"{table.sha256}|{split}".encode()).hexdigest(),
                      split=split, spec_version=SPEC_VERSION, seed=seed, frames=frames, frames_unscored=None,
                      data_source=str(table.path), command=f"drivedegrade analyse {table.path}",
                      tool_version=_tool_version())
    return ImportedRun(mc, analysis, prov, agreement_notes(analysis, mc))


def _tool_version() -> str:
    from .. import __version__

    return str(__version__)


def provenance_section(table: Table, run: ImportedRun) -> Builtins:
    """The certificate's ``provenance``: what it proves and where the figures came from."""
    return {"kind": IMPORTED_KIND, "statement": IMPORTED_TEXT, "table": str(table.path),
            "table_sha256": table.sha256, "rows": len(table.of(run.provenance.planner_name)),
            "convention": run.cells.convention, "per_frame": run.cells.per_frame,
            "intervals": "paired frame bootstrap of the per-frame files" if run.cells.per_frame else
            "none: the table gives per-cell figures only",
            "derived": list(run.cells.derived), "notes": list(run.notes), "ignored_columns": list(table.ignored)}


def folder_name(model: str) -> str:
    """A model's output folder name: its name with anything but letters, digits, dot, dash and underscore as _."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", model).strip("_") or "model"


def imported_fragment(table: Table, run: ImportedRun) -> str:
    """The report's section saying what an imported certificate is (after the plugin's sections)."""
    items = "".join(f"<li>{html.escape(x)}</li>" for x in [*run.cells.derived, *run.notes])
    intervals = "paired frame bootstrap of the per-frame files" if run.cells.per_frame else "none (per-cell figures)"
    return (f"<section><h2>Imported results</h2><p><strong>{html.escape(IMPORTED_TEXT)}.</strong> Figures from "
            f"<code>{html.escape(str(table.path))}</code> (sha256 {table.sha256[:16]}...), L2 under the "
            f"{html.escape(run.cells.convention)} convention; intervals: {intervals}. The trajectories, the null "
            "control on plans and the montage need the plans and images, which the table does not carry.</p>"
            f"{'<ul>' + items + '</ul>' if items else ''}</section>")


def write_model(table: Table, run: ImportedRun, out: Path,
                signing_key: Ed25519PrivateKey | None = None) -> tuple[Builtins, Path]:
    """cells.csv, report.html and certificate.json of one model in ``out/<model>/``, written as one set."""
    from ..atomic import atomic_write_set
    from ..certificate.seal import build_certificate, certificate_text, seal
    from .cells_csv import cells_csv_text
    from .html import render_report

    folder = out / folder_name(run.provenance.planner_name)
    cert = build_certificate(run.analysis, run.provenance)
    cert["provenance"] = provenance_section(table, run)
    cert["completeness"] = {"complete": True, "missing_cells": []}
    if signing_key is not None:
        from ..certificate.signing import sign

        cert = sign(cert, signing_key)
    cert = seal(cert)
    page = render_report(run.analysis, replace(run.provenance), created=cert.get("created", ""),
                         digest=cert["digest"], closed_html=imported_fragment(table, run),
                         signed_by=str((cert.get("signature") or {}).get("public_key_fingerprint", "")))
    atomic_write_set({folder / "cells.csv": cells_csv_text(run.analysis, run.provenance).encode("utf-8"),
                      folder / "report.html": page.encode("utf-8"),
                      folder / "certificate.json": certificate_text(cert).encode("utf-8")})
    return cert, folder


def summary_line(run: ImportedRun, folder: Path) -> str:
    """One terminal line per model: the verdict, the axes and where the outputs went."""
    a, v = run.analysis, run.analysis.verdict
    axes = {"pdms": a.axes_pdms, "epdms": a.axes_epdms}.get(v.metric) or a.axes
    flag = (" NEGATIVE GAP" if v.negative_gap else "") + (f" (axes: {v.computed_label})"
                                                          if v.label != v.computed_label else "")
    return (f"{run.provenance.planner_name}: {v.label}{flag} (on {v.metric}: quality {format_value(axes.quality)}, "
            f"removal {format_value(axes.removal)}, gap {format_value(axes.gap)}, mean {format_value(axes.mean)}); "
            f"wrote {folder}/cells.csv, report.html and certificate.json ({IMPORTED_TEXT})")


def floor_of(table: Table, floor: str | None, floor_l2: float | None, convention: str | None) -> float | None:
    """The floor's clean L2: `floor_l2`, or the clean l2_avg of the model `floor` names in the table."""
    if floor is None:
        return floor_l2
    if floor_l2 is not None:
        raise DataError("--floor and --floor-l2: give one")
    if floor not in table.models():
        raise DataError(f"--floor {floor!r}: no such model in {table.path} (models: {', '.join(table.models())})")
    mc = model_cells(table, floor, convention)
    from ..scoring.records import finite_mean

    value = finite_mean(mc.records["clean"].l2_avg_per_frame(mc.convention))
    if not math.isfinite(value):
        raise DataError(f"--floor {floor!r}: its clean row gives no L2 under the {mc.convention} convention")
    return value


def analyse_table(path: str | Path, out: str | Path, *, convention: str | None = None, flat: float = DEFAULT_FLAT,
                  metric: str | None = None, floor: str | None = None, floor_l2: float | None = None,
                  models: Sequence[str] = (), split: str = "as given", null_identical: bool = False,
                  signing_key: Ed25519PrivateKey | None = None) -> list[str]:
    """Analyse every model of the table (or those `models` names) into `out`; the terminal lines."""
    table = read_table(path)
    chosen = list(models) or table.models()
    unknown = [m for m in chosen if m not in table.models()]
    if unknown:
        raise DataError(f"--model {unknown[0]!r}: no such model in {table.path} (models: "
                        f"{', '.join(table.models())})")
    folders: dict[str, str] = {}
    for model in chosen:
        other = folders.setdefault(folder_name(model), model)
        if other != model:
            raise DataError(f"models {other!r} and {model!r} would share the output folder {folder_name(model)}: "
                            "rename one in the table")
    base = floor_of(table, floor, floor_l2, convention)
    lines = [f"analyse: {table.path}: {len(table.rows)} rows, {len(chosen)} model(s)"
             + (f"; ignored columns: {', '.join(table.ignored)}" if table.ignored else "")]
    for model in chosen:
        run = analyse_model(table, model, convention=convention, flat=flat, metric=metric,
                            floor_l2=None if model == floor else base, split=split, null_identical=null_identical)
        _, folder = write_model(table, run, Path(out), signing_key)
        lines.append(summary_line(run, folder))
        lines += detail_lines(run)
    return lines


def detail_lines(run: ImportedRun) -> list[str]:
    """What the terminal says under a model's line: the figures derived from a given retention (counted), the
    null control when one was checked, and every agreement note."""
    lines = []
    if run.cells.derived:
        cells = [d.split(" (seed")[0] for d in run.cells.derived]
        lines.append(f"  derived from a given retention: {len(cells)} figure(s) ({', '.join(cells[:4])}"
                     f"{', ...' if len(cells) > 4 else ''}); the certificate lists each")
    nc = run.analysis.null_control
    if nc is not None:
        lines.append("  null control (against clean): " + (
            "passed, every figure equal" if nc.passed else
            f"FAILED: {str(run.analysis.verdict.reason).removeprefix('the null control failed: ')}"))
    return lines + [f"  NOTE: {n}" for n in run.notes]
