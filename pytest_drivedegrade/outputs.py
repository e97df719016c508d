"""Write a finished run's outputs: cells.csv, certificate.json, report.html and the JUnit suite properties."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .corruptions.registry import SPEC_VERSION


def _provenance(plugin: Any, context: Any, name: str, key: dict[str, Any], session: Any):
    from .report.certificate import Provenance

    source = "embedded world" if plugin.options.data is None else str(plugin.options.data)
    args = " ".join(str(a) for a in session.config.invocation_params.args)
    return Provenance(planner_name=name, planner_fingerprint=key["planner_fingerprint"],
                      dataset_fingerprint=key["dataset_fingerprint"], split=plugin.options.split,
                      spec_version=SPEC_VERSION, seed=plugin.options.seed, frames=len(context.frames),
                      frames_unscored=context.frames_unscored, data_source=source, command=f"pytest {args}",
                      tool_version=__version__)


def _montage(context: Any, seed: int) -> np.ndarray | None:
    """One front-camera frame under every family at S4 (the report's figure)."""
    from .corruptions.preview import montage

    frame = context.frames[0]
    try:
        image = context.decode(frame, "CAM_FRONT")
    except Exception:  # noqa: BLE001 - the figure is optional; a bad image was already reported by the cells
        return None
    return montage(image, severity=4, seed=seed, frame=frame.token, camera="CAM_FRONT", width=220)


def write_outputs(plugin: Any, session: Any, context: Any, name: str, key: dict[str, Any],
                  records: dict[str, Any], analysis: Any, out: Any, missing: list[str]) -> dict[str, Any]:
    """Write the three files into <report>/<planner>/ and return the sealed certificate. A run with missing
    cells (a crash, Ctrl-C, -k) says so in the certificate, so it is not mistaken for a complete baseline.
    `records`: cell -> CellRecord."""
    from .report.cells import write_cells_csv
    from .report.certificate import build_certificate, certificate_text, seal
    from .report.html import trajectory_examples, write_report
    from .report.io import atomic_write_text
    from .report.junit import suite_properties

    folder = Path(plugin.options.report_dir) / name
    prov = _provenance(plugin, context, name, key, session)
    cert = build_certificate(analysis, prov)
    cert["completeness"] = {"complete": not missing, "missing_cells": list(missing)}
    cert = seal(cert)
    atomic_write_text(folder / "certificate.json", certificate_text(cert))
    write_cells_csv(folder / "cells.csv", analysis, prov)
    gt = {f.token: f.gt_future for f in context.frames}
    write_report(folder / "report.html", analysis, prov, montage=_montage(context, plugin.options.seed),
                 trajectories=trajectory_examples(records, gt, analysis.summaries),
                 created=cert.get("created", ""), digest=cert["digest"])
    xml = _junit(session.config)
    if xml is not None:
        for prop, value in suite_properties(analysis):
            xml.add_global_property(prop, value)
    out.lines.append(f"wrote {folder / 'report.html'}, cells.csv and certificate.json")
    return cert


def _junit(config: Any) -> Any:
    from _pytest.junitxml import xml_key

    return config.stash.get(xml_key, None)
