"""`drivedegrade reproduce` of a certificate with closed-loop cells (SPEC sections 11 and 13): the rerun drives
closed-clean and the sampled closed cells beside the open ones and finds them bit-identical; a planner changed by
1e-9 m on a black front image only is reported DIFFERENT in closed-blackout-s5 alone, naming its route, seed and
the step where the paths part; ``--loop open`` drives no closed cell, and a closed-loop-only certificate reproduces.

Small: the small world's one val route, one seed, at most 4 planner calls a run, a planner that reads one camera.
"""

from __future__ import annotations

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json  # noqa: E402

from pytest_drivedegrade.cli import main  # noqa: E402

pytest_plugins = ["plugin_support"]

PLANNER = '''
import numpy as np
import pytest


class Driver:
    """Drives at a speed set by the front image's brightness."""

    cameras = ("CAM_FRONT",)
    name = "driver"

    def predict(self, images, ego, cmd):
        light = float(images["CAM_FRONT"][::16, ::16].mean()) / 255.0
        speed = max(float(ego.velocity[0]), 2.0) * (0.5 + light)
        return np.arange(1, 7)[:, None] * 0.5 * np.array([speed, 0.0])


@pytest.fixture(scope="session")
def planner():
    return Driver()
'''

CLOSED = ("--drivedegrade-closed-cells", "clean,blackout-s5,blackout-s3", "--drivedegrade-closed-steps", "4",
          "--drivedegrade-closed-seeds", "1", "-p", "no:randomly", "-p", "no:xdist", "--drivedegrade-closed-scenarios",
          "0", "--drivedegrade-closed-lights", "0")


def results(out: str) -> dict[str, str]:
    """The reproduce lines ``[i/n t s] cell: verdict`` by cell."""
    lines = [line.split("] ", 1)[1] for line in out.splitlines() if line.startswith("[")]
    return dict(line.split(": ", 1) for line in lines)


def test_closed_cells_reproduce_bit_for_bit_and_a_changed_planner_is_named_by_closed_cell(dd, capsys):
    planner = dd.pytester.makepyfile(driver=PLANNER)
    result = dd.run("--drivedegrade-loop", "both", *CLOSED, planner="driver.py", families="blackout", severities="5")
    assert result.ret == 0, result.stdout.str()
    cert_path = dd.folder("driver") / "certificate.json"
    cert = load_json(cert_path)
    assert [c["cell"] for c in cert["closed_loop"]["cells"]] == ["closed-clean", "closed-blackout-s5",
                                                                   "closed-blackout-s3"]
    capsys.readouterr()

    assert main(["reproduce", str(cert_path), str(planner), "--cells", "0", "--closed-cells", "2",
                 "--seed", "0"]) == 0
    out, err = capsys.readouterr()
    assert results(out) == {c: "identical" for c in ("clean", "null", "closed-clean", "closed-blackout-s5",
                                                      "closed-blackout-s3")}, out + err
    assert "all 5 cell(s) identical" in out and "closed-loop runs bit for bit" in out
    assert "NOTE" not in err, err  # the rerun's own loop and closed cells are not "another run's" settings
    assert "--drivedegrade-loop both --drivedegrade-closed-cells clean,blackout-s5,blackout-s3" in err

    # --closed-cells 0: closed-clean only; --loop open: no closed cell
    assert main(["reproduce", str(cert_path), str(planner), "--cells", "0", "--closed-cells", "0",
                 "--seed", "0", "--loop", "open"]) == 0
    out, _ = capsys.readouterr()
    assert set(results(out)) == {"clean", "null"}

    planner.write_text(PLANNER.replace("(0.5 + light)", "(0.5 + light + (1e-9 if light == 0.0 else 0.0))"))
    assert main(["reproduce", str(cert_path), str(planner), "--cells", "0", "--closed-cells", "2", "--seed", "0",
                 "--any-planner", "--loop", "closed"]) == 1
    out, err = capsys.readouterr()
    got = results(out)
    route = cert["closed_loop"]["cells"][1]["run_rows"][0][0]
    assert got["closed-clean"] == got["closed-blackout-s3"] == "identical", out
    assert got["closed-blackout-s5"].startswith(f"DIFFERENT (route {route} seed 0: the path parts at step 0"), out
    assert "1 of 3 cell(s) DIFFERENT from the certificate: closed-blackout-s5" in out

    # without the certified cell files beside it the trace digests still differ, the step is unknown
    (cert_path.parent / "cells" / "closed-blackout-s5.json").unlink()
    assert main(["reproduce", str(cert_path), str(planner), "--closed-cells", "2", "--seed", "0",
                 "--any-planner", "--loop", "closed"]) == 1
    out, _ = capsys.readouterr()
    assert results(out)["closed-blackout-s5"].startswith(f"DIFFERENT (route {route} seed 0: the path differs "
                                                         "(trace digest "), out
    assert "the step is unknown: the certified cell file is not beside the certificate" in out


def test_a_closed_loop_only_certificate_reproduces_and_refuses_an_open_loop_rerun(dd, capsys):
    planner = dd.pytester.makepyfile(driver=PLANNER)
    dd.run("--drivedegrade-loop", "closed", *CLOSED, "--drivedegrade-closed-cells", "clean,blackout-s5",
           planner="driver.py").assert_outcomes(passed=2)
    cert_path = dd.folder("driver") / "certificate.json"
    assert load_json(cert_path)["cells"] == []
    capsys.readouterr()
    assert main(["reproduce", str(cert_path), str(planner), "--closed-cells", "1", "--seed", "3"]) == 0
    out, err = capsys.readouterr()
    assert results(out) == {"closed-clean": "identical", "closed-blackout-s5": "identical"}, out + err
    assert main(["reproduce", str(cert_path), str(planner), "--loop", "open"]) == 2
    _, err = capsys.readouterr()
    assert "--loop open: the certificate has no open-loop cell to rerun (it was made with --drivedegrade-loop " \
           "closed)" in err
