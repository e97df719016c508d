"""`drivedegrade verify` on the certificate's ``reliance`` section (spec 5, issue 40): each input's plan movement
recomputed from the cells' stored endpoint shifts and the null control's stored wander, and the label the verdict
must then carry (``scoring.reliance.read_movement`` over the axes' label).

A certificate without the section (spec 4 and earlier) is read as it was written: the axes alone give its label,
and `expected_label` says so by returning the axes' label unchanged.

At the certificate's precision a cell whose stored shift lies within 1e-6 of the stored wander cannot be decided
again (the run compared unrounded figures); the certificate's own ``moved`` list is taken for that cell.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from ..scoring.records import Axes
from ..scoring.reliance import RELIANCE_INPUTS, InputMovement, Reliance, input_cells, read_movement
from ..scoring.verdict import FamilyGroups, verdict

TOLERANCE = 1e-6  #: the certificate's precision (two stored numbers compared)

Cell = Mapping[str, object]


def _number(v: object) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _names(v: object) -> tuple[str, ...]:
    return tuple(map(str, v)) if isinstance(v, list) else ()


def recompute_reliance(cert: Mapping[str, object], cells: Sequence[Cell],
                       groups: FamilyGroups) -> tuple[Reliance | None, list[str]]:
    """The reliance the cells give (None without a ``reliance`` section) and every recorded figure that differs
    from it, as ``reliance.<input>.<field>: certificate says X, its cells give Y``."""
    section = cert.get("reliance")
    if not isinstance(section, Mapping):
        return None, []
    nc = cert.get("null_control")
    wander = _number(nc.get("max_l2_change")) if isinstance(nc, Mapping) else None
    wander = wander or 0.0
    shifts = {str(c.get("cell")): _number(c.get("endpoint_shift")) for c in cells}
    problems: list[str] = []
    if abs((_number(section.get("wander")) or 0.0) - wander) > TOLERANCE:
        problems.append(f"reliance.wander: certificate says {section.get('wander')!r}, its null control gives "
                        f"{wander:.6f}")
    inputs = {}
    for name, wanted in input_cells(groups.quality, groups.removal).items():
        got = section.get(name)
        recorded = got if isinstance(got, Mapping) else {}
        ran = tuple(c for c in wanted if shifts.get(c) is not None)
        said = set(_names(recorded.get("moved")))
        moved = tuple(c for c in ran if _moved(shifts[c], wander, c in said))  # type: ignore[arg-type]
        shift = math.fsum(shifts[c] for c in ran) / len(ran) if ran else None  # type: ignore[misc]
        inputs[name] = InputMovement(shift, ran, moved)
        if sorted(said) != sorted(moved):
            problems.append(f"reliance.{name}.moved: certificate says {sorted(said)!r}, its cells give "
                            f"{sorted(moved)!r}")
        said_shift = _number(recorded.get("shift"))
        if (said_shift is None) != (shift is None) or (shift is not None and said_shift is not None
                                                        and abs(said_shift - shift) > 2 * TOLERANCE):
            problems.append(f"reliance.{name}.shift: certificate says {recorded.get('shift')!r}, its cells give "
                            f"{shift!r}")
    return Reliance(wander, {n: inputs[n] for n in RELIANCE_INPUTS}), problems


def _moved(shift: float, wander: float, recorded: bool) -> bool:
    """Beyond the wander, at the certificate's precision; the recorded answer where undecidable."""
    if abs(shift - wander) <= TOLERANCE:
        return recorded
    return shift > wander


def expected_label(axes: Mapping[str, object], flat: float, reliance: Reliance | None) -> str:
    """The label a certificate's (checked) axes and reliance give: the axes' label read beside the plans'
    movement; without a reliance section (spec 4), the axes' label."""
    got = Axes.from_builtins(axes)
    return read_movement(verdict(got, flat), got, reliance).label
