"""report.html: one self-contained page (charts as embedded PNG, CSS inline, no external URL).

Jinja2 renders ``templates/report.html.j2`` with autoescape on for every template (the file ends in ``.j2``, so
extension-based autoescape would miss it): planner names, cell ids and frame tokens come from user code and
data and are always escaped. Charts come from ``plots``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write_text
from ..cells import CellRecord, is_camera_ladder
from ..certificate.seal import Provenance, epdms_unscored
from ..scoring.records import (
    AXES,
    BESIDE_AXES,
    EGO_AXES,
    CellSummary,
    FamilyThresholds,
    Interval,
    RunAnalysis,
    format_value,
)
from .terminal import floor_warning

TEMPLATES = Path(__file__).parent / "templates"
LABEL_CLASS = {"camera-reliant": "reliant", "quality-insensitive": "insensitive",
               "not-shown-to-use-cameras": "flat", "camera-sensitive": "insensitive",
               "undetermined": "undetermined"}


@dataclass(frozen=True)
class TrajectoryExample:
    """One frame for the bird's-eye panel: ground truth and the plans of clean and the chosen cells."""

    frame: str
    gt: np.ndarray
    plans: dict[str, np.ndarray]

    def as_mapping(self) -> dict[str, object]:
        return {"frame": self.frame, "gt": self.gt, "plans": self.plans}


def most_damaging(summaries: Sequence[CellSummary], n: int = 3) -> list[CellSummary]:
    """The `n` ladder cells with the lowest retention (ties broken by cell id, so the choice is stable)."""
    ladder = [s for s in summaries if is_camera_ladder(s.family)
              and math.isfinite(s.retention)]
    return sorted(ladder, key=lambda s: (s.retention, s.cell))[:n]


def trajectory_examples(records: Mapping[str, CellRecord], gt: Mapping[str, Any], summaries: Sequence[CellSummary],
                        *, n_cells: int = 3, n_frames: int = 2) -> list[TrajectoryExample]:
    """Pick frames where the most damaging cells moved the 3 s endpoint furthest from clean's plan.

    `records` maps cell id -> record (clean included); `gt` maps frame token -> (6, 2) ground truth.
    """
    clean = records.get("clean")
    cells = [s.cell for s in most_damaging(summaries, n_cells) if s.cell in records]
    if clean is None or not cells:
        return []
    shift = sum(np.nan_to_num(records[c].endpoint_shift(clean)) for c in cells)
    order = [i for i in np.argsort(-shift, kind="stable") if clean.frames[i] in gt][:n_frames]
    return [TrajectoryExample(clean.frames[i], np.asarray(gt[clean.frames[i]], dtype=float),
                              {"clean": clean.plans[i], **{c: records[c].plans[i] for c in cells}}) for i in order]


#: The EPDMS's own terms and score, as the sub-score table shows them (nc, dac, ttc, ep are the PDMS's).
EPDMS_TERMS: tuple[str, ...] = ("epdms", "ddc", "tlc", "lk", "hc", "ec")


def _fmt(value: object, digits: int = 3) -> str:
    return format_value(value, digits, missing="—")


def _range(ci: Interval | None, digits: int = 3, never: str = "never") -> str:
    """"low – high" of a [low, high] interval; an open (null) bound reads `never`; "—" without an interval."""
    if not ci:
        return "—"
    return " – ".join(never if v is None else f"{v:.{digits}f}" for v in ci)


def _share(value: float | None) -> str:
    return "—" if value is None else f"{100 * value:.0f} %"


def _family_info(families: Mapping[str, Any] | None) -> dict[str, dict[str, str]]:
    """group / axis / S5 parameter per family, from the registry when it is importable."""
    if families is None:
        try:
            from ..corruptions.ladder import FAMILIES
        except ImportError:
            return {}
        families = FAMILIES
    out = {}
    for name, fam in families.items():
        try:
            s5 = fam.describe(5)
        except Exception:  # noqa: BLE001 - a description is decoration, never a failure
            s5 = ""
        out[name] = {"group": str(getattr(fam, "group", "")), "axis": str(getattr(fam, "axis", "")), "s5": s5}
    return out


