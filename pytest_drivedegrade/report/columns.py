"""The one column spec: every per-cell figure's name, and which of them each output carries.

cells.csv, the certificate's cells and the JUnit testcase properties all select from the names built here and in
`certificate.fields` (the certificate's own, below the renderers), so a metric is named once. Names up to
``retention_ci_high`` are stable (SPEC section 6): add, never rename.
"""

from __future__ import annotations

from ..certificate.fields import EPDMS, EXTRA, IDENTITY, PDMS, STABLE, TWO_STAGE, per_horizon
from ..metrics.trajectory import CONVENTIONS

__all__ = ["COMMAND", "CSV", "EPDMS", "EXTRA", "HORIZONS", "IDENTITY", "L2_AVG", "PDMS", "PROVENANCE", "STABLE",
           "TESTCASE", "TWO_STAGE", "per_horizon"]

#: Mean L2 over the three horizons in each convention (``l2_avg`` is the stp3 one).
L2_AVG: tuple[str, ...] = tuple(f"l2_avg_{c}" for c in CONVENTIONS)
#: L2, collision and VRU collision at 1/2/3 s in both conventions.
HORIZONS: tuple[str, ...] = tuple(name for kind in ("l2", "collision", "vru") for c in CONVENTIONS
                                  for name in per_horizon(kind, c))
#: What makes a row traceable.
PROVENANCE: tuple[str, ...] = ("planner", "planner_fingerprint", "dataset_fingerprint", "split", "spec_version",
                               "seed", "convention")

#: The command_swap cell's following figure (spec 5, issue 40), on its row of cells.csv only (empty on every other
#: row): the figure, its 95 % interval, the label, the frames scored and the junction frames (an alternative given).
COMMAND: tuple[str, ...] = ("command_following", "command_following_ci_low", "command_following_ci_high",
                            "command_label", "command_frames", "junction_frames")
#: cells.csv, in this order.
CSV: tuple[str, ...] = (*STABLE, *L2_AVG, *HORIZONS, *EXTRA, *PDMS, "map_scored", *EPDMS, *PROVENANCE, *COMMAND,
                        *TWO_STAGE)
#: JUnit testcase properties of a cell item, known as soon as the cell ran (no retention yet: clean may run on
#: another worker).
TESTCASE: tuple[str, ...] = (*IDENTITY, "failed_frames", "data_errors", "l2_avg", *per_horizon("l2", "stp3"),
                             *per_horizon("l2", "uniad"), "collision_3s_stp3", "vru_3s_stp3", "jerk", "resumed", "pdms")
