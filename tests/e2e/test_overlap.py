"""--drivedegrade-prefetch end to end (SPEC section 16): the next frames made and the last one scored beside the
planner's calls give the serial path's outputs bit for bit (plans digests, cells.csv, every cell's record) for the
reference planners, in one process and under -n 2; a planner that raises, hangs or writes into its input mid-stream
is reported exactly as serially; the cost ledger gives each process's wall time and planner_busy."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, no_traceback, read_csv  # noqa: E402
from test_shards import two_scene_world  # noqa: E402, F401 - 2 val scenes: the temporal planner resets between them

PLANNERS = Path(__file__).resolve().parents[2] / "planners"

pytest_plugins = ["plugin_support"]


def outputs(folder: Path) -> tuple[str, dict[str, str], dict[str, dict], object]:
    """cells.csv, the certificate's plans digest per cell, every stored cell record without its timings, and the
    certificate's floor (worked out beside the cells on an xdist controller, at the end in one process)."""
    cert = load_json(folder / "certificate.json")
    records = {}
    for path in sorted((folder / "cells").glob("*.json")):
        record = load_json(path)["record"]
        record.pop("seconds")
        records[path.stem] = record
    return ((folder / "cells.csv").read_text(), {c["cell"]: c["plans_digest"] for c in cert["cells"]}, records,
            cert["floor"])


@pytest.mark.parametrize("planner", ["camera_cnn.py", "temporal_cnn.py"])
def test_prefetch_gives_the_serial_outputs_bit_for_bit(dd, two_scene_world, planner):  # noqa: F811
    kw = {"planner": str(PLANNERS / planner), "data": two_scene_world, "families": "frame_dropout,jpeg,blackout",
          "severities": "3,5"}
    name = planner.removesuffix(".py")
    got = {}
    for depth, layout in (("0", "-p no:xdist"), ("1", "-p no:xdist"), ("3", "-p no:xdist"), ("3", "-n 2")):
        report = f"p{depth}{layout[1]}"
        dd.run(*layout.split(), "--drivedegrade-frames", "8", "--drivedegrade-prefetch", depth, report=report,
               **kw).assert_outcomes(passed=9)
        got[report] = outputs(dd.pytester.path / report / name)
        cost = load_json(dd.pytester.path / report / name / "certificate.json")["cost"]
        assert cost["wall"] > 0 and 0 < cost["planner_busy"] <= 1
        assert len(cost["processes"]) == (2 if layout == "-n 2" else 1)
        # each figure is rounded to 6 decimals in the certificate: the sum may be off by half a unit per term
        assert cost["wall"] == pytest.approx(sum(p["wall"] for p in cost["processes"]),
                                             abs=5e-7 * (len(cost["processes"]) + 1))
    serial = got.pop("p0p")
    for report, other in got.items():
        assert other[0] == serial[0], report
        assert other[1] == serial[1], report
        assert other[2] == serial[2], report
        assert other[3] == serial[3], report
    assert len(serial[1]) == 9
    assert serial[3]["l2_avg"] is not None  # the floor was trained and run, not skipped


def test_a_failing_planner_is_reported_as_in_the_serial_path(dd, scored_tokens):
    """Faults on the second frame of four (raise, NaN, a write into the input, a hang past the timeout) while the
    frames after it are being made and the one before it scored. The timeout is 2 s so that the first call, which
    reads the data set for its ground truth, passes on a loaded machine."""
    frame = scored_tokens[1]
    faults = {"gaussian_blur-s1": "raise", "gaussian_blur-s5": "nan", "jpeg-s5": "write", "blackout-s1": "hang"}
    dd.write_planner(faults={cell: (fault, frame) for cell, fault in faults.items()})
    runs = {}
    for depth in ("0", "3"):
        result = dd.run("-p", "no:xdist", "--drivedegrade-timeout", "2", "--drivedegrade-prefetch", depth,
                        report=f"r{depth}")
        result.assert_outcomes(passed=5, failed=4)
        no_traceback(result)
        lines = [line for line in result.stdout.lines if line.startswith(("cell ", "  frame ", "    frame "))
                 or "frame '" in line]
        runs[depth] = (lines, outputs(dd.folder(report=f"r{depth}")))
    assert runs["3"] == runs["0"]
    assert any("took longer than 2 s" in line for line in runs["0"][0])
    assert any("boom in the test planner" in line for line in runs["0"][0])


