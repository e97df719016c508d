"""The one end of a run (`report.publish`): a `FinishedRun` in, the three outputs and the summary lines out, the
same for the pytest controller and `drivedegrade merge` (their end-to-end equality is tests/e2e/test_shards.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_analysis import ORDER, synthetic_run

from pytest_drivedegrade.certificate import seal
from pytest_drivedegrade.certificate.finished import FinishedRun, FloorFigures
from pytest_drivedegrade.report.publish import publish
from pytest_drivedegrade.settings import RunSettings

SETTINGS = RunSettings(frames=8, seed=3, flat=0.95, batch=4, reuse=False)
KEY = {"planner_fingerprint": "sha256:p", "dataset_fingerprint": "sha256:d"}


def finished(**changes) -> FinishedRun:
    recs, gt = synthetic_run(8, families=ORDER[:2])
    prov = seal.run_provenance(SETTINGS, planner_name="demo", key=KEY, frames=8, frames_unscored=0,
                               command="pytest --drivedegrade demo.py")
    base = FinishedRun(records={r.cell: r for r in recs}, provenance=prov, settings=SETTINGS,
                       floor=FloorFigures.of([2.0, 4.0], [4.0, 8.0]), gt=gt, front=None,
                       missing_cells=("fog-s9",), resumed_cells=("null", "clean"), notes=("reused 2 cells",))
    return FinishedRun(**{**base.__dict__, **changes})


def test_floor_figures_known_answers():
    assert FloorFigures.of(None) == FloorFigures()
    assert FloorFigures.of([1.0, np.nan, 3.0]).l2 == 2.0 and FloorFigures.of([1.0, 3.0]).extra == {}
    assert FloorFigures.of([2.0, 4.0], [6.0, 6.0]).extra == {"ego_removal": pytest.approx(0.5)}


def test_run_provenance_takes_the_settings_and_the_recorded_tool():
    prov = seal.run_provenance(SETTINGS, planner_name="demo", key=KEY, frames=8, frames_unscored=1, command="c")
    assert (prov.split, prov.seed, prov.frames_requested, prov.timeout, prov.data_source) == \
        ("val", 3, 8, 60.0, "embedded world")
    assert prov.planner_fingerprint == "sha256:p" and prov.versions["numpy"] == np.__version__
    old = seal.run_provenance(SETTINGS, planner_name="demo", key=KEY, frames=8, frames_unscored=1, command="c",
                              recorded={"spec_version": "0.9", "tool_version": "0.1", "versions": {"numpy": "1"}})
    assert (old.spec_version, old.tool_version, dict(old.versions)) == ("0.9", "0.1", {"numpy": "1"})


def test_publish_writes_what_the_run_says(tmp_path):
    out = publish(finished(), tmp_path)
    cert = seal.verify(tmp_path / "demo" / "certificate.json")
    assert cert == out.certificate and (tmp_path / "demo" / "cells.csv").is_file()
    assert {"batch": 4, "reuse": False, "device": "cpu", "seed": 3, "timeout": 60.0}.items() <= \
        cert["settings"].items()
    assert cert["floor"]["ego_removal"] == 0.5 and math.isclose(out.analysis.floor.ego_removal, 0.5)
    assert cert["completeness"] == {"complete": False, "missing_cells": ["fog-s9"]}
    assert cert["cost"]["resumed_cells"] == ["clean", "null"] and cert["cost"]["predictions"] == 13 * 8
    assert out.lines[-3] == "reused 2 cells" and out.lines[-2].startswith("cost: 104 predictions, 0 frames reused")
    assert out.lines[-1].startswith("wrote ") and not any("INCOMPLETE" in line for line in out.lines)


def test_a_merge_missing_shards_says_so(tmp_path):
    out = publish(finished(missing_shards=(2,), resumed_cells=None, missing_cells=()), tmp_path)
    cert = json.loads((tmp_path / "demo" / "certificate.json").read_text())
    assert cert["completeness"] == {"complete": False, "missing_cells": [], "missing_shards": [2]}
    assert "resumed_cells" not in cert["cost"]
    assert "INCOMPLETE: shard(s) 2 missing; the certificate says completeness: false" in out.lines


def test_publish_signs_with_the_given_key(tmp_path):
    from pytest_drivedegrade.certificate.signing import keygen, load_private_key, load_public_key, verify_signature

    key_path, pub_path = keygen(tmp_path / "k")
    publish(finished(), tmp_path, signing_key=load_private_key(key_path.read_bytes(), "k"))
    cert = seal.verify(tmp_path / "demo" / "certificate.json")
    assert verify_signature(cert, load_public_key(pub_path)) == cert["signature"]["public_key_fingerprint"]
