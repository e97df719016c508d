"""The example adapters in planners/examples certified end to end, as an author would run them: -n 0 and -n 2
give bit-identical cells, the null control passes, and the temporal adapter is reset once per scene per cell.

They run on a world with two val scenes (so a stream crosses a scene boundary), rendered once into this test
session's cache and shared by the xdist workers.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

# torch once in this process, before pytester's in-process runs: a run drops the modules it imported itself,
# and torch imported a second time in one process fails (its operator registry is process-wide)
import torch  # noqa: F401
import torch.nn.functional  # noqa: F401

# the plugin's session modules too: `plugin/__init__` reaches `context` as the package's attribute, which
# outlives a run that dropped the module, while `session` imports it afresh: two SESSION_KEYs otherwise
import pytest_drivedegrade.plugin.session  # noqa: F401

pytest.register_assert_rewrite("plugin_support")
from plugin_support import Runner, by_cell, load_json, no_traceback, read_csv  # noqa: E402 - after the rewrite

pytest_plugins = ["plugin_support"]

EXAMPLES = Path(__file__).resolve().parents[2] / "planners" / "examples"
FAMILIES, SEVERITIES = "jpeg,blackout", "1,3,5"
CELLS = ("clean", "null", "blind", "jpeg-s1", "jpeg-s3", "jpeg-s5", "blackout-s1", "blackout-s3", "blackout-s5")
LOG_ENV = "DRIVEDEGRADE_EXAMPLE_LOG"


@pytest.fixture(scope="session")
def scenes(two_scene_world: Path) -> list[tuple[str, list[int]]]:
    """(scene token, scored keyframe indices) in stream order, for the 4 frames a Runner scores."""
    from plugin_support import FRAMES

    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    out: list[tuple[str, list[int]]] = []
    for f in NuScenesReader(two_scene_world, split="val").scorable_frames(limit=FRAMES):
        if not out or out[-1][0] != f.scene_token:
            out.append((f.scene_token, []))
        out[-1][1].append(f.index)
    return out


def certify(pytester: pytest.Pytester, world: Path, cache: Path, example: str, log: Path,
            monkeypatch: pytest.MonkeyPatch, *extra: str) -> tuple[pytest.RunResult, Path]:
    """`pytest --drivedegrade <example>.py` on the two-scene world; returns the run and its report folder."""
    shutil.copy(EXAMPLES / f"{example}.py", pytester.path / f"{example}.py")
    monkeypatch.setenv(LOG_ENV, str(log))
    report = f"rep-{log.stem}"
    result = Runner(pytester, world, cache).run(*extra, planner=f"{example}.py", families=FAMILIES,
                                                 severities=SEVERITIES, report=report)
    return result, pytester.path / report / example


def per_process(log: Path) -> dict[str, list[str]]:
    """The adapter's log lines grouped by the process that wrote them, pid stripped."""
    out: dict[str, list[str]] = {}
    for line in log.read_text().splitlines():
        pid, rest = line.split(" ", 1)
        out.setdefault(pid, []).append(rest)
    return out


def one_cell(scenes: list[tuple[str, list[int]]]) -> list[str]:
    """What one cell writes: per scene, a reset, then its frames in order, prev_bev only after the first."""
    lines = []
    for token, indices in scenes:
        lines.append(f"reset {token}")
        lines += [f"predict {token} {i} {int(k > 0)}" for k, i in enumerate(indices)]
    return lines


@pytest.mark.parametrize("example", ["mmdet3d_style", "navsim_style"])
def test_example_certified_serially_and_under_xdist(pytester, two_scene_world, shared_cache, scenes, monkeypatch,
                                                     example):
    assert len(scenes) == 2, scenes  # the stream crosses a scene boundary
    logs = {n: pytester.path / f"log{n}.txt" for n in (0, 2)}
    folders = {}
    for n, log in logs.items():
        result, folders[n] = certify(pytester, two_scene_world, shared_cache, example, log, monkeypatch,
                                     *(("-n", "2") if n else ()))
        result.assert_outcomes(passed=len(CELLS))
        assert result.ret == 0
        no_traceback(result)
        result.stdout.fnmatch_lines(["*null control: passed (max abs diff 0 m)*"])
    assert (folders[0] / "cells.csv").read_text() == (folders[2] / "cells.csv").read_text()
    rows = by_cell(read_csv(folders[0] / "cells.csv"))
    assert list(rows) == list(CELLS) and {r["frames"] for r in rows.values()} == {"4"}
    for folder in folders.values():
        cert = load_json(folder / "certificate.json")
        assert cert["null_control"]["passed"] is True
        assert cert["planner"]["name"] == example

    if example == "navsim_style":
        assert not any(log.exists() for log in logs.values())  # no reset, no log
        # reads the front three only: blackout-s3 (the rear three out) is the clean plan, bit for bit
        assert float(rows["blackout-s3"]["retention"]) == 1.0
        return
    # -n 0: one process streams every cell: per cell, reset once per scene before its first frame, after the
    # pre-flight's check of the first frame (twice, each after a reset) on a planner of its own
    preflight = [f"reset {scenes[0][0]}", f"predict {scenes[0][0]} {scenes[0][1][0]} 0"] * 2
    serial = per_process(logs[0])
    assert len(serial) == 1
    (lines,) = serial.values()
    assert lines == preflight + one_cell(scenes) * len(CELLS)
    # -n 2: each worker streams whole cells the same way (a worker may also compute the clean reference); the
    # controller made only the pre-flight's calls
    parallel = per_process(logs[2])
    assert sorted(parallel.values()).count(preflight) == 1
    parallel = {pid: lines for pid, lines in parallel.items() if lines != preflight}
    cell = one_cell(scenes)
    total = 0
    for lines in parallel.values():
        assert len(lines) % len(cell) == 0 and lines == cell * (len(lines) // len(cell))
        total += len(lines) // len(cell)
    assert total >= len(CELLS)
