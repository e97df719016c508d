"""The report's charts, each rendered off-screen (Agg, no pyplot state) to a ``data:image/png;base64`` URI.

Every function takes plain data and returns a string the HTML template embeds as is, so the report stays one
self-contained file. Imported only when a report is written (matplotlib is not light).
"""

from __future__ import annotations

import base64
import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.axes import Axes as MplAxes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from ..cells import is_camera_ladder
from ..constants import EGO_LENGTH, EGO_WIDTH
from ..scoring.records import Axes, CellSummary, FamilyThresholds, Interval, Threshold
from ..scoring.retention import THRESHOLD_LEVELS

INK, MUTED, ACCENT, GRID = "#1f2933", "#7b8794", "#2463eb", "#e4e7eb"
LEVEL_COLORS = {"s10": "#d97706", "s25": "#dc2626"}
CELL_COLORS = ("#dc2626", "#d97706", "#7c3aed", "#0891b2", "#65a30d")


def _label(text: object, limit: int = 40) -> str:
    """User text (planner name, frame token) as a literal matplotlib label: ``$`` would start mathtext."""
    return str(text)[:limit].replace("$", r"\$")


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), dpi=110)
    FigureCanvasAgg(fig)
    fig.patch.set_facecolor("white")
    return fig


def _style(ax: MplAxes) -> None:
    ax.spines[["top", "right"]].set_visible(False)
    ax.spines[["left", "bottom"]].set_color(MUTED)
    ax.tick_params(colors=INK, labelsize=8)
    ax.grid(color=GRID, linewidth=0.6)
    ax.set_axisbelow(True)


def to_data_uri(fig: Figure) -> str:
    """PNG bytes of `fig` as a data URI (no timestamp metadata, so the bytes are reproducible)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None}, bbox_inches="tight", facecolor="white")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def image_data_uri(rgb: np.ndarray) -> str:
    """An RGB uint8 image (the S4 montage) as a PNG data URI."""
    arr = np.ascontiguousarray(np.asarray(rgb, dtype=np.uint8))
    h, w = arr.shape[:2]
    fig = Figure(figsize=(w / 100, h / 100), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(arr, interpolation="nearest")
    ax.axis("off")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None}, dpi=100)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _curves(summaries: Sequence[CellSummary]) -> dict[str, list[CellSummary]]:
    out: dict[str, list[CellSummary]] = {}
    for s in summaries:
        if is_camera_ladder(s.family):
            out.setdefault(s.family, []).append(s)
    return {f: sorted(c, key=lambda s: s.severity) for f, c in out.items()}


#: The top of a retention axis when every value lies below it: a little above 1 (no damage).
RETENTION_TOP = 1.08


def upper_limit(values: Sequence[float | None]) -> float:
    """The top of a retention axis: `RETENTION_TOP`, or above the largest finite value (a corruption can improve
    a plan: occlusion at 1.110 was clipped at 1.08), rounded up to 0.05 with room for its marker."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    top = max(finite, default=0.0) + 0.03
    return RETENTION_TOP if top <= RETENTION_TOP else math.ceil(top * 20) / 20


