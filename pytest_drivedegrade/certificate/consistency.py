"""Does a certificate's arithmetic add up? `drivedegrade verify` recomputes, from the certificate's own cells,
the thresholds (``scoring.retention.tolerance_threshold`` on each family's retention curve), the axes (quality,
removal, gap, mean, and the ego axis, from S5 retentions and the family groups of the ladder) and the verdict
label (from those axes and the flat line in ``verdict.flat`` / ``settings.flat``; ``undetermined`` whenever a
cell has failed frames, its ``conformance_errors`` or ``data_errors`` above 0, SPEC section 11), and names every
field that disagrees with both values.

A digest, and even a signature, only says the file is what someone wrote; this says that what was written is
self-consistent, so a hand-made certificate whose cells and axes disagree fails even when resealed.

Tolerance: the certificate stores 6 decimals, so each stored number is off its exact value by up to half a unit
of the 6th decimal (5e-7). A figure recomputed from n stored inputs is allowed ``5e-7 * (n + 1)`` (1e-6 for a
mean or a copy, 1.5e-6 for the gap); a threshold, which divides by the retention drop across its segment, is
allowed that error propagated through the interpolation, and is not checked where a retention lies within 1e-6
of the threshold level (which severity crosses first is then undecidable at the certificate's precision).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

from ..cells import cell_id, is_camera_ladder
from ..constants import DEFAULT_FLAT, EGO_BLIND, EGO_NOISE
from ..corruptions.ladder import FAMILIES
from ..scoring.records import AXES, EGO_AXES, Axes, FamilyThresholds, Threshold
from ..scoring.retention import THRESHOLD_LEVELS, tolerance_threshold
from ..scoring.verdict import BLIND_EQUALS_CLEAN, FamilyGroups, compute_axes, ego_label
from .reliance_check import expected_label, recompute_reliance
from .seal import DIGITS

HALF_UNIT = 0.5 * 10.0 ** -DIGITS  #: the rounding error of one stored number
TOLERANCE = 2 * HALF_UNIT  #: 1e-6: the certificate's precision
#: How far each recomputed axis may be off: a mean of stored values is off by their average rounding (<= 5e-7)
#: plus the axis's own rounding; the gap is a difference of two stored numbers; an ego axis a copy of one.
AXIS_TOLERANCE: dict[str, float] = {"quality": TOLERANCE, "removal": TOLERANCE, "gap": 3 * HALF_UNIT,
                                    "mean": TOLERANCE, "ego": TOLERANCE, "ego_removal": TOLERANCE}

Cell = Mapping[str, object]  #: one cell of a certificate, as read


def _section(cert: Mapping[str, object], key: str) -> Mapping[str, object]:
    got = cert.get(key)
    return got if isinstance(got, Mapping) else {}


def _number(v: object) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _fmt(v: object) -> str:
    return "null" if v is None else f"{v:.6f}" if isinstance(v, float) else repr(v)


def _compare(problems: list[str], field: str, recorded: object, recomputed: float | None, tol: float) -> None:
    """Add a problem naming `field` and both values when the certificate's value is off the recomputed one."""
    got = _number(recorded)
    if recorded is not None and got is None:
        problems.append(f"{field}: certificate says {_fmt(recorded)}, not a number")
        return
    if got is None and recomputed is None:
        return
    if got is None or recomputed is None or abs(got - recomputed) > tol + 1e-12:
        problems.append(f"{field}: certificate says {_fmt(got)}, its cells give {_fmt(recomputed)}")


def _curves(cells: Sequence[Cell], key: str) -> dict[str, dict[int, float]]:
    curves: dict[str, dict[int, float]] = {}
    for c in cells:
        fam = c.get("family")
        if isinstance(fam, str) and is_camera_ladder(fam):
            value = _number(c.get(key))
            severity = c.get("severity", 0)
            curves.setdefault(fam, {})[int(severity) if isinstance(severity, (int, float)) else 0] = \
                math.nan if value is None else value
    return curves


def _threshold_tolerance(curve: Mapping[int, float], level: float) -> float | None:
    """The allowed difference of a threshold recomputed from stored retentions; None when undecidable."""
    points = sorted((s, r) for s, r in curve.items() if s > 0 and math.isfinite(r))
    if any(abs(r - level) <= TOLERANCE for _, r in points):
        return None
    prev = None
    for s, r in points:
        if r < level:
            if prev is None:
                return TOLERANCE
            s0, r0 = prev
            return TOLERANCE + 2 * HALF_UNIT * (s - s0) / (r0 - r)
        prev = (s, r)
    return TOLERANCE


