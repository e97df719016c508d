"""The report's closed-loop section (SPEC section 13): the DS table with bounds, a per-run strip plot per cell, and
bird's-eye traces of the routes where a degraded run parts most from clean (unscored runs dashed). A fragment for
report.html, or a page of its own for a run of closed cells only."""

from __future__ import annotations

import html
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_text
from ..certificate.closed import ClosedRun
from ..closedloop.analysis import SWAP_CELL
from ..closedloop.results import RunResult
from ..scoring.closed_loop import ClosedAnalysis
from .plots import ACCENT, INK, MUTED, _figure, _style, to_data_uri


def _f(value: float | None, digits: int = 1) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def strip_plot(analysis: ClosedAnalysis) -> str:
    """Each run's DS per cell (one row a cell); an unscored run is a hollow bar from 0 to 100 (any DS it could
    have had); the complete-case mean a tick."""
    cells = analysis.cells
    fig = _figure(7.0, 0.45 * len(cells) + 0.9)
    ax = fig.add_subplot(111)
    _style(ax)
    for y, c in enumerate(cells):
        ds = [r.ds for r in c.rows if r.ds is not None]
        jitter = np.linspace(-0.15, 0.15, len(ds)) if len(ds) > 1 else np.zeros(len(ds))
        ax.scatter(ds, y + jitter, s=14, color=ACCENT, alpha=0.8, zorder=3)
        for _ in range(c.unscored):
            ax.plot([0, 100], [y, y], color=MUTED, linestyle="--", linewidth=1.0, zorder=2)
        if c.mean is not None:
            ax.plot([c.mean, c.mean], [y - 0.3, y + 0.3], color=INK, linewidth=2.0, zorder=4)
    ax.set_yticks(range(len(cells)), [c.cell for c in cells])
    ax.set_xlim(-3, 103)
    ax.set_xlabel("Driving Score per run (tick: mean of scored runs; dashed: an unscored run, any DS in [0, 100])")
    ax.invert_yaxis()
    return to_data_uri(fig)


def _parting(clean: RunResult, other: RunResult) -> float:
    n = min(len(clean.trace), len(other.trace))
    gap = float(np.max(np.linalg.norm(clean.trace[:n, :2] - other.trace[:n, :2], axis=1))) if n else 0.0
    return gap + (0.0 if len(clean.trace) == len(other.trace) else 1e-3) + (1e6 if other.ds is None else 0.0)


def divergent(run: ClosedRun, n: int = 3) -> list[tuple[str, RunResult, RunResult, float]]:
    """(cell, clean run, degraded run, largest distance between their paths) for the `n` runs that part most
    from clean's (an unscored run first), at most one per route."""
    records = run.records
    clean = records.get("closed-clean")
    if clean is None:
        return []
    found = []
    for cell, record in records.items():
        if cell in ("closed-clean", SWAP_CELL):  # the swap drives other routes than clean's
            continue
        for a, b in zip(clean.runs, record.runs):
            found.append((cell, a, b, _parting(a, b)))
    found.sort(key=lambda x: (-x[3], x[0], x[2].route, x[2].seed))
    out, routes = [], set()
    for item in found:
        if item[3] > 0 and item[2].route not in routes:
            out.append(item)
            routes.add(item[2].route)
    return out[:n]


def trace_panels(items: Sequence[tuple[str, RunResult, RunResult, float]]) -> str | None:
    """Bird's-eye paths (world x, y): clean solid grey, the degraded run in colour, dashed when unscored."""
    if not items:
        return None
    fig = _figure(3.4 * len(items), 3.4)
    for i, (cell, clean, other, _) in enumerate(items):
        ax = fig.add_subplot(1, len(items), i + 1)
        _style(ax)
        ax.plot(clean.trace[:, 0], clean.trace[:, 1], color=MUTED, linewidth=2.0, label="closed-clean")
        ax.plot(other.trace[:, 0], other.trace[:, 1], color=ACCENT, linewidth=1.4,
                linestyle="--" if other.ds is None else "-", label=cell)
        ax.scatter(clean.trace[:1, 0], clean.trace[:1, 1], color=INK, s=16, zorder=4)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{other.route} seed {other.seed}: DS {_f(clean.ds)} -> {_f(other.ds)}", fontsize=8)
        ax.legend(fontsize=7, loc="best")
    return to_data_uri(fig)


