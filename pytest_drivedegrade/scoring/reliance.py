"""Every input's reliance read both ways (SPEC section 20, issue 40): does the plan move, and does accuracy change.

The camera axes say whether accuracy falls when the cameras degrade or go; they cannot say whether the planner
read its cameras at all. A planner whose plans move with its images while its error holds (or falls: a weak planner
misled by its images) has flat axes exactly like a planner that ignores images, and only the second is "not shown
to use its cameras". Here each input (the cameras' quality, the cameras' presence, the ego status, the command) gets
its plan movement from its cells: the mean 3 s endpoint shift from clean's plan, against the null control's largest
wander (``separable_from_null``). `read_movement` then words the verdict so that it never claims what the cells
contradict:

* plans do not move beyond the null's wander: ``not-shown-to-use-cameras`` (the only case the paper's "not using
  the cameras" means);
* plans move and accuracy falls: ``camera-reliant`` / ``quality-insensitive`` (the axes' labels, unchanged);
* plans move and accuracy does not fall: ``camera-sensitive`` (case ``accuracy-holds``), or accuracy rises beyond
  its interval (case ``gains-from-loss``): the planner reads its cameras without gaining accuracy from them;
* no camera cell's movement measured (an imported table, whose plans the suite never sees): the axes' label, said
  to be read on accuracy alone (never "its plans do not move").

Retention above 1 with its whole 95 % interval above 1 is its own finding and is never worded as "flat".

Pure functions over plain data; nothing here reads files, imports pytest or touches a planner.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

from ..cells import cell_id
from ..constants import EGO_BLIND, EGO_NOISE
from .records import Axes, Builtins, CellSummary, Verdict, format_value

#: The inputs whose plan movement the profile shows, in the report's order.
RELIANCE_INPUTS: tuple[str, ...] = ("quality", "presence", "ego", "command")
#: What each input is called for people.
INPUT_NAMES: Mapping[str, str] = {"quality": "cameras' quality", "presence": "cameras' presence",
                                  "ego": "ego status", "command": "command"}
#: The label of a planner whose plans move with its cameras while its accuracy does not fall.
CAMERA_SENSITIVE = "camera-sensitive"
#: The command cells an input reads when they ran (issue 40's command cells; none in this release's ladder).
COMMAND_CELLS: tuple[str, ...] = ("command_blind",)


@dataclass(frozen=True)
class InputMovement:
    """How far one input's cells move the plan: the mean 3 s endpoint shift from clean's plan (m) over the
    `cells` that ran, and those of them separable from the null control's wander (`moved`). ``shift`` is None
    when none of the input's cells ran (the input was not probed)."""

    shift: float | None
    cells: tuple[str, ...]
    moved: tuple[str, ...]

    @property
    def moves(self) -> bool | None:
        """Whether any of the input's cells moved the plan beyond the null's wander; None when none ran."""
        return None if not self.cells else bool(self.moved)

    def to_builtins(self) -> Builtins:
        return {"shift": self.shift, "cells": list(self.cells), "moved": list(self.moved), "moves": self.moves}


@dataclass(frozen=True)
class Reliance:
    """Each input's plan movement (`RELIANCE_INPUTS`) and the null control's wander they are read against
    (the largest waypoint displacement of the null cell from clean, m; 0 with a bit-identical null)."""

    wander: float
    inputs: Mapping[str, InputMovement]

    def of(self, name: str) -> InputMovement:
        return self.inputs.get(name, InputMovement(None, (), ()))

    def cameras_move(self) -> bool:
        """Whether a camera cell (quality or presence) moved the plan beyond the null's wander."""
        return bool(self.of("quality").moves or self.of("presence").moves)

    def to_builtins(self) -> Builtins:
        """The certificate's ``reliance`` section."""
        return {"wander": self.wander, **{name: self.of(name).to_builtins() for name in RELIANCE_INPUTS}}


def input_cells(quality: Sequence[str], removal: str) -> dict[str, tuple[str, ...]]:
    """The cells each input's movement is read from: the quality families at S5; the removal family at S5 and
    blind (every camera off); ego_noise S5 and ego_blind; the command cells."""
    return {"quality": tuple(cell_id(f, 5) for f in quality), "presence": (cell_id(removal, 5), "blind"),
            "ego": (cell_id(EGO_NOISE, 5), cell_id(EGO_BLIND, 0)), "command": COMMAND_CELLS}