def recompute_thresholds(curves: Mapping[str, Mapping[int, float]]) -> dict[str, FamilyThresholds]:
    """Each family's thresholds from its stored retention curve."""
    return {fam: FamilyThresholds({key: Threshold(tolerance_threshold(curve, level))
                                   for key, level in THRESHOLD_LEVELS.items()}) for fam, curve in curves.items()}


def check_thresholds(cert: Mapping[str, object], cells: Sequence[Cell]) -> list[str]:
    problems: list[str] = []
    recorded = _section(cert, "thresholds")
    curves = _curves(cells, "retention")
    for fam in sorted(set(recorded) - set(curves)):
        problems.append(f"thresholds.{fam}: certificate has thresholds for a family none of its cells has")
    for fam, got in recompute_thresholds(curves).items():
        entry = recorded.get(fam)
        if not isinstance(entry, Mapping):
            problems.append(f"thresholds.{fam}: missing, its cells give a retention curve")
            continue
        for key, level in THRESHOLD_LEVELS.items():
            tol = _threshold_tolerance(curves[fam], level)
            if tol is not None:
                _compare(problems, f"thresholds.{fam}.{key}", entry.get(key), got.levels[key].value, tol)
    return problems


def recompute_axes(cells: Sequence[Cell], key: str, groups: FamilyGroups) -> Axes:
    """The axes (and the ego axis) from the cells' stored `key` retention."""
    s5 = {fam: curve[5] for fam, curve in _curves(cells, key).items() if 5 in curve}
    by_cell = {c.get("cell"): _number(c.get(key)) for c in cells}
    return replace(compute_axes(s5, groups), ego=by_cell.get(cell_id(EGO_NOISE, 5)),
                   ego_removal=by_cell.get(cell_id(EGO_BLIND, 0)))


def check_axes(axes: Mapping[str, object], cells: Sequence[Cell], key: str, where: str,
               groups: FamilyGroups) -> list[str]:
    """quality, removal, gap, mean and the ego axis of `axes` against those recomputed from the cells' `key`
    (an ego axis only where the certificate has it)."""
    problems: list[str] = []
    got = recompute_axes(cells, key, groups)
    for name in (*AXES, *(n for n in EGO_AXES if n in axes)):
        _compare(problems, f"{where}.{name}", axes.get(name), got.value(name), AXIS_TOLERANCE[name])
    return problems


def _failed(cells: Sequence[Cell]) -> list[str]:
    """The cells with failed frames (planner contract failures or data faults), as the certificate counts them."""
    return [str(c.get("cell")) for c in cells
            if any(isinstance(n := c.get(k), int) and n > 0 for k in ("conformance_errors", "data_errors"))]

def _cell_tolerance(clean: float, cell: float) -> float:
    """How far a retention recomputed from two stored L2 figures may be off the stored one: each stored figure
    is off by up to HALF_UNIT, propagated through clean / cell, plus the retention's own rounding."""
    return HALF_UNIT * (1.0 / abs(cell) + abs(clean) / cell ** 2) + TOLERANCE


def _recomputable(c: Cell, clean: Cell, seeds: int) -> bool:
    """A cell whose retention is exactly clean's L2 over its own: every frame planned in both (no failed frame,
    as many frames as clean) and one corruption seed (with several, retention is the mean of per-seed ratios)."""
    fam = c.get("family")
    seeded = seeds > 1 and isinstance(fam, str) and fam in FAMILIES and FAMILIES[fam].random
    return not seeded and not _failed([c, clean]) and c.get("frames") == clean.get("frames")


def check_cell_retentions(cert: Mapping[str, object], cells: Sequence[Cell]) -> list[str]:
    """Each cell's ``retention`` against its own figures: clean's ``l2_avg`` over the cell's (M(clean) / M(cell),
    an error metric; the other way round for a reward), wherever every frame was planned in both and one seed ran.
    The thresholds and axes are recomputed from the stored retentions; this ties those retentions to the L2."""
    settings = _section(cert, "settings")
    seeds = settings.get("seeds", 1)
    kind = settings.get("kind", "error")
    clean = next((c for c in cells if c.get("cell") == "clean"), None)
    base = None if clean is None else _number(clean.get("l2_avg"))
    if clean is None or base is None or base == 0 or kind not in ("error", "reward"):
        return []
    problems: list[str] = []
    for c in cells:
        own = _number(c.get("l2_avg"))
        if own is None or own == 0 or not _recomputable(c, clean, seeds if isinstance(seeds, int) else 1):
            continue
        got = base / own if kind == "error" else own / base
        tol = _cell_tolerance(base, own) if kind == "error" else _cell_tolerance(own, base)
        recorded = _number(c.get("retention"))
        if recorded is None or abs(recorded - got) > tol + 1e-12:
            problems.append(f"cells.{c.get('cell')}.retention: certificate says {_fmt(c.get('retention'))}, its l2_avg "
                            f"{own:.6f} against clean's {base:.6f} gives {got:.6f}")
    return problems


