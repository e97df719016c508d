"""JUnit properties: each cell's figures as testcase properties, axes and verdict as suite properties.

Values are plain ``str`` / ``float`` / ``int`` only: a numpy scalar, ``Path`` or ``Enum`` in
``item.user_properties`` crashes a run under ``-n`` (xdist serialises them), and ``record_testsuite_property``
wants the same. Non-finite floats and None become the string ``"none"``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..certificate.seal import epdms_unscored
from ..scoring.records import AXES, BESIDE_AXES, EGO_AXES, CellSummary, RunAnalysis
from ..scoring.reliance import RELIANCE_INPUTS
from .columns import EPDMS, PDMS, STABLE, TWO_STAGE, per_horizon

#: Testcase properties of a finished summary, in the order they appear in the XML.
CELL_PROPERTIES = (*STABLE, *per_horizon("l2", "stp3"), *per_horizon("l2", "uniad"), "collision_3s_stp3",
                   "vru_3s_stp3", "jerk", "endpoint_shift", "energy", "separable_from_null", "conformance_errors",
                   "data_errors", *PDMS, *EPDMS, *TWO_STAGE)

SUITE_PREFIX = "drivedegrade_"


def plain(value: object) -> str | float | int:
    """A property value xdist and the JUnit writer accept: bool -> "true"/"false", numpy -> builtins."""
    if value is None:
        return "none"
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return round(float(value), 6) if math.isfinite(value) else "none"
    return str(value)


def cell_properties(summary: CellSummary | Mapping[str, Any]) -> list[tuple[str, str | float | int]]:
    """(name, value) pairs for ``item.user_properties`` of one cell's test item."""
    row = summary.flat() if isinstance(summary, CellSummary) else dict(summary)
    return [(name, plain(row[name])) for name in CELL_PROPERTIES if name in row]


def suite_properties(analysis: RunAnalysis) -> list[tuple[str, str | float | int]]:
    """(name, value) pairs for ``record_testsuite_property``: axes, verdict, null control, floor, thresholds."""
    ax, verdict, nc = analysis.axes, analysis.verdict, analysis.null_control
    out: list[tuple[str, object]] = [(f"axis_{k}", ax.value(k)) for k in (*AXES, *BESIDE_AXES, *EGO_AXES)]
    out += [(f"axis_pdms_{k}", analysis.axes_pdms.value(k)) for k in AXES]
    if analysis.axes_epdms is not None:  # and each EPDMS term the run did not score, with the reason
        out += [(f"axis_epdms_{k}", analysis.axes_epdms.value(k)) for k in AXES]
        out += [(f"epdms_unscored_{k}", why) for k, why in epdms_unscored(analysis).items()]
    if analysis.axes_epdms2 is not None:  # --drivedegrade-two-stage: the axes on two-stage EPDMS retention
        out += [(f"axis_epdms2_{k}", analysis.axes_epdms2.value(k)) for k in AXES]
    out += [("verdict", verdict.label), ("verdict_flat", verdict.flat), ("verdict_negative_gap", verdict.negative_gap),
            ("verdict_text", verdict.text), ("verdict_confidence", verdict.confidence),
            ("verdict_ego_label", verdict.ego_label), ("verdict_metric", verdict.metric),
            ("verdict_reason", verdict.reason)]
    for k in AXES:
        low, high = ax.interval(k) or (None, None)
        out += [(f"axis_{k}_ci_low", low), (f"axis_{k}_ci_high", high)]
    out += [("null_control_passed", None if nc is None else nc.passed),
            ("null_control_max_abs_diff", None if nc is None else nc.max_abs_diff)]
    out += [("floor_l2_avg", analysis.floor.l2_avg)]
    if analysis.reliance is not None:  # each input's plan movement (spec 5): shift (m) and whether it moves
        out += [("reliance_wander", analysis.reliance.wander)]
        for name in RELIANCE_INPUTS:
            got = analysis.reliance.of(name)
            out += [(f"reliance_{name}_shift", got.shift), (f"reliance_{name}_moves", got.moves)]
    if analysis.command is not None:  # the command_swap cell's following figure (spec 5)
        f = analysis.command.following
        out += [("command_following", f.value), ("command_following_ci_low", f.low),
                ("command_following_ci_high", f.high), ("command_label", f.label), ("command_frames", f.frames),
                ("command_junction_frames", analysis.command.junction_frames)]
    for fam, t in sorted(analysis.thresholds.items()):
        out += [(f"threshold_{fam}_{key}", x.value) for key, x in t.levels.items()]
    return [(SUITE_PREFIX + name, plain(value)) for name, value in out]
