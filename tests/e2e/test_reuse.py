"""Reuse of identical inputs end to end (README "Batches, reuse and cost"): a front-camera planner is not called
on the frames whose inputs equal clean's, the cells are bit-identical to a run with --drivedegrade-no-reuse, and
the certificate's cost ledger counts the reused frames; --drivedegrade-device reaches the planner."""

from __future__ import annotations

import collections
import os

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import FRAMES, load_json, no_traceback, read_csv  # noqa: E402

from pytest_drivedegrade.stream import REUSE_CONTROL_EVERY  # noqa: E402

pytest_plugins = ["plugin_support"]

CELLS = ("blackout-s1", "blackout-s3", "blackout-s5", "frame_dropout-s1", "frame_dropout-s3", "frame_dropout-s5")


def certify(dd, *extra, report):
    calls = dd.pytester.path / "calls.txt"  # one path: the planner file (and its fingerprint) is the same
    dd.write_planner(cameras=("CAM_FRONT",), count_file=str(calls))
    result = dd.run("-p", "no:xdist", *extra, report=report, families="blackout,frame_dropout", severities="1,3,5")
    result.assert_outcomes(passed=3 + len(CELLS))
    no_traceback(result)
    counted = collections.Counter(calls.read_text().split())
    calls.unlink()
    return result, counted, dd.folder(report=report)


def test_reused_frames_are_not_predicted_and_the_cells_are_bit_identical(dd):
    on, calls_on, folder_on = certify(dd, report="on")
    off, calls_off, folder_off = certify(dd, "--drivedegrade-no-reuse", report="off")
    # without reuse every cell predicts every frame; with it, blackout S1 (CAM_BACK) none, while blackout S3 (the
    # rear cameras), this front planner's second null control, still calls it on every frame: reusing there would
    # make that control pass without looking
    assert all(calls_off[c] == FRAMES for c in ("clean", "null", "blind", *CELLS))
    assert calls_on["blackout-s1"] == 1  # the reuse control: the second reused frame is predicted all the same
    assert calls_on["blackout-s3"] == calls_on["blackout-s5"] == FRAMES
    assert calls_on["clean"] == calls_on["null"] == FRAMES
    a, b = load_json(folder_on / "certificate.json"), load_json(folder_off / "certificate.json")
    assert a["cells"] == b["cells"] and a["axes"] == b["axes"] and a["null_control"] == b["null_control"]
    assert read_csv(folder_on / "cells.csv") == read_csv(folder_off / "cells.csv")
    cost = a["cost"]["cells"]
    # the reuse control's calls: the 2nd reused frame of a cell and every REUSE_CONTROL_EVERY-th after it
    controls = {c: (cost[c]["reused"] + REUSE_CONTROL_EVERY - 2) // REUSE_CONTROL_EVERY for c in cost}
    for cell in ("clean", "null", "blind", *CELLS):
        # the ledger counts the calls made for plans; the reuse control's calls check reused ones
        assert cost[cell]["predictions"] == calls_on[cell] - controls[cell], cell
        assert cost[cell]["predictions"] + cost[cell]["reused"] == FRAMES, cell
    assert cost["blackout-s1"]["reused"] == FRAMES and cost["blackout-s3"]["reused"] == 0
    assert a["cost"]["reused"] == sum(FRAMES - calls_on[c] + controls[c] for c in CELLS) >= FRAMES
    assert b["cost"]["reused"] == 0 and b["cost"]["predictions"] == 9 * FRAMES
    assert a["settings"]["reuse"] is True and b["settings"]["reuse"] is False and a["settings"]["device"] == "cpu"
    on.stdout.fnmatch_lines([f"*cost: {a['cost']['predictions']} predictions, {a['cost']['reused']} frames reused "
                             "the clean plan*"])
    html = (folder_on / "report.html").read_text()
    assert f"blackout-s1 {FRAMES}" in html and "blackout-s3 " not in html


DEVICE_PLANNER = '''
import os

import numpy as np
import pytest


class P:
    cameras = ()

    def __init__(self, device):
        self.device = device

    def predict(self, images, ego, cmd):
        return np.zeros((6, 2))


@pytest.fixture(scope="session")
def planner(drivedegrade_context):
    with open("seen.txt", "w") as f:
        f.write(f"{drivedegrade_context.device} {os.environ.get('DRIVEDEGRADE_DEVICE')}")
    return P(drivedegrade_context.device)
'''


def test_the_device_reaches_the_planner_and_cuda_without_a_gpu_is_a_usage_error(dd, monkeypatch):
    monkeypatch.setenv("DRIVEDEGRADE_DEVICE", "leftover")  # the run's option wins over the environment ...
    dd.pytester.makepyfile(myplanner=DEVICE_PLANNER)
    dd.run("-p", "no:xdist", families="jpeg", severities="1").assert_outcomes(passed=4)
    assert (dd.pytester.path / "seen.txt").read_text() == "cpu cpu"
    assert os.environ["DRIVEDEGRADE_DEVICE"] == "leftover"  # ... for the run only
    bad = dd.run("-p", "no:xdist", "--drivedegrade-device", "tpu", families="jpeg", severities="1")
    assert bad.ret == pytest.ExitCode.USAGE_ERROR
    bad.stderr.fnmatch_lines(["*--drivedegrade-device: unknown device 'tpu'; valid devices: cpu, cuda, cuda:N*"])
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU: the no-GPU usage error cannot be shown here")
    gpu = dd.run("-p", "no:xdist", "--drivedegrade-device", "cuda", families="jpeg", severities="1")
    assert gpu.ret == pytest.ExitCode.USAGE_ERROR
    gpu.stderr.fnmatch_lines(["*--drivedegrade-device: cuda asked for, but this machine has no CUDA device*"])
    no_traceback(gpu)
