"""The CI gate: a run's retentions against a stored baseline certificate, cell by cell and axis by axis."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..constants import DEFAULT_TOLERANCE
from ..errors import DriveDegradeError


class BaselineError(DriveDegradeError):
    """A baseline certificate that cannot be compared: another spec version or data set, or malformed."""


@dataclass(frozen=True)
class Regression:
    """One retention that fell more than the tolerance below its baseline."""

    name: str  # a cell id, or "axis:quality"
    baseline: float
    current: float

    @property
    def drop(self) -> float:
        return self.baseline - self.current

    def message(self) -> str:
        return f"{self.name}: retention {self.current:.3f} vs baseline {self.baseline:.3f} (drop {self.drop:.3f})"


def baseline_seeds(cert: Mapping[str, Any]) -> int:
    """How many corruption seeds a certificate's random cells ran under (1 for certificates before seeds)."""
    settings = cert.get("settings")
    got = settings.get("seeds", 1) if isinstance(settings, Mapping) else 1
    return int(got) if isinstance(got, int) and not isinstance(got, bool) else 1


def check_baseline_compatible(baseline: Mapping[str, Any], *, spec_version: str | None,
                              dataset_fingerprint: str | None, seeds: int | None = None) -> None:
    """Raise ``BaselineError`` when the baseline was certified under another spec version or data set, or (when
    `seeds` is given) under another number of corruption seeds: a retention averaged over three seeds is not
    the same quantity as one seed's, so comparing them would gate on noise."""
    theirs = (baseline.get("spec_version"), (baseline.get("dataset") or {}).get("fingerprint"))
    for what, mine, other in (("spec version", spec_version, theirs[0]),
                              ("dataset fingerprint", dataset_fingerprint, theirs[1])):
        if mine != other:
            raise BaselineError(f"the baseline certificate has {what} {other!r} but this run has {mine!r}; "
                                "retentions are comparable only under the same ladder and data")
    theirs_seeds = baseline_seeds(baseline)
    if seeds is not None and seeds != theirs_seeds:
        raise BaselineError(f"the baseline certificate was made with {theirs_seeds} corruption seed(s) per random "
                            f"cell (--drivedegrade-seeds {theirs_seeds}) but this run uses {seeds}; retentions are "
                            f"compared only like with like: rerun with --drivedegrade-seeds {theirs_seeds}, or "
                            "certify a new baseline with this seed count")


def cell_regression(cell: str, current: float, baseline: Mapping[str, Any], tolerance: float) -> Regression | None:
    """The regression of one cell against the baseline certificate, or None (also when the cell is new)."""
    base = {c.get("cell"): c.get("retention") for c in baseline.get("cells", [])}.get(cell)
    if base is None or current is None or not math.isfinite(current):
        return None
    return Regression(cell, float(base), float(current)) if float(base) - current > tolerance else None


def compare_to_baseline(current: Mapping[str, Any], baseline: Mapping[str, Any],
                        tolerance: float = DEFAULT_TOLERANCE) -> dict[str, list[Regression]]:
    """Cells and axes (quality, removal, mean) whose retention fell more than `tolerance` below the baseline.

    `current` and `baseline` are certificate-shaped mappings. Returns {"cells": [...], "axes": [...]}; an axis
    regression fails the session. Raises ``BaselineError`` on an incompatible baseline.
    """
    check_baseline_compatible(baseline, spec_version=current.get("spec_version"),
                              dataset_fingerprint=(current.get("dataset") or {}).get("fingerprint"),
                              seeds=baseline_seeds(current))
    cells = [reg for c in current.get("cells", [])
             if (reg := cell_regression(c["cell"], c.get("retention"), baseline, tolerance))]
    axes = []
    for name in ("quality", "removal", "mean"):
        mine, theirs = (current.get("axes") or {}).get(name), (baseline.get("axes") or {}).get(name)
        if mine is not None and theirs is not None and theirs - mine > tolerance:
            axes.append(Regression(f"axis:{name}", float(theirs), float(mine)))
    return {"cells": cells, "axes": axes}
