"""Ray planner actors (SPEC section 9, `--drivedegrade-ray`), end to end on a world with two val scenes: a run on
a local cluster gives the cells.csv of a local run (camera_cnn, and the temporal reference planner that uses
`reset` and the frame context); an actor killed mid-run is replaced, its shard rerun and nothing lost; the
planner is built once per actor from the planner file alone (same-file fixtures, teardown), never on the
controller; the usage errors. Each Ray run is a subprocess with its own local cluster (2 CPUs), and no Ray
process may outlive it."""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("ray")
pytest.register_assert_rewrite("plugin_support")
from plugin_support import no_traceback  # noqa: E402

from pytest_drivedegrade.errors import DriveDegradeError  # noqa: E402
from pytest_drivedegrade.plugin.actors import PlannerFile  # noqa: E402

pytest_plugins = ["plugin_support"]
#: Every test that starts Ray runs on one xdist worker (`--dist loadgroup`, pyproject addopts): the no_stray_ray
#: check counts the Ray daemons that appeared during a test, and another worker's Ray run would be counted.
pytestmark = pytest.mark.xdist_group("ray")

PLANNERS = Path(__file__).resolve().parents[2] / "planners"
FRAMES = ("--drivedegrade-frames", "8")
RAY = ("--drivedegrade-ray", "local")

STEADY = '''
import os

import numpy as np
import pytest

MARKER = {marker!r}
CALLS = 0
KILL_AT = 7  # an actor dies on its 7th prediction, inside its second scene group


class Steady:
    """Constant velocity plus an offset, moved sideways by the front camera's brightness; with MARKER present,
    the process dies on its KILL_AT-th prediction (once: the marker goes first)."""

    cameras = ("CAM_FRONT",)
    name = "steady"

    def __init__(self, offset):
        self.offset = offset

    def predict(self, images, ego, cmd):
        global CALLS
        CALLS += 1
        if CALLS == KILL_AT and os.path.exists(MARKER):  # mid-run: the planner cannot know the cell, by design
            os.remove(MARKER)
            os._exit(1)
        steps = np.arange(1, 7)[:, None] * 0.5
        plan = steps * np.array(ego.velocity, dtype=float) + self.offset
        plan[:, 1] += float(images["CAM_FRONT"][::8, ::8].mean()) / 255.0
        return plan


def log(event):
    with open(os.environ["STEADY_LOG"], "a") as f:  # one file for both runs, so one planner fingerprint
        f.write(f"{{event}} {{os.getpid()}}\\n")


@pytest.fixture(scope="session")
def offset(drivedegrade_context):
    return 0.25 + 0.01 * len(drivedegrade_context.frames)


@pytest.fixture(scope="session")
def planner(offset):
    log("built")
    yield Steady(offset)
    log("teardown")
'''


def ray_processes() -> set[int]:
    """Pids of running Ray daemons (raylet, GCS server), read from /proc (zombies have no command line)."""
    found = set()
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                cmdline = (proc / "cmdline").read_bytes()
            except OSError:
                continue
            if b"raylet" in cmdline or b"gcs_server" in cmdline:
                found.add(int(proc.name))
    return found


@pytest.fixture
def no_stray_ray():
    """The test's Ray runs leave no Ray daemon behind (ray.shutdown ran)."""
    before = ray_processes()
    yield
    # Daemons told to stop can take over 30 s to exit on a loaded machine (the full suite beside two CPU-bound
    # loops, load about 5 on 2 cores, left two behind at 30 s): what this asserts is that none is left running,
    # so it waits for a slow exit as long as a loaded machine needs.
    deadline = time.monotonic() + 120
    while (left := ray_processes() - before) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not left, f"Ray processes left running: {sorted(left)}"


def events(log: Path) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {"built": [], "teardown": []}
    for line in log.read_text().splitlines():
        event, pid = line.split()
        out[event].append(int(pid))
    return out


@pytest.mark.parametrize("planner, extra, actors, groups", [
    ("camera_cnn.py", ("--drivedegrade-seeds", "2"), 2, None),  # the seeds loop through the pool too
    ("temporal_cnn.py", (), 2, 12),  # 6 cells x 2 scene groups: every cell split between the actors
    ("temporal_cnn.py", (), 1, 6),  # one actor: every cell whole, its two scenes' resets inside one call
])
def test_a_ray_run_gives_the_cells_of_a_local_run(dd, two_scene_world, no_stray_ray, planner, extra, actors,
                                                  groups):
    kw = {"planner": str(PLANNERS / planner), "data": two_scene_world, "families": "jpeg,frame_dropout,gaussian_noise",
          "severities": "5"}
    dd.run("-p", "no:xdist", *FRAMES, *extra, report="local", **kw).assert_outcomes(passed=6)
    result = dd.run(*RAY, "--drivedegrade-ray-actors", str(actors), *FRAMES, *extra, report="ray", subprocess=True,
                    **kw)
    result.assert_outcomes(passed=6)
    name = planner.removesuffix(".py")
    local, ray = (dd.pytester.path / report / name / "cells.csv" for report in ("local", "ray"))
    assert ray.read_text() == local.read_text()  # bit-identical cells
    result.stdout.fnmatch_lines([f"*ray: {actors} planner actor(s) on a local cluster; * scene group(s) run*"])
    run = int(re.search(r"(\d+) scene group\(s\) run", result.stdout.str()).group(1))
    assert run >= 12 if groups is None else run == groups
    assert "died" not in result.stdout.str()


