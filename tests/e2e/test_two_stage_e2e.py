"""End-to-end: --drivedegrade-two-stage (issue 39), NAVSIM v2's two-stage pseudo-simulation as a cell mode: the
two-stage EPDMS and its retention in cells.csv, the certificate (its axes, section and settings; verify agrees),
JUnit and report.html; the verdict put on it (--drivedegrade-metric epdms2); the same cells bit for bit with -n 0
and -n 2; refused off the embedded world, with a planner that has reset(), and epdms2 without the mode."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, no_traceback, read_csv, stored_records, verify_cli  # noqa: E402

pytest_plugins = ["plugin_support"]

#: A planner that reads the front camera: constant acceleration ahead, drifting sideways as the front image
#: darkens (so a corruption, or a moved camera, moves its plan); it needs nothing but its inputs, so it plans at
#: stage two's start poses as at the logged ones.
PLANNER = '''
import numpy as np
import pytest

T = 0.5 * np.arange(1, 7)


class BrightPlanner:
    name = "bright"
    cameras = ("CAM_FRONT",)

    def predict(self, images, ego, cmd):
        side = 4.0 * max(0.0, 0.3 - float(images["CAM_FRONT"].mean()) / 255.0)
        vx, vy = ego.velocity
        x = np.maximum.accumulate(np.maximum(vx * T + 0.5 * ego.acceleration[0] * T * T, 0.0))
        return np.stack([x, vy * T + side * T], axis=1)
{extra}

@pytest.fixture(scope="session")
def planner():
    return BrightPlanner()
'''
TWO = ("--drivedegrade-two-stage", "--drivedegrade-metric", "epdms2")
COLUMNS = ("epdms_stage2", "epdms2", "epdms2_frames", "epdms2_retention", "epdms2_retention_ci_low",
           "epdms2_retention_ci_high")
FAMILIES, SEVERITIES = "jpeg,blackout", "5"


def _planner(dd, extra: str = "") -> None:
    dd.pytester.makepyfile(myplanner=PLANNER.format(extra=extra))


def test_two_stage_columns_certificate_report_and_verdict(dd):
    _planner(dd)
    result = dd.run(*TWO, "--junitxml=two.xml", "-n", "0", families=FAMILIES, severities=SEVERITIES)
    no_traceback(result)
    result.assert_outcomes(passed=5)
    folder = dd.folder("bright")
    rows = {r["cell"]: r for r in read_csv(folder / "cells.csv")}
    assert set(rows) == {"clean", "null", "blind", "jpeg-s5", "blackout-s5"}
    for cell, row in rows.items():
        assert all(row[c] != "" for c in COLUMNS), (cell, row)
        assert int(row["epdms2_frames"]) > 0
        assert 0.0 <= float(row["epdms2"]) <= float(row["epdms"]) + 1e-6 or cell != "clean"
        assert 0.0 <= float(row["epdms_stage2"]) <= 1.0
    assert float(rows["clean"]["epdms2_retention"]) == 1.0
    assert float(rows["blind"]["epdms2_retention"]) != 1.0  # black cameras move this planner at stage two too
    cert = load_json(folder / "certificate.json")
    assert cert["settings"]["two_stage"] is True and cert["verdict"]["metric"] == "epdms2"
    assert cert["verdict"]["text"].startswith("On two-stage EPDMS retention")
    assert set(cert["axes_epdms2"]) >= {"quality", "removal", "gap", "mean"}
    assert cert["two_stage"]["sigma_squared"] == 0.1 and len(cert["two_stage"]["starts"]) == 7
    by_cell = {c["cell"]: c for c in cert["cells"]}
    assert by_cell["blackout-s5"]["epdms2_retention"] == pytest.approx(float(rows["blackout-s5"]["epdms2_retention"]),
                                                                       abs=1e-6)
    assert cert["axes_epdms2"]["removal"] == pytest.approx(by_cell["blackout-s5"]["epdms2_retention"], abs=1e-6)
    verified = verify_cli(folder / "certificate.json")
    assert verified.returncode == 0, verified.stdout + verified.stderr
    from pytest_drivedegrade.certificate.consistency import check_consistency

    assert not check_consistency(cert)
    edited = {**cert, "axes_epdms2": {**cert["axes_epdms2"], "removal": 0.5}}  # verify recomputes it from the cells
    assert any(p.startswith("axes_epdms2.removal") for p in check_consistency(edited)), check_consistency(edited)
    stored = load_json(folder / "cells" / "jpeg-s5.json")["record"]
    assert len(stored["epdms2"]) == len(stored["frames"]) and any(math.isfinite(v) for v in stored["epdms2"])
    assert stored["seconds"]["stage_two_calls"] == 7 * int(rows["jpeg-s5"]["epdms2_frames"])  # in the cost
    assert cert["cost"]["stage_two_calls"] == sum(7 * int(r["epdms2_frames"]) for r in rows.values())
    result.stdout.fnmatch_lines(["cost: * predictions and * stage-two calls*"])
    html = (folder / "report.html").read_text()
    assert 'id="two-stage"' in html and "two-stage retention" in html
    junit = (dd.pytester.path / "two.xml").read_text()
    assert 'name="drivedegrade_axis_epdms2_removal"' in junit, junit[:3000]
    assert re.search(r'<property name="epdms2" value="0\.\d+"', junit)  # each cell item's own two-stage EPDMS


def test_one_stage_run_leaves_the_two_stage_columns_empty(dd):
    _planner(dd)
    result = dd.run("-n", "0", families="jpeg", severities=SEVERITIES)
    no_traceback(result)
    folder = dd.folder("bright")
    for row in read_csv(folder / "cells.csv"):
        assert all(row[c] == "" for c in COLUMNS), row
    cert = load_json(folder / "certificate.json")
    assert "axes_epdms2" not in cert and "two_stage" not in cert and "two_stage" not in cert["settings"]
    assert all("epdms2" not in c for c in cert["cells"])
    assert "epdms2" not in load_json(folder / "cells" / "clean.json")["record"]
    assert "stage_two_calls" not in cert["cost"]


def test_two_stage_cells_are_bit_identical_with_two_workers(dd):
    """The stage-two renders and corruptions are keyed by the frame, not by the process: -n 2 stores the very
    records -n 0 stores (timings aside)."""
    _planner(dd)
    serial = dd.run(*TWO, "-n", "0", report="serial", families=FAMILIES, severities=SEVERITIES)
    no_traceback(serial)
    spread = dd.run(*TWO, "-n", "2", report="spread", families=FAMILIES, severities=SEVERITIES, subprocess=True)
    assert spread.ret == 0, spread.stdout.str()[-3000:]
    one, two = (stored_records(dd.folder("bright", report=r)) for r in ("serial", "spread"))
    assert set(one) == set(two) and len(one) == 5
    assert all(one[c] == two[c] for c in one)
    assert (dd.folder("bright", "serial") / "cells.csv").read_text() == \
        (dd.folder("bright", "spread") / "cells.csv").read_text()


def test_refused_on_nuscenes_data(dd, tmp_path):
    """A data root that is not the embedded world (nuScenes' layout, no world manifest) cannot be rendered at a pose
    the car did not drive: a usage error saying so, before any cell."""
    from pytest_drivedegrade.data.nuscenes import WORLD_MANIFEST

    logs = tmp_path / "nuscenes"
    shutil.copytree(dd.world, logs)
    (logs / WORLD_MANIFEST).unlink()
    _planner(dd)
    result = dd.run("--drivedegrade-two-stage", data=logs, families="jpeg", severities=SEVERITIES)
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    text = result.stderr.str() + result.stdout.str()
    assert "--drivedegrade-two-stage needs the embedded world" in text and "never drove" in text
    assert not (dd.pytester.path / "rep").exists() or not list(Path(dd.pytester.path / "rep").glob("*/cells"))


def test_refused_for_a_planner_with_reset_and_epdms2_without_the_mode(dd):
    _planner(dd, extra="\n    def reset(self, scene_token):\n        pass\n")
    result = dd.run("--drivedegrade-two-stage", families="jpeg", severities=SEVERITIES)
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    assert "cannot score a planner with reset()" in result.stderr.str() + result.stdout.str()
    _planner(dd)
    result = dd.run("--drivedegrade-metric", "epdms2", families="jpeg", severities=SEVERITIES)
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    assert "it needs --drivedegrade-two-stage" in result.stderr.str()