def plan_movement(shifts: Mapping[str, float], wander: float, quality: Sequence[str],
                  removal: str = "blackout") -> Reliance:
    """Each input's movement from the cells' endpoint shifts (`shifts`: cell id -> mean 3 s endpoint shift from
    clean, m) against the null's `wander` (m). A cell is moved by the rule of ``separable_from_null`` (its shift
    above the wander); a cell whose shift is not finite (no frame planned in both) is not counted as run."""
    out = {}
    for name, cells in input_cells(quality, removal).items():
        ran = tuple(c for c in cells if c in shifts and math.isfinite(shifts[c]))
        moved = tuple(c for c in ran if shifts[c] > wander)
        shift = math.fsum(shifts[c] for c in ran) / len(ran) if ran else None
        out[name] = InputMovement(shift, ran, moved)
    return Reliance(float(wander), out)


def run_movement(summaries: Sequence[CellSummary], wander: float | None, quality: Sequence[str],
                 removal: str = "blackout") -> Reliance:
    """`plan_movement` over a run's summaries (their ``endpoint_shift``) and the null's ``max_l2_change``."""
    shifts = {s.cell: float(s.metrics.get("endpoint_shift", math.nan)) for s in summaries}
    return plan_movement(shifts, float(wander or 0.0), quality, removal)


def gains(axes: Axes, axis: str) -> bool:
    """Retention above 1 beyond its interval: the axis's whole 95 % interval above 1 (at the certificate's
    precision). Never without an interval: a point above 1 alone is within the noise as far as the run knows."""
    ci = axes.interval(axis)
    return ci is not None and ci[0] is not None and round(ci[0], 6) > 1.0


def _gain_words(axes: Axes, axis: str) -> str:
    ci = axes.interval(axis)
    low, high = (format_value(v) for v in (ci or (None, None)))
    what = {"quality": "image quality degrades", "removal": "cameras are removed"}[axis]
    return f"accuracy rises when {what} ({axis} {format_value(axes.value(axis))}, 95 % interval {low} .. {high})"


def _shift_words(reliance: Reliance) -> str:
    parts = [f"{INPUT_NAMES[n]} {format_value(reliance.of(n).shift)} m" for n in ("quality", "presence")
             if reliance.of(n).shift is not None]
    moved = len(reliance.of("quality").moved) + len(reliance.of("presence").moved)
    ran = len(reliance.of("quality").cells) + len(reliance.of("presence").cells)
    return (f"mean 3 s endpoint shift from clean: {', '.join(parts)}; {moved} of {ran} camera cells beyond the "
            f"null's wander of {reliance.wander:.3g} m")


def read_movement(v: Verdict, axes: Axes, reliance: Reliance | None) -> Verdict:
    """The verdict `v` (from the axes alone: ``verdict.verdict``) read beside the plans' movement: a planner whose
    camera cells move its plans is never worded as indistinguishable from one that ignores images, and retention
    above 1 beyond its interval is said, never called flat. `reliance` None (a certificate of spec 4, a closed
    loop): `v` as is. Labels other than the axes' three are left alone (undetermined stays undetermined)."""
    if reliance is None or v.label not in ("camera-reliant", "quality-insensitive", "not-shown-to-use-cameras"):
        return v
    up = [axis for axis in ("quality", "removal") if gains(axes, axis)]
    if v.label == "not-shown-to-use-cameras":
        if reliance.of("quality").moves is None and reliance.of("presence").moves is None:
            # no camera cell's movement measured (an imported table: plans not seen): read on accuracy alone
            return replace(v, text=v.text + " Whether its plans move with its cameras is not known: no camera "
                           "cell's plan movement was measured.")
        if not reliance.cameras_move():
            return replace(v, text=v.text + f" Its plans do not move: {_shift_words(reliance)}.")
        case = "gains-from-loss" if up else "accuracy-holds"
        nums = v.text[v.text.index("(") + 1:v.text.index(")")]
        tail = ("; " + " and ".join(_gain_words(axes, a) for a in up) + ": it gains from their loss, so what its "
                "images show misleads it") if up else ": it reads its cameras without gaining accuracy from them"
        text = (f"Camera-sensitive without reliance: its plans move when its cameras degrade or are removed "
                f"({_shift_words(reliance)}), but its accuracy does not fall ({nums}){tail}. A planner that ignores "
                "images would not move; this one does not need its images to keep its accuracy.")
        return replace(v, label=CAMERA_SENSITIVE, case=case, text=text)
    if v.label == "quality-insensitive" and "quality" in up:
        return replace(v, text=v.text.replace("planning stays flat when image quality degrades",
                                              _gain_words(axes, "quality"), 1))
    if v.label == "camera-reliant" and v.case == "quality-only" and "removal" in up:
        ci = axes.interval("removal") or (None, None)
        words = (f"removing cameras raises its accuracy (removal {format_value(axes.removal)}, 95 % interval "
                 f"{format_value(ci[0])} .. {format_value(ci[1])})")
        return replace(v, text=v.text.replace("removing cameras leaves it flat", words, 1))
    return v