def test_a_run_without_clean_still_waits_for_the_floor_started_beside_its_cells(dd, monkeypatch):
    """-n 2 -k jpeg-s1: the controller starts the floor on a thread, the run ends without clean (no report, so the
    floor is never taken), and the session still waits for the thread before it ends: none is left running torch
    into the interpreter's shutdown."""
    import threading
    import time

    from pytest_drivedegrade.plugin import egofloor

    finished = threading.Event()
    real = egofloor.floor_frames

    def slow(*args, **kwargs):
        time.sleep(4.0)  # longer than the one cell the workers run
        try:
            return real(*args, **kwargs)
        finally:
            finished.set()

    monkeypatch.setattr(egofloor, "floor_frames", slow)
    dd.write_planner()
    result = dd.run("-n", "2", "-k", "jpeg-s1", report="nc")
    result.assert_outcomes(passed=1)
    result.stdout.fnmatch_lines(["*no clean cell result*"])
    assert finished.is_set()
    assert not any(t.name == "drivedegrade-floor" for t in threading.enumerate())


def test_a_planner_scribbling_over_its_images_cannot_poison_what_later_cells_derive(dd):
    """Issue 23's derived values (raindrop's quarter-resolution view and the energy's bit count, kept per decoded
    clean image for the process's later cells): a planner that overwrites every image it reads through raw
    memory in frame_dropout-s1 (which delivers the decoded clean images themselves, held or current) fails that
    cell naming the write, and every later cell of the same process, raindrop and its energy included, reads
    exactly what a run without the scribbling reads."""
    from plugin_support import by_cell, read_csv

    rows, outputs = {}, {}
    for name, fault in (("scribbled", "scribble"), ("plain", "nan")):
        # both planners carry a fault (so neither is deterministic and no cell reuses clean's plans); the plain
        # one's is in a cell this run does not have
        target = "frame_dropout-s1" if fault == "scribble" else "jpeg-s5"
        dd.write_planner(faults={target: (fault, None)})
        result = dd.run("-p", "no:xdist", "--drivedegrade-prefetch", "0", report=name,
                        families="frame_dropout,raindrop", severities="1,2")
        rows[name] = by_cell(read_csv(dd.folder(report=name) / "cells.csv"))
        outputs[name] = result.stdout.str()
    for cell in ("clean", "frame_dropout-s2", "raindrop-s1", "raindrop-s2", "blind", "null"):
        got, want = ({k: v for k, v in rows[run][cell].items() if k != "planner_fingerprint"}  # two planner files
                     for run in ("scribbled", "plain"))
        assert got == want, cell
    assert rows["scribbled"]["frame_dropout-s1"]["conformance_errors"] != "0"
    assert "frame_dropout-s1" in outputs["scribbled"] and "wrote into" in outputs["scribbled"]


COUNTER = '''
import os

import cv2
import numpy as np
import pytest


class Counter:
    """Straight ahead; notes OpenCV's thread count at each call (process id, count)."""

    cameras = ("CAM_FRONT",)
    name = "counter"

    def predict(self, images, ego, cmd, context):
        with open({log!r}, "a") as fh:
            fh.write(f"{{os.getpid()}} {{cv2.getNumThreads()}}\\n")
        if {tamper!r}:  # a planner that sets OpenCV's threads itself, mid-cell
            cv2.setNumThreads(7)
        plan = np.zeros((6, 2))
        plan[:, 0] = np.arange(1, 7) + float(images["CAM_FRONT"][::16, ::16].mean()) / 255.0
        return plan


@pytest.fixture(scope="session")
def planner():
    return Counter()
'''


