"""Issue 37, "Planner code runs in the process that decides the exit status": under -n 2 the controller never
imports the planner file (it only parses it), so a module-level `atexit` `os._exit(0)` cannot turn a printed
regression into exit 0, and an `os._exit(0)` in predict (a worker's) fails the run. Under -n 0 the planner
shares the process: `os._exit` called by planner code is caught while the run is live, and a run that failed
ends with its own status even when a planner's atexit handler calls `os._exit(0)`."""

from __future__ import annotations

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import FRAGILE, no_traceback  # noqa: E402

pytest_plugins = ["plugin_support"]

FAMILIES, SEVERITIES = "low_light,blackout", "5"
#: Prepended to a planner file: where it was imported (by pid), and an exit-at-shutdown handler.
ATEXIT = '''
import atexit as _atexit
import os as _os

with open({imported!r}, "a") as _f:
    _f.write(f"{{_os.getpid()}}\\n")
_atexit.register(_os._exit, 0)
'''


def regressed(dd, planner_head: str, *workers: str):
    """A baseline from the honest planner, then the fragile one (with `planner_head` prepended), gated."""
    dd.write_planner()
    dd.run("-p", "no:xdist", families=FAMILIES, severities=SEVERITIES, report="base").assert_outcomes(passed=5)
    path = dd.write_planner(scale=FRAGILE)
    path.write_text(planner_head + path.read_text())
    base = str(dd.folder(report="base") / "certificate.json")
    return dd.run(*workers, "--drivedegrade-baseline", base, families=FAMILIES, severities=SEVERITIES,
                  report="gated", subprocess=True)


@pytest.mark.parametrize("workers", [("-n", "2"), ("-n", "0")])
def test_an_atexit_os_exit_in_the_planner_file_never_turns_a_printed_regression_into_exit_0(dd, workers):
    imported = dd.pytester.path / "imported.txt"
    result = regressed(dd, ATEXIT.format(imported=str(imported)), *workers)
    text = result.stdout.str()
    assert "REGRESSION" in text, text
    assert result.ret == 1, text  # old code: 0 (the controller imported the file, its atexit ended with 0)
    no_traceback(result)
    pids = set(imported.read_text().split())
    if workers[1] == "2":  # imported by the two workers and the pre-flight's own process (`plugin.isolated`):
        assert len(pids) == 3, pids  # the controller parsed it without running it


@pytest.mark.parametrize("workers", [("-n", "2"), ("-n", "0")])
def test_an_os_exit_0_in_predict_is_a_failed_run_never_exit_0(dd, workers):
    """The planner ends its process with status 0 at its third predict: under -n 2 the worker's crash fails its
    cell; under -n 0 the call is refused (the run goes on: the cell fails naming it); never exit 0."""
    path = dd.write_planner()
    path.write_text(path.read_text().replace(
        "    def predict(self, images, ego, cmd, context):\n",
        "    calls = 0\n\n    def predict(self, images, ego, cmd, context):\n"
        "        TestPlanner.calls += 1\n        if TestPlanner.calls == 3:\n            os._exit(0)\n"))
    result = dd.run(*workers, families="jpeg", severities="1", report="exited", subprocess=True)
    text = result.stdout.str() + result.stderr.str()
    assert result.ret not in (0, None), text
    if workers[1] == "0":
        assert "os._exit" in text, text


def test_under_n2_a_planner_file_that_fails_to_import_is_still_a_usage_error_naming_it(dd):
    """The controller no longer imports the planner file under -n, so an import-time failure happens in the
    workers: the run still ends with the usage error (exit 4) naming the file and the exception."""
    dd.pytester.makepyfile(bad='import pytest\n\nraise RuntimeError("boom at import")\n\n\n'
                               '@pytest.fixture(scope="session")\ndef planner():\n    return None\n')
    result = dd.run("-n", "2", planner="bad.py", families="jpeg", severities="1", subprocess=True)
    assert result.ret == pytest.ExitCode.USAGE_ERROR, result.stdout.str()
    # the pre-flight's own process imports it first: the usage error, before any cell and any worker
    result.stderr.fnmatch_lines(["ERROR: --drivedegrade: importing *bad.py:3 failed: RuntimeError: boom at import"])


def test_under_n2_a_planner_that_ends_the_pre_flights_process_fails_the_run_before_any_cell(dd):
    """The pre-flight builds and calls the planner in a process of its own under -n 2 (`plugin.isolated`): a
    planner that ends that process with status 0 (here at its first predict) leaves no answer, and the run is a
    usage error naming what happened, with no cell run; never a pass."""
    dd.pytester.makepyfile(ender='import os\n\nimport pytest\n\n\nclass Ender:\n    cameras = ("CAM_FRONT",)\n\n'
                                 '    def predict(self, images, ego, cmd):\n        os._exit(0)\n\n\n'
                                 '@pytest.fixture(scope="session")\ndef planner():\n    return Ender()\n')
    result = dd.run("-n", "2", planner="ender.py", families="jpeg", severities="1", report="ended",
                    subprocess=True)
    assert result.ret == pytest.ExitCode.USAGE_ERROR, result.stdout.str() + result.stderr.str()
    result.stderr.fnmatch_lines(["*drivedegrade pre-flight: the process that builds and checks the planner ended "
                                 "(exit 0) without an answer, so no cell ran*"])
    assert not (dd.pytester.path / "ended").exists()
