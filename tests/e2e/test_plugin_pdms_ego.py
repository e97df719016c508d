"""End-to-end: the PDMS columns and axes (spec 3), --drivedegrade-metric, and the ego cells with the ego-only
floor's known answer (SPEC section 10)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import AXIS_FAMILIES, load_json, no_traceback, read_csv, verify_cli  # noqa: E402

pytest_plugins = ["plugin_support"]

REPO = Path(__file__).resolve().parents[2]
PDMS_COLUMNS = ("pdms", "nc", "dac", "ttc", "ep", "comfort", "pdms_retention", "pdms_retention_ci_low",
                "pdms_retention_ci_high")


def test_the_ego_only_floor_is_ego_reliant_and_flat_on_the_cameras(dd):
    """Known answer: the floor reads no image (camera axes 1.000) and everything from the ego status, so zeroing
    it (ego_blind) wrecks its plans: ego_removal well below the flat line, `ego-reliant`."""
    dd.pytester.makepyfile(ego_floor=(REPO / "planners" / "ego_mlp.py").read_text())
    result = dd.run("--junitxml=ego.xml", planner="ego_floor.py", families=AXIS_FAMILIES + ",ego_noise,ego_blind",
                    severities="5")
    no_traceback(result)
    result.assert_outcomes(passed=15)
    [cert_path] = (dd.pytester.path / "rep").glob("*/certificate.json")
    cert = load_json(cert_path)
    axes = cert["axes"]
    assert axes["quality"] == axes["removal"] == 1.0
    assert axes["ego_removal"] < 0.75 and cert["verdict"]["ego_label"] == "ego-reliant"
    # S5 noise (past positions sigma 0.8 m, velocity 1.6 m/s) throws the floor's regressor out of its training
    # range: on this world it costs even more than zeroing the ego status
    assert axes["ego"] is not None and axes["ego"] < 0.95
    assert cert["verdict"]["label"] == "not-shown-to-use-cameras"
    assert cert["axes_pdms"]["quality"] == cert["axes_pdms"]["removal"] == 1.0
    rows = {r["cell"]: r for r in read_csv(cert_path.parent / "cells.csv")}
    assert {"ego_noise-s5", "ego_blind"} <= set(rows) and rows["ego_blind"]["severity"] == "0"
    result.stdout.fnmatch_lines(["*ego*ego-reliant*"])


def test_pdms_columns_and_the_verdict_on_pdms(dd):
    dd.write_planner()
    result = dd.run("--drivedegrade-metric", "pdms")
    no_traceback(result)
    folder = dd.folder()
    rows = read_csv(folder / "cells.csv")
    for row in rows:
        for col in PDMS_COLUMNS[:6]:
            assert 0.0 <= float(row[col]) <= 1.0, (row["cell"], col, row[col])
        assert float(row["pdms_retention_ci_low"]) <= float(row["pdms_retention"]) <= \
            float(row["pdms_retention_ci_high"]) + 1e-9
    clean = next(r for r in rows if r["cell"] == "clean")
    assert float(clean["pdms_retention"]) == 1.0 and float(clean["map_scored"]) == 1.0
    cert = load_json(folder / "certificate.json")
    assert cert["verdict"]["metric"] == "pdms" and cert["settings"]["verdict_metric"] == "pdms"
    assert set(cert["axes_pdms"]) >= {"quality", "removal", "gap", "mean", "ego", "ego_removal"}
    assert all("pdms_retention" in c for c in cert["cells"])
    html = (folder / "report.html").read_text()
    assert "PDMS" in html


EPDMS_COLUMNS = ("epdms", "ddc", "tlc", "lk", "hc", "ec", "epdms_retention", "epdms_retention_ci_low",
                 "epdms_retention_ci_high")


def test_epdms_columns_axes_and_the_verdict_on_epdms(dd):
    """Spec 4.1: the EPDMS terms in cells.csv (tlc empty: the world has no traffic lights, and the certificate
    says so), axes_epdms that verify recomputes, and the verdict put on EPDMS retention."""
    dd.write_planner()
    result = dd.run("--drivedegrade-metric", "epdms", "-n", "2", "--junitxml=e.xml", families="gaussian_blur,blackout",
                    severities="1,5")
    no_traceback(result)
    folder = dd.folder()
    rows = read_csv(folder / "cells.csv")
    for row in rows:
        for col in ("epdms", "ddc", "lk", "hc", "ec"):  # the world has lanes, a past, consecutive frames
            assert 0.0 <= float(row[col]) <= 1.0, (row["cell"], col, row[col])
        assert row["tlc"] == ""
        assert float(row["epdms_retention_ci_low"]) <= float(row["epdms_retention"]) <= \
            float(row["epdms_retention_ci_high"]) + 1e-9
    assert float(next(r for r in rows if r["cell"] == "clean")["epdms_retention"]) == 1.0
    cert = load_json(folder / "certificate.json")
    assert cert["verdict"]["metric"] == "epdms" and cert["verdict"]["text"].startswith("On EPDMS retention")
    assert set(cert["axes_epdms"]) >= {"quality", "removal", "gap", "mean"}
    assert cert["epdms_unscored"] == {"tlc": "the data have no traffic lights"}
    assert verify_cli(folder / "certificate.json").returncode == 0
    page = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", (folder / "report.html").read_text()))
    assert "L2, PDMS and EPDMS retention, side by side" in page
    assert "tlc not scored: the data have no traffic lights." in page
    junit = (dd.pytester.path / "e.xml").read_text()  # the page's figures as JUnit properties too
    assert '<property name="drivedegrade_epdms_unscored_tlc" value="the data have no traffic lights"' in junit
    removal = re.search(r'name="drivedegrade_axis_epdms_removal" value="([^"]+)"', junit).group(1)
    assert float(removal) == pytest.approx(cert["axes_epdms"]["removal"], abs=1e-6)  # blackout S5 ran


def test_an_unknown_metric_is_a_usage_error(dd):
    dd.write_planner()
    result = dd.run("--drivedegrade-metric", "mse")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*--drivedegrade-metric: unknown metric 'mse'*"])


def test_the_ego_box_is_recorded_and_an_unknown_one_is_a_usage_error(dd):
    dd.write_planner()
    result = dd.run("--drivedegrade-ego-box", "lorry")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*--drivedegrade-ego-box: unknown ego box 'lorry'; valid boxes: nuscenes, pacifica*"])
    result = dd.run("--drivedegrade-ego-box", "pacifica", families="blackout", severities="5")
    no_traceback(result)
    cert = load_json(dd.folder() / "certificate.json")
    assert cert["settings"]["ego_box"] == "pacifica"
    assert verify_cli(dd.folder() / "certificate.json").returncode == 0
