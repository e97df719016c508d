"""Issue 20, the planners built to defeat the suite without touching a camera's pixels (M12) and the null
control's rear-camera rule end to end. Each test is named after the issue's item it covers."""

from __future__ import annotations

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import AXIS_FAMILIES, load_json, no_traceback, verify_cli  # noqa: E402

pytest_plugins = ["plugin_support"]

#: A planner that memoises its plan per frame: the first call on a frame plans from the front camera (the ground
#: truth, pushed sideways by the damage to the front image, so a blacked-out camera moves the plan by metres);
#: every later call on that frame returns the first plan, whatever the images. Keyed by the ego status (no
#: context: the suite may even reuse clean's plans for it) or by ``context.token``; with or without a ``reset``
#: that leaves the memo alone.
MEMO = '''
import cv2
import numpy as np
import pytest


class Memo:
    cameras = ("CAM_FRONT",)
    name = "memo"

    def __init__(self, data_root, split):
        from pytest_drivedegrade.data.nuscenes import NuScenesReader

        frames = list(NuScenesReader(data_root, split=split).frames())
        self.truth = {{f.token: (f.gt_future, f.cameras["CAM_FRONT"].path) for f in frames}}
        self.egos = [(f.ego.as_vector(), f.token) for f in frames]
        self.memo = {{}}

    def plan(self, images, token):
        future, front = self.truth[token]
        clean = cv2.imread(front)[..., ::-1]
        d = float(np.abs(images["CAM_FRONT"].astype(np.int16) - clean).mean()) / 255.0
        return np.array(future, dtype=float) + [0.02, 10.0 * d]

    def remember(self, key, images, token):
        if key not in self.memo:
            self.memo[key] = self.plan(images, token)
        return self.memo[key].copy()
{body}

@pytest.fixture(scope="session")
def planner(request):
    return Memo(request.config.getoption("drivedegrade_data"), request.config.getoption("drivedegrade_split") or "val")
'''

BY_EGO = '''
    def predict(self, images, ego, cmd):
        vector = ego.as_vector()
        token = min(self.egos, key=lambda e: float(np.abs(e[0] - vector).sum()))[1]  # the frame it is
        return self.remember(vector.tobytes(), images, token)
'''
BY_TOKEN = '''
    def predict(self, images, ego, cmd, context):
        return self.remember(context.token, images, context.token)
'''
RESET = '''
    def reset(self, scene_token):
        pass  # the memo survives: it is what the planner is built around
'''
MEMOISERS = {"ego": BY_EGO, "token": BY_TOKEN, "ego-reset": BY_EGO + RESET, "token-reset": BY_TOKEN + RESET}


def memo_source(kind: str) -> str:
    return MEMO.format(body=MEMOISERS[kind])


@pytest.fixture(params=[("-n", "0"), ("-n", "2")], ids=["n0", "n2"])
def layout(request: pytest.FixtureRequest) -> tuple[str, ...]:
    return request.param


@pytest.mark.parametrize(("kind", "workers"), [*((k, "0") for k in sorted(MEMOISERS)), ("token", "2"),
                                              ("ego-reset", "2")])
def test_m12_a_memoising_planner_is_never_certified_not_shown_to_use_cameras(dd, kind, workers):
    """M12: the planner memoising its plan per frame (by ego status or context.token, with or without a reset
    that keeps the memo) was certified not-shown-to-use-cameras with every axis 1.000 under -n 0 (and under -n 2
    its label hung on which cell a worker ran first). Clean is now planned first in every process, so its blind
    cell equals clean bit for bit wherever it runs while beating the ego-only floor: undetermined, with that
    reason, the axes' label kept as computed_label, and verify agrees."""
    dd.pytester.makepyfile(memo=memo_source(kind))
    result = dd.run("-n", workers, planner="memo.py", families=AXIS_FAMILIES, severities="5")
    no_traceback(result)
    cert = load_json(dd.folder("memo") / "certificate.json")
    v = cert["verdict"]
    assert (v["label"], v["case"], v["computed_label"]) == \
        ("undetermined", "blind-equals-clean", "not-shown-to-use-cameras"), v
    assert "with every camera off (blind) the plans equal clean's bit for bit on 4 frames" in v["reason"]
    assert cert["axes"]["quality"] == cert["axes"]["removal"] == 1.0
    assert cert["floor"]["blind_l2_avg"] < cert["floor"]["l2_avg"]
    result.stdout.fnmatch_lines(["verdict: undetermined - Undetermined: with every camera off (blind)*", "axes: *",
                                 "UNDETERMINED by the memo check (blind equals clean): with every camera off*"])
    assert verify_cli(dd.folder("memo") / "certificate.json").returncode == 0


def test_rear_null_control_names_a_secretly_read_rear_camera_end_to_end(dd, layout):
    """"The rear null-control rule is caught only by a unit test with fakes": a planner that declares CAM_FRONT
    and reads CAM_BACK, run without the null cell (``-k "clean or jpeg or blackout or blind"``), so that blackout
    S3 (which blacks out exactly the rear cameras it says it does not read) is the only control: that cell fails,
    naming CAM_BACK, and no other cell fails."""
    dd.write_planner(read_back=True)
    result = dd.run(*layout, "-k", "clean or jpeg or blackout or blind", families="jpeg,blackout", severities="3")
    no_traceback(result)
    result.assert_outcomes(passed=3, failed=1)  # clean, jpeg-s3, blind pass; no null cell ran
    result.stdout.fnmatch_lines(["null control failed in cell blackout-s3: plans are not bit-identical to clean*",
                                 "*declared-unread camera(s) that change the plan: CAM_BACK; add them to "
                                 "planner.cameras"], consecutive=True)