def tolerance_curves(summaries: Sequence[CellSummary], thresholds: Mapping[str, FamilyThresholds],
                     cols: int = 4) -> str | None:
    """Small multiples: retention vs severity per family (clean at S0 = 1), 95% CI band, 0.90 / 0.75 lines and
    the interpolated thresholds as markers. One shared y range so the panels compare at a glance."""
    curves = _curves(summaries)
    if not curves:
        return None
    rows = math.ceil(len(curves) / cols)
    lows = [s.retention_ci_low for c in curves.values() for s in c if math.isfinite(s.retention_ci_low)]
    ymin = min(0.5, math.floor(min(lows, default=0.5) * 10) / 10)
    ymax = upper_limit([v for c in curves.values() for s in c for v in (s.retention, s.retention_ci_high)])
    fig = _figure(3.0 * cols, 2.1 * rows)
    for i, (fam, cells) in enumerate(curves.items()):
        ax = fig.add_subplot(rows, cols, i + 1)
        _style(ax)
        sev = [0] + [s.severity for s in cells]
        ax.fill_between(sev, [1.0] + [s.retention_ci_low for s in cells], [1.0] + [s.retention_ci_high for s in cells],
                        color=ACCENT, alpha=0.15, linewidth=0)
        ax.plot(sev, [1.0] + [s.retention for s in cells], color=ACCENT, marker="o", markersize=3.5, linewidth=1.6)
        for key, level in THRESHOLD_LEVELS.items():
            ax.axhline(level, color=LEVEL_COLORS[key], linestyle="--", linewidth=0.9)
            t = thresholds[fam].levels[key] if fam in thresholds else Threshold(None)
            if t.value is not None:
                ax.plot([t.value], [level], marker="v", color=LEVEL_COLORS[key], markersize=6)
            span = _span(t.ci, hi=5.2)
            if span is not None:  # the threshold's 95 % interval (to the edge when some resamples never cross)
                ax.plot(span, [level, level], color=LEVEL_COLORS[key], linewidth=3.2, alpha=0.45,
                        solid_capstyle="butt")
        ax.set_title(fam, fontsize=9.5, color=INK, loc="left", fontweight="bold")
        ax.set_xlim(-0.2, 5.2)
        ax.set_xticks(range(6), ["clean", "S1", "S2", "S3", "S4", "S5"])
        ax.set_ylim(ymin, ymax)
    fig.tight_layout(h_pad=1.2, w_pad=1.0)
    return to_data_uri(fig)


def _span(ci: Interval | None, hi: float) -> tuple[float, float] | None:
    """An interval to draw: an open (null) upper bound runs to `hi`; None when there is nothing to draw."""
    if ci is None or ci[0] is None:
        return None
    return ci[0], hi if ci[1] is None else ci[1]


def _yerr(point: float, ci: Interval | None) -> list[list[float]] | None:
    """matplotlib's asymmetric error for one point from its [low, high]; None without a finite interval."""
    if ci is None or ci[0] is None or ci[1] is None:
        return None
    return [[max(0.0, point - ci[0])], [max(0.0, ci[1] - point)]]


def _value(summary: CellSummary, key: str) -> float:
    """A summary's `key`: an attribute (``retention``) or a metric (``pdms_retention``); NaN when absent."""
    got = getattr(summary, key, None) if key in ("retention", "l2_avg") else summary.metrics.get(key)
    return float(got) if got is not None else math.nan


def retention_heatmap(summaries: Sequence[CellSummary], key: str = "retention",
                      label: str = "retention") -> str | None:
    """Family x severity retention (`key`: ``retention`` on L2, ``pdms_retention`` on PDMS), red (lost) to green
    (kept), each cell annotated with its value."""
    curves = _curves(summaries)
    if not curves:
        return None
    fams = list(curves)
    grid = np.full((len(fams), 5), np.nan)
    for i, fam in enumerate(fams):
        for s in curves[fam]:
            if 1 <= s.severity <= 5:
                grid[i, s.severity - 1] = _value(s, key)
    if not np.isfinite(grid).any():
        return None
    fig = _figure(6.4, 0.36 * len(fams) + 1.0)
    ax = fig.add_subplot(1, 1, 1)
    im = ax.imshow(np.ma.masked_invalid(grid), cmap="RdYlGn", vmin=0.5, vmax=1.0, aspect="auto")
    for (i, j), v in np.ndenumerate(grid):
        if math.isfinite(v):  # white on the dark ends of the scale (deep red and deep green), ink elsewhere
            r, g, b, _ = im.cmap(im.norm(v))
            ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=8,
                    color="white" if 0.299 * r + 0.587 * g + 0.114 * b < 0.5 else INK)
    ax.set_xticks(range(5), [f"S{k}" for k in range(1, 6)])
    ax.set_yticks(range(len(fams)), fams)
    ax.tick_params(labelsize=8.5, length=0)
    ax.xaxis.tick_top()
    for side in ax.spines.values():
        side.set_visible(False)
    cbar = fig.colorbar(im, ax=ax, fraction=0.04, pad=0.02)
    cbar.ax.tick_params(labelsize=7.5)
    cbar.set_label(f"{label} (clipped to 0.5 .. 1.0)", fontsize=8)
    return to_data_uri(fig)


