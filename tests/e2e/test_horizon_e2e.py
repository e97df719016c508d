"""The NAVSIM-style example certified with NAVSIM's eight poses (issue 39): on a world generated with 4 s of
future its certificate says the PDMS/EPDMS scored 4 s; on the default 3 s data the same planner stops before any
cell with the usage error."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

# torch once in this process, before pytester's in-process runs (see test_examples)
import torch  # noqa: F401
import torch.nn.functional  # noqa: F401

import pytest_drivedegrade.plugin.session  # noqa: F401

pytest.register_assert_rewrite("plugin_support")
from plugin_support import Runner, by_cell, load_json, no_traceback, read_csv  # noqa: E402 - after the rewrite

pytest_plugins = ["plugin_support"]

EXAMPLE = Path(__file__).resolve().parents[2] / "planners" / "examples" / "navsim_style.py"


@pytest.fixture(scope="module")
def horizon_worlds(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    from pytest_drivedegrade.data.world import write_world

    root = tmp_path_factory.mktemp("horizon-e2e")
    return {s: write_world(root / f"w{s}", scenes=2, workers=1, future_s=s) for s in (3, 4)}


def _run(pytester: pytest.Pytester, world: Path, cache: Path, report: str) -> tuple[pytest.RunResult, Path]:
    shutil.copy(EXAMPLE, pytester.path / "navsim_style.py")
    result = Runner(pytester, world, cache).run(planner="navsim_style.py", families="jpeg", severities="3",
                                                report=report)
    return result, pytester.path / report / "navsim_style"


def test_eight_poses_certified_over_4_s(pytester, horizon_worlds, shared_cache, monkeypatch):
    monkeypatch.setenv("NAVSIM_POSES", "8")
    result, folder = _run(pytester, horizon_worlds[4], shared_cache, "rep8")
    no_traceback(result)
    assert result.ret == 0, result.stdout.str()
    cert = load_json(folder / "certificate.json")
    assert cert["settings"]["pdms_horizon_s"] == 4.0
    rows = by_cell(read_csv(folder / "cells.csv"))
    assert {"clean", "jpeg-s3", "null", "blind"} <= set(rows)
    monkeypatch.setenv("NAVSIM_POSES", "6")
    six, folder6 = _run(pytester, horizon_worlds[4], shared_cache, "rep6")
    assert six.ret == 0 and load_json(folder6 / "certificate.json")["settings"]["pdms_horizon_s"] == 3.0
    rows6 = by_cell(read_csv(folder6 / "cells.csv"))
    # L2 is the first six poses' either way: the same plans there, the same L2
    assert rows6["clean"]["l2_avg"] == rows["clean"]["l2_avg"]


def test_eight_poses_on_3_s_data_stop_before_any_cell(pytester, horizon_worlds, shared_cache, monkeypatch):
    monkeypatch.setenv("NAVSIM_POSES", "8")
    result, folder = _run(pytester, horizon_worlds[3], shared_cache, "rep3")
    no_traceback(result)
    assert result.ret != 0
    result.stderr.fnmatch_lines(["*declares poses = 8 (4 s) but the data at * holds 3 s of future*--future 4*"])
    assert not (folder / "cells.csv").exists() or "jpeg-s3" not in (folder / "cells.csv").read_text()