def _context(analysis: RunAnalysis, provenance: Provenance, charts: dict[str, str | None],
             families: Mapping[str, Any] | None, extra: Mapping[str, object]) -> dict[str, object]:
    info = _family_info(families)
    s5 = {s.family: s for s in analysis.summaries if s.severity == 5}
    thresholds = [{"family": fam, **info.get(fam, {}), **_threshold_cells(t),
                   "r5": _fmt(s5[fam].retention) if fam in s5 else "—",
                   "ci5": (f"{_fmt(s5[fam].retention_ci_low)} – {_fmt(s5[fam].retention_ci_high)}"
                           if fam in s5 else "—")} for fam, t in analysis.thresholds.items()]
    cells = [{"cell": s.cell, "retention": _fmt(s.retention), "ci": f"{_fmt(s.retention_ci_low)} – "
              f"{_fmt(s.retention_ci_high)}", "l2": _fmt(s.l2_avg), "col": _fmt(s.metrics.get("collision_3s_stp3")),
              "shift": _fmt(s.metrics.get("endpoint_shift")), "energy": _fmt(s.metrics.get("energy")),
              "sep": _fmt(s.separable_from_null), "errors": s.conformance_errors,
              "data_errors": s.data_errors,
              "low": math.isfinite(s.retention) and s.retention < 0.9} for s in analysis.summaries]
    ax, verdict = analysis.axes, analysis.verdict
    axes = {k: _fmt(ax.value(k)) for k in (*AXES, *BESIDE_AXES, *EGO_AXES)}
    ranges = {k: _range(ax.interval(k)) for k in AXES}
    return {"p": provenance, "verdict": verdict, "label_class": LABEL_CLASS.get(verdict.label),
            "axes": axes, "ranges": ranges, "confidence": verdict.confidence,
            "borderline": verdict.borderline, "missing": list(ax.missing), "null": analysis.null_control,
            "floor": {k: _fmt(v) for k, v in analysis.floor.to_builtins().items()}, "settings": analysis.settings,
            "thresholds": thresholds, "cells": cells, "charts": charts, "floor_warning": floor_warning(analysis),
            **extra}


def _threshold_cells(t: FamilyThresholds) -> dict[str, str]:
    """A family's thresholds for the table: value, 95 % interval and share never reached, per level."""
    out = {}
    for key, x in t.levels.items():
        out.update({key: _fmt(x.value, 2), f"{key}_ci": _range(x.ci, 2), f"{key}_never": _share(x.never)})
    return out


def pdms_ego_charts(analysis: RunAnalysis, provenance: Provenance) -> dict[str, str | None]:
    """The PDMS and EPDMS retention heatmaps (none without a scored cell) and the camera-vs-ego reliance chart
    (spec 3, spec 4.1, SPEC section 10)."""
    from . import plots
    from .profile import command_retention, reliance_profile

    blind = next((s.retention for s in analysis.summaries if s.cell == "blind"), None)
    return {"profile": reliance_profile(analysis.reliance, analysis.axes, analysis.verdict.flat,
                                        planner=provenance.planner_name,
                                        command=command_retention(analysis.summaries),
                                        following=None if analysis.command is None else analysis.command.following),
            "heatmap_pdms": plots.retention_heatmap(analysis.summaries, "pdms_retention", "PDMS retention"),
            "heatmap_epdms": plots.retention_heatmap(analysis.summaries, "epdms_retention", "EPDMS retention"),
            "reliance": plots.reliance_chart(analysis.axes, analysis.verdict.flat, planner=provenance.planner_name,
                                             blind=blind, floor_ego=analysis.floor.ego_removal)}


