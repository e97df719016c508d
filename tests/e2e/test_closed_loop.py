"""Closed-loop cells end to end (SPEC section 13): `closed_loop.csv` is the same under -n 0, -n 2 and two shards
merged; the certificate's closed_loop section verifies; a planner that secretly reads a rear camera fails the
closed null control naming the route and step; a planner that raises leaves runs unscored and the bounds widen.

Small and fast: the small world's one val route, 2 seeds, at most 4 planner calls a run, a planner that reads one
camera and computes almost nothing.
"""

from __future__ import annotations

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, no_traceback, read_csv  # noqa: E402

from pytest_drivedegrade.certificate.consistency import check_consistency  # noqa: E402
from pytest_drivedegrade.cli import main  # noqa: E402

pytest_plugins = ["plugin_support"]

PLANNER = '''
import numpy as np
import pytest


class Driver:
    """Drives at a speed set by the front image's brightness; `back` reads CAM_BACK although undeclared, from a
    route's second call on (the pre-flight, one call after a reset, cannot see it: the closed null control must);
    `raise_dark` raises on a black front image (blackout S5) at the third call."""

    cameras = ("CAM_FRONT",)
    name = "driver"
    back = {back!r}
    raise_dark = {raise_dark!r}

    def reset(self, route):
        self.calls = 0

    def predict(self, images, ego, cmd):
        self.calls += 1
        light = float(images["CAM_FRONT"][::16, ::16].mean()) / 255.0
        if self.back and self.calls > 1:
            light += float(images["CAM_BACK"][::16, ::16].mean()) / 255.0
        if self.raise_dark and light == 0.0 and self.calls == 3:
            raise RuntimeError("no front image")
        speed = max(float(ego.velocity[0]), 2.0) * (0.5 + light)
        return np.arange(1, 7)[:, None] * 0.5 * np.array([speed, 0.0])


@pytest.fixture(scope="session")
def planner():
    return Driver()
'''

CLOSED = ("--drivedegrade-loop", "closed", "--drivedegrade-closed-cells", "clean,blackout-s5,blackout-s3",
          "--drivedegrade-closed-steps", "4", "--drivedegrade-split", "all", "-p", "no:randomly",
          "--drivedegrade-closed-scenarios", "0", "--drivedegrade-closed-lights", "0")


def write(dd, back=False, raise_dark=False):
    dd.pytester.makepyfile(driver=PLANNER.format(back=back, raise_dark=raise_dark))


def closed(dd, *extra, report="rep"):
    return dd.run(*CLOSED, *extra, planner="driver.py", report=report)


def test_closed_loop_csv_is_the_same_under_n0_n2_and_two_shards_merged(dd):
    write(dd)
    serial = closed(dd, "-p", "no:xdist")
    serial.assert_outcomes(passed=3)
    folder = dd.folder("driver")
    text = (folder / "closed_loop.csv").read_text()
    rows = read_csv(folder / "closed_loop.csv")
    # deterministic families run the first seed only: a second would replay it (issue 36)
    assert [(r["cell"], r["seed"]) for r in rows] == [(c, "0") for c in ("closed-clean", "closed-blackout-s5",
                                                                         "closed-blackout-s3")]
    assert all(r["end"] == "scene_end" and r["steps"] == "4" for r in rows)
    # blackout S3 is clean's run for run (the planner reads the front camera only); blackout S5 drives slower
    assert [r["trace_digest"] for r in rows[2:]] == [r["trace_digest"] for r in rows[:1]]
    assert float(rows[1]["ds"]) < float(rows[0]["ds"])
    cert = load_json(folder / "certificate.json")
    section = cert["closed_loop"]
    assert section["null_control"]["mode"] == "identical" and section["null_control"]["passed"] is True
    assert section["loop"] == "closed" and section["closed_steps"] == 4
    assert check_consistency(cert) == []
    assert main(["verify", str(folder / "certificate.json")]) == 0
    parallel = closed(dd, "-n", "2", "--drivedegrade-no-resume", report="rep2")
    parallel.assert_outcomes(passed=3)
    assert (dd.folder("driver", "rep2") / "closed_loop.csv").read_text() == text
    for i in (1, 2):
        closed(dd, "-p", "no:xdist", "--drivedegrade-shard", f"{i}/2", report="sh").assert_outcomes(passed=3)
    shards = dd.pytester.path / "sh" / "driver"
    out = dd.pytester.path / "merged"
    assert main(["merge", str(shards / "shard-2-of-2"), str(shards / "shard-1-of-2"), "--out", str(out)]) == 0
    assert (out / "driver" / "closed_loop.csv").read_text() == text
    merged = load_json(out / "driver" / "certificate.json")
    assert merged["closed_loop"]["cells"] == section["cells"]



