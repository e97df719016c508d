"""Issue 20, part B, end to end: the merge checks its shards (M5) on shards of unequal size (2 and 1 frames, so a
mean of per-shard means is not the pooled mean), a baseline is refused under --drivedegrade-shard (M6)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, read_csv  # noqa: E402
from test_temporal import TEMPORAL  # noqa: E402

from pytest_drivedegrade.cli import main  # noqa: E402

pytest_plugins = ["plugin_support"]

#: Results of the runs below, made once per session (a folder per run), copied into each test that edits them.
_MADE: dict[str, Path] = {}


def _run(dd, world, *extra, report):
    return dd.run("-p", "no:xdist", "--drivedegrade-frames", "3", *extra, planner="temporal.py", report=report,
                  data=world, families="jpeg,blackout", severities="5")


@pytest.fixture()
def unequal(dd, two_scene_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with `full/temporal` (the unsharded run of 3 frames) and `sh/temporal/shard-{1,2}-of-2` (2 frames
    and 1 frame); made once, then copied into the test's own folder."""
    if "unequal" not in _MADE:
        dd.pytester.makepyfile(temporal=TEMPORAL.format(leak=False))
        _run(dd, two_scene_world, report="full").assert_outcomes(passed=5)
        for i, n in ((1, 2), (2, 1)):
            result = _run(dd, two_scene_world, "--drivedegrade-shard", f"{i}/2", report="sh")
            result.assert_outcomes(passed=5)
            result.stdout.fnmatch_lines([f"*shard {i}/2: {n} of 3 frames (1 scene(s))*"])
        made = tmp_path_factory.mktemp("unequal")
        for folder in ("full", "sh"):
            shutil.copytree(dd.pytester.path / folder, made / folder)
        _MADE["unequal"] = made
    return Path(shutil.copytree(_MADE["unequal"], dd.pytester.path / "made"))


def _shard(base: Path, i: int) -> Path:
    return base / "sh" / "temporal" / f"shard-{i}-of-2"


def test_m5_unequal_shards_merge_to_the_pooled_floor_and_the_unsharded_cells(unequal: Path) -> None:
    """Shards of 2 and 1 frames: the merged cells and floor equal the unsharded run's; the floor's L2 is the mean
    over the 3 frames (pooled), which here differs from the mean of the two shards' means."""
    out = unequal / "merged"
    assert main(["merge", str(_shard(unequal, 1)), str(_shard(unequal, 2)), "--out", str(out)]) == 0
    full, merged = load_json(unequal / "full" / "temporal" / "certificate.json"), \
        load_json(out / "temporal" / "certificate.json")
    assert read_csv(out / "temporal" / "cells.csv") == read_csv(unequal / "full" / "temporal" / "cells.csv")
    assert merged["floor"] == full["floor"] and merged["axes"] == full["axes"]
    assert merged["completeness"]["complete"] is True and merged["dataset"]["frames"] == 3
    per_shard = [np.asarray(load_json(_shard(unequal, i) / "shard.json")["floor_l2"], dtype=float) for i in (1, 2)]
    assert [len(p) for p in per_shard] == [2, 1]
    pooled, of_means = np.concatenate(per_shard).mean(), np.mean([p.mean() for p in per_shard])
    assert abs(pooled - of_means) > 1e-3  # the two rules give different numbers on these shards
    assert merged["floor"]["l2_avg"] == round(float(pooled), 6) != round(float(of_means), 6)


def test_m5_a_relabelled_copy_of_shard_1_does_not_merge_as_complete(unequal: Path, capsys) -> None:
    """Shard 1's folder copied and its manifest's index edited to 2: given with shard 1 it would double-count
    shard 1's frames and leave shard 2's out, yet every index 1..N is there."""
    fake = unequal / "fake" / "shard-2-of-2"
    shutil.copytree(_shard(unequal, 1), fake)
    manifest = json.loads((fake / "shard.json").read_text())
    manifest["index"] = 2
    (fake / "shard.json").write_text(json.dumps(manifest))
    code = main(["merge", str(_shard(unequal, 1)), str(fake), "--out", str(unequal / "m")])
    err = capsys.readouterr().err
    assert code == 2 and "shards 1 and 2 both hold frame" in err and "relabelled" in err
    assert not (unequal / "m" / "temporal" / "certificate.json").exists()
    # with --allow-incomplete too: overlapping shards are never merged
    assert main(["merge", str(_shard(unequal, 1)), str(fake), "--out", str(unequal / "m"),
                 "--allow-incomplete"]) == 2


