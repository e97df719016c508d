"""Scene shards and `drivedegrade merge` (SPEC section 9), end to end: two shards run one after the other and
merged give the unsharded run's cells.csv and certificate sections, for a temporal planner too; a missing shard
is named; --allow-incomplete says completeness: false."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, read_csv  # noqa: E402
from test_temporal import TEMPORAL  # noqa: E402

from pytest_drivedegrade.cli import main  # noqa: E402

PLANNERS = Path(__file__).resolve().parents[2] / "planners"

pytest_plugins = ["plugin_support"]

SAME = ("cells", "thresholds", "axes", "verdict", "floor", "null_control", "spec_version", "planner", "dataset",
        "settings")


@pytest.fixture(scope="session")
def two_scene_world(eleven_scene_world: Path) -> Path:
    """11 scenes: 9 train (tables only) and 2 val scenes with rendered images (`conftest.eleven_scene_world`)."""
    return eleven_scene_world


def run(dd, world, *extra, report):
    return dd.run("-p", "no:xdist", *extra, planner="temporal.py", report=report, data=world,
                  families="jpeg,blackout", severities="5")


def test_two_shards_merged_equal_the_unsharded_run(dd, two_scene_world, capsys):
    dd.pytester.makepyfile(temporal=TEMPORAL.format(leak=False))
    run(dd, two_scene_world, report="full").assert_outcomes(passed=5)
    for i in (1, 2):
        result = run(dd, two_scene_world, "--drivedegrade-shard", f"{i}/2", report="sh")
        result.assert_outcomes(passed=5)
        result.stdout.fnmatch_lines([f"*shard {i}/2: * of 4 frames (1 scene(s)), 5 cell(s) finished*"])
    shards = dd.pytester.path / "sh" / "temporal"
    assert sorted(p.name for p in shards.iterdir() if p.is_dir()) == ["shard-1-of-2", "shard-2-of-2"]
    assert not (shards / "certificate.json").exists()  # a shard writes no certificate of its own
    out = dd.pytester.path / "merged"
    capsys.readouterr()
    assert main(["merge", str(shards / "shard-2-of-2"), str(shards / "shard-1-of-2"), "--out", str(out)]) == 0
    # one progress line in a log (stderr is no terminal here): milestones and the closing count, no line per cell
    progress = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("drivedegrade merge")]
    assert progress[-1].startswith("drivedegrade merge: 10 cell files in ") and len(progress) <= 4, progress
    full, merged = dd.pytester.path / "full" / "temporal", out / "temporal"
    assert read_csv(merged / "cells.csv") == read_csv(full / "cells.csv")
    a, b = load_json(full / "certificate.json"), load_json(merged / "certificate.json")
    for key in SAME:
        assert a[key] == b[key], key
    # so `drivedegrade reproduce` can check a merged certificate against a rerun of any layout
    assert [c["plans_digest"] for c in b["cells"]] == [c["plans_digest"] for c in a["cells"]]
    digests = {c["cell"]: c["plans_digest"] for c in b["cells"]}
    assert len(digests) == 5 and digests["null"] == digests["clean"]  # the null control passed: the same plans
    assert b["tool"]["versions"] == a["tool"]["versions"] and b["dataset"]["frames_requested"] == 4
    assert (merged / "report.html").stat().st_size > 10_000


def test_a_missing_shard_is_named_and_needs_allow_incomplete(dd, two_scene_world, capsys):
    dd.pytester.makepyfile(temporal=TEMPORAL.format(leak=False))
    run(dd, two_scene_world, "--drivedegrade-shard", "2/2", report="sh").assert_outcomes(passed=5)
    shard = dd.pytester.path / "sh" / "temporal" / "shard-2-of-2"
    assert main(["merge", str(shard), "--out", str(dd.pytester.path / "m")]) == 2
    assert "missing shard(s) 1/2" in capsys.readouterr().err
    assert main(["merge", str(shard), "--out", str(dd.pytester.path / "m"), "--allow-incomplete"]) == 0
    assert "INCOMPLETE: shard(s) 1 missing" in capsys.readouterr().out
    cert = load_json(dd.pytester.path / "m" / "temporal" / "certificate.json")
    assert cert["completeness"]["complete"] is False and cert["completeness"]["missing_shards"] == [1]
    assert cert["dataset"]["frames"] == 2


def test_shards_of_different_runs_are_refused(dd, two_scene_world, capsys):
    dd.pytester.makepyfile(temporal=TEMPORAL.format(leak=False))
    run(dd, two_scene_world, "--drivedegrade-shard", "1/2", report="a").assert_outcomes(passed=5)
    run(dd, two_scene_world, "--drivedegrade-shard", "2/2", "--drivedegrade-seed", "3",
        report="b").assert_outcomes(passed=5)
    code = main(["merge", str(dd.pytester.path / "a" / "temporal"), str(dd.pytester.path / "b" / "temporal"),
                 "--out", str(dd.pytester.path / "m")])
    assert code == 2 and "is not from the same run" in capsys.readouterr().err


def test_more_shards_than_scenes_is_a_usage_error(dd, two_scene_world):
    dd.pytester.makepyfile(temporal=TEMPORAL.format(leak=False))
    result = run(dd, two_scene_world, "--drivedegrade-shard", "3/3", report="x")
    assert result.ret == 4
    assert "cannot split 2 scene(s) into 3 shards" in result.stderr.str()


@pytest.mark.parametrize("planner", ["camera_cnn.py", "temporal_cnn.py"])
def test_the_reference_planners_merge_to_their_unsharded_cells(dd, two_scene_world, planner):
    """Issue 'Real scale', done-when: two shards merged give cells.csv equal, byte for byte, to the single-process
    run for camera_cnn and for the temporal reference planner (which resets per scene and reads the context)."""
    kw = {"planner": str(PLANNERS / planner), "data": two_scene_world, "families": "frame_dropout,jpeg",
          "severities": "3,5"}
    dd.run("-p", "no:xdist", "--drivedegrade-frames", "8", report="full", **kw).assert_outcomes(passed=7)
    for i in (1, 2):
        dd.run("-p", "no:xdist", "--drivedegrade-frames", "8", "--drivedegrade-shard", f"{i}/2", report="sh",
               **kw).assert_outcomes(passed=7)
    name = planner.removesuffix(".py")
    shards, out = dd.pytester.path / "sh" / name, dd.pytester.path / "merged"
    assert main(["merge", str(shards / "shard-1-of-2"), str(shards / "shard-2-of-2"), "--out", str(out)]) == 0
    full = dd.pytester.path / "full" / name
    assert (out / name / "cells.csv").read_text() == (full / "cells.csv").read_text()
    # the cost ledger joins too: predictions made and frames that reused the clean plan (camera_cnn reuses in
    # frame_dropout, the temporal planner never)
    a, b = (load_json(f / "certificate.json")["cost"] for f in (full, out / name))
    assert (b["predictions"], b["reused"]) == (a["predictions"], a["reused"])
    assert (a["reused"] > 0) is (planner == "camera_cnn.py")