def test_closed_loop_csv_is_the_same_with_and_without_prefetch(dd):
    """--drivedegrade-prefetch 2 judges each plan's steps while the next cameras render (threads beside the
    planner): closed_loop.csv is the serial path's (prefetch 0) byte for byte, and the cells' figures too."""
    write(dd)
    for depth in ("0", "2"):
        closed(dd, "-p", "no:xdist", "--drivedegrade-prefetch", depth, "--drivedegrade-closed-cells",
               "clean,blackout-s5", report=f"p{depth}").assert_outcomes(passed=2)
    serial, threaded = (dd.folder("driver", f"p{d}") for d in ("0", "2"))
    assert (threaded / "closed_loop.csv").read_text() == (serial / "closed_loop.csv").read_text()
    assert load_json(threaded / "certificate.json")["closed_loop"]["cells"] == \
        load_json(serial / "certificate.json")["closed_loop"]["cells"]

def test_a_tampered_closed_loop_figure_fails_verify(dd):
    write(dd)
    closed(dd, "-p", "no:xdist").assert_outcomes(passed=3)
    from pytest_drivedegrade.certificate.seal import seal

    cert = load_json(dd.folder("driver") / "certificate.json")
    cert["closed_loop"]["cells"][1]["ds_mean"] += 5.0
    assert any(p.startswith("closed_loop.cells.closed-blackout-s5.ds_mean") for p in check_consistency(seal(cert)))


def test_a_planner_that_secretly_reads_a_rear_camera_fails_the_closed_null_control(dd):
    write(dd, back=True)
    result = closed(dd, "-p", "no:xdist", "--drivedegrade-closed-seeds", "1")
    result.assert_outcomes(passed=2, failed=1)
    no_traceback(result)
    result.stdout.fnmatch_lines(["*closed null control failed in cell closed-blackout-s3: route scene-* (seed 0) "
                                 "parts from closed-clean at step 1*"])  # its first call with the rear read
    section = load_json(dd.folder("driver") / "certificate.json")["closed_loop"]
    assert section["null_control"]["passed"] is False and section["null_control"]["first_step"] == 1


def test_a_planner_that_raises_leaves_its_runs_unscored_and_the_bounds_widen(dd):
    write(dd, raise_dark=True)
    result = closed(dd, "-p", "no:xdist")
    result.assert_outcomes(passed=2, failed=1)
    result.stdout.fnmatch_lines(["*run scene-* (seed 0) unscored: step 2: RuntimeError: no front image*"])
    cells = {c["cell"]: c for c in load_json(dd.folder("driver") / "certificate.json")["closed_loop"]["cells"]}
    dark = cells["closed-blackout-s5"]
    assert dark["unscored"] == 1 and dark["ds_mean"] is None  # blackout is deterministic: one seed
    assert (dark["ds_low"], dark["ds_high"]) == (0.0, 100.0)
    assert dark["retention_low"] == 0.0 and dark["retention_high"] > 1.0
    rows = read_csv(dd.folder("driver") / "closed_loop.csv")
    assert [r["end"] for r in rows if r["cell"] == "closed-blackout-s5"] == ["unscored"]


@pytest.mark.xdist_group("ray")
def test_closed_cells_on_ray_planner_actors_give_the_local_closed_loop_csv(dd):
    pytest.importorskip("ray")
    write(dd)
    closed(dd, "-p", "no:xdist", "--drivedegrade-closed-cells", "clean,blackout-s5").assert_outcomes(passed=2)
    ray = dd.run(*CLOSED, "--drivedegrade-closed-cells", "clean,blackout-s5", "--drivedegrade-ray", "local",
                 "-p", "no:xdist", planner="driver.py", report="ray", subprocess=True)
    ray.assert_outcomes(passed=2)
    no_traceback(ray)
    assert (dd.folder("driver", "ray") / "closed_loop.csv").read_text() == \
        (dd.folder("driver") / "closed_loop.csv").read_text()


