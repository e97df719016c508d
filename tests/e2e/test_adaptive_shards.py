"""Adaptive runs (SPEC section 14) beyond one process: shards that own whole families, merged into the unsharded
run's certificate bit for bit (and verified); the sequential gate's stops recomputed by verify; a full baseline
gating an adaptive run and an adaptive baseline gating a full one. Small worlds and few frames."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, no_traceback, stored_records, verify_cli  # noqa: E402

from pytest_drivedegrade.certificate.seal import seal, write_certificate  # noqa: E402
from pytest_drivedegrade.cli import main  # noqa: E402
from pytest_drivedegrade.scoring.sequential import METHOD  # noqa: E402

pytest_plugins = ["plugin_support"]

FRAMES = ("--drivedegrade-frames", "12")
#: What a merge must give exactly as the unsharded run: every analysed section and the adaptive one.
SAME = ("cells", "thresholds", "axes", "verdict", "floor", "null_control", "settings", "adaptive", "dataset")


@pytest.mark.parametrize("temporal", [False, True], ids=["frames", "scenes"])
def test_two_adaptive_shards_merge_to_the_unsharded_run_and_verify(dd, capsys, temporal):
    """Whole scenes both ways: the test planner takes `context` without `reset` (issue 36: such a planner gets
    whole scenes, not single frames), the temporal one has `reset` on a run of fewer than SCENE_UNITS_BELOW
    scenes. Single-frame units across processes: `test_adaptive_ray.py` (camera_cnn) and -n 2 in
    `test_adaptive_run.py`."""
    if temporal:
        from test_temporal import TEMPORAL

        dd.pytester.makepyfile(temporal=TEMPORAL.format(leak=False))
    else:
        dd.write_planner()
    name = "temporal" if temporal else "testplanner"
    kw = {"families": "jpeg,blackout", "severities": "1,2,3,4,5", **({"planner": "temporal.py"} if temporal else {})}
    dd.run("-p", "no:xdist", *FRAMES, "--drivedegrade-adaptive", report="full", **kw).assert_outcomes(passed=13)
    owned = {1: 8, 2: 5}  # clean, blind, null and blackout S1-S5; jpeg S1-S5
    for i in (1, 2):
        result = dd.run("-p", "no:xdist", *FRAMES, "--drivedegrade-adaptive", "--drivedegrade-shard", f"{i}/2",
                        report="sh", **kw)
        result.assert_outcomes(passed=owned[i])
        no_traceback(result)
        result.stdout.fnmatch_lines([f"*shard {i}/2: 12 of 12 frames (*), {owned[i]} cell(s) finished*"])
    shards = dd.folder(name, report="sh")
    out = dd.pytester.path / "merged"
    assert main(["merge", str(shards / "shard-2-of-2"), str(shards / "shard-1-of-2"), "--out", str(out)]) == 0
    assert f"adaptive (alpha 0.05, {METHOD}):" in capsys.readouterr().out
    full, merged = dd.folder(name, report="full"), out / name
    a, b = load_json(full / "certificate.json"), load_json(merged / "certificate.json")
    for key in SAME:
        assert a[key] == b[key], key
    assert (merged / "cells.csv").read_text() == (full / "cells.csv").read_text()
    assert stored_records(merged) == stored_records(full) and len(stored_records(full)) == 13
    plan = b["adaptive"]["plan"]
    assert (plan["window"], plan["warmup"]) == (12, 0)  # one 12-frame scene
    done = verify_cli(merged / "certificate.json")
    assert done.returncode == 0, done.stderr
    if not temporal:  # a merged adaptive certificate reruns, unsharded, bit for bit
        capsys.readouterr()
        planner = dd.pytester.path / "myplanner.py"
        assert main(["reproduce", str(merged / "certificate.json"), str(planner), "--cells", "3", "--seed", "0"]) == 0
        assert "identical" in capsys.readouterr().out


def test_adaptive_shards_are_refused_beyond_the_run_s_families(dd):
    dd.write_planner()
    result = dd.run("-p", "no:xdist", "--drivedegrade-adaptive", "--drivedegrade-shard", "3/3", families="jpeg")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*--drivedegrade-shard: an adaptive run is sharded by whole families * this one has "
                                 "2 group(s) *: use at most 2 shards*"])
    no_traceback(result)


GATE = {"families": "low_light,blackout", "severities": "5"}


def verify_baseline(cert: Path, baseline: Path) -> subprocess.CompletedProcess:
    """`drivedegrade verify CERT --baseline BASE`."""
    return subprocess.run([sys.executable, "-m", "pytest_drivedegrade.cli", "verify", str(cert), "--baseline",
                           str(baseline)], capture_output=True, text=True, check=False)


def test_a_gate_run_records_its_test_and_verify_recomputes_every_stop(dd):
    """A full baseline gates an adaptive run: each cell's sequential test is in adaptive.gate, verify recomputes
    where it settled, and a tampered stop or decision fails verify."""
    dd.write_planner()
    dd.run("-p", "no:xdist", *FRAMES, report="base", **GATE).assert_outcomes(passed=5)
    baseline = dd.folder(report="base") / "certificate.json"
    done = dd.run("-p", "no:xdist", *FRAMES, "--drivedegrade-baseline", str(baseline), "--drivedegrade-adaptive",
                  **GATE)
    done.assert_outcomes(passed=5)
    assert done.ret == 0
    cert_path = dd.folder() / "certificate.json"
    cert = load_json(cert_path)
    gate = cert["adaptive"]["gate"]
    assert gate["baseline_digest"] == load_json(baseline)["digest"] and gate["tolerance"] == 0.02
    assert sorted(gate["cells"]) == ["blackout-s5", "blind", "low_light-s5"]
    for cell, part in gate["cells"].items():
        entry = cert["adaptive"]["cells"][cell]
        assert part["side"] == "above" and part["units"] == entry.get("stored_units", entry["units"]), cell
    check = verify_cli(cert_path)
    assert check.returncode == 0, check.stderr
    assert verify_baseline(cert_path, baseline).returncode == 0  # the recorded parts are the baseline's
    check = verify_baseline(cert_path, cert_path)  # another certificate than the baseline
    assert check.returncode == 1 and "is not the baseline this run was gated against" in check.stderr
    part = gate["cells"]["low_light-s5"]
    for field, value in (("side", "below"), ("units", part["units"] - 1)):
        tampered = load_json(cert_path)
        tampered["adaptive"]["gate"]["cells"]["low_light-s5"][field] = value
        write_certificate(dd.folder() / "tampered.json", seal(tampered))  # resealed: only verify's recomputation
        check = verify_cli(dd.folder() / "tampered.json")
        assert check.returncode == 1, field
        assert "adaptive: cell low_light-s5: the gate's test says" in check.stderr, check.stderr
    tampered = load_json(cert_path)  # the baseline's mean moved: only the baseline itself can tell
    entry = tampered["adaptive"]["gate"]["cells"]["low_light-s5"]
    entry["mean"] = (float.fromhex(entry["mean"]) + 1e-9).hex()
    write_certificate(dd.folder() / "tampered.json", seal(tampered))
    check = verify_baseline(dd.folder() / "tampered.json", baseline)
    assert check.returncode == 1 and "adaptive.gate.cells.low_light-s5.mean: certificate says" in check.stderr


def test_an_adaptive_baseline_gates_a_full_run_on_its_intervals(dd):
    """The adaptive baseline's retentions are intervals: an unchanged planner is never failed, a fragile one is
    failed where its retention lies below an interval's low end by more than the tolerance, and the cells the
    baseline decided nothing from are named, not gated."""
    from plugin_support import FRAGILE

    dd.write_planner()
    dd.run("-p", "no:xdist", *FRAMES, "--drivedegrade-adaptive", report="base", **GATE).assert_outcomes(passed=5)
    gate = ("--drivedegrade-baseline", str(dd.folder(report="base") / "certificate.json"))
    same = dd.run("-p", "no:xdist", *FRAMES, *gate, **GATE)
    same.assert_outcomes(passed=5)
    assert same.ret == 0
    no_traceback(same)
    same.stdout.fnmatch_lines(["*baseline (adaptive, intervals): not gated, the adaptive baseline has no interval "
                               "for blind (*",
                               "*baseline (adaptive, intervals, alpha 0.05): 0 regression(s) beyond tolerance 0.02*"])
    dd.write_planner(scale=FRAGILE)
    worse = dd.run("-p", "no:xdist", *FRAMES, *gate, report="fragile", **GATE)
    assert worse.ret == 1
    no_traceback(worse)
    worse.stdout.fnmatch_lines(["*REGRESSION low_light-s5: retention 0.0*, below the adaptive baseline's interval "
                                "(low end 0.1*) by more than 0.02, settled at the baseline's level 0.05*"])
    for extra, message in ((("--drivedegrade-families", "low_light,fog"), "1 cell(s) of this run are not in the "
                                                                          "adaptive baseline: fog-s5"),
                           (("--drivedegrade-adaptive",), "an adaptive baseline cannot gate an adaptive run: the "
                                                          "sequential gate pairs each unit")):
        refused = dd.run("-p", "no:xdist", *FRAMES, *gate, *extra, severities="5")
        assert refused.ret == pytest.ExitCode.USAGE_ERROR, extra
        assert message in refused.stderr.str(), extra
