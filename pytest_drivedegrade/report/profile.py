"""The reliance profile (spec 5, issue 40): how far each input moves the plan, on one chart, with what happens to
accuracy beside it. One bar per input (the cameras' quality, the cameras' presence, the ego status, the command):
its mean 3 s endpoint shift from clean's plan, the null control's wander as a dashed line, the bar coloured by what
accuracy did (falls below the flat line, holds, rises beyond its interval) and labelled with the retention. An
input whose cells did not run is named "not probed", never drawn as zero.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from ..constants import COMMAND_BLIND
from ..scoring.command import Following
from ..scoring.records import Axes, CellSummary, format_value
from ..scoring.reliance import INPUT_NAMES, RELIANCE_INPUTS, Reliance, gains

#: The axis each input's accuracy is read from (None: the command_blind cell's own retention, `command_retention`).
ACCURACY_AXIS: Mapping[str, str | None] = {"quality": "quality", "presence": "removal", "ego": "ego_removal",
                                           "command": None}
FALLS, HOLDS, RISES, UNKNOWN = "#dc2626", "#2463eb", "#7c3aed", "#9aa5b1"
BASE = 1e-3  #: m: the chart's left edge (log scale); a shift below it is drawn as no bar, its figure still written


def command_retention(summaries: Sequence[CellSummary]) -> float | None:
    """The command_blind cell's L2 retention (None when it did not run)."""
    return next((s.retention for s in summaries if s.cell == COMMAND_BLIND), None)


def profile_rows(reliance: Reliance, axes: Axes, flat: float, command: float | None = None,
                 following: Following | None = None) -> list[dict[str, object]]:
    """One row per input: name, shift (m, None: not probed), moves, retention (the command's: `command`), what
    accuracy did ("falls", "holds", "rises" beyond its interval, "n/a") and, for the command, whether the plan
    goes where the command says (`following`: command_swap's figure; None when that cell did not run)."""
    rows: list[dict[str, object]] = []
    for name in RELIANCE_INPUTS:
        got, axis = reliance.of(name), ACCURACY_AXIS[name]
        value = axes.value(axis) if axis is not None else command
        if value is None or not math.isfinite(value):
            accuracy = "n/a"
        elif round(value, 6) < flat:
            accuracy = "falls"
        else:
            accuracy = "rises" if axis in ("quality", "removal") and gains(axes, axis) else "holds"
        rows.append({"input": name, "name": INPUT_NAMES[name], "shift": got.shift, "moves": got.moves,
                     "cells": len(got.cells), "moved": len(got.moved), "retention": value, "accuracy": accuracy,
                     "following": following if name == "command" else None})
    return rows


def reliance_profile(reliance: Reliance | None, axes: Axes, flat: float, *, planner: str,
                     command: float | None = None, following: Following | None = None) -> str | None:
    """The profile chart as a data URI; None without a reliance (a certificate of spec 4)."""
    if reliance is None:
        return None
    from .plots import INK, MUTED, _figure, _label, _style, to_data_uri

    rows = profile_rows(reliance, axes, flat, command, following)
    fig = _figure(6.4, 2.9)
    ax = fig.add_subplot(1, 1, 1)
    _style(ax)
    shifts = [float(r["shift"]) for r in rows if isinstance(r["shift"], float)]
    top = max([*shifts, reliance.wander, 10 * BASE])
    colours = {"falls": FALLS, "holds": HOLDS, "rises": RISES, "n/a": UNKNOWN}
    ax.set_xscale("log")  # the ego cells move a plan by tens of metres, a camera cell by centimetres: both read
    for y, row in enumerate(rows):
        shift = row["shift"]
        if not isinstance(shift, float):
            ax.text(BASE * 1.1, y, "not probed (no cell ran)" + _following_words(row.get("following")), va="center",
                    fontsize=8, color=MUTED)
            continue
        if shift > BASE:
            ax.barh([y], [shift - BASE], left=BASE, color=colours[str(row["accuracy"])], height=0.6)
        ax.text(max(shift, BASE) * 1.15, y, _annotation(row), va="center", fontsize=7.5, color=INK)
    wander = "null's wander 0 m (bit-identical)"
    if reliance.wander > BASE:
        ax.axvline(reliance.wander, color=MUTED, linestyle="--", linewidth=0.9)
        wander = f"dashed: the null's wander {reliance.wander:.3g} m"
    ax.set_yticks(range(len(rows)), [str(r["name"]) for r in rows], fontsize=8.5)
    ax.set_ylim(len(rows) - 0.4, -0.8)  # top to bottom in the inputs' order, the first label clear of the title
    ax.set_xlim(BASE, top * 400)  # room for the labels right of the longest bar
    ax.set_xlabel(f"plan movement: mean 3 s endpoint shift from clean (m, log scale; {wander})", fontsize=8.5)
    ax.set_title(f"{_label(planner)}: what each input does to the plan (colour: accuracy falls / holds / rises)",
                 fontsize=8.5, color=INK)
    return to_data_uri(fig)


def _annotation(row: Mapping[str, object]) -> str:
    moved = "moves" if row["moves"] else "within the null"
    return (f"{format_value(row['shift'], 2)} m, {moved}; retention {format_value(row['retention'])} "
            f"({row['accuracy']}){_following_words(row.get('following'))}")


def _following_words(got: object) -> str:
    """The command bar's following figure (command_swap), or nothing when that cell did not run."""
    if not isinstance(got, Following):
        return ""
    if got.value is None:
        return "; following not measured (no junction frame)"
    spread = "" if got.low is None else f" [{format_value(got.low)} .. {format_value(got.high)}]"
    return f"; following {format_value(got.value)}{spread} over {got.frames} junction frames ({got.label})"


def profile_lines(reliance: Reliance | None, axes: Axes, flat: float, command: float | None = None,
                  following: Following | None = None) -> Sequence[str]:
    """The profile as terminal lines (one per input)."""
    if reliance is None:
        return []
    out = []
    for row in profile_rows(reliance, axes, flat, command, following):
        if row["shift"] is None:
            gone = " (command_blind did not run)" if row.get("following") is not None else ""
            out.append(f"  {row['name']}: not probed{gone}{_following_words(row.get('following'))}")
        else:
            out.append(f"  {row['name']}: plans {_annotation(row)}")
    return out