def pdms_ego_context(analysis: RunAnalysis, n: int = 5) -> dict[str, object]:
    """The template's PDMS, EPDMS and ego figures: the axes sets side by side, the ego axis and label, whether a
    map was scored, the EPDMS terms left unscored (with the certificate's reason), and the PDMS and EPDMS
    sub-scores of the `n` most damaging cells (on L2 retention). EPDMS is shown where the clean cell scored it."""
    def sub(s: CellSummary) -> dict[str, str]:
        m = s.metrics
        return {"cell": s.cell, "retention": _fmt(s.retention), "pdms_retention": _fmt(m.get("pdms_retention")),
                "epdms_retention": _fmt(m.get("epdms_retention")),
                **{k: _fmt(m.get(k)) for k in ("pdms", "nc", "dac", "ttc", "ep", "comfort", *EPDMS_TERMS)}}

    clean = next((s for s in analysis.summaries if s.cell == "clean"), None)
    mapped = None if clean is None else clean.metrics.get("map_scored")
    ax_e = analysis.axes_epdms
    epdms = ax_e is not None and clean is not None and math.isfinite(float(clean.metrics.get("epdms", math.nan)))
    return {"axes_both": [{"k": k, "l2": _fmt(analysis.axes.value(k)), "pdms": _fmt(analysis.axes_pdms.value(k)),
                           "epdms": _fmt(ax_e.value(k) if ax_e is not None else None)} for k in AXES],
            "epdms_shown": epdms,
            "epdms_unscored": [{"term": k, "why": why} for k, why in epdms_unscored(analysis).items()] if epdms else [],
            "ego": {"ego": _fmt(analysis.axes.ego), "ego_removal": _fmt(analysis.axes.ego_removal),
                    "label": analysis.verdict.ego_label},
            "verdict_metric": analysis.verdict.metric,
            "map_scored": mapped is not None and math.isfinite(mapped) and mapped > 0,
            "damaging_pdms": [sub(s) for s in most_damaging(analysis.summaries, n)],
            "clean_pdms": sub(clean) if clean is not None else None, "two_stage": two_stage_context(analysis)}


def two_stage_context(analysis: RunAnalysis) -> dict[str, object] | None:
    """The two-stage section (--drivedegrade-two-stage): the axes on two-stage and one-stage EPDMS retention, and
    per cell its one-stage, stage-two and two-stage EPDMS with both retentions; None in a one-stage run."""
    ax2, ax = analysis.axes_epdms2, analysis.axes_epdms
    if ax2 is None:
        return None
    from ..closedloop.twostage import STAGE_TWO_STARTS

    def row(s: CellSummary) -> dict[str, object]:
        m = s.metrics
        return {"cell": s.cell, "frames": m.get("epdms2_frames", "—"), "epdms": _fmt(m.get("epdms")),
                "stage2": _fmt(m.get("epdms_stage2")), "epdms2": _fmt(m.get("epdms2")),
                "retention": _fmt(m.get("epdms_retention")), "retention2": _fmt(m.get("epdms2_retention")),
                "ci2": f"{_fmt(m.get('epdms2_retention_ci_low'))} – {_fmt(m.get('epdms2_retention_ci_high'))}"}

    return {"starts": len(STAGE_TWO_STARTS), "cells": [row(s) for s in analysis.summaries],
            "axes": [{"k": k, "epdms2": _fmt(ax2.value(k)), "epdms": _fmt(ax.value(k) if ax is not None else None)}
                     for k in AXES]}


def render_report(analysis: RunAnalysis, provenance: Provenance, *, montage: np.ndarray | None = None,
                  trajectories: Sequence[TrajectoryExample | Mapping[str, Any]] = (),
                  floor_point: tuple[float, float] = (1.0, 1.0), families: Mapping[str, Any] | None = None,
                  created: str = "", digest: str = "", cost: Mapping[str, Any] | None = None,
                  signed_by: str = "", closed_html: str = "") -> str:
    """The page as a string. `montage`: the S4 montage of one front frame (RGB uint8), optional; `cost`: the
    certificate's cost ledger, shown as a panel; `signed_by`: the signing key's fingerprint ("" unsigned), so the
    page says what the seal proves."""
    from jinja2 import Environment, FileSystemLoader, StrictUndefined

    from . import plots

    blind = next((s.retention for s in analysis.summaries if s.cell == "blind"), None)
    traj: list[Mapping[str, Any]] = [t.as_mapping() if isinstance(t, TrajectoryExample) else t for t in trajectories]
    charts = {
        "curves": plots.tolerance_curves(analysis.summaries, analysis.thresholds),
        "heatmap": plots.retention_heatmap(analysis.summaries),
        "axes": plots.axes_chart(analysis.axes, analysis.verdict.flat, planner=provenance.planner_name,
                                 blind=blind, floor=floor_point),
        "montage": plots.image_data_uri(montage) if montage is not None else None,
        "trajectories": plots.trajectory_panels(traj),
        **pdms_ego_charts(analysis, provenance),
    }
    env = Environment(loader=FileSystemLoader(str(TEMPLATES)), autoescape=True, undefined=StrictUndefined,
                      trim_blocks=True, lstrip_blocks=True)
    extra = {"created": created, "seal_html": seal_html(digest, signed_by), "closed_html": closed_html,
             "traj_cells": [c for t in traj[:1] for c in t["plans"]], "cost": _cost_rows(cost),
             **pdms_ego_context(analysis)}
    return env.get_template("report.html.j2").render(_context(analysis, provenance, charts, families, extra))


