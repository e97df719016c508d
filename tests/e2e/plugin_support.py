"""Shared set-up of the plugin's end-to-end tests (tests/test_plugin*.py), loaded by them as a pytest plugin.

One small world (3 scenes, seed 1) and one pytest cache folder (so the ego-only floor is trained once) serve
every `pytester` run; `Runner` builds the command line and planners are written from `planner_source`.
"""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# Import the heavy stages once here, before pytester's in-process runs: each run drops the modules it imported
# itself, and a matplotlib imported twice in one process breaks (its classes no longer match).
import cryptography.exceptions  # noqa: F401 - certificate signatures: their classes must match across runs
import cryptography.hazmat.primitives.asymmetric.ed25519  # noqa: F401
import cryptography.hazmat.primitives.serialization  # noqa: F401
import jinja2  # noqa: F401
import pytest
import torch._dynamo  # noqa: F401 - torch.manual_seed imports it lazily; twice in one process it fails

import pytest_drivedegrade.floor  # noqa: F401
import pytest_drivedegrade.plugin.session  # noqa: F401 - with plugin.context: one SESSION_KEY for every run
import pytest_drivedegrade.report.html  # noqa: F401
import pytest_drivedegrade.report.plots  # noqa: F401
import pytest_drivedegrade.run  # noqa: F401

#: Three ladder families at two severities: 3 diagnostic + 6 ladder cells, a few seconds per run.
FAMILIES = "jpeg,blackout,gaussian_blur"
SEVERITIES = "1,5"
SMALL_CELLS = ("clean", "null", "blind", "gaussian_blur-s1", "gaussian_blur-s5", "jpeg-s1", "jpeg-s5", "blackout-s1",
               "blackout-s5")  # in report order: diagnostic cells, then the ladder's order
#: The same cells in collection (run) order: clean first, the null control last (see DriveDegradeSession.cells).
RUN_ORDER = ("clean", *SMALL_CELLS[3:], "blind", "null")
#: Every family the two axes need at S5 (nine quality families and blackout), for the verdict tests.
AXIS_FAMILIES = "gaussian_blur,motion_blur,gaussian_noise,low_light,jpeg,downscale,color_quant,fog,snow,blackout"
FRAMES = 4

PLANNER = '''
import os
import time

import cv2
import numpy as np
import pytest

T = 0.5 * np.arange(1, 7)
HANG_S = 600.0


def current_cell():
    """The cell being run, from pytest's own PYTEST_CURRENT_TEST ("path::jpeg-s5 (call)"): the planner's own
    bookkeeping, since `images` does not say which corruption it carries."""
    test = os.environ.get("PYTEST_CURRENT_TEST", "")
    return test.rpartition("::")[2].rpartition(" ")[0]


class TestPlanner:
    """Ground truth plus 0.5 m, drifting sideways with the damage to the front camera when it reads that camera.

    `faults` maps a cell id to (fault, frame token or None for every frame): how it misbehaves there. Its output
    then depends on the cell, not on its inputs alone, so it says it is not deterministic (the suite must call it
    in every cell rather than reuse a clean plan where the inputs equal clean's).
    """

    cameras = {cameras!r}
    name = {name!r}
    faults = {faults!r}
    deterministic = not faults
    read_back = {read_back!r}
    count_file = {count_file!r}
    marker = {marker!r}

    def __init__(self, data_root, split):
        """The ground truth is read here, when the fixture is built, not in the first predict() call: reading the
        data set there took seconds on a loaded machine and ran past the fault test's --drivedegrade-timeout."""
        from pytest_drivedegrade.data.nuscenes import NuScenesReader

        reader = NuScenesReader(data_root, split=split)
        self.truth = {{f.token: (f.gt_future, f.cameras["CAM_FRONT"].path) for f in reader.frames()}}

    def frame_truth(self, token):
        """(ground-truth future, clean CAM_FRONT path) of a keyframe, read from the data set by the planner
        itself (test-only bookkeeping: the suite hands the planner neither)."""
        return self.truth[token]

    def predict(self, images, ego, cmd, context):
        cell = current_cell()
        if self.count_file:
            with open(self.count_file, "a") as f:
                f.write(cell + "\\n")
        # Test-only shortcut: the ground truth and the clean image come from the data set, so the plan's error
        # is a known function of how much the delivered front image differs from the clean one.
        future, front = self.frame_truth(context.token)
        plan = np.array(future, dtype=float) + [{ahead!r}, 0.0]
        if "CAM_FRONT" in self.cameras:
            delivered = images["CAM_FRONT"]  # first: a data fault in it is the suite's to report
            clean = cv2.imread(front)  # None where the test broke the file on purpose
            clean = delivered if clean is None else clean[..., ::-1]
            d = float(np.abs(delivered.astype(np.int16) - clean).mean()) / 255.0
            plan[:, 1] += {scale_expr}
        if self.read_back:
            plan[:, 1] += float(images["CAM_BACK"].mean()) / 255.0
        fault, frame = self.faults.get(cell, (None, None))
        if fault and frame in (None, context.token):
            plan = self.misbehave(fault, images, plan)
        return plan

    def misbehave(self, fault, images, plan):
        if fault == "raise":
            raise RuntimeError("boom in the test planner")
        if fault == "nan":
            plan[3, 1] = float("nan")
        if fault == "shape":
            return plan[:5]
        if fault == "huge":
            plan[5, 0] = 1e200
        if fault == "write":
            images["CAM_FRONT"][0, 0, 0] = 7
        if fault == "scribble":  # every image it reads, overwritten through raw memory (no flag stops that)
            import ctypes

            for cam in self.cameras:
                ctypes.memset(images[cam].ctypes.data, 255, images[cam].nbytes)
        if fault == "hang":  # until --drivedegrade-timeout interrupts it: a hang, not a slow call
            time.sleep(HANG_S)
        if fault == "exit" and os.path.exists(self.marker):
            os._exit(1)
        if fault == "interrupt" and os.path.exists(self.marker):
            raise KeyboardInterrupt
        return plan


@pytest.fixture(scope="session")
def planner(request):
    return TestPlanner(request.config.getoption("drivedegrade_data"),
                       request.config.getoption("drivedegrade_split") or "val")
'''

