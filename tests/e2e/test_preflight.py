"""The pre-flight check (SPEC section 20, issue 41): before any cell, the planner's declared needs against the
data, one clean frame predicted and validated, and the run's estimate in one line. A mismatch is one message and
no cell runs; --drivedegrade-dry-run stops after the check."""

from __future__ import annotations

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import FRAMES, no_traceback  # noqa: E402

pytest_plugins = ["plugin_support"]

#: A planner built without pytest's `request`, so the pre-flight can build it; `{body}` is predict's last lines.
SOURCE = '''
import numpy as np
import pytest


class Planner:
    cameras = ("CAM_FRONT",)
    name = "pf"
{attrs}

    def predict(self, images, ego, cmd):
        plan = np.cumsum(np.full((6, 2), [1.0, 0.0]), axis=0) + float(images["CAM_FRONT"][0, 0, 0]) * 0
{body}


@pytest.fixture(scope="session")
def planner():
    return Planner()
'''


def write(dd, body: str = "        return plan", attrs: str = "") -> None:
    dd.pytester.makepyfile(pf=SOURCE.format(body=body, attrs=attrs))


def preflight_error(result: pytest.RunResult) -> str:
    """The usage error's text; asserts that no cell ran (no item collected, no outputs written)."""
    assert result.ret == pytest.ExitCode.USAGE_ERROR, result.stdout.str() + result.stderr.str()
    no_traceback(result)
    text = result.stderr.str()
    assert "drivedegrade pre-flight: the planner and the data disagree, so no cell ran" in text
    assert text.count("ERROR:") == 1  # one message
    assert "passed" not in result.stdout.str() and "failed" not in result.stdout.str()
    return text


@pytest.mark.parametrize("body, attrs, expected", [
    ("        return np.zeros((8, 3))", "", "*has shape (8, 3), not (6, 2)*"),
    ("        return plan + float(images['CAM_BACK'].mean())", "",
     "*predict() reads CAM_BACK, which planner.cameras (CAM_FRONT) does not declare, and its plan*changes when "
     "they are black*"),
    ("        return plan", "    poses = 8",
     "*declares poses = 8 (4 s) but the data at * holds 3 s of future per scored frame (6 keyframes)*--future 4*"),
    ("        return plan.astype(int)", "", "*has dtype int64, not a float dtype*"),
    ("        return plan * np.nan", "", "*is not finite*"),
    ("        return plan", "    lidar = True", "*planner.lidar is set but predict() takes no `context`*"),
], ids=["shape-8x3", "undeclared-camera", "8-poses-on-3s", "dtype", "nan", "lidar-without-context"])
def test_a_mismatch_stops_before_any_cell_with_one_message(dd, body, attrs, expected):
    write(dd, body, attrs)
    result = dd.run(planner="pf.py")
    preflight_error(result)
    result.stderr.fnmatch_lines([expected])
    assert not (dd.pytester.path / "rep" / "pf").exists()


def test_a_valid_planner_prints_its_estimate_first_and_dry_run_stops_there(dd):
    write(dd)
    dry = dd.run("--drivedegrade-dry-run", planner="pf.py")
    assert dry.ret == pytest.ExitCode.OK
    cells = 9  # plugin_support's three families at two severities, clean, null and blind
    line = f"drivedegrade pre-flight: clean frame '*' predicted and valid (* ms per frame); {cells} cells, " \
        f"{cells * FRAMES} predictions, about * seconds in one process"
    dry.stdout.fnmatch_lines([line])
    assert "no cell ran" in dry.stderr.str() + dry.stdout.str()
    assert not (dd.pytester.path / "rep" / "pf").exists()
    full = dd.run(planner="pf.py")
    full.assert_outcomes(passed=cells)
    full.stdout.fnmatch_lines(["*drivedegrade cells: 1/9 cells (11 %) * s, about * left, clean done*",
                               "*drivedegrade cells: 9 cells in * s"])  # the cells' progress line, first to last
    out = full.stdout.str()
    assert out.index("drivedegrade pre-flight:") < out.index("PASSED" if "PASSED" in out else "pf.py ")
    again = dd.run(planner="pf.py")  # every cell stored with the same key: nothing left to predict
    again.stdout.fnmatch_lines([f"drivedegrade pre-flight: clean frame * {cells} cells, 0 predictions, *",
                                f"drivedegrade pre-flight: note: {cells} of {cells} cells are stored with this run's "
                                "key and are reused*"])


def test_a_fixture_pytest_alone_provides_leaves_the_frame_to_the_first_cell(dd):
    """plugin_support's planner asks for `request`: it cannot be built before the cells, and the line says so."""
    dd.write_planner()
    result = dd.run("--drivedegrade-dry-run")
    assert result.ret == pytest.ExitCode.OK
    result.stdout.fnmatch_lines(["drivedegrade pre-flight: no frame checked before the cells (*requests "
                                 "'request'*); 9 cells, 36 predictions (time not estimated)"])
