"""End-to-end runs of the pytest plugin under faults (SPEC section 7): a misbehaving planner, a null control
that catches an undeclared camera, bad input, a killed worker and Ctrl-C. Each fault fails what it touches,
says where, and loses nothing already computed.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import SMALL_CELLS, by_cell, load_json, no_traceback, read_csv  # noqa: E402

pytest_plugins = ["plugin_support"]


def failed_cells(result: pytest.RunResult) -> set[str]:
    return set(re.findall(r"^FAILED \S+?::(\S+)", result.stdout.str(), re.M))


def test_conformance_faults_fail_only_their_cells(dd, scored_tokens):
    """One planner, five faults in five cells (one frame each); the other cells pass and the outputs are written.

    The timeout separates a hang (the planner sleeps until interrupted) from a normal call by a measured margin:
    a normal call took at most 59 ms (median 36 ms) at a load of 12.8 on 2 cores (issue 41's measurement), so
    1 s holds at a load of 15 with room to spare. It failed before because the planner read the whole data set in
    its first predict() call (282 ms at that load, on top of the call), against a 0.5 s timeout; it now reads it
    when it is built."""
    frame = scored_tokens[1]
    faults = {"gaussian_blur-s1": "raise", "gaussian_blur-s5": "nan", "jpeg-s1": "shape", "jpeg-s5": "write",
              "blackout-s1": "hang"}
    dd.write_planner(faults={cell: (fault, frame) for cell, fault in faults.items()})
    result = dd.run("--drivedegrade-timeout", "1")
    result.assert_outcomes(passed=4, failed=5)
    assert failed_cells(result) == set(faults)
    no_traceback(result)
    head = "cell {}: 1 of 4 frames failed the planner contract"
    where = f"*frame '{frame}'*"
    result.stdout.fnmatch_lines([
        head.format("gaussian_blur-s1"), f"{where}: predict() raised RuntimeError: boom in the test planner",
        head.format("gaussian_blur-s5"), f"{where} is not finite (first at step 3, coordinate 1)*Got ndarray*nan*",
        head.format("jpeg-s1"), f"{where} has shape (5, 2), not (6, 2)*",
        head.format("jpeg-s5"), f"{where}: predict() wrote to its input image*read-only*",
        head.format("blackout-s1"), f"{where}: predict() took longer than 1 s*--drivedegrade-timeout*",
    ], consecutive=False)
    rows = by_cell(read_csv(dd.folder() / "cells.csv"))
    assert list(rows) == list(SMALL_CELLS)
    assert {c: rows[c]["conformance_errors"] for c in faults} == {c: "1" for c in faults}
    assert {c: rows[c]["frames"] for c in faults} == {c: "3" for c in faults}  # the failed frame is left out
    assert rows["clean"]["conformance_errors"] == "0" and rows["clean"]["frames"] == "4"


def test_clean_with_a_failed_frame_is_run_once_for_its_item_and_the_null_control(dd, scored_tokens):
    """The null control compares against the clean item's own record, also when a clean frame failed (a
    stored result with failures is not reused by a rerun, but within the run it is the reference)."""
    calls = dd.pytester.path / "calls.txt"
    dd.write_planner(faults={"clean": ("raise", scored_tokens[1])}, count_file=str(calls))
    result = dd.run(families="jpeg", severities="1")
    assert "clean" in failed_cells(result) and "jpeg-s1" not in failed_cells(result)
    assert calls.read_text().split().count("clean") == 4  # the four scored frames, once


def test_null_control_names_the_undeclared_camera(dd):
    """cameras=("CAM_FRONT",) but CAM_BACK is read: null and blackout-s3 (the rear control) fail naming it."""
    dd.write_planner(read_back=True)
    result = dd.run(families="blackout", severities="3")
    result.assert_outcomes(passed=2, failed=2)
    assert failed_cells(result) == {"null", "blackout-s3"}
    no_traceback(result)
    result.stdout.fnmatch_lines([  # in run order: blackout-s3, then the null control last
        "null control failed in cell blackout-s3*",
        "*declared-unread camera(s) that change the plan: CAM_BACK; add them to planner.cameras",
        "null control failed in cell null: plans are not bit-identical to clean (max abs difference *)",
        "*declared-unread camera(s) that change the plan: CAM_BACK; add them to planner.cameras",
    ], consecutive=False)
    assert load_json(dd.folder() / "certificate.json")["null_control"]["passed"] is False


def test_blackout_s3_is_a_null_control_for_a_front_only_planner(dd):
    dd.write_planner()
    result = dd.run(families="blackout", severities="3")
    result.assert_outcomes(passed=4)
    rows = by_cell(read_csv(dd.folder() / "cells.csv"))
    assert rows["blackout-s3"]["retention"] == "1.0" and rows["blackout-s3"]["endpoint_shift"] == "0.0"


@pytest.mark.parametrize("planner, options, expected", [
    ("nothere.py", [], "*--drivedegrade: planner file *nothere.py does not exist*"),
    ("broken.py", [], "*--drivedegrade: *broken.py:3: syntax error*"),
    ("nofixture.py", [], "*nofixture.py defines no `planner` fixture*"),
    ("myplanner.py", ["--drivedegrade-families", "jpeg,fgo"],
     "*--drivedegrade-families: unknown family 'fgo'; valid families: gaussian_blur, motion_blur*lens_dirt*"),
    ("myplanner.py", ["--drivedegrade-severities", "0,6"], "*--drivedegrade-severities: severity '0' is not one of*"),
    ("myplanner.py", ["--drivedegrade-baseline", "notjson.json"],
     "*--drivedegrade-baseline: *notjson.json: not valid JSON*line 1*"),
    ("myplanner.py", ["--drivedegrade-baseline", "edited.json"],
     "*--drivedegrade-baseline: *edited.json: digest mismatch*edited section(s): axes*"),
    ("myplanner.py", ["--drivedegrade-data", "nowhere"], "*--drivedegrade: nuScenes data root *nowhere does not "
                                                         "exist*"),
    ("myplanner.py", ["--drivedegrade-report", "notjson.json/rep"], "*--drivedegrade-report: cannot create the "
                                                                     "report folder *notjson.json/rep: Not a dir*"),
    ("myplanner.py", ["--drivedegrade-baseline", "nan.json"],
     "*--drivedegrade-baseline: *nan.json: malformed: a NaN literal at axes.quality*"),
    ("myplanner.py", ["--drivedegrade-baseline", "deep.json"],
     "*--drivedegrade-baseline: *deep.json: malformed: nested deeper than 64 levels at line 1, column *"),
    ("myplanner.py", ["--drivedegrade-baseline", "dup.json"],
     "*--drivedegrade-baseline: *dup.json: malformed: duplicate key 'axes' in the top-level object*"),
], ids=["missing", "syntax", "no-fixture", "family", "severity", "baseline-not-json", "baseline-edited", "no-data",
        "report-not-a-folder", "baseline-nan", "baseline-deep", "baseline-duplicate-key"])
def test_bad_input_is_a_usage_error(dd, planner, options, expected):
    """(Trust case 11 for the baseline-nan, -deep and -duplicate-key cases: a usage error, not an INTERNALERROR.)"""
    from pytest_drivedegrade.certificate.seal import seal

    dd.write_planner()
    dd.pytester.makepyfile(broken="import pytest\n\ndef planner(:\n    pass\n",
                           nofixture="def not_a_planner():\n    pass\n")
    (dd.pytester.path / "notjson.json").write_text("{not json")
    cert = seal({"schema": "drivedegrade-certificate/1", "axes": {"quality": 0.9}})
    cert["axes"]["quality"] = 0.99
    (dd.pytester.path / "edited.json").write_text(json.dumps(cert))
    (dd.pytester.path / "nan.json").write_text('{"axes": {"quality": NaN}}')
    (dd.pytester.path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    (dd.pytester.path / "dup.json").write_text('{"axes": {}, "axes": {"quality": 1.0}}')
    result = dd.pytester.runpytest_inprocess(*dd.args(*options, planner=planner))
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines([expected])
    no_traceback(result)


def test_truncated_jpeg_fails_the_cells_that_read_it(dd, small_world, scored_tokens, tmp_path):
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    data = tmp_path / "world"
    shutil.copytree(small_world, data)
    frame = next(f for f in NuScenesReader(data, split="val").scorable_frames(limit=4) if f.token == scored_tokens[1])
    image = Path(frame.cameras["CAM_FRONT"].path)
    image.write_bytes(image.read_bytes()[:2000])
    dd.write_planner()
    result = dd.run(data=data, families="jpeg,blackout", severities="5")
    # Every cell that decodes CAM_FRONT of that frame fails; blind and blackout-s5 (front camera black) do not.
    assert failed_cells(result) == {"clean", "null", "jpeg-s5"}
    result.assert_outcomes(passed=2, failed=3)
    no_traceback(result)
    result.stdout.fnmatch_lines(["cell jpeg-s5: 1 of 4 frames had data errors (the data set's fault, not the "
                                 "planner's)",
                                 f"*frame '{frame.token}': truncated JPEG {image}*no end-of-image marker*"])
    assert "failed the planner contract" not in result.stdout.str()
    rows = by_cell(read_csv(dd.folder() / "cells.csv"))
    assert rows["clean"]["frames"] == "3" and rows["jpeg-s5"]["data_errors"] == "1"
    assert rows["jpeg-s5"]["conformance_errors"] == "0"

    image.write_bytes((small_world / image.relative_to(data)).read_bytes())  # the data set is repaired
    again = dd.run(data=data, families="jpeg,blackout", severities="5")
    again.assert_outcomes(passed=5)  # the repaired image changes the data fingerprint: all computed again
    assert by_cell(read_csv(dd.folder() / "cells.csv"))["clean"]["frames"] == "4"


def test_malformed_planner_attributes_fail_with_a_message(dd):
    dd.write_planner(cameras=("CAM_FRNT",))
    result = dd.run(families="jpeg", severities="1")
    result.assert_outcomes(failed=4)
    no_traceback(result)
    assert "cell clean: planner.cameras names unknown camera(s) ['CAM_FRNT']; valid names are CAM_FRONT, " \
        "CAM_FRONT_RIGHT" in result.stdout.str()
    result.stdout.fnmatch_lines(["*no cell finished: nothing to analyse*"])


def test_killed_worker_is_reported_and_the_rerun_resumes(dd):
    marker, calls = dd.pytester.path / "die", dd.pytester.path / "calls.txt"
    marker.touch()
    dd.write_planner(faults={"jpeg-s5": ("exit", None)}, marker=str(marker), count_file=str(calls))
    first = dd.run("-n", "2")
    assert first.ret == 1
    first.stdout.fnmatch_lines(["*worker*crashed while running*jpeg-s5*",
                                "*missing cells (1): jpeg-s5; rerun the same command*"], consecutive=False)
    stored = sorted(p.stem for p in (dd.folder() / "cells").glob("*.json"))
    assert stored == sorted(set(SMALL_CELLS) - {"jpeg-s5"})
    assert (dd.folder() / "cells.csv").is_file()  # what finished is reported

    marker.unlink()
    calls.write_text("")
    again = dd.run("--junitxml=again.xml")
    again.assert_outcomes(passed=9)
    assert "missing cells" not in again.stdout.str()
    assert set(calls.read_text().split()) == {"jpeg-s5"}  # only the missing cell is computed
    assert len(read_csv(dd.folder() / "cells.csv")) == 9


def test_ctrl_c_keeps_finished_cells_and_the_rerun_resumes(dd):
    marker, calls = dd.pytester.path / "stop", dd.pytester.path / "calls.txt"
    marker.touch()
    dd.write_planner(faults={"jpeg-s1": ("interrupt", None)}, marker=str(marker), count_file=str(calls))
    first = dd.run()
    assert first.ret == pytest.ExitCode.INTERRUPTED
    first.stdout.fnmatch_lines(["*KeyboardInterrupt*"])
    done = ("clean", "gaussian_blur-s1", "gaussian_blur-s5")  # the cells run before jpeg-s1
    assert sorted(p.stem for p in (dd.folder() / "cells").glob("*.json")) == sorted(done)

    marker.unlink()
    calls.write_text("")
    again = dd.run()
    again.assert_outcomes(passed=9)
    assert set(calls.read_text().split()) == set(SMALL_CELLS) - set(done)


@pytest.mark.parametrize("name, expected", [
    ("bad\x00name", "*unusable planner name: planner.name 'bad\\x00name' contains the non-printable character "
                    "U+0000 at position 3*"),
    ("n" * 10_000, "*unusable planner name: planner.name 'nnn*'... is 10000 characters long; a planner name is at "
                   "most * printable characters*"),
], ids=["nul", "10000-chars"])
def test_unusable_planner_name_stops_the_run_clearly(dd, name, expected):
    """Trust case 11: a NUL or a 10 000-character planner.name fails the first cell with the rule it breaks and
    stops the session: no INTERNALERROR, no traceback, no report folder made from the name, and a stored
    result of another planner in the report folder is left as it was."""
    dd.write_planner(name="other")
    dd.run(families="jpeg", severities="1").assert_outcomes(passed=4)
    before = {p: p.read_bytes() for p in (dd.pytester.path / "rep").rglob("*") if p.is_file()}
    dd.write_planner(name=name)
    result = dd.run(families="jpeg", severities="1")
    assert result.ret == pytest.ExitCode.INTERRUPTED  # the session stops at the first cell
    result.assert_outcomes(failed=1)
    no_traceback(result)
    assert "INTERNALERROR" not in result.stdout.str() + result.stderr.str()
    result.stdout.fnmatch_lines([expected])
    after = {p: p.read_bytes() for p in (dd.pytester.path / "rep").rglob("*") if p.is_file()}
    assert after == before


def test_a_swapped_image_recomputes_every_cell_and_says_so(dd, small_world, scored_tokens, tmp_path):
    """Trust case 6: one scored image replaced by another (the world's manifest unchanged) changes the dataset
    fingerprint, so no stored cell is reused and the summary says why; an unchanged rerun reuses them all."""
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    data = tmp_path / "world"
    shutil.copytree(small_world, data)
    dd.write_planner()
    dd.run(data=data, families="jpeg", severities="1").assert_outcomes(passed=4)
    first = load_json(dd.folder() / "certificate.json")["dataset"]["fingerprint"]
    same = dd.run(data=data, families="jpeg", severities="1")
    same.stdout.fnmatch_lines(["*reused 4 stored cell(s) (same run key, digest verified)*"])

    frames = NuScenesReader(data, split="val").scorable_frames(limit=4)
    front, other = (Path(f.cameras["CAM_FRONT"].path) for f in frames[1:3])
    shutil.copyfile(other, front)
    swapped = dd.run(data=data, families="jpeg", severities="1")
    swapped.assert_outcomes(passed=4)
    assert "stored cell(s) (same run key" not in swapped.stdout.str()
    swapped.stdout.fnmatch_lines(["cost: 16 predictions, 0 frames reused the clean plan*"])
    swapped.stdout.fnmatch_lines(["*not reused: 4 stored cell(s) recomputed because their run key differs in "
                                  "dataset_fingerprint (the scored frames' files changed): blind, clean, jpeg-s1, "
                                  "null*"])
    assert load_json(dd.folder() / "certificate.json")["dataset"]["fingerprint"] != first


def test_a_same_name_planner_does_not_overwrite_another_planners_reports(dd):
    """Trust case 12: a report folder whose certificate records another planner file (a planner of the same
    name) is refused at the first cell, before any cell computes, saying to pass --drivedegrade-report; the
    outputs are left as they were; --drivedegrade-report-overwrite replaces them."""
    dd.write_planner(name="shared")
    dd.run(families="jpeg", severities="1").assert_outcomes(passed=4)
    cert = dd.folder("shared") / "certificate.json"
    assert load_json(cert)["planner"]["file"].endswith("/myplanner.py")  # relative to rootdir
    before = {p: p.read_bytes() for p in dd.folder("shared").rglob("*") if p.is_file()}
    dd.write_planner(filename="otherplanner", name="shared", scale="40.0 * d")
    result = dd.run(families="jpeg", severities="1", planner="otherplanner.py")
    assert result.ret == pytest.ExitCode.INTERRUPTED
    result.assert_outcomes(failed=1)
    no_traceback(result)
    result.stdout.fnmatch_lines(["*--drivedegrade-report: *shared holds the certificate of another planner named "
                                 "'shared' (planner file *myplanner.py; this run's is *otherplanner.py); pass another "
                                 "--drivedegrade-report, or --drivedegrade-report-overwrite*"])
    assert {p: p.read_bytes() for p in dd.folder("shared").rglob("*") if p.is_file()} == before
    again = dd.run("--drivedegrade-report-overwrite", families="jpeg", severities="1", planner="otherplanner.py")
    again.assert_outcomes(passed=4)
    assert load_json(cert)["planner"]["file"].endswith("/otherplanner.py")
    dd.run(families="jpeg", severities="1", planner="otherplanner.py").assert_outcomes(passed=4)  # its own now


def test_stray_temporary_files_are_swept_at_start_up_and_said(dd):
    """Trust case 12: the temporaries a kill -9 leaves (named exactly as the atomic writer names them, older than
    the run) in the planner folder and cells/ are removed at start-up and the terminal says so; files that only
    look alike, or are newer than the run's start, are kept."""
    import os
    import time

    dd.write_planner()
    dd.run(families="jpeg", severities="1").assert_outcomes(passed=4)
    folder = dd.folder()
    old = time.time() - 3600
    stray = [folder / ".certificate.json.a1b2c3d_.tmp", folder / "cells" / ".jpeg-s1.json.zz9x0q1k.tmp"]
    kept = [folder / ".notes.txt.a1b2c3d4.tmp", folder / "certificate.json.a1b2c3d4.tmp",
            folder / ".cells.csv.short.tmp", folder / "cells" / ".jpeg-s1.json.zz9x0q1k.tmp.bak"]
    for path in stray + kept:
        path.write_text("partial")
        os.utime(path, (old, old))
    future = folder / ".report.html.f0f0f0f0.tmp"
    future.write_text("in flight")
    os.utime(future, (time.time() + 3600, time.time() + 3600))
    result = dd.run(families="jpeg", severities="1")
    result.assert_outcomes(passed=4)
    result.stdout.fnmatch_lines(["drivedegrade: removed 2 temporary file(s) left in *rep by an interrupted write: "
                                 "testplanner/.certificate.json.a1b2c3d_.tmp, "
                                 "testplanner/cells/.jpeg-s1.json.zz9x0q1k.tmp"])
    assert not any(p.exists() for p in stray) and all(p.exists() for p in [*kept, future])
    quiet = dd.run(families="jpeg", severities="1")
    assert "temporary file(s)" not in quiet.stdout.str()