#: The marks around the page's seal rows: `drivedegrade sign` rewrites what lies between them (issue 37 H1).
SEAL_OPEN, SEAL_CLOSE = "<!-- drivedegrade:seal -->", "<!-- /drivedegrade:seal -->"


def seal_html(digest: str, signed_by: str) -> str:
    """The report's rows on the certificate's digest and what its seal proves, between `SEAL_OPEN` and
    `SEAL_CLOSE` ("" without a digest): signed by the key `signed_by` (its fingerprint), or integrity only."""
    if not digest:
        return ""
    from markupsafe import escape

    if signed_by:
        proves = (f"signed (Ed25519, key fingerprint <code>{escape(signed_by)}</code>): it proves who issued the "
                  "certificate; <code>drivedegrade verify certificate.json --public-key KEY.pub</code> checks the "
                  "signature, the digest and the arithmetic")
    else:
        proves = ("integrity only, unsigned: the digest catches an accidental edit, not a deliberate one; sign it "
                  "after the run with <code>drivedegrade sign certificate.json --key KEY</code> to prove who "
                  "issued it. <code>drivedegrade verify certificate.json</code> checks the digest and the "
                  "arithmetic")
    return (f"{SEAL_OPEN}<dt>certificate digest</dt><dd><code>{escape(digest)}</code></dd>\n    <dt>what the seal "
            f"proves</dt><dd>{proves};\n      <code>drivedegrade reproduce certificate.json PLANNER</code> reruns "
            f"sampled cells bit for bit</dd>{SEAL_CLOSE}")


def reseal_page(page: str, digest: str, signed_by: str) -> str | None:
    """`page` (a report.html) with its seal rows rewritten for a certificate now sealed as `digest` and signed
    by `signed_by`; None when the page has no single seal block (an older page, or not ours)."""
    if page.count(SEAL_OPEN) != 1 or page.count(SEAL_CLOSE) != 1:
        return None
    head, rest = page.split(SEAL_OPEN)
    _, tail = rest.split(SEAL_CLOSE)
    return head + seal_html(digest, signed_by) + tail


def _cost_rows(cost: Mapping[str, Any] | None) -> dict[str, object] | None:
    """The cost panel: predictions, and seconds per part with its share of the cells' time."""
    if not cost:
        return None
    sec = {k: float(v) for k, v in cost["seconds"].items()}
    total = sum(sec.values()) or 1.0
    names = {"planner": "planner (predict)", "inject": "injecting corruptions", "decode": "decoding images",
             "metrics": "scoring: L2, collisions", "pdms": "scoring: PDMS-like", "check": "input write check"}
    rows = [{"part": names.get(k, k), "seconds": f"{v:.1f}", "share": f"{100 * v / total:.1f} %"}
            for k, v in sorted(sec.items(), key=lambda kv: -kv[1])]
    fps = cost.get("planner_frames_per_second")
    cells = cost.get("cells", {})
    reused_cells = ", ".join(f"{c} {int(v['reused'])}" for c, v in sorted(cells.items()) if v.get("reused"))
    processes = [{"wall": f"{float(p['wall']):.1f}", "busy": _percent(p.get("planner_busy"))}
                 for p in cost.get("processes", [])]
    wall = cost.get("wall")
    return {"predictions": cost["predictions"], "reused": cost.get("reused", 0), "rows": rows,
            "fps": f"{fps:.1f}" if fps else "—", "reused_cells": reused_cells,
            "wall": f"{float(wall):.1f}" if wall else None, "busy": _percent(cost.get("planner_busy")),
            "processes": processes}


def _percent(share: object) -> str:
    return f"{100 * float(share):.0f} %" if isinstance(share, (int, float)) else "—"


def write_report(path: str | os.PathLike[str], analysis: RunAnalysis, provenance: Provenance, **kwargs: Any) -> Path:
    """Render and write report.html atomically (keyword arguments as ``render_report``)."""
    return atomic_write_text(path, render_report(analysis, provenance, **kwargs))