#: The lead paragraph of runs imported from the CARLA leaderboard (`drivedegrade closed-loop import`).
CARLA_LEAD = ("CARLA leaderboard runs, read from its results files (one leaderboard run per cell): DS is the "
              "leaderboard's Driving Score; a route whose agent or simulator failed, or that never ran, is unscored "
              "and bounded, never dropped: bounds put it at 0 and at 100.")


def _lead(run: ClosedRun | None) -> str:
    if run is None:
        return CARLA_LEAD
    return (f"The planner drives the embedded world ({run.settings.closed_hz} Hz plans, LQR tracker and bicycle "
            "model at 10 Hz, other agents replaying their logs) through the degraded cameras. Driving Score = 100 x "
            "route completion x the CARLA leaderboard's infraction factors, counting "
            f"{'every collision' if run.settings.closed_collisions == 'all' else 'at-fault collisions only'}; "
            "an unscored run (the planner raised, timed out or returned a bad plan) is bounded, never dropped: "
            "bounds put it at 0 and at 100.")


def _null_text(analysis: ClosedAnalysis, imported: bool, imported_null: str = "blackout S3") -> str:
    null, e = analysis.null, html.escape
    if null is None:
        return "The null control's cells did not run."
    if null.mode == "identical":
        where = f"parts from clean at step {null.first_step}" if null.first_step is not None else "differs from clean"
        return (f"Null control: blackout S3 (the rear cameras, which the planner does not read) reproduces clean "
                f"run for run, {'DS and end alike' if imported else 'bit for bit'}." if null.passed else
                f"Null control FAILED: route {e(str(null.first_route))} (seed {null.first_seed}) {where}.")
    why = ("The simulator is not deterministic, so the null control is blackout S3 (the rear views a front-camera "
           "agent never reads) against clean:" if imported and imported_null == "blackout S3" else
           "The agent reads a rear camera, so the null is a clean rerun:" if imported else
           "The planner reads a rear camera, so the null is a clean rerun:")
    band = null.band or (None, None)
    return (f"{why} it wanders by {_f(null.wander, 3)} DS; its paired per-route differences from clean give the "
            f"null band [{_f(band[0])}, {_f(band[1])}] DS, and a cell whose paired route-level interval of its DS "
            "difference from clean reaches into the band is not separable from the null.")


def swap_text(analysis: ClosedAnalysis) -> str | None:
    """What the command swap measured, in a sentence (None when its cell did not run)."""
    got = analysis.command_swap
    if got is None:
        return None

    def num(key: str, digits: int) -> str:
        value = got.get(key)
        return f"{float(value):.{digits}f}" if isinstance(value, (int, float)) else "n/a"

    return (f"command followed in closed loop: {num('command_followed', 3)} (mean route completion of "
            f"{got.get('routes')} junction route(s) swapped to go straight on, {got.get('complete_runs')} of "
            f"{got.get('runs')} run(s) complete, DS {num('ds_mean', 1)}); the same routes unswapped in closed-clean: "
            f"completion {num('clean_completion', 3)}, DS {num('clean_ds_mean', 1)}. A planner that turns where the "
            "log turned, whatever the command says, leaves the swapped route at the junction; one that never turns "
            "completes it, but not the routes unswapped")


def _swap_note(analysis: ClosedAnalysis) -> str:
    text = swap_text(analysis) or ""
    return (f"{SWAP_CELL} drives the junction routes with their command swapped (the route goes straight on where "
            f"the log turned; the planner is told STRAIGHT there): {text[0].upper()}{text[1:]}. It is not paired "
            "with closed-clean run for run (other routes), so it has no retention and no axis.")


