"""The closed loop's outputs (SPEC section 13): ``closed_loop.csv`` (one row per run), the terminal lines, and the
files of a run that drove closed cells only (its certificate, csv and report)."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import TYPE_CHECKING

from ..atomic import atomic_write_text
from ..certificate.closed import ClosedRun
from ..closedloop.analysis import RunRow
from ..scoring.closed_loop import ClosedAnalysis
from ..scoring.verdict import VERDICT_LABELS

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    from ..certificate.seal import Provenance

#: Infraction kinds closed_loop.csv counts, a column each (off_road: runs of spec-4 records).
CSV_KINDS = ("collision_pedestrian", "collision_vehicle", "collision_static", "off_road", "outside_route_lanes",
             "min_speed", "red_light")
#: closed_loop.csv's columns: the run, its score, why it ended, its infractions by kind, its path.
CSV_COLUMNS = ("planner", "cell", "family", "severity", "route", "seed", "ds", "completion", "end", "steps",
               *CSV_KINDS, "trace_digest", "error")


def _num(value: float | None) -> str:
    return "" if value is None else f"{value:.6f}"


def closed_csv_text(planner: str, run: ClosedRun) -> str:
    """One row per run, cells in selection order, runs in run order (the same text on any worker layout)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for cell, record in run.records.items():
        for r in record.runs:
            row = RunRow.of(r)
            kinds = [row.infractions.get(k, 0) for k in CSV_KINDS]
            writer.writerow([planner, cell, record.family, record.severity, r.route, r.seed, _num(r.ds),
                             _num(r.completion), row.end, r.steps, *kinds, row.trace, r.error])
    return out.getvalue()


def write_closed_csv(folder: Path, planner: str, run: ClosedRun) -> Path:
    return atomic_write_text(folder / "closed_loop.csv", closed_csv_text(planner, run))


def _fmt(value: float | None, digits: int = 1) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _agreement(agrees: bool | None) -> str:
    """The closed verdict against the open one: yes, no, or why they were not compared (not Python's None)."""
    if agrees is None:
        return "not compared: no open-loop verdict (a closed-only run)"
    return "yes" if agrees else "no"


def closed_lines(analysis: ClosedAnalysis, run: ClosedRun | None, imported_null: str = "blackout S3") -> list[str]:
    """The terminal summary of the closed cells: one line per cell, the null control, the verdict (`run` None:
    runs imported from CARLA, whose null control is `imported_null` against clean)."""
    lines = ["closed loop: cell: DS mean (std) [bounds], completion, retention [bounds], infractions"]
    for c in analysis.cells:
        low, high = c.bounds
        kinds = ", ".join(f"{k} {v}" for k, v in c.infractions.items()) or "none"
        lines.append(f"  {c.cell}: DS {_fmt(c.mean)} ({_fmt(c.std)}) [{_fmt(low)}, {_fmt(high)}], completion "
                     f"{_fmt(c.completion, 3)}, retention {_fmt(c.retention, 3)} [{_fmt(c.retention_low, 3)}, "
                     f"{_fmt(c.retention_high, 3)}], {c.unscored} of {len(c.rows)} unscored; {kinds}"
                     + ("; not separable from the null" if c.separable_from_null is False else ""))
    from .closed_html import swap_text

    swap = swap_text(analysis)
    lines += [f"  {swap}"] if swap else []
    null = analysis.null
    if null is not None and null.mode == "identical":
        how = "bit for bit" if run is not None else "DS and end alike (the simulator keeps the traces)"
        where = f"parts from clean at step {null.first_step}" if null.first_step is not None else "differs from clean"
        lines.append(f"closed null control: blackout S3 reproduces clean run for run, {how}" if null.passed else
                     f"closed null control FAILED: route {null.first_route} (seed {null.first_seed}) {where}")
    elif null is not None:
        what = "the planner reads a rear camera; a clean rerun" if run is not None else \
            "the agent reads a rear camera; a clean rerun against clean" if imported_null == "a clean rerun" else \
            f"the simulator is not deterministic; {imported_null} against clean"
        band = null.band or (None, None)
        lines.append(f"closed null control: {what} wanders by {_fmt(null.wander, 3)} DS (null bounds "
                     f"[{_fmt(null.low)}, {_fmt(null.high)}]); null band of its paired route differences "
                     f"[{_fmt(band[0])}, {_fmt(band[1])}] DS")
    sep = analysis.separation
    lines.append(f"closed-loop verdict: {analysis.label}" + (f" ({analysis.reason})" if analysis.reason else "")
                 + ("" if analysis.robust or analysis.label not in VERDICT_LABELS else
                    f" (not robust: the bounds and route intervals allow {', '.join(sorted(set(analysis.labels)))})")
                 +
                 f"; availability-vs-quality separation {sep.get('holds')}, under every assignment of the unscored "
                 f"runs {sep.get('holds_under_every_assignment')}; agrees with the open loop: "
                 f"{_agreement(analysis.agrees)}")
    if run is not None and run.missing:
        lines.append(f"closed loop: missing cells ({len(run.missing)}): {', '.join(run.missing)}")
    return lines


def publish_closed_only(report_dir: Path, prov: Provenance, run: ClosedRun, flat: float, *,
                        signing_key: Ed25519PrivateKey | None = None, isolated: bool = False) \
        -> tuple[dict[str, object], list[str]]:
    """A run of closed cells only: its certificate (signed when a key is given), closed_loop.csv and report.html;
    (the sealed certificate, the terminal lines)."""
    from ..certificate.closed import closed_only_certificate
    from ..certificate.seal import seal, write_certificate
    from .closed_html import write_closed_report

    folder = Path(report_dir) / prov.planner_name
    cert = closed_only_certificate(prov, run, flat, isolated=isolated)
    if signing_key is not None:
        from ..certificate.signing import sign

        cert = sign(cert, signing_key)
    cert = seal(cert)
    write_certificate(folder / "certificate.json", cert)
    write_closed_csv(folder, prov.planner_name, run)
    analysis = run.analysis(None, flat)
    write_closed_report(folder / "report.html", prov.planner_name, analysis, run, digest=str(cert["digest"]))
    return cert, [*closed_lines(analysis, run), f"wrote {folder / 'report.html'}, closed_loop.csv and "
                                                "certificate.json"]
