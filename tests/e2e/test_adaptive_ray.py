"""--drivedegrade-adaptive on Ray planner actors (SPEC sections 9 and 14): the controller runs each cell's
sequential run unit by unit through the actors, and the stored cells, cells.csv and the certificate's adaptive
section are those of a single-process run, bit for bit."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("ray")
pytest.register_assert_rewrite("plugin_support")
import test_ray  # noqa: E402
from plugin_support import load_json, no_traceback, stored_records, verify_cli  # noqa: E402

pytest_plugins = ["plugin_support"]
#: Every test that starts Ray runs on one xdist worker (`--dist loadgroup`): see test_ray.
pytestmark = pytest.mark.xdist_group("ray")

no_stray_ray = test_ray.no_stray_ray  # the fixture: no Ray daemon outlives the run
PLANNERS = Path(__file__).resolve().parents[2] / "planners"


def without_reused(records: dict[str, dict]) -> dict[str, dict]:
    return {c: {k: v for k, v in r.items() if k != "reused"} for c, r in records.items()}


def test_an_adaptive_ray_run_gives_the_cells_of_a_local_one(dd, two_scene_world, no_stray_ray):
    kw = {"planner": str(PLANNERS / "camera_cnn.py"), "data": two_scene_world, "families": "jpeg,blackout",
          "severities": "1,2,3,4,5"}
    adaptive = ("--drivedegrade-frames", "16", "--drivedegrade-adaptive")
    dd.run("-p", "no:xdist", *adaptive, report="local", **kw).assert_outcomes(passed=13)
    result = dd.run(*test_ray.RAY, *adaptive, report="ray", subprocess=True, **kw)
    result.assert_outcomes(passed=13)
    no_traceback(result)
    result.stdout.fnmatch_lines(["*ray: 2 planner actor(s) on a local cluster*"])
    local, ray = (dd.pytester.path / report / "camera_cnn" for report in ("local", "ray"))
    assert (ray / "cells.csv").read_text() == (local / "cells.csv").read_text()
    # every severity runs now (issue 36), blackout S1-S2 too, whose inputs equal clean's for camera_cnn: the local
    # run reuses the clean plan there, an actor predicts every frame it is sent (`RunContext.reuses_clean`), so
    # only the count of reused frames differs
    assert without_reused(stored_records(ray)) == without_reused(stored_records(local))
    a, b = load_json(local / "certificate.json"), load_json(ray / "certificate.json")
    assert a["adaptive"] == b["adaptive"] and a["cells"] == b["cells"]
    assert b["adaptive"]["families"]["blackout"]["visited"] == [1, 2, 3, 4, 5]  # no severity skipped (issue 36)
    assert b["adaptive"]["passes"] < b["adaptive"]["full_passes"]
    done = verify_cli(ray / "certificate.json")
    assert done.returncode == 0, done.stderr