@pytest.mark.parametrize(("layout", "depth"), [("-n 2", "0"), ("-p no:xdist", "0"), ("-p no:xdist", "2")])
def test_cells_run_with_opencvs_threads_set_to_the_cores_each_process_has(dd, monkeypatch, layout, depth):
    """Every call of every cell sees the OpenCV thread count `pacing.opencv_threads` gives its layout (under -n 2
    each worker its half of the cores; one process, with or without a loading thread, all of them), and a run in
    this process puts the count back afterwards."""

    import cv2

    from pytest_drivedegrade.pacing import OPENCV_THREADS_ENV
    from pytest_drivedegrade.settings import cores

    monkeypatch.delenv(OPENCV_THREADS_ENV, raising=False)
    monkeypatch.delenv("PYTEST_XDIST_WORKER_COUNT", raising=False)  # this test's own xdist worker is not the run's
    log = dd.pytester.path / f"threads{depth}{layout[1]}.txt"
    dd.pytester.makepyfile(counter=COUNTER.format(log=str(log), tamper=False))
    before = cv2.getNumThreads()
    dd.run(*layout.split(), "--drivedegrade-prefetch", depth, planner="counter.py", report=f"t{depth}{layout[1]}",
           families="jpeg", severities="3").assert_outcomes(passed=4)
    assert cv2.getNumThreads() == before
    cpus, processes = cores(), 2 if layout == "-n 2" else 1
    want = max(1, cpus // processes)
    calls = [line.split() for line in log.read_text().splitlines()]
    if layout == "-n 2":  # the pre-flight's two calls come first, from a process of its own (`plugin.isolated`,
        # neither a worker nor the controller, which runs no planner code): they run no cell, so their count is
        # not the cells' (as when the controller made them)
        preflight = [c for c in calls if c[0] == calls[0][0]]
        assert calls[:2] == preflight and str(os.getpid()) not in {pid for pid, _ in calls}, calls
        calls = calls[2:]
    assert len(calls) >= 4 and {int(n) for _, n in calls} == {want}, calls
    assert len({pid for pid, _ in calls}) == processes


def test_a_planner_that_sets_opencvs_threads_itself_changes_no_figure_and_is_put_back(dd, monkeypatch):
    """A planner calling cv2.setNumThreads(7) in every predict, in one process and under -n 2: every cells.csv
    figure is the well-behaved planner's, every cell still starts on the run's count (the planner's setting lasts
    to the end of the cell at most) and the count before the run is back after it."""
    import cv2

    from pytest_drivedegrade.pacing import OPENCV_THREADS_ENV, opencv_threads

    monkeypatch.delenv(OPENCV_THREADS_ENV, raising=False)
    monkeypatch.delenv("PYTEST_XDIST_WORKER_COUNT", raising=False)
    outside = cv2.getNumThreads()
    before = opencv_threads() + 1  # a count no cell sets, so that only putting it back gives it again
    cv2.setNumThreads(before)
    try:
        tables = {}
        for tamper, layout in ((False, "-p no:xdist"), (True, "-p no:xdist"), (True, "-n 2")):
            report = f"x{int(tamper)}{layout[1]}"
            log = dd.pytester.path / f"{report}.txt"
            dd.pytester.makepyfile(counter=COUNTER.format(log=str(log), tamper=tamper))
            dd.run(*layout.split(), planner="counter.py", report=report, families="jpeg,gaussian_blur",
                   severities="3").assert_outcomes(passed=5)
            assert cv2.getNumThreads() == before
            rows = read_csv(dd.pytester.path / report / "counter" / "cells.csv")
            tables[report] = [{k: v for k, v in row.items() if k != "planner_fingerprint"} for row in rows]
            if tamper:  # the first call of each cell sees the run's count; later ones the planner's 7
                counts = {int(line.split()[1]) for line in log.read_text().splitlines()}
                assert counts == {opencv_threads(), 7} if layout == "-p no:xdist" else 7 in counts, counts
        assert len(tables["x0p"]) == 5
        assert tables["x1p"] == tables["x0p"]  # every figure; only the planner file's fingerprint differs
        assert tables["x1n"] == tables["x0p"]
    finally:
        cv2.setNumThreads(outside)
