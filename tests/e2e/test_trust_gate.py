"""Issue 37 H2, "The sequential gate trusts the baseline's cells/ folder": an adaptive gated run checks every
file of the baseline's cells/ against the record_digests its certificate sealed before any cell runs; a cell
file of another run copied over the baseline's (the regressed run's own low_light S5) is refused naming the
file, as is a file the certificate sealed no record of. On the old code the swapped baseline let the regressed
planner pass the gate (exit 0)."""

from __future__ import annotations

import shutil

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import FRAGILE, no_traceback  # noqa: E402

pytest_plugins = ["plugin_support"]

FAMILIES, SEVERITIES, FRAMES = "low_light,blackout", "5", ("--drivedegrade-frames", "12")


@pytest.mark.parametrize("how", ["swapped", "unsealed"])
def test_the_sequential_gate_refuses_a_baseline_cell_file_its_certificate_did_not_seal(dd, how):
    dd.write_planner()
    dd.run("-p", "no:xdist", *FRAMES, families=FAMILIES, severities=SEVERITIES, report="base").assert_outcomes(
        passed=5)
    dd.write_planner(scale=FRAGILE)
    dd.run("-p", "no:xdist", *FRAMES, families=FAMILIES, severities=SEVERITIES, report="bad").assert_outcomes(
        passed=5)
    cells = dd.folder(report="base") / "cells"
    target = cells / ("low_light-s5.json" if how == "swapped" else "fog-s5.json")
    shutil.copyfile(dd.folder(report="bad") / "cells" / "low_light-s5.json", target)
    gate = ("--drivedegrade-baseline", str(dd.folder(report="base") / "certificate.json"), "--drivedegrade-adaptive")
    result = dd.run("-p", "no:xdist", *FRAMES, *gate, families=FAMILIES, severities=SEVERITIES, report="gated")
    text = result.stdout.str() + result.stderr.str()
    assert result.ret == pytest.ExitCode.USAGE_ERROR, text
    no_traceback(result)
    assert f"--drivedegrade-baseline: {target}" in text or f"{target} is not the record the certificate sealed" \
        in text, text
    assert ("record_digests differs" if how == "swapped" else "sealed no record of cell 'fog-s5'") in text, text
    assert not (dd.pytester.path / "gated").exists()  # refused before any cell ran
    if how == "unsealed":  # the folder as the baseline's run wrote it: the regression is caught
        target.unlink()
        worse = dd.run("-p", "no:xdist", *FRAMES, *gate, families=FAMILIES, severities=SEVERITIES, report="gated")
        assert worse.ret == 1, worse.stdout.str()
        worse.stdout.fnmatch_lines(["*REGRESSION low_light-s5*"], consecutive=False)
