"""--drivedegrade-adaptive end to end (SPEC section 14): the same adaptive cells serially and under -n 2, verify
recomputing every stop from cells/*.json (and failing a tampered one), reproduce rerunning an adaptive run bit for
bit, and the options' usage errors. Few frames and two families, so every run stays a few seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, no_traceback, stored_records, verify_cli  # noqa: E402
from test_shards import two_scene_world  # noqa: E402, F401 - 2 val scenes: the temporal planner resets between them

from pytest_drivedegrade.certificate.seal import seal, write_certificate  # noqa: E402
from pytest_drivedegrade.cli import main  # noqa: E402

PLANNERS = Path(__file__).resolve().parents[2] / "planners"

pytest_plugins = ["plugin_support"]


def section(folder: Path) -> dict:
    return load_json(folder / "certificate.json")["adaptive"]


@pytest.mark.parametrize("planner", ["camera_cnn.py", "temporal_cnn.py"])
def test_adaptive_cells_are_the_same_serially_and_under_n2_and_verify(dd, two_scene_world, planner):  # noqa: F811
    kw = {"planner": str(PLANNERS / planner), "data": two_scene_world, "families": "jpeg,blackout",
          "severities": "1,2,3,4,5"}
    name = planner.removesuffix(".py")
    got = {}
    for layout in ("-p no:xdist", "-n 2"):
        report = f"r{layout[1]}"
        result = dd.run(*layout.split(), "--drivedegrade-frames", "16", "--drivedegrade-adaptive", report=report,
                        **kw)
        result.assert_outcomes(passed=13)
        no_traceback(result)
        result.stdout.fnmatch_lines(["*adaptive (alpha 0.05, betting): * forward passes against *"])
        folder = dd.pytester.path / report / name
        got[layout] = (stored_records(folder), (folder / "cells.csv").read_text(), section(folder))
        done = verify_cli(folder / "certificate.json")
        assert done.returncode == 0, done.stderr
    serial, parallel = got["-p no:xdist"], got["-n 2"]
    assert parallel[0] == serial[0]
    assert parallel[1] == serial[1]
    assert parallel[2] == serial[2]
    sec = serial[2]
    if name == "temporal_cnn":  # a planner with reset on a run of 2 scenes: whole scenes, no warm-up
        assert sec["plan"]["warmup"] == 0 and len(sec["plan"]["units"]) == 2
    else:
        assert sec["plan"]["window"] == 1
    assert sec["cells"]["clean"]["stop"] == "full" and sec["cells"]["clean"]["units"] == len(sec["plan"]["units"])
    assert all(c["stop"] in ("full", "settled", "data", "skipped") for c in sec["cells"].values())
    assert "Union bound over the 11 stopping cells" in sec["guarantee"]
    for fam in ("jpeg", "blackout"):  # no severity skipped: monotone retention is not assumed (issue 36)
        entry = sec["families"][fam]
        assert entry["visited"] == [1, 2, 3, 4, 5] and entry["skipped"] == []
    assert sec["plan"]["draw"]["planner_fingerprint"] == load_json(folder / "certificate.json")["planner"][
        "fingerprint"]


def test_verify_fails_a_tampered_stopping_decision_and_reproduce_reruns_bit_for_bit(dd, capsys):
    planner = dd.write_planner()
    dd.run("-p", "no:xdist", "--drivedegrade-adaptive", families="jpeg", severities="1,2,3,4,5").assert_outcomes(
        passed=8)
    cert_path = dd.folder() / "certificate.json"
    assert verify_cli(cert_path).returncode == 0
    capsys.readouterr()
    assert main(["reproduce", str(cert_path), str(planner), "--cells", "3", "--seed", "0"]) == 0
    assert "identical" in capsys.readouterr().out
    cert = load_json(cert_path)
    cell = next(c for c, e in cert["adaptive"]["cells"].items() if e["stop"] in ("settled", "data"))
    cert["adaptive"]["cells"][cell]["units"] -= 1  # claim the cell stopped a unit earlier, and reseal
    write_certificate(cert_path, seal(cert))
    done = verify_cli(cert_path)
    assert done.returncode == 1
    assert f"adaptive.cells.{cell}.units: certificate says" in done.stderr
    cert["adaptive"]["cells"][cell]["units"] += 1
    cert["adaptive"]["method"] = "asymptotic"  # a certificate stopped by the former rule: said so, not a mismatch
    write_certificate(cert_path, seal(cert))
    done = verify_cli(cert_path)
    assert done.returncode == 1 and "stopped on the 'asymptotic' confidence sequence; this version stops on" \
        in done.stderr, done.stderr


def test_adaptive_usage_errors(dd):
    for extra, message in ((["--drivedegrade-alpha", "0.1"], "--drivedegrade-alpha: needs --drivedegrade-adaptive"),
                           (["--drivedegrade-adaptive", "--drivedegrade-alpha", "0.9"], "must be between"),
                           (["--drivedegrade-adaptive", "--drivedegrade-seeds", "2"], "--drivedegrade-seeds above 1")):
        dd.write_planner()
        result = dd.run("-p", "no:xdist", *extra)
        assert result.ret == pytest.ExitCode.USAGE_ERROR
        assert message in result.stderr.str(), json.dumps(extra)


def test_the_sequential_gate_passes_an_unchanged_planner_and_fails_a_planted_regression(dd):
    """A full run is the baseline (its cells/ beside its certificate); adaptive runs are gated against it."""
    from plugin_support import FRAGILE

    dd.write_planner()
    families, severities, frames = "low_light,blackout", "5", ("--drivedegrade-frames", "12")
    dd.run("-p", "no:xdist", *frames, families=families, severities=severities, report="base").assert_outcomes(
        passed=5)
    baseline = dd.folder(report="base") / "certificate.json"
    gate = ("--drivedegrade-baseline", str(baseline), "--drivedegrade-adaptive")
    same = dd.run("-p", "no:xdist", *frames, *gate, families=families, severities=severities)
    same.assert_outcomes(passed=5)
    assert same.ret == 0
    same.stdout.fnmatch_lines(["*baseline (sequential, alpha 0.05): 0 regression(s) beyond tolerance 0.02, "
                               "3 cell(s) settled as no regression*"])
    assert section(dd.folder())["rule"] == "gate"
    done = verify_cli(dd.folder() / "certificate.json")
    assert done.returncode == 0, done.stderr
    dd.write_planner(scale=FRAGILE)
    worse = dd.run("-p", "no:xdist", *frames, *gate, families=families, severities=severities, report="fragile")
    assert worse.ret == 1
    no_traceback(worse)
    worse.stdout.fnmatch_lines(["*REGRESSION low_light-s5: retention 0.0* on the units tested, baseline 0.1*: "
                                "dropped by more than 0.02, settled at level 0.05*",
                                "*baseline (sequential, alpha 0.05): 3 regression(s) beyond tolerance 0.02*"])
    # 12 frames of one scene, one unit (a context planner without reset gets whole scenes): every cell runs it, so
    # each test decides from the exact values, and blackout and blind regressed too


def test_a_change_on_a_few_frames_fails_the_adaptive_gate(dd):
    """Issue 36 end to end: the planner changed only on 2 of 40 frames (5 %) under gaussian_blur, 3 m sideways,
    gated adaptively against its own full run. The old gate drew the frames in the corruption seed's order, saw
    none of the changed ones in its first 10 units (they are the last two of that order here), found every
    paired difference 0 and settled "no regression" at unit 10; now no decision is taken on a prefix without
    information and the gate fails."""
    from pytest_drivedegrade.payload import CellPayload

    dd.write_planner()
    kw = {"families": "gaussian_blur", "severities": "1,2,3,4,5"}
    frames = ("--drivedegrade-frames", "40")
    dd.run("-p", "no:xdist", *frames, report="base", **kw).assert_outcomes(passed=8)
    base = dd.folder(report="base")
    tokens = CellPayload.from_builtins(load_json(base / "cells" / "clean.json")).record.frames
    late = {tokens[int(i)] for i in np.random.default_rng(0).permutation(len(tokens))[-2:]}
    dd.write_planner(scale=f"10.0 * d + 3.0 * (context.token in {sorted(late)!r}) * cell.startswith('gaussian_blur')")
    gate = ("--drivedegrade-baseline", str(base / "certificate.json"), "--drivedegrade-adaptive")
    got = dd.run("-p", "no:xdist", *frames, *gate, report="changed", **kw)
    assert got.ret == 1, got.stdout.str()
    no_traceback(got)
    got.stdout.fnmatch_lines(["*REGRESSION gaussian_blur-s*", "*baseline (sequential, alpha 0.05): * regression(s)*"])
    assert "0 regression(s)" not in got.stdout.str()
    sec = section(dd.folder(report="changed"))
    assert sec["plan"]["draw"]["baseline_digest"] == load_json(base / "certificate.json")["digest"]
    done = verify_cli(dd.folder(report="changed") / "certificate.json")
    assert done.returncode == 0, done.stderr


def test_adaptive_units_score_their_frames_bit_for_bit_as_the_full_run(dd):
    """Every frame an adaptive cell scored has the full run's row of that cell, bit for bit:
    for frame_dropout too, whose held frame may come from before the unit (the span replays the scene's loss
    draws; without that, 30 % of this cell's plans differ)."""
    from pytest_drivedegrade.cells import FRAME_ARRAYS
    from pytest_drivedegrade.payload import CellPayload

    dd.write_planner()
    kw = {"families": "frame_dropout,jpeg", "severities": "5"}
    frames = ("--drivedegrade-frames", "16")
    dd.run("-p", "no:xdist", *frames, report="full", **kw).assert_outcomes(passed=5)
    dd.run("-p", "no:xdist", *frames, "--drivedegrade-adaptive", report="ada", **kw).assert_outcomes(passed=5)
    compared = 0
    for cell in ("frame_dropout-s5", "jpeg-s5", "clean"):
        full, ada = (CellPayload.from_builtins(load_json(dd.folder(report=r) / "cells" / f"{cell}.json")).record
                     for r in ("full", "ada"))
        ran = np.isfinite(ada.l2_avg_per_frame())
        assert ran.any() and ada.frames == full.frames
        for a in FRAME_ARRAYS:  # EC too: it reads the previous keyframe's plan, which a whole scene runs
            np.testing.assert_array_equal(ada.array(a.name)[ran], full.array(a.name)[ran], err_msg=f"{cell} {a.name}")
        compared += int(ran.sum())
    assert compared >= 16
    # the test planner takes `context` without `reset`: whole scenes as units (issue 36: single frames cut its
    # memory, frame_dropout S5 1.031 against the full run's 0.439), so a unit runs as the full run does
    plan = section(dd.folder(report="ada"))["plan"]
    assert plan["warmup"] == 0 and plan["window"] > 1 and len(plan["units"]) == 1