def test_both_loops_put_the_closed_section_beside_the_open_cells_with_their_agreement(dd):
    write(dd)
    result = dd.run("--drivedegrade-loop", "both", "--drivedegrade-closed-cells", "clean,blackout-s5",
                    "--drivedegrade-closed-steps", "4", "--drivedegrade-closed-seeds", "1", "-p", "no:randomly",
                    "-p", "no:xdist", "--junitxml=j.xml", "--drivedegrade-closed-scenarios", "0",
                    "--drivedegrade-closed-lights", "0",
                    planner="driver.py", families="blackout", severities="5")
    assert result.ret == 0 and result.parseoutcomes()["passed"] >= 6  # the open cells and the two closed ones
    folder = dd.folder("driver")
    cert = load_json(folder / "certificate.json")
    assert {c["cell"] for c in cert["cells"]} >= {"clean", "blackout-s5", "null"}
    section = cert["closed_loop"]
    assert section["loop"] == "both" and section["open_loop"]["label"] == cert["verdict"]["label"]
    assert [c["cell"] for c in section["cells"]] == ["closed-clean", "closed-blackout-s5"]
    assert check_consistency(cert) == []
    assert "id='closed-loop'" in (folder / "report.html").read_text()
    assert len(read_csv(folder / "closed_loop.csv")) == 2 and (folder / "cells.csv").is_file()
    junit = (dd.pytester.path / "j.xml").read_text()  # the closed items' figures as testcase properties
    assert 'name="closed_ds_mean"' in junit and 'name="closed_cell" value="closed-blackout-s5"' in junit



def test_both_loops_in_two_shards_merged_give_the_unsharded_csvs(dd, eleven_scene_world):
    """`--drivedegrade-loop both` sharded: each shard scores its scene's open frames and drives its share of every
    closed cell's runs (2 val scenes: 2 routes, one seed); merged, closed_loop.csv and cells.csv equal the
    unsharded run's byte for byte."""
    write(dd)
    both = ("--drivedegrade-loop", "both", *CLOSED[2:6], "--drivedegrade-closed-seeds", "1", "-p", "no:randomly",
            "-p", "no:xdist", "--drivedegrade-closed-scenarios", "0", "--drivedegrade-closed-lights", "0")
    kw = {"planner": "driver.py", "families": "blackout", "severities": "5", "data": eleven_scene_world}
    assert dd.run(*both, report="full", **kw).ret == 0
    for i in (1, 2):
        shard = dd.run(*both, "--drivedegrade-shard", f"{i}/2", report="sh", **kw)
        assert shard.ret == 0, shard.stdout.str()
    shards, out = dd.pytester.path / "sh" / "driver", dd.pytester.path / "merged"
    assert main(["merge", str(shards / "shard-1-of-2"), str(shards / "shard-2-of-2"), "--out", str(out)]) == 0
    full, merged = dd.folder("driver", "full"), out / "driver"
    assert len(read_csv(full / "closed_loop.csv")) == 6 and len(read_csv(full / "cells.csv")) >= 3
    assert len({r["route"] for r in read_csv(full / "closed_loop.csv")}) == 2
    for name in ("closed_loop.csv", "cells.csv"):
        assert (merged / name).read_text() == (full / name).read_text(), name
    a, b = load_json(full / "certificate.json"), load_json(merged / "certificate.json")
    assert b["closed_loop"]["loop"] == "both" and b["closed_loop"]["cells"] == a["closed_loop"]["cells"]
    assert b["verdict"] == a["verdict"] and check_consistency(b) == []

def test_reactive_agents_are_an_option_recorded_in_the_closed_loop_section(dd):
    """--drivedegrade-closed-agents reactive drives the cells with IDM agents, says so in the certificate's
    closed_loop section (and its cells' key, so a log-replay run's stored cells are not reused), and verifies; a
    value other than log or reactive is a usage error naming both."""
    write(dd)
    closed(dd, "-p", "no:xdist", "--drivedegrade-closed-agents", "reactive").assert_outcomes(passed=3)
    folder = dd.folder("driver")
    cert = load_json(folder / "certificate.json")
    assert cert["closed_loop"]["closed_agents"] == "reactive"
    assert check_consistency(cert) == [] and main(["verify", str(folder / "certificate.json")]) == 0
    stored = load_json(folder / "cells" / "closed-clean.json")
    assert stored["key"]["closed_agents"] == "reactive"
    bad = closed(dd, "-p", "no:xdist", "--drivedegrade-closed-agents", "idm", report="bad")
    assert bad.ret == 4
    bad.stderr.fnmatch_lines(["*--drivedegrade-closed-agents*expected log or reactive, got 'idm'*"])
