"""The names of a cell's figures that the certificate carries (SPEC section 6), and its per-cell field list.

The certificate is the contract, so its names are declared here, below the renderers: `report.columns` builds
cells.csv's and the JUnit properties' selections from these blocks, so a metric is still named once. Names up to
``retention_ci_high`` are stable: add, never rename.
"""

from __future__ import annotations

from ..constants import REPORT_HORIZONS_S


def per_horizon(kind: str, convention: str) -> tuple[str, ...]:
    """`kind` at each report horizon under `convention`, e.g. l2_1s_stp3, l2_2s_stp3, l2_3s_stp3."""
    return tuple(f"{kind}_{h}s_{convention}" for h in REPORT_HORIZONS_S)


#: Which cell, on how many frames (frames with a finite plan).
IDENTITY: tuple[str, ...] = ("cell", "family", "severity", "frames")
#: SPEC section 6's stable names: identity, the cell's mean L2 and its retention with the bootstrap CI.
STABLE: tuple[str, ...] = (*IDENTITY, "l2_avg", "retention", "retention_ci_low", "retention_ci_high")
#: The rest of a cell's summary.
#: `conformance_errors` counts frames the planner failed, `data_errors` frames whose images could not be produced.
EXTRA: tuple[str, ...] = ("jerk", "endpoint_shift", "energy", "separable_from_null", "conformance_errors",
                          "data_errors")
#: The PDMS-like score (spec 3), mean per cell, its sub-scores, and PDMS retention M(cell) / M(clean) (a reward)
#: with its paired bootstrap CI; all in [0, 1] (retention may exceed 1), empty where not scored.
PDMS: tuple[str, ...] = ("pdms", "nc", "dac", "ttc", "ep", "comfort", "pdms_retention", "pdms_retention_ci_low",
                         "pdms_retention_ci_high")
#: The EPDMS (spec 4.1, NAVSIM v2), mean per cell, its own terms (ddc, tlc, lk, hc, ec; nc, dac, ep, ttc are the
#: PDMS's), and EPDMS retention with its paired bootstrap CI; empty where not scored (tlc: no traffic lights).
EPDMS: tuple[str, ...] = ("epdms", "ddc", "tlc", "lk", "hc", "ec", "epdms_retention", "epdms_retention_ci_low",
                          "epdms_retention_ci_high")
#: The two-stage pseudo-simulation (--drivedegrade-two-stage, issue 39): the cell's mean stage-two EPDMS (the
#: weighted stage-two scenes), its mean two-stage EPDMS (stage one's times stage two's, per frame), the frames
#: with a stage two, and two-stage EPDMS retention with its paired bootstrap CI; absent (empty in cells.csv) in a
#: one-stage run.
TWO_STAGE: tuple[str, ...] = ("epdms_stage2", "epdms2", "epdms2_frames", "epdms2_retention",
                              "epdms2_retention_ci_low", "epdms2_retention_ci_high")
#: The certificate's per-cell fields (cells.csv carries every metric; key order is irrelevant in sealed JSON).
CERTIFICATE_CELL: tuple[str, ...] = (*STABLE, *EXTRA, *per_horizon("l2", "stp3"), *per_horizon("l2", "uniad"),
                                     *per_horizon("collision", "stp3"), "vru_3s_stp3", *PDMS, "map_scored", *EPDMS,
                                     *TWO_STAGE)

#: What a certificate made by `drivedegrade analyse` from a per-cell table proves, as its ``provenance``
#: section says it (``kind`` IMPORTED_KIND) and `verify`, `reproduce` and `compare` repeat it.
IMPORTED_KIND = "imported"
IMPORTED_TEXT = "imported: metrics as given, arithmetic recomputed, plans not seen"


def is_imported(cert: object) -> bool:
    """Whether a certificate was made from a table by `drivedegrade analyse` (its provenance kind)."""
    prov = cert.get("provenance") if isinstance(cert, dict) else None
    return isinstance(prov, dict) and prov.get("kind") == IMPORTED_KIND


def imported_source(cert: object) -> str:
    """The table an imported certificate's figures came from ("" for any other certificate)."""
    prov = cert.get("provenance") if isinstance(cert, dict) else None
    return str(prov.get("table", "")) if isinstance(prov, dict) else ""


#: Where a certificate records whether its planner ran isolated (--drivedegrade-isolate, issue 37).
ISOLATED_KEY = "planner_isolated"


def planner_isolated(cert: object) -> bool | None:
    """Whether the run's planner was called only in a child process given its inputs (True), beside the stream
    in the run's own processes (False), or None where the certificate does not say (one written before the
    field existed, or imported)."""
    settings = cert.get("settings") if isinstance(cert, dict) else None
    found = settings.get(ISOLATED_KEY) if isinstance(settings, dict) else None
    return found if isinstance(found, bool) else None


def isolation_text(cert: object) -> str:
    """`planner_isolated` in words, as `drivedegrade verify` and `sign` print it."""
    isolated = planner_isolated(cert)
    if isolated:
        return ("planner isolated: yes (--drivedegrade-isolate: each call in a child process given only the "
                "frame's inputs)")
    if isolated is None:
        return ("planner isolated: not recorded (a certificate from before the field existed: its planner ran "
                "beside the stream, not isolated)")
    return ("planner isolated: no (its code ran in the run's processes, where it could find which cell was "
            "running; --drivedegrade-isolate closes that)")
