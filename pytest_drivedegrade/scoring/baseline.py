"""The CI gate: a run's retentions against a stored baseline certificate, cell by cell and axis by axis."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from ..constants import DEFAULT_TOLERANCE
from ..errors import DriveDegradeError
from ..settings import RunSettings
from .records import AXES, Axes


class BaselineError(DriveDegradeError):
    """A baseline certificate that cannot be compared: another spec version, data set or settings, or
    malformed."""


@dataclass(frozen=True)
class Regression:
    """One retention (on the verdict's metric) that fell more than the tolerance below its baseline."""

    name: str  # a cell id, or "axis:quality"
    baseline: float
    current: float
    tolerance: float = 0.0
    metric: str = "l2"

    @property
    def drop(self) -> float:
        return self.baseline - self.current

    def message(self) -> str:
        """``name: retention X vs baseline Y (drop D)`` with as many decimals (3 at least) as it takes for the
        printed drop to exceed the printed tolerance: 1.0000 vs 0.9996 reads ``drop 0.0004``, never 0.000."""
        d = shown_digits(self.drop, self.tolerance)
        what = {"pdms": "PDMS retention", "epdms": "EPDMS retention",
                "epdms2": "two-stage EPDMS retention"}.get(self.metric, "retention")
        return f"{self.name}: {what} {self.current:.{d}f} vs baseline {self.baseline:.{d}f} (drop {self.drop:.{d}f})"


def shown_digits(drop: float, tolerance: float, least: int = 3, most: int = 12) -> int:
    """The fewest decimals, from `least`, at which `drop` (above `tolerance`) prints above the tolerance."""
    for d in range(least, most + 1):
        if round(drop, d) > round(tolerance, d):
            return d
    return most


#: Each verdict metric's (per-cell retention field, axes section) in a certificate.
METRIC_FIELDS = {"l2": ("retention", "axes"), "pdms": ("pdms_retention", "axes_pdms"),
                 "epdms": ("epdms_retention", "axes_epdms"), "epdms2": ("epdms2_retention", "axes_epdms2")}


def gate_metric(cert: Mapping[str, object]) -> str:
    """The metric a certificate's verdict is put on, which its gate compares (``verdict.metric``, l2 before it
    was recorded)."""
    metric = _section(cert, "verdict").get("metric", "l2")
    return metric if isinstance(metric, str) and metric in METRIC_FIELDS else "l2"


#: The metric convention of certificates written before it was recorded, and the tool's (not an option).
CONVENTION = "stp3"
#: The axes the gate compares (of `records.AXES`; the gap is their difference).
GATED_AXES = tuple(a for a in AXES if a != "gap")


def _section(cert: Mapping[str, object], name: str) -> Mapping[str, object]:
    part = cert.get(name)
    return part if isinstance(part, Mapping) else {}


def baseline_seeds(cert: Mapping[str, Any]) -> int:
    """How many corruption seeds a certificate's random cells ran under (1 for certificates before seeds)."""
    got = _section(cert, "settings").get("seeds", 1)
    return int(got) if isinstance(got, int) and not isinstance(got, bool) else 1


def settings_mismatches(baseline: Mapping[str, Any], settings: RunSettings, *, frames_scored: int | None = None,
                        convention: str = CONVENTION) -> list[str]:
    """What of this run (its `settings`, the frames it scores and its metric convention) the baseline certificate
    has another value of, as 'name: baseline X, this run Y (option)': the settings `RunSettings.baseline_differences`
    names (the table in `settings` says which and why), the seed count apart (`check_baseline_compatible`)."""
    out = []
    theirs_frames = _section(baseline, "dataset").get("frames")
    if frames_scored is not None and theirs_frames is not None and theirs_frames != frames_scored:
        out.append(f"scored frames: baseline {theirs_frames!r}, this run {frames_scored!r} (--drivedegrade-frames)")
    out += [d.against_baseline() for d in settings.baseline_differences(RunSettings.from_certificate(baseline))
            if d.name != "seeds"]
    theirs_convention = _section(baseline, "settings").get("convention", CONVENTION)
    if theirs_convention != convention:
        out.append(f"metric convention: baseline {theirs_convention!r}, this run {convention!r} (the tool's default)")
    return out


def check_baseline_compatible(baseline: Mapping[str, Any], *, spec_version: str | None,
                              dataset_fingerprint: str | None, settings: RunSettings | None = None,
                              frames_scored: int | None = None, convention: str = CONVENTION) -> None:
    """Raise ``BaselineError`` when the baseline was certified under another spec version, another number of
    corruption seeds, other settings that change the numbers (`settings_mismatches`), or on another data set: a
    retention averaged over three seeds is not the same quantity as one seed's, so comparing them would gate on
    noise. Without `settings`, only the spec version and the data set are compared."""
    theirs = (baseline.get("spec_version"), _section(baseline, "dataset").get("fingerprint"))
    if spec_version != theirs[0]:
        raise BaselineError(f"the baseline certificate has spec version {theirs[0]!r} but this run has "
                            f"{spec_version!r}; retentions are comparable only under the same ladder and data")
    theirs_seeds = baseline_seeds(baseline)
    if settings is not None and settings.seeds != theirs_seeds:
        raise BaselineError(f"the baseline certificate was made with {theirs_seeds} corruption seed(s) per random "
                            f"cell (--drivedegrade-seeds {theirs_seeds}) but this run uses {settings.seeds}; "
                            f"retentions are compared only like with like: rerun with --drivedegrade-seeds "
                            f"{theirs_seeds}, or certify a new baseline with this seed count")
    differ = [] if settings is None else settings_mismatches(baseline, settings, frames_scored=frames_scored,
                                                             convention=convention)
    if differ:
        raise BaselineError(f"the baseline certificate was made under other settings that change the numbers: "
                            f"{'; '.join(differ)}; rerun with the baseline's settings, or certify a new baseline "
                            "with these")
    if dataset_fingerprint != theirs[1]:
        raise BaselineError(f"the baseline certificate has dataset fingerprint {theirs[1]!r} but this run has "
                            f"{dataset_fingerprint!r}; retentions are comparable only under the same ladder and "
                            "data")


def planner_mismatch(baseline: Mapping[str, Any], name: str | None) -> str | None:
    """Why the baseline is another planner's (its name differs: a planner's identity is its name, since the
    same planner retrained has another fingerprint and is the normal baseline), or None."""
    theirs = (baseline.get("planner") or {}).get("name") if isinstance(baseline.get("planner"), Mapping) else None
    if theirs == name:
        return None
    return (f"the baseline certificate is of planner {theirs!r} but this run certifies {name!r}; pass "
            "--drivedegrade-baseline-any-planner to gate one planner against another's certificate")


def _retentions(cert: Mapping[str, object], metric: str = "l2") -> dict[object, object]:
    """A certificate's retention on `metric` per cell id (whatever it holds; the gate checks the values it
    uses)."""
    cells, key = cert.get("cells"), METRIC_FIELDS[metric][0]
    return {c.get("cell"): c.get(key) for c in cells if isinstance(c, Mapping)} \
        if isinstance(cells, list) else {}


def not_compared(baseline: Mapping[str, Any], cells: Iterable[str], axes: Mapping[str, Any] | None = None,
                 metric: str = "l2") -> list[str]:
    """What the gate cannot compare, one phrase per kind: the baseline is incomplete (``completeness.complete``
    false), it has no retention for some of `cells`, or no value for a gated axis that this run has; and, once
    the run is done (`axes`: this run's, None at start-up), what the baseline has and this run did not compute
    (a run narrowed by ``-k`` or a shorter family list: its cells and axes). Empty when both cover each other."""
    cells = list(cells)
    out = []
    comp = baseline.get("completeness")
    if isinstance(comp, Mapping) and comp.get("complete") is False:
        missing = comp.get("missing_cells") or []
        out.append(f"the baseline run is incomplete (completeness.complete is false; {len(missing)} cell(s) missing"
                   + (f", shard(s) missing: {', '.join(map(str, comp['missing_shards']))}"
                      if comp.get("missing_shards") else "") + ")")
    theirs = _retentions(baseline, metric)
    lacking = [c for c in cells if theirs.get(c) is None]
    if lacking:
        shown = ", ".join(lacking[:8]) + (f" and {len(lacking) - 8} more" if len(lacking) > 8 else "")
        out.append(f"{len(lacking)} cell(s) of this run have no retention in the baseline: {shown}")
    mine, theirs_axes = Axes.from_builtins(axes), Axes.from_builtins(baseline.get(METRIC_FIELDS[metric][1]))
    null_axes = [a for a in GATED_AXES if mine.value(a) is not None and theirs_axes.value(a) is None]
    if null_axes:
        out.append(f"axes {', '.join(null_axes)} are null in the baseline")
    return out + ([] if axes is None else _not_computed(theirs, cells, theirs_axes, mine))


def _not_computed(theirs: Mapping[object, object], cells: list[str], base_axes: Axes, axes: Axes) -> list[str]:
    """The baseline's cells (with a retention) and gated axes that this finished run has no value for."""
    out = []
    skipped = [str(c) for c, r in theirs.items() if r is not None and c not in set(cells)]
    if skipped:
        shown = ", ".join(skipped[:8]) + (f" and {len(skipped) - 8} more" if len(skipped) > 8 else "")
        out.append(f"{len(skipped)} cell(s) of the baseline were not computed by this run: {shown}")
    dropped = [a for a in GATED_AXES if base_axes.value(a) is not None and axes.value(a) is None]
    if dropped:
        out.append(f"axes {', '.join(dropped)} of the baseline are null in this run")
    return out


def cell_regression(cell: str, current: float, baseline: Mapping[str, Any], tolerance: float,
                    metric: str = "l2") -> Regression | None:
    """The regression of one cell's retention on `metric` against the baseline certificate, or None (also when
    the cell is new)."""
    base = _retentions(baseline, metric).get(cell)
    if not isinstance(base, (int, float)) or current is None or not math.isfinite(current):
        return None
    return Regression(cell, float(base), float(current), tolerance, metric) \
        if float(base) - current > tolerance else None


def compare_to_baseline(current: Mapping[str, Any], baseline: Mapping[str, Any],
                        tolerance: float = DEFAULT_TOLERANCE) -> dict[str, list[Regression]]:
    """Cells and axes (quality, removal, mean) whose retention fell more than `tolerance` below the baseline, on
    the metric of `current`'s verdict (`gate_metric`: L2 retention and ``axes``, or PDMS retention and
    ``axes_pdms``; the baseline's metric is the same, or `check_baseline_compatible` refuses it).

    `current` and `baseline` are certificate-shaped mappings. Returns {"cells": [...], "axes": [...]}; an axis
    regression fails the session. Raises ``BaselineError`` on an incompatible baseline.
    """
    frames = _section(current, "dataset").get("frames")
    check_baseline_compatible(baseline, spec_version=current.get("spec_version"),
                              dataset_fingerprint=(current.get("dataset") or {}).get("fingerprint"),
                              settings=RunSettings.from_certificate(current),
                              frames_scored=frames if isinstance(frames, int) else None,
                              convention=str(_section(current, "settings").get("convention", CONVENTION)))
    metric = gate_metric(current)
    key, axes_key = METRIC_FIELDS[metric]
    cells = [reg for c in current.get("cells", [])
             if (reg := cell_regression(c["cell"], c.get(key), baseline, tolerance, metric))]
    axes = []
    ours, base_axes = Axes.from_builtins(current.get(axes_key)), Axes.from_builtins(baseline.get(axes_key))
    for name in GATED_AXES:
        mine, theirs = ours.value(name), base_axes.value(name)
        if mine is not None and theirs is not None and theirs - mine > tolerance:
            axes.append(Regression(f"axis:{name}", theirs, mine, tolerance, metric))
    return {"cells": cells, "axes": axes}