def _quadrants(points: Sequence[float | None], flat: float,
               corners: tuple[str, str, str, str]) -> tuple[Figure, MplAxes, float]:
    """The frame both retention-plane charts share: a square plot from `lo` (below every finite point, at
    most 0.5) to `upper_limit` on both axes, the "flat on both" corner shaded, and the four corner labels
    (top right, bottom right, top left, bottom left; "" for none). Returns (figure, axes, lo)."""
    pts = [v for v in points if v is not None and math.isfinite(v)]
    lo = min(0.5, math.floor(min(pts) * 10) / 10 - 0.05)
    hi = upper_limit(pts)
    fig = _figure(5.2, 4.6)
    ax = fig.add_subplot(1, 1, 1)
    _style(ax)
    ax.add_patch(Rectangle((flat, flat), 2, 2, color="#e5e7eb", alpha=0.7, linewidth=0))
    kw: dict[str, Any] = dict(fontsize=7.5, color=MUTED, style="italic")
    places = ((flat + 0.005, hi - 0.005, "top"), (flat + 0.005, lo + 0.01, "bottom"), (lo + 0.01, hi - 0.005, "top"),
              (lo + 0.01, lo + 0.01, "bottom"))
    for (x, y, va), text in zip(places, corners):
        if text:  # an empty label leaves its corner bare
            ax.text(x, y, text, va=va, **kw)
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    return fig, ax, lo


def axes_chart(axes: Axes, flat: float, *, planner: str, blind: float | None = None,
               floor: tuple[float, float] = (1.0, 1.0)) -> str | None:
    """Quality (x) vs removal (y) S5 retention: the planner, the ego-only floor and the blind point.

    The flat line on each axis splits the plane into the verdict regions; the diagonal is gap = 0. The blind
    point sits at (r_blind, r_blind): a planner for which every corruption is as bad as losing all cameras.
    """
    q, r = axes.quality, axes.removal
    if q is None or r is None:
        return None
    q_ci, r_ci = axes.interval("quality"), axes.interval("removal")
    bounds = [v for ci in (q_ci, r_ci) for v in (ci or ()) if v is not None]
    fig, ax, lo = _quadrants([q, r, blind, *floor, *bounds], flat,
                             ("not shown to\nuse cameras", "quality-insensitive", "", "camera-reliant"))
    ax.add_patch(Rectangle((flat, lo - 1), 2, flat - lo + 1, color="#fde68a", alpha=0.5, linewidth=0))
    ax.add_patch(Rectangle((lo - 1, lo - 1), flat - lo + 1, 3, color="#fecaca", alpha=0.45, linewidth=0))
    ax.plot([lo, 10.0], [lo, 10.0], color=MUTED, linewidth=0.8, linestyle=":")
    ax.scatter([floor[0]], [floor[1]], marker="s", s=60, color="#6b7280", zorder=3, label="ego-only floor")
    if blind is not None and math.isfinite(blind):
        ax.scatter([blind], [blind], marker="X", s=70, color="#111827", zorder=3, label="blind (all cameras off)")
    xerr, yerr = _yerr(q, q_ci), _yerr(r, r_ci)
    if xerr is not None or yerr is not None:  # the axes' 95 % intervals from the joint bootstrap
        ax.errorbar([q], [r], xerr=xerr, yerr=yerr, fmt="none", ecolor=ACCENT, elinewidth=1.4, capsize=4,
                    zorder=3.5)
    ax.scatter([q], [r], marker="o", s=90, color=ACCENT, edgecolor="white", zorder=4, label=_label(planner))
    ax.set_xlabel("quality axis: mean S5 retention, nine quality families", fontsize=8.5)
    ax.set_ylabel("removal axis: blackout S5 retention", fontsize=8.5)
    ax.legend(fontsize=7.5, loc="upper left", frameon=False)
    return to_data_uri(fig)


