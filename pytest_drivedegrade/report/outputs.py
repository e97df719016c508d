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

    from ..certificate.closed import ClosedRun


def write_outputs(report_dir: Path, prov: Provenance, records: Mapping[str, CellRecord], analysis: RunAnalysis,
                  missing: Sequence[str], *, gt: Mapping[str, np.ndarray], montage: np.ndarray | None,
                  completeness: Mapping[str, object] | None = None, cost: Mapping[str, Any] | None = None,
                  signing_key: Ed25519PrivateKey | None = None,
                  closed: ClosedRun | None = None,
                  adaptive: Mapping[str, object] | None = None,
                  digests: Mapping[str, str] | None = None) -> tuple[dict[str, Any], str]:
    """Write the three files (four with closed-loop cells) as one set (`atomic_write_set`: all rendered and
    written to temporaries first, the certificate renamed last, so a crash on the way leaves the previous set
    whole, issue 20 L1) and return (the sealed certificate, a line saying what was written). `missing`
    cells (a crash, Ctrl-C, -k) and `completeness` (missing shards) go into the certificate's completeness.
    `gt`: frame token -> ground truth (the trajectory panels). With `signing_key` the certificate is signed
    before it is sealed, so its digest covers the signature. `digests`: records' digests already known
    (`FinishedRun.digests`)."""
    from ..atomic import atomic_write_set
    from ..certificate.seal import build_certificate, certificate_text, seal
    from .cells_csv import cells_csv_text
    from .html import render_report, trajectory_examples

    folder = Path(report_dir) / prov.planner_name
    cert = build_certificate(analysis, prov, records=records, digests=digests)
    cert["completeness"] = {"complete": not missing, "missing_cells": list(missing), **(completeness or {})}
    if cost is not None:
        cert["cost"] = dict(cost)
    if closed is not None:  # the closed loop's section (SPEC section 13), signed and sealed with the rest
        cert["closed_loop"] = closed.section(analysis.verdict.label, analysis.verdict.flat)
    if adaptive is not None:
        cert["adaptive"] = dict(adaptive)
    if signing_key is not None:
        from ..certificate.signing import sign

        cert = sign(cert, signing_key)
    cert = seal(cert)
    extra, closed_html = _closed_report(prov.planner_name, closed, analysis)
    html = render_report(analysis, prov, montage=montage,
                         trajectories=trajectory_examples(records, gt, analysis.summaries),
                         created=cert.get("created", ""), digest=cert["digest"], cost=cost,
                         signed_by=str((cert.get("signature") or {}).get("public_key_fingerprint", "")),
                         closed_html=closed_html)
    atomic_write_set({folder / "cells.csv": cells_csv_text(analysis, prov).encode("utf-8"),
                      **{folder / name: text.encode("utf-8") for name, text in extra.items()},
                      folder / "report.html": html.encode("utf-8"),
                      folder / "certificate.json": certificate_text(cert).encode("utf-8")})
    return cert, f"wrote {folder / 'report.html'}, cells.csv" + (", closed_loop.csv" if closed else "") + \
        " and certificate.json"


def _closed_report(planner: str, closed: ClosedRun | None,
                   analysis: RunAnalysis) -> tuple[dict[str, str], str]:
    """(closed_loop.csv's text by its file name, the report's closed-loop section); both empty without
    closed-loop cells."""
    if closed is None:
        return {}, ""
    from .closed_html import closed_fragment
    from .closed_outputs import closed_csv_text

    return ({"closed_loop.csv": closed_csv_text(planner, closed)},
            closed_fragment(closed.analysis(analysis.verdict.label, analysis.verdict.flat), closed))
