"""Issue 20, M12 on Ray planner actors (`--drivedegrade-ray local`): each actor plans clean before any other cell,
so a planner that memoises its plan per frame holds clean's plans in every actor, its blind cell equals clean bit
for bit, and the verdict is undetermined as in a local run."""

from __future__ import annotations

import pytest

pytest.importorskip("ray")
pytest.register_assert_rewrite("plugin_support")
import test_ray  # noqa: E402
from plugin_support import AXIS_FAMILIES, load_json, no_traceback  # noqa: E402
from test_trust20c import memo_source  # noqa: E402

pytest_plugins = ["plugin_support"]
#: Every test that starts Ray runs on one xdist worker (see tests/e2e/test_trust_ray.py).
pytestmark = pytest.mark.xdist_group("ray")

no_stray_ray = test_ray.no_stray_ray  # the fixture: no Ray daemon outlives the run


def test_m12_a_memoising_planner_is_never_certified_not_shown_to_use_cameras_on_ray(dd, no_stray_ray):
    """M12 with the cells' frame groups spread over two actors by a shared queue: without the actors' own clean
    first, a frame first seen by an actor in a later cell would memoise that cell's plan."""
    source = memo_source("token").replace(  # an actor builds the planner from its RunContext, not from `request`
        "def planner(request):\n    return Memo(request.config.getoption(\"drivedegrade_data\"), "
        "request.config.getoption(\"drivedegrade_split\") or \"val\")",
        "def planner(drivedegrade_context):\n    return Memo(drivedegrade_context.reader.root, "
        "drivedegrade_context.settings.split)")
    assert "drivedegrade_context" in source
    dd.pytester.makepyfile(memo=source)
    result = dd.run(*test_ray.RAY, planner="memo.py", families=AXIS_FAMILIES, severities="5", subprocess=True)
    no_traceback(result)
    result.stdout.fnmatch_lines(["*ray: 2 planner actor(s) on a local cluster*"], consecutive=False)
    v = load_json(dd.folder("memo") / "certificate.json")["verdict"]
    assert (v["label"], v["case"]) == ("undetermined", "blind-equals-clean"), v