def check_null_control(cert: Mapping[str, object], cells: Sequence[Cell]) -> list[str]:
    """The recorded null control against the clean and null cells' ``plans_digest``: equal digests mean
    bit-identical plans, so the control cannot have failed or changed a frame; different digests with every
    frame planned in both mean different plans, so it cannot have passed."""
    nc = _section(cert, "null_control")
    by_cell = {c.get("cell"): c for c in cells}
    clean, null = by_cell.get("clean"), by_cell.get("null")
    if clean is None or null is None:
        return []
    a, b = clean.get("plans_digest"), null.get("plans_digest")
    if not isinstance(a, str) or not isinstance(b, str):
        # issue 37 (low): a certificate that records plans digests (any cell's, or the seal's record_digests)
        # must record clean's and null's; deleting one skipped this check. Older certificates record none.
        recorded = "record_digests" in cert or any(isinstance(c.get("plans_digest"), str) for c in cells)
        gone = [name for name, d in (("clean", a), ("null", b)) if not isinstance(d, str)]
        return [f"cells.{name}.plans_digest: missing (or not a string) in a certificate that records plans "
                "digests, so the null control cannot be checked" for name in gone] if recorded else []
    passed, changed = nc.get("passed"), nc.get("frames_changed", 0)
    if a == b and (passed is False or (isinstance(changed, int) and changed > 0)):
        return [f"null_control.passed: certificate says {passed!r} with {changed!r} frame(s) changed, but the "
                "null cell's plans_digest equals clean's: its plans are bit-identical, so the control passed"]
    complete = not _failed([clean, null]) and clean.get("frames") == null.get("frames")
    if a != b and complete and passed is not False:
        return [f"null_control.passed: certificate says {passed!r}, but the null cell's plans_digest differs from "
                "clean's with every frame planned in both: its plans differ, so the control failed"]
    return []


def check_verdict(cert: Mapping[str, object], cells: Sequence[Cell] = (),
                  groups: FamilyGroups | None = None) -> list[str]:
    """The label from the certificate's (checked) axes and its flat line, read beside its plans' movement where
    it records one (``reliance``, spec 5: recomputed from the cells by ``reliance_check``), or ``undetermined``
    when a cell has failed frames (then ``verdict.failed_cells`` must name exactly those cells) or the null
    control failed; the flat line agrees with settings."""
    v, settings = _section(cert, "verdict"), _section(cert, "settings")
    reliance, problems = recompute_reliance(cert, cells, groups or FamilyGroups.from_registry())
    flat = _number(v.get("flat", settings.get("flat", DEFAULT_FLAT)))
    if flat is None:
        return [f"verdict.flat: certificate says {_fmt(v.get('flat'))}, not a number"]
    if "flat" in settings:
        _compare(problems, "settings.flat", settings.get("flat"), flat, 0.0)
    metric = v.get("metric", "l2")
    axes = _section(cert, {"pdms": "axes_pdms", "epdms": "axes_epdms", "epdms2": "axes_epdms2"}.get(str(metric),
                                                                                                    "axes"))
    # the label from the certificate's own axes (checked against its cells by `check_axes`)
    label = expected_label(axes, flat, reliance)
    failed = _failed(cells)
    if failed:
        if v.get("label") != "undetermined":
            problems.append(f"verdict.label: certificate says {v.get('label')!r}, but {len(failed)} of its cells "
                            f"have failed frames ({', '.join(failed[:8])}), which makes it 'undetermined'")
        recorded = v.get("failed_cells")
        named = sorted(map(str, recorded)) if isinstance(recorded, Mapping) else recorded
        if named != sorted(failed):
            problems.append(f"verdict.failed_cells: certificate names {named!r}, its cells with failed frames are "
                            f"{failed!r}")
        if "computed_label" in v and v.get("computed_label") != label:
            problems.append(f"verdict.computed_label: certificate says {v.get('computed_label')!r}, its axes and "
                            f"flat line {flat:g} give {label!r}")
    elif _section(cert, "null_control").get("passed") is False:
        if v.get("label") != "undetermined":
            problems.append(f"verdict.label: certificate says {v.get('label')!r}, but its null control failed, "
                            "which makes it 'undetermined'")
        if "computed_label" in v and v.get("computed_label") != label:
            problems.append(f"verdict.computed_label: certificate says {v.get('computed_label')!r}, its axes and "
                            f"flat line {flat:g} give {label!r}")
    elif v.get("case") == BLIND_EQUALS_CLEAN:
        problems += check_blind_equals_clean(cert, cells, label)
    elif v.get("label") != label:
        problems.append(f"verdict.label: certificate says {v.get('label')!r}, its axes and flat line {flat:g} "
                        f"give {label!r}")
    elif named := v.get("failed_cells"):
        shown = sorted(map(str, named)) if isinstance(named, (Mapping, list)) else named
        problems.append(f"verdict.failed_cells: certificate names {shown!r}, but none of its cells has failed "
                        "frames")
    if "ego_label" in v and "ego_removal" in axes:
        nc_failed = _section(cert, "null_control").get("passed") is False or v.get("case") == BLIND_EQUALS_CLEAN
        expected = "undetermined" if failed or nc_failed else ego_label(_number(axes.get("ego_removal")), flat)
        if v.get("ego_label") != expected:
            problems.append(f"verdict.ego_label: certificate says {v.get('ego_label')!r}, its ego axis gives "
                            f"{expected!r}")
    return problems


