"""NAVSIM's 4 s horizon (issue 39): a planner declaring ``poses = 8`` is scored with PDMS/EPDMS over 4 s on data
holding 4 s of future (a world made with ``future_s=4``), L2 over the first six poses; a six-pose planner's cells
are unchanged; an 8-pose planner on data with 3 s of future is a usage error before any cell."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.cells import CellRecord
from pytest_drivedegrade.constants import HORIZON_STEPS
from pytest_drivedegrade.data.frame import AgentBoxes, EgoStatus
from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.errors import DataError, InvalidInput, PlannerOutputError
from pytest_drivedegrade.metrics.pdms import KEY_STATES, TTC_SCHEDULE, PreparedFrame
from pytest_drivedegrade.metrics.pdms.constants import SIM_DT, TTC_PROJECTIONS_S, key_states, ttc_schedule
from pytest_drivedegrade.planning import (
    call_style,
    check_horizon,
    horizon_problem,
    planner_fingerprint,
    planner_poses,
    validate_output,
)

EXAMPLE = Path(__file__).resolve().parents[2] / "planners" / "examples" / "navsim_style.py"


class _Planner:
    def __init__(self, poses: object = None) -> None:
        if poses is not None:
            self.poses = poses

    def predict(self, images, ego, cmd):  # pragma: no cover - never called here
        return np.zeros((6, 2))


# -- the contract --------------------------------------------------------------------------------------------------

def test_planner_poses_default_six_and_navsim_eight():
    assert planner_poses(_Planner()) == 6 and planner_poses(_Planner(8)) == 8 and planner_poses(_Planner(6)) == 6
    assert call_style(_Planner(8)).poses == 8 and call_style(_Planner()).poses == 6


@pytest.mark.parametrize("bad", [7, 4, "8", True, 8.0, None.__class__])
def test_planner_poses_rejects_anything_else(bad):
    with pytest.raises(InvalidInput, match=r"planner.poses must be 6 or 8"):
        planner_poses(_Planner(bad))


def test_check_horizon_is_a_usage_error_only_when_the_data_are_short():
    check_horizon(6, 6)
    check_horizon(6, 8)
    check_horizon(8, 8)
    with pytest.raises(InvalidInput, match=r"poses = 8 \(4 s\) but the data holds 3 s of future.*--future 4"):
        check_horizon(8, 6)
    assert horizon_problem(_Planner(8), 8) == "" and horizon_problem(_Planner(), 6) == ""
    assert "--future 4" in horizon_problem(_Planner(8), 6, "the data at /x")
    assert "planner.poses must be" in horizon_problem(_Planner(5), 8)


def test_validate_output_takes_the_declared_shape():
    plan = np.cumsum(np.ones((8, 2)), axis=0)
    assert validate_output(plan, "t", 8).shape == (8, 2)
    with pytest.raises(PlannerOutputError, match=r"has shape \(8, 2\), not \(6, 2\)"):
        validate_output(plan, "t")
    with pytest.raises(PlannerOutputError, match=r"not \(8, 2\) \(the planner declares poses = 8\)"):
        validate_output(plan[:6], "t", 8)


def test_fingerprint_moves_only_for_eight_poses():
    six, eight = _Planner(), _Planner(8)
    assert planner_fingerprint(six) == planner_fingerprint(_Planner(6))
    assert planner_fingerprint(eight) != planner_fingerprint(six)


# -- the score over 4 s ----------------------------------------------------------------------------------------------

def test_six_pose_schedules_are_the_old_constants():
    """The six-pose path runs on the very constants it ran on before (the literal of the former formula)."""
    old_keys = np.arange(1, 7) * 5
    old = tuple(sorted((int(i - round(d / SIM_DT)), d, k) for k, i in enumerate(old_keys.tolist())
                       for d in TTC_PROJECTIONS_S if i - round(d / SIM_DT) >= 0))
    assert TTC_SCHEDULE == old == ttc_schedule(6)
    assert np.array_equal(KEY_STATES, old_keys) and np.array_equal(key_states(6), old_keys)
    assert key_states(8).tolist() == [5, 10, 15, 20, 25, 30, 35, 40]
    assert max(s[0] for s in ttc_schedule(8)) == 40 and len(ttc_schedule(8)) == 8 * 4 - 2  # none 0.6, 0.9 s before 0.5


def _car_at(x: float, steps: int) -> list[AgentBoxes]:
    box = AgentBoxes(np.array([[x, 0.0]]), np.array([[4.5, 1.9]]), np.zeros(1), ("vehicle",))
    return [box] * steps


def test_a_collision_in_the_fourth_second_counts_only_over_4_s():
    """8 m/s straight on; a parked car whose rear is at 27.25 m: the ego's nose reaches it between 3 and 3.5 s.
    Over 3 s the plan is collision-free; over 4 s it is an at-fault collision (NC 0)."""
    speed = 8.0
    plan8 = np.stack([speed * 0.5 * np.arange(1, 9), np.zeros(8)], axis=1)
    ego = EgoStatus((speed, 0.0), (0.0, 0.0), 0.0)
    three = PreparedFrame.prepare(plan8[:6], _car_at(29.5, 6), ego)
    four = PreparedFrame.prepare(plan8, _car_at(29.5, 8), ego)
    assert len(four.steps) == 8 and len(three.steps) == 6
    assert three.score(plan8[:6]).nc == 1.0
    assert four.score(plan8).nc == 0.0 and four.score(plan8).pdms == 0.0
    # the progress over 4 s is the expert's own, 32 m, not 24
    free = PreparedFrame.prepare(plan8, [AgentBoxes.empty()] * 8, ego)
    assert free.score(plan8).pdms == pytest.approx(1.0)
    assert free.expert_m == pytest.approx(32.0, abs=0.5) and three.expert_m == pytest.approx(24.0, abs=0.5)


def test_eight_pose_plans_in_a_cell_record_round_trip():
    plans = np.arange(2 * 8 * 2, dtype=float).reshape(2, 8, 2)
    nan6 = np.full((2, 6), np.nan)
    rec = CellRecord("clean", "clean", 0, ["a", "b"], plans, nan6, nan6, nan6, np.full(2, np.nan),
                     np.full(2, np.nan))
    back = CellRecord.from_builtins(json.loads(json.dumps(rec.to_builtins())))
    assert back.plans.shape == (2, 8, 2) and np.array_equal(back.plans, plans)
    moved = CellRecord("x", "x", 1, ["a", "b"], plans + 1.0, nan6, nan6, nan6, np.full(2, np.nan), np.full(2, np.nan))
    assert np.allclose(moved.endpoint_shift(rec), np.sqrt(2.0))  # the 3 s waypoint (index 5), not the 4 s one
    with pytest.raises(InvalidInput, match="expected"):
        CellRecord("x", "x", 1, ["a", "b"], plans[:, :7], nan6, nan6, nan6, np.full(2, np.nan), np.full(2, np.nan))


# -- the data: a world with 4 s of future --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def worlds(tmp_path_factory) -> dict[int, Path]:
    """The same two-scene world (one val scene, rendered) with 3 s and with 4 s of future per scored frame."""
    from pytest_drivedegrade.data.world import write_world

    root = tmp_path_factory.mktemp("horizon")
    return {s: write_world(root / f"w{s}", scenes=2, workers=1, future_s=s) for s in (3, 4)}


def _records(path: Path) -> set[str]:
    return {json.dumps(r, sort_keys=True) for r in json.loads(path.read_text())}


def test_a_4_s_world_adds_two_keyframes_and_keeps_the_default_worlds(worlds):
    w3, w4 = worlds[3], worlds[4]
    m3, m4 = (json.loads((w / "drivedegrade_world.json").read_text()) for w in (w3, w4))
    assert "future_s" not in m3 and m4["future_s"] == 4 and m3["fingerprint"] != m4["fingerprint"]
    assert m3["events"] == m4["events"]  # the same scored frames' events
    scenes = json.loads((w4 / "v1.0-trainval" / "scene.json").read_text())
    assert {s["nbr_samples"] for s in scenes} == {42}
    # every ego pose of the default world is in the 4 s world unchanged, and every image, byte for byte
    assert _records(w3 / "v1.0-trainval" / "ego_pose.json") < _records(w4 / "v1.0-trainval" / "ego_pose.json")
    images = sorted(p.relative_to(w3) for p in (w3 / "samples").rglob("*.jpg"))
    assert images and all((w3 / p).read_bytes() == (w4 / p).read_bytes() for p in images)
    r3, r4 = NuScenesReader(w3, split="val"), NuScenesReader(w4, split="val")
    assert (r3.future_poses, r4.future_poses) == (6, 8)
    f3, f4 = r3.scorable_frames(), r4.scorable_frames()
    assert [f.token for f in f3] == [f.token for f in f4] and len(f3) == 34  # the same scored frames
    for a, b in zip(f3, f4):
        assert np.array_equal(a.gt_future, b.gt_future) and a.command == b.command
        assert all(np.array_equal(x.center, y.center) for x, y in zip(a.agents, b.agents))
        assert b.future(8).shape == (8, 2) and np.array_equal(b.future(8)[:6], a.gt_future)
        assert len(b.future_agents(8)) == 8
    with pytest.raises(ValueError, match="holds 6 future keyframes, not 8"):
        f3[0].future(8)
    # a keyframe's 4 s future is its next eight keyframes' positions, in its frame
    assert [f.index for f in f4[:9]] == list(range(9))
    ahead = np.array([f4[k].pose[:2] for k in range(1, 9)])  # type: ignore[index]
    assert np.allclose(f4[0].future(8), _to_ego(f4[0], ahead), atol=1e-9)


def _to_ego(frame, xy: np.ndarray) -> np.ndarray:
    assert frame.pose is not None
    x, y, yaw = frame.pose
    d = np.asarray(xy) - np.array([x, y])
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)


def test_a_bad_future_in_a_manifest_is_a_data_error(worlds, tmp_path):
    import shutil

    copy = tmp_path / "w"
    shutil.copytree(worlds[3] / "v1.0-trainval", copy / "v1.0-trainval")
    manifest = json.loads((worlds[3] / "drivedegrade_world.json").read_text())
    (copy / "drivedegrade_world.json").write_text(json.dumps({**manifest, "future_s": 5}))
    with pytest.raises(DataError, match="future_s must be 3 or 4"):
        NuScenesReader(copy, split="val")


def _example(poses: int):
    import importlib.util

    spec = importlib.util.spec_from_file_location("navsim_style_horizon", EXAMPLE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.NavsimStyleAgent(poses=poses)


def _context(world: Path):
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    return RunContext.open(RunSettings(data=world, frames=6), planner_path=EXAMPLE)


ARRAYS = ("plans", "l2", "collision", "collision_vru", "jerk", "bit1", "nc", "dac", "ttc", "ep", "comfort", "pdms",
          "map_scored", "ddc", "tlc", "lk", "hc", "ec", "epdms")


@pytest.mark.parametrize("cell", [("clean", 0), ("jpeg", 3)])
def test_six_pose_cells_identical_on_the_4_s_world_and_eight_pose_scored_over_4_s(worlds, cell):
    """The done-when: the NAVSIM-style example with 6 poses has bit-identical cells on the 3 s and the 4 s world;
    with 8 poses on the 4 s world its plans' first six are the 6-pose plans, its L2 theirs, its PDMS/EPDMS those
    of the 8-pose plans over 4 s (each frame's equal to a fresh `PreparedFrame` over 8 poses)."""
    six, eight = _example(6), _example(8)
    c3, c4 = _context(worlds[3]), _context(worlds[4])
    assert [f.token for f in c3.frames] == [f.token for f in c4.frames]
    r3, r4 = c3.run_cell(six, *cell), c4.run_cell(six, *cell)
    for name in ARRAYS:
        assert np.array_equal(r3.array(name), r4.array(name), equal_nan=True), name
    assert r3.plans_digest() == r4.plans_digest() and r3.plans.shape == (6, 6, 2)
    # an 8-pose planner on the 3 s world: the usage error, before any cell
    assert "--future 4" in horizon_problem(eight, c3.reader.future_poses)
    assert horizon_problem(eight, c4.reader.future_poses) == ""
    r8 = c4.run_cell(eight, *cell)
    assert r8.plans.shape == (6, 8, 2) and not r8.errors
    assert np.array_equal(r8.plans[:, :HORIZON_STEPS], r4.plans)
    for name in ("l2", "collision", "collision_vru", "jerk", "bit1"):
        assert np.array_equal(r8.array(name), r4.array(name), equal_nan=True), name
    for i, frame in enumerate(c4.frames):
        fresh = PreparedFrame.of(frame, c4.reader.drivable_area(frame), lane_map=c4.reader.lane_map(frame), poses=8)
        assert fresh.score(r8.plans[i]).pdms == r8.pdms[i]
    assert not np.array_equal(r8.ep, r4.ep)  # progress over 4 s is another figure than over 3 s