#: The plan drifts sideways in proportion to the damage d (mean absolute difference of the delivered front
#: image from the clean one, in [0, 1]); 0.5 m off the ground truth when the image is clean.
REACTIVE = "10.0 * d"
#: A more fragile variant: the same reaction, four times as strong.
FRAGILE = "40.0 * d"


def planner_source(*, cameras: tuple[str, ...] = ("CAM_FRONT",), name: str | None = "testplanner",
                   faults: dict[str, tuple[str, str | None]] | None = None, read_back: bool = False,
                   marker: str = "", count_file: str = "", scale: str = REACTIVE, ahead: float = 0.5) -> str:
    """Source of a planner file; `faults` maps cell id -> (fault, frame token or None); `ahead`: its clean plan's
    offset along x from the ground truth, in m (0.5 m beats the ego-only floor on the small world)."""
    return PLANNER.format(cameras=tuple(cameras), name=name, faults=dict(faults or {}), read_back=read_back,
                          marker=marker, count_file=count_file, scale_expr=scale, ahead=float(ahead))


@dataclass
class Runner:
    """Builds `pytest --drivedegrade ...` command lines for pytester with the small world and shared cache."""

    pytester: pytest.Pytester
    world: Path
    cache: Path

    def args(self, *extra: str, planner: str | None = "myplanner.py", report: str = "rep",
             families: str = FAMILIES, severities: str = SEVERITIES, data: Path | None = None) -> list[str]:
        head = ["--drivedegrade"] + ([planner] if planner else [])
        return [*head, "--drivedegrade-data", str(data or self.world), "--drivedegrade-frames", str(FRAMES),
                "--drivedegrade-families", families, "--drivedegrade-severities", severities,
                "--drivedegrade-report", report, "-o", f"cache_dir={self.cache}", *extra]

    def run(self, *extra: str, subprocess: bool = False, **kw: Any) -> pytest.RunResult:
        args = self.args(*extra, **kw)
        if subprocess:
            return self.pytester.runpytest_subprocess(*args)
        return self.pytester.runpytest_inprocess(*args, no_reraise_ctrlc=True)

    def write_planner(self, filename: str = "myplanner", **kw: Any) -> Path:
        return self.pytester.makepyfile(**{filename: planner_source(**kw)})

    def folder(self, name: str = "testplanner", report: str = "rep") -> Path:
        return self.pytester.path / report / name


def read_csv(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(path.read_text())))


def by_cell(rows: list[dict[str, str]]) -> dict[str, dict[str, str]]:
    return {r["cell"]: r for r in rows}


def verify_cli(path: Path) -> subprocess.CompletedProcess:
    """`drivedegrade verify PATH`, the command a CI job runs."""
    return subprocess.run([sys.executable, "-m", "pytest_drivedegrade.cli", "verify", str(path)],
                          capture_output=True, text=True, check=False)


def no_traceback(result: pytest.RunResult) -> None:
    text = result.stdout.str() + result.stderr.str()
    assert "Traceback" not in text, text


def load_json(path: Path) -> Any:
    return json.loads(path.read_text())


def stored_records(folder: Path) -> dict[str, dict]:
    """Every stored cell record of a report folder without its timings (which `record_digests` covers, so those
    differ by run), by cell."""
    out = {}
    for path in sorted((folder / "cells").glob("*.json")):
        record = load_json(path)["record"]
        record.pop("seconds")
        out[path.stem] = record
    return out


def _warm_up_matplotlib() -> None:
    """Render one small chart, so matplotlib's lazily imported parts are loaded outside the runs too."""
    import io

    from pytest_drivedegrade.report.plots import _figure

    fig = _figure(1, 1)
    fig.add_subplot().plot([0, 1], [0, 1], label="x")
    fig.savefig(io.BytesIO(), format="png")


_warm_up_matplotlib()


@pytest.fixture(scope="session")
def shared_cache(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One pytest cache folder for every run, so the ego-only floor is trained on the small world once; kept in
    this test session's own cache when it has one (the world is deterministic, so later sessions reuse it)."""
    cache = getattr(request.config, "cache", None)
    return Path(cache.mkdir("drivedegrade-plugin-tests")) if cache is not None else tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="session")
def scored_tokens(small_world: Path) -> list[str]:
    """The tokens of the frames a run scores, in order."""
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    return [f.token for f in NuScenesReader(small_world, split="val").scorable_frames(limit=FRAMES)]


@pytest.fixture
def dd(pytester: pytest.Pytester, small_world: Path, shared_cache: Path) -> Runner:
    return Runner(pytester, small_world, shared_cache)