def test_a_killed_actor_is_replaced_and_only_its_shard_rerun(dd, two_scene_world, no_stray_ray, monkeypatch):
    marker, logs = dd.pytester.path / "kill-once", {r: dd.pytester.path / f"{r}.log" for r in ("local", "ray")}
    kw = {"planner": "steady.py", "data": two_scene_world, "families": "jpeg,blackout", "severities": "5"}
    dd.pytester.makepyfile(steady=STEADY.format(marker=str(marker)))
    monkeypatch.setenv("STEADY_LOG", str(logs["local"]))
    dd.run("-p", "no:xdist", *FRAMES, report="local", **kw).assert_outcomes(passed=5)
    marker.write_text("")
    monkeypatch.setenv("STEADY_LOG", str(logs["ray"]))
    result = dd.run(*RAY, *FRAMES, report="ray", subprocess=True, **kw)
    result.assert_outcomes(passed=5)
    assert not marker.exists()  # an actor did die mid-run
    result.stdout.fnmatch_lines(["*ray: actor * (pid *) died while running cell * (seed 0), frames *; "
                                 "replaced, 1 shard rerun*nothing lost*"])
    local, ray = (dd.pytester.path / r / "steady" / "cells.csv" for r in ("local", "ray"))
    assert ray.read_text() == local.read_text()
    # Built once per actor (two, and the replacement), from the file's own fixtures; never on the controller;
    # the generator fixture torn down in the two actors alive at the end.
    seen = events(logs["ray"])
    assert len(seen["built"]) == len(set(seen["built"])) == 3
    assert len(seen["teardown"]) == 2 and set(seen["teardown"]) < set(seen["built"])


def test_a_fixture_an_actor_cannot_give_is_a_usage_error(dd, two_scene_world, no_stray_ray):
    dd.pytester.makepyfile(needs_tmp='''
import pytest


@pytest.fixture(scope="session")
def weights(tmp_path_factory):
    return tmp_path_factory.mktemp("w")


@pytest.fixture(scope="session")
def planner(weights):
    raise AssertionError("never built")
''')
    result = dd.run(*RAY, planner="needs_tmp.py", report="r", data=two_scene_world, subprocess=True)
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*--drivedegrade-ray: building the planner in a Ray actor failed: *needs_tmp.py: "
                                 "fixture 'weights' requests 'tmp_path_factory' (planner -> weights -> "
                                 "tmp_path_factory), which a Ray actor cannot provide*"])
    no_traceback(result)


@pytest.mark.parametrize("options, expected", [
    (("-n", "2", *RAY), "*--drivedegrade-ray: cannot be combined with -n 2 (xdist)*drop -n (or give -n 0)*"),
    (("--drivedegrade-ray", "nowhere"), "*--drivedegrade-ray: expected local, auto, ray://HOST:PORT or HOST:PORT, "
                                        "got 'nowhere'*"),
    (("--drivedegrade-ray-actors", "2"), "*--drivedegrade-ray-actors: needs --drivedegrade-ray ADDRESS*"),
    ((*RAY, "--drivedegrade-ray-gpus", "-1"), "*--drivedegrade-ray-gpus: must be at least 0.0, got -1.0*"),
    ((*RAY, "--drivedegrade-ray-actors", "0"), "*--drivedegrade-ray-actors: must be at least 1, got 0*"),
], ids=["with-n", "address", "actors-alone", "gpus", "actors"])
def test_bad_ray_options_are_usage_errors(dd, options, expected):
    dd.write_planner()
    result = dd.pytester.runpytest_inprocess(*dd.args(*options))
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines([expected])
    no_traceback(result)


def test_without_ray_installed_the_option_says_how_to_install_it(dd, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    dd.write_planner()
    result = dd.pytester.runpytest_inprocess(*dd.args(*RAY))
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    assert ('--drivedegrade-ray: Ray is not installed; install the ray extra: pip install -e ".[ray]"'
            in result.stderr.str())  # a plain search: fnmatch reads [ray] as a character class


def test_the_planner_file_builds_outside_pytest_with_its_own_fixtures_and_teardown(tmp_path):
    """What an actor does, without Ray: same-file fixtures once each, the context given, teardown in reverse."""
    path = tmp_path / "built_alone.py"
    path.write_text('''
import pytest

EVENTS = []


@pytest.fixture(scope="session")
def weights(drivedegrade_context):
    EVENTS.append("weights")
    yield {"context": drivedegrade_context}
    EVENTS.append("weights down")


@pytest.fixture(name="scale")
def _scale(weights):
    EVENTS.append("scale")
    return 2.0


@pytest.fixture(scope="session")
def planner(weights, scale):
    EVENTS.append("planner")
    yield (weights, scale)
    EVENTS.append("planner down")
''')
    context = object()
    planner, close = PlannerFile(path)(context)  # type: ignore[arg-type]
    assert planner == ({"context": context}, 2.0)
    events_module = sys.modules["drivedegrade_planner_built_alone"]
    assert events_module.EVENTS == ["weights", "scale", "planner"]
    assert close() == []
    assert events_module.EVENTS[3:] == ["planner down", "weights down"]


def test_a_planner_fixture_asking_for_request_names_it(tmp_path):
    path = tmp_path / "asks_request.py"
    path.write_text('''
import pytest


@pytest.fixture
def planner(request):
    return request.param
''')
    with pytest.raises(DriveDegradeError, match=r"fixture 'planner' requests 'request' \(planner -> request\), "
                                                r"which a Ray actor cannot provide.*build it without 'request'"):
        PlannerFile(path)(object())  # type: ignore[arg-type]