def closed_fragment(analysis: ClosedAnalysis, run: ClosedRun | None, imported_null: str = "blackout S3") -> str:
    """The section's HTML (escaped text; charts as data URIs); `run` None for runs imported from CARLA (no
    traces: the simulator keeps them)."""
    e = html.escape
    rows = []
    for c in analysis.cells:
        low, high = c.bounds
        kinds = ", ".join(f"{k} {v}" for k, v in c.infractions.items()) or "none"
        sep = {None: "", True: "yes", False: "not separable from the null"}[c.separable_from_null]
        rows.append(f"<tr><td>{e(c.cell)}</td><td class='n'>{len(c.rows)}</td><td class='n'>{c.unscored}</td>"
                    f"<td class='n'>{_f(c.mean)} ({_f(c.std)})</td><td class='n'>[{_f(low)}, {_f(high)}]</td>"
                    f"<td class='n'>{_f(c.completion, 3)}</td><td class='n'>{_f(c.retention, 3)} "
                    f"[{_f(c.retention_low, 3)}, {_f(c.retention_high, 3)}]</td><td>{e(kinds)}</td>"
                    f"<td>{e(sep)}</td></tr>")
    separation = analysis.separation
    traces = None if run is None else trace_panels(divergent(run))
    also = (f" ({analysis.reason})" if analysis.reason else "") + ("" if analysis.robust else
            f" (the bounds and route intervals also allow {', '.join(sorted(set(analysis.labels)))})")
    return (
        "<section id='closed-loop'><h2>Closed loop</h2>"
        f"<p class='lead'>{e(_lead(run))}</p>"
        "<table><tr><th>cell</th><th>runs</th><th>unscored</th><th>DS mean (std)</th><th>bounds</th>"
        "<th>completion</th><th>retention [bounds]</th><th>infractions</th><th>separable</th></tr>"
        + "".join(rows) + "</table>"
        + (f"<p>{e(_swap_note(analysis))}</p>" if analysis.command_swap is not None else "") +
        f"<p>{_null_text(analysis, run is None, imported_null)}</p>"
        f"<p>Closed-loop verdict: <b>{e(analysis.label)}</b>{e(also)}"
        f". Availability-versus-quality separation: {e(str(separation.get('holds')))}; under every assignment of the "
        f"unscored runs: {e(str(separation.get('holds_under_every_assignment')))}. Agrees with the open-loop verdict: "
        f"{e(str(analysis.agrees))}.</p>"
        f"<img alt='closed-loop DS per run' src='{strip_plot(analysis)}'>"
        + (f"<h3>Where the paths part most</h3><img alt='bird&#39;s-eye traces' src='{traces}'>" if traces else "")
        + "</section>")


_STYLE = ("<style>body{font-family:sans-serif;margin:2em;color:#1f2933}td.n{text-align:right}"
          "td,th{padding:2px 8px;border-bottom:1px solid #e4e7eb}</style>")


def write_closed_report(path: str | os.PathLike[str], planner: str, analysis: ClosedAnalysis, run: ClosedRun, *,
                        digest: str = "") -> Path:
    """A page of its own for a run of closed cells only."""
    from .html import seal_html

    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>DriveDegrade closed loop: {html.escape(planner)}"
            f"</title>{_STYLE}</head><body>"
            f"<h1>{html.escape(planner)}: closed loop</h1><dl>{seal_html(digest, '')}</dl>"
            + closed_fragment(analysis, run) + "</body></html>\n")
    return atomic_write_text(path, page)


def write_imported_report(path: str | os.PathLike[str], analysis: ClosedAnalysis,
                          sources: Sequence[tuple[str, str]], null: str = "blackout S3") -> Path:
    """The page of `drivedegrade closed-loop import`: the closed-loop section of CARLA leaderboard runs and the
    results files it read, as (cell, file) pairs."""
    e = html.escape
    files = "".join(f"<li>{e(cell)}: {e(path)}</li>" for cell, path in sources)
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>DriveDegrade closed loop: CARLA leaderboard"
            f"</title>{_STYLE}</head><body><h1>CARLA leaderboard: closed loop</h1>"
            + closed_fragment(analysis, None, null) + f"<h3>Results files</h3><ul>{files}</ul></body></html>\n")
    return atomic_write_text(path, page)