def test_m5_a_shard_given_twice_is_refused_as_given_twice(unequal: Path, capsys) -> None:
    """The duplicate-shard check: the same folder twice (with the other shard) is named, not double-counted."""
    one = str(_shard(unequal, 1))
    code = main(["merge", one, one, str(_shard(unequal, 2)), "--out", str(unequal / "m")])
    assert code == 2 and "shard(s) given twice: [1]" in capsys.readouterr().err


def test_m5_shards_that_do_not_cover_the_run_are_not_complete(unequal: Path, capsys) -> None:
    """Both shards there, but the run scored more frames than they hold (a manifest's frames_total says 4)."""
    for i in (1, 2):
        path = _shard(unequal, i) / "shard.json"
        manifest = json.loads(path.read_text())
        manifest["frames_total"] = 4
        path.write_text(json.dumps(manifest))
    code = main(["merge", str(_shard(unequal, 1)), str(_shard(unequal, 2)), "--out", str(unequal / "m")])
    assert code == 2 and "the shards hold 3 frame(s) but the run scores 4" in capsys.readouterr().err


@pytest.mark.parametrize(("field", "value"), [("index", "1"), ("cells", 3), ("frames_total", None)])
def test_m5_a_malformed_shard_manifest_is_named(unequal: Path, capsys, field: str, value: object) -> None:
    path = _shard(unequal, 1) / "shard.json"
    manifest = json.loads(path.read_text())
    manifest[field] = value
    path.write_text(json.dumps(manifest))
    code = main(["merge", str(_shard(unequal, 1)), str(_shard(unequal, 2)), "--out", str(unequal / "m")])
    assert code == 2 and f"a malformed shard manifest ({field} missing or of the wrong type)" in \
        capsys.readouterr().err


def test_m6_a_baseline_under_a_shard_is_refused(dd, two_scene_world: Path, tmp_path: Path) -> None:
    """A shard's cells cover a part of the frames, the baseline the whole run: comparing them would gate the
    wrong quantity. Refused before anything runs, saying what to do."""
    dd.pytester.makepyfile(temporal=TEMPORAL.format(leak=False))
    baseline = tmp_path / "baseline.json"
    baseline.write_text("{}")
    result = _run(dd, two_scene_world, "--drivedegrade-shard", "1/2", "--drivedegrade-baseline", str(baseline),
                  report="sh")
    assert result.ret == 4
    err = result.stderr.str()
    assert "--drivedegrade-baseline: a shard cannot be gated" in err and "drivedegrade merge" in err
    assert "Traceback" not in err


PLANNERS = Path(__file__).resolve().parents[2] / "planners"


def test_new_user_b_settings_reuse_and_cost_reused_agree_on_a_resumed_run(dd) -> None:
    """camera_cnn takes the clean plan on frame_dropout frames whose inputs equal clean's. Rerun with
    --drivedegrade-no-reuse, the stored frame_dropout cell (which reused) is computed again, every frame
    predicted, so the certificate does not say reuse: false beside reused > 0; clean (nothing reused) resumes."""
    kw = {"planner": str(PLANNERS / "camera_cnn.py"), "families": "frame_dropout", "severities": "1"}
    dd.run("-p", "no:xdist", **kw).assert_outcomes(passed=4)
    first = load_json(dd.folder("camera_cnn") / "certificate.json")
    assert first["settings"]["reuse"] is True and first["cost"]["reused"] > 0
    result = dd.run("-p", "no:xdist", "--drivedegrade-no-reuse", **kw)
    result.assert_outcomes(passed=4)
    cert = load_json(dd.folder("camera_cnn") / "certificate.json")
    assert cert["settings"]["reuse"] is False and cert["cost"]["reused"] == 0
    assert cert["cost"]["cells"]["frame_dropout-s1"]["predictions"] == cert["dataset"]["frames"]
    assert "frame_dropout-s1" not in cert["cost"]["resumed_cells"] and "clean" in cert["cost"]["resumed_cells"]
    result.stdout.fnmatch_lines(["*recomputed because their run key differs in reuse (they took the clean plan on "
                                 "some frames; this run has --drivedegrade-no-reuse): frame_dropout-s1*"])
    assert [c["plans_digest"] for c in cert["cells"]] == [c["plans_digest"] for c in first["cells"]]