def reliance_chart(axes: Axes, flat: float, *, planner: str, blind: float | None = None,
                   floor_ego: float | None = None) -> str | None:
    """Camera removal (x: blackout S5 retention) vs ego removal (y: ego_blind retention), SPEC section 10.

    The planner's point; the blind point (every camera off, the ego status kept) at (r_blind, 1); the ego-only
    floor at (1, its own ego_blind retention): it reads no camera, so camera removal cannot touch it.
    """
    x, y = axes.removal, axes.ego_removal
    if x is None or y is None:
        return None
    fig, ax, lo = _quadrants([x, y, blind, floor_ego], flat,
                             ("relies on\nneither", "ego-reliant", "camera-reliant", "relies on both"))
    ax.axvline(flat, color=MUTED, linestyle="--", linewidth=0.8)
    ax.axhline(flat, color=MUTED, linestyle="--", linewidth=0.8)
    if floor_ego is not None and math.isfinite(floor_ego):
        ax.scatter([1.0], [floor_ego], marker="s", s=60, color="#6b7280", zorder=3, label="ego-only floor")
    if blind is not None and math.isfinite(blind):
        ax.scatter([blind], [1.0], marker="X", s=70, color="#111827", zorder=3, label="blind (all cameras off)")
    ax.scatter([x], [y], marker="o", s=90, color=ACCENT, edgecolor="white", zorder=4, label=_label(planner))
    ax.set_xlabel("camera removal: blackout S5 retention", fontsize=8.5)
    ax.set_ylabel("ego removal: ego_blind retention", fontsize=8.5)
    ax.legend(fontsize=7.5, loc="lower right", frameon=False)
    return to_data_uri(fig)


def trajectory_panels(examples: Sequence[Mapping[str, Any]]) -> str | None:
    """Bird's-eye view of planned trajectories, one panel per example frame: ground truth, clean plan and
    the plans of the most damaging cells. x (forward) points up and y (left) points left, as seen from above.

    Each example: ``{"frame": token, "gt": (6, 2), "plans": {cell_id: (6, 2)}}`` with "clean" among the plans.
    """
    if not examples:
        return None
    fig = _figure(3.4 * len(examples), 4.6)
    handles: dict[str, Line2D] = {}
    for i, ex in enumerate(examples):
        ax = fig.add_subplot(1, len(examples), i + 1)
        _style(ax)
        ax.add_patch(Rectangle((-EGO_WIDTH / 2, -EGO_LENGTH / 2), EGO_WIDTH, EGO_LENGTH, color="#9ca3af", zorder=2))
        handles["ground truth"] = _bev_line(ax, ex["gt"], INK, "--")
        colors = iter(CELL_COLORS)
        for cell, plan in ex["plans"].items():
            handles[_label(cell, 28)] = _bev_line(ax, plan, ACCENT if cell == "clean" else next(colors, MUTED), "-")
        # plans mostly differ in how far they go, so the lateral axis is not drawn to scale: at least +-3 m,
        # wide enough for every line, so sideways deviations stay visible
        reach = max(3.0, 1.15 * max(float(np.nanmax(np.abs(np.asarray(p, dtype=float)[:, 1]), initial=0.0))
                                    for p in [ex["gt"], *ex["plans"].values()]))
        ax.set_xlim(-reach, reach)
        ax.set_title(f"frame {_label(ex['frame'], 18)}", fontsize=8.5, color=INK, loc="left")
        ax.set_xlabel("lateral (m, left is left)", fontsize=7.5)
        ax.set_ylabel("forward (m)", fontsize=7.5)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=min(len(handles), 6), fontsize=8,
               frameon=False)
    return to_data_uri(fig)


def _bev_line(ax: MplAxes, plan: np.ndarray, color: str, style: str) -> Line2D:
    """Draw one trajectory from the ego origin in bird's-eye axes (horizontal = -y, vertical = x)."""
    pts = np.vstack([np.zeros((1, 2)), np.asarray(plan, dtype=float).reshape(-1, 2)])
    ax.plot(-pts[-1, 1], pts[-1, 0], marker="D", color=color, markersize=6, markeredgecolor="white", zorder=4)
    return ax.plot(-pts[:, 1], pts[:, 0], style, color=color, linewidth=1.8, marker="o", markersize=2.8)[0]