def check_blind_equals_clean(cert: Mapping[str, object], cells: Sequence[Cell], label: str) -> list[str]:
    """M12's case (`scoring.verdict.blind_equals_clean`), as far as the certificate shows it: the label is
    undetermined, blind's plans digest is clean's, and blind's L2 is below the floor's (the bootstrap interval
    over per-frame floor errors is not in the certificate, so its bound is taken as recorded)."""
    v = _section(cert, "verdict")
    digests = {c.get("cell"): c.get("plans_digest") for c in cells if c.get("cell") in ("clean", "blind")}
    problems = []
    if v.get("label") != "undetermined":
        problems.append(f"verdict.label: certificate says {v.get('label')!r} with case {BLIND_EQUALS_CLEAN!r}, "
                        "which makes it 'undetermined'")
    if len(digests) != 2 or digests["clean"] != digests["blind"] or not digests["clean"]:
        problems.append(f"verdict.case: certificate says {BLIND_EQUALS_CLEAN!r}, but its blind and clean cells do "
                        "not have the same plans digest")
    if _section(cert, "floor").get("blind_below_floor") is not True:
        problems.append(f"verdict.case: certificate says {BLIND_EQUALS_CLEAN!r}, but floor.blind_below_floor is not "
                        "true")
    if "computed_label" in v and v.get("computed_label") != label:
        problems.append(f"verdict.computed_label: certificate says {v.get('computed_label')!r}, its axes give "
                        f"{label!r}")
    return problems


def check_consistency(cert: Mapping[str, Any], groups: FamilyGroups | None = None) -> list[str]:
    """Every inconsistency between a certificate's cells and its thresholds, axes and verdict, as
    ``field: certificate says X, its cells give Y``; empty when the arithmetic adds up. `groups` defaults to the
    ladder's family groups (``FamilyGroups.from_registry()``)."""
    if groups is None:
        groups = FamilyGroups.from_registry()
    cells = [c for c in cert.get("cells", []) if isinstance(c, Mapping)] if isinstance(cert.get("cells"), list) \
        else []
    problems = check_cell_retentions(cert, cells) + check_null_control(cert, cells) + check_thresholds(cert, cells)
    if isinstance(cert.get("axes"), Mapping):
        problems += check_axes(cert["axes"], cells, "retention", "axes", groups)
    if isinstance(cert.get("axes_pdms"), Mapping) and any("pdms_retention" in c for c in cells):
        problems += check_axes(cert["axes_pdms"], cells, "pdms_retention", "axes_pdms", groups)
    from .closed import check_closed_loop  # the closed loop's section (SPEC 13), recomputed from its run rows

    if isinstance(cert.get("axes_epdms"), Mapping) and any("epdms_retention" in c for c in cells):
        problems += check_axes(cert["axes_epdms"], cells, "epdms_retention", "axes_epdms", groups)
    if isinstance(cert.get("axes_epdms2"), Mapping) and any("epdms2_retention" in c for c in cells):
        problems += check_axes(cert["axes_epdms2"], cells, "epdms2_retention", "axes_epdms2", groups)
    from .command_check import check_command  # the command-following figure (spec 5), from its stored sums

    return problems + check_verdict(cert, cells, groups) + check_command(cert) + check_closed_loop(cert)


def incompleteness(cert: Mapping[str, Any]) -> str | None:
    """Why a certificate is incomplete (``completeness.complete == false``), or None."""
    comp = cert.get("completeness")
    if not isinstance(comp, Mapping) or comp.get("complete") is not False:
        return None
    parts = []
    if comp.get("missing_cells"):
        parts.append(f"missing cell(s): {', '.join(map(str, comp['missing_cells']))}")
    if comp.get("missing_shards"):
        parts.append(f"missing shard(s): {', '.join(map(str, comp['missing_shards']))}")
    return "; ".join(parts) or "completeness.complete is false"
