"""Write a finished run's outputs into `<report>/<planner>/`: cells.csv, certificate.json and report.html."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..cells import CellRecord
from ..certificate.seal import Provenance
from ..scoring.records import RunAnalysis

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey


def write_outputs(report_dir: Path, prov: Provenance, records: Mapping[str, CellRecord], analysis: RunAnalysis,
                  missing: Sequence[str], *, gt: Mapping[str, np.ndarray], montage: np.ndarray | None,
                  completeness: Mapping[str, object] | None = None, cost: Mapping[str, Any] | None = None,
                  signing_key: Ed25519PrivateKey | None = None,
                  adaptive: Mapping[str, object] | None = None) -> tuple[dict[str, Any], str]:
    """Write the three files and return (the sealed certificate, a line saying what was written). `missing`
    cells (a crash, Ctrl-C, -k) and `completeness` (missing shards) go into the certificate's completeness.
    `gt`: frame token -> ground truth (the trajectory panels). With `signing_key` the certificate is signed
    before it is sealed, so its digest covers the signature."""
    from ..certificate.seal import build_certificate, seal, write_certificate
    from .cells_csv import write_cells_csv
    from .html import trajectory_examples, write_report

    folder = Path(report_dir) / prov.planner_name
    cert = build_certificate(analysis, prov, records=records)
    cert["completeness"] = {"complete": not missing, "missing_cells": list(missing), **(completeness or {})}
    if cost is not None:
        cert["cost"] = dict(cost)
    if adaptive is not None:
        cert["adaptive"] = dict(adaptive)
    if signing_key is not None:
        from ..certificate.signing import sign

        cert = sign(cert, signing_key)
    cert = seal(cert)
    write_certificate(folder / "certificate.json", cert)
    write_cells_csv(folder / "cells.csv", analysis, prov)
    write_report(folder / "report.html", analysis, prov, montage=montage,
                 trajectories=trajectory_examples(records, gt, analysis.summaries),
                 created=cert.get("created", ""), digest=cert["digest"], cost=cost,
                 signed_by=str((cert.get("signature") or {}).get("public_key_fingerprint", "")))
    return cert, f"wrote {folder / 'report.html'}, cells.csv and certificate.json"