def test_new_user_d_no_output_holds_an_absolute_path(dd, tmp_path_factory: pytest.TempPathFactory) -> None:
    """Planner, report folder and data set given as absolute paths: the certificate, report, CSV and cell files
    record them relative to rootdir (pytester's rootdir is the folder above its test folder, which holds the
    world too); no output holds the absolute path of any of them."""
    dd.write_planner()
    root = dd.pytester.path
    report = root / "out"
    result = dd.run("-p", "no:xdist", "--drivedegrade-report", str(report), planner=str(root / "myplanner.py"))
    result.assert_outcomes(passed=9)
    folder = report / "testplanner"
    cert = load_json(folder / "certificate.json")
    rootdir = Path(result.stdout.str().split("rootdir: ", 1)[1].split()[0].rstrip(","))
    inside = root.relative_to(rootdir).as_posix()
    assert cert["planner"]["file"] == f"{inside}/myplanner.py"
    assert cert["dataset"]["source"] == dd.world.relative_to(rootdir).as_posix()
    command = cert["tool"]["command"]
    assert f"pytest --drivedegrade {inside}/myplanner.py " in command and f" --drivedegrade-report {inside}/out" in \
        command
    outputs = [folder / "certificate.json", folder / "report.html", folder / "cells.csv",
               *sorted((folder / "cells").glob("*.json"))]
    for path in outputs:
        text = path.read_text()
        for secret in (str(rootdir), str(Path.home())):
            assert secret not in text, (path.name, secret)


CHANGING = '''
import os
from pathlib import Path

import numpy as np
import pytest

MARKER, VERSION = {marker!r}, Path({version!r})
CALLS = 0


class Changing:
    """Declares its weights' version (read when built) as its fingerprint; with MARKER present, its 7th
    prediction installs new weights (the version file changes) and kills its process, so Ray replaces it."""

    cameras = ("CAM_FRONT",)
    name = "changing"

    def __init__(self):
        self.fingerprint = VERSION.read_text()

    def predict(self, images, ego, cmd):
        global CALLS
        CALLS += 1
        if CALLS == 7 and os.path.exists(MARKER):
            os.remove(MARKER)
            VERSION.write_text("weights-v2")
            os._exit(1)
        plan = np.arange(1, 7)[:, None] * 0.5 * np.array(ego.velocity, dtype=float)
        plan[:, 1] += float(images["CAM_FRONT"][::8, ::8].mean()) / 255.0
        return plan


@pytest.fixture(scope="session")
def planner():
    return Changing()
'''


@pytest.mark.xdist_group("ray")
def test_l6_a_replacement_ray_actor_with_another_fingerprint_fails_loudly(dd, two_scene_world: Path) -> None:
    """An actor dies after the planner's weights changed on disk: its replacement builds a planner with another
    fingerprint, and the run stops naming it, rather than mixing cells of two planners under one certificate."""
    pytest.importorskip("ray")
    marker, version = dd.pytester.path / "kill-once", dd.pytester.path / "version.txt"
    version.write_text("weights-v1")
    marker.write_text("")
    dd.pytester.makepyfile(changing=CHANGING.format(marker=str(marker), version=str(version)))
    result = dd.run("--drivedegrade-ray", "local", "--drivedegrade-frames", "8", planner="changing.py",
                    data=two_scene_world, families="jpeg,blackout", severities="5", report="ray", subprocess=True)
    assert not marker.exists()  # an actor did die mid-run
    out = result.stdout.str() + result.stderr.str()
    assert "the replacement of Ray actor" in out and "built a planner with another fingerprint than the run's" in out
    assert result.ret != 0
    cert = dd.pytester.path / "ray" / "changing" / "certificate.json"
    assert not cert.exists() or load_json(cert)["completeness"]["complete"] is False
