"""The one column spec: every per-cell figure's name, and which of them each output carries.

cells.csv, the certificate's cells and the JUnit testcase properties all select from the names built here, so a
metric is named once. Names up to ``retention_ci_high`` are stable (SPEC section 6): add, never rename.
"""

from __future__ import annotations

from ..constants import REPORT_HORIZONS_S
from ..metrics.trajectory import CONVENTIONS


def per_horizon(kind: str, convention: str) -> tuple[str, ...]:
    """`kind` at each report horizon under `convention`, e.g. l2_1s_stp3, l2_2s_stp3, l2_3s_stp3."""
    return tuple(f"{kind}_{h}s_{convention}" for h in REPORT_HORIZONS_S)


#: Which cell, on how many frames (frames with a finite plan).
IDENTITY: tuple[str, ...] = ("cell", "family", "severity", "frames")
#: SPEC section 6's stable names: identity, the cell's mean L2 and its retention with the bootstrap CI.
STABLE: tuple[str, ...] = (*IDENTITY, "l2_avg", "retention", "retention_ci_low", "retention_ci_high")
#: Mean L2 over the three horizons in each convention (``l2_avg`` is the stp3 one).
L2_AVG: tuple[str, ...] = tuple(f"l2_avg_{c}" for c in CONVENTIONS)
#: L2, collision and VRU collision at 1/2/3 s in both conventions.
HORIZONS: tuple[str, ...] = tuple(name for kind in ("l2", "collision", "vru") for c in CONVENTIONS
                                  for name in per_horizon(kind, c))
#: The rest of a cell's summary.
#: `conformance_errors` counts frames the planner failed, `data_errors` frames whose images could not be produced.
EXTRA: tuple[str, ...] = ("jerk", "endpoint_shift", "energy", "separable_from_null", "conformance_errors",
                          "data_errors")
#: The PDMS-like score (spec 3), mean per cell, its sub-scores, and PDMS retention M(cell) / M(clean) (a reward)
#: with its paired bootstrap CI; all in [0, 1] (retention may exceed 1), empty where not scored.
PDMS: tuple[str, ...] = ("pdms", "nc", "dac", "ttc", "ep", "comfort", "pdms_retention", "pdms_retention_ci_low",
                         "pdms_retention_ci_high")
#: What makes a row traceable.
PROVENANCE: tuple[str, ...] = ("planner", "planner_fingerprint", "dataset_fingerprint", "split", "spec_version",
                               "seed", "convention")

#: cells.csv, in this order.
CSV: tuple[str, ...] = (*STABLE, *L2_AVG, *HORIZONS, *EXTRA, *PDMS, "map_scored", *PROVENANCE)
#: The certificate's per-cell fields (the CSV carries every metric; key order is irrelevant in sealed JSON).
CERTIFICATE_CELL: tuple[str, ...] = (*STABLE, *EXTRA, *per_horizon("l2", "stp3"), *per_horizon("l2", "uniad"),
                                     *per_horizon("collision", "stp3"), "vru_3s_stp3", *PDMS, "map_scored")
#: JUnit testcase properties of a cell item, known as soon as the cell ran (no retention yet: clean may run on
#: another worker).
TESTCASE: tuple[str, ...] = (*IDENTITY, "failed_frames", "data_errors", "l2_avg", *per_horizon("l2", "stp3"),
                             *per_horizon("l2", "uniad"), "collision_3s_stp3", "vru_3s_stp3", "jerk", "resumed", "pdms")
