"""The closed-loop simulator: reference drivers validate it (the world's expert scores >= 95, constant velocity
scores below it naming the infraction), rendering at the logged pose reproduces the data's images, failed runs
are unscored with bounds that widen, and a run is bit-identical when repeated."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.closedloop import (
    CellResult,
    Corruption,
    Route,
    RunResult,
    judge,
    load_routes,
    route_of,
    run_cell,
    run_route,
)
from pytest_drivedegrade.closedloop.camera import RouteCameras
from pytest_drivedegrade.closedloop.expert import WorldExpert
from pytest_drivedegrade.closedloop.leaderboard import driving_score
from pytest_drivedegrade.closedloop.loop_io import ego_status, frame_context, route_command
from pytest_drivedegrade.closedloop.results import END_BLOCKED, END_DEVIATED, END_UNSCORED
from pytest_drivedegrade.closedloop.simulate import Rules
from pytest_drivedegrade.data.context import FrameContext
from pytest_drivedegrade.data.frame import Command, EgoStatus
from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.data.world.scene import make_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "planners"))
from constant_velocity import ConstantVelocity  # noqa: E402

#: World seed 1: scene 6 has a braking lead vehicle the expert follows, scene 10 a bend (seen when choosing them).
SEED, LEAD, BEND = 1, 6, 10


@pytest.fixture(scope="module")
def routes() -> dict[int, Route]:
    return {i: route_of(make_scene(SEED, i, f"scene-{i}")) for i in (0, 2, LEAD, BEND)}


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from pytest_drivedegrade.data.world import write_world
    return write_world(tmp_path_factory.mktemp("w"), scenes=2, seed=SEED)


class FrontReader:
    """Reads CAM_FRONT and steers by nothing: constant velocity slowed by the image's darkness (so an image
    change shows in the trace); records what it was given."""

    cameras = ("CAM_FRONT",)

    def __init__(self) -> None:
        self.seen: list[tuple[tuple[str, ...], int, tuple[int, ...]]] = []
        self.contexts: list[FrameContext] = []

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command,
                context: FrameContext | None = None) -> np.ndarray:
        assert context is not None
        self.seen.append((tuple(images), context.index, images["CAM_FRONT"].shape))
        self.contexts.append(context)
        factor = float(images["CAM_FRONT"].mean()) / 255.0
        return np.arange(1, 7)[:, None] * 0.5 * np.array([ego.velocity[0] * (0.5 + factor), 0.0])


class RaisesOn:
    """Constant velocity that raises on one route."""

    cameras: tuple[str, ...] = ()

    def __init__(self, bad: str) -> None:
        self.bad, self.route = bad, ""

    def reset(self, route: str) -> None:
        self.route = route

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        if self.route == self.bad:
            raise RuntimeError("boom")
        return ConstantVelocity().predict(images, ego, cmd)


def test_the_worlds_expert_scores_at_least_95_on_every_route(routes: dict[int, Route]) -> None:
    expert = WorldExpert(list(routes.values()))
    for route in routes.values():
        run = run_route(expert, route)
        assert run.ds is not None and run.ds >= 95.0, (route.name, run.ds, run.end, run.infractions)
        assert not [i for i in run.infractions if i.kind.startswith("collision")]


def test_the_expert_drives_every_route_of_a_data_root(world: Path) -> None:
    found = load_routes(world, scenarios=3, lights=1)
    val = NuScenesReader(world).manifest["splits"]["val"]  # type: ignore[index]
    assert [r.name for r in found] == [*val, "scenario-0000-crossing", "scenario-0001-braking",
                                       "scenario-0002-blocked", "lights-0000"]
    assert [r.name for r in load_routes(world)][-7:] == ["scenario-0017-blocked",
                                                         *(f"lights-{i:04d}" for i in range(6))]
    assert [r.name for r in load_routes(world, limit=len(val) + 1)] == [*val, "scenario-0000-crossing"]
    for route in found:
        assert route.length > 20.0
        run = run_route(WorldExpert(found), route)
        assert run.ds is not None and run.ds >= 95.0


def test_rendering_at_the_logged_pose_reproduces_the_datas_image(world: Path) -> None:
    route = load_routes(world)[0]
    frame = next(iter(NuScenesReader(world).frames()))
    assert frame.scene_name == route.name and frame.index == 0
    ego = route.scene.ego
    pose = (float(ego.xy[0, 0]), float(ego.xy[0, 1]), float(ego.yaw[0]))
    image = RouteCameras(route, ("CAM_FRONT",)).images(pose, 0)["CAM_FRONT"]
    assert np.array_equal(image, NuScenesReader.load_image(frame.cameras["CAM_FRONT"]))


def test_constant_velocity_scores_below_the_expert_naming_the_infraction(routes: dict[int, Route]) -> None:
    lead, bend = routes[LEAD], routes[BEND]
    assert "brake" in lead.scene.events and "bend" in bend.scene.events
    expert = WorldExpert(list(routes.values()))
    at_lead = run_route(ConstantVelocity(), lead)
    assert at_lead.ds is not None and at_lead.ds < run_route(expert, lead).ds  # type: ignore[operator]
    assert [(i.kind, i.what) for i in at_lead.infractions if i.kind != "min_speed"] == [("collision_vehicle", "lead")]
    slow = [i.value for i in at_lead.infractions if i.kind == "min_speed"]
    assert slow and all(v is not None and v < 100.0 for v in slow)  # slower than the expert behind the lead
    factor = float(np.prod([1.0 - 0.3 * (1.0 - v / 100.0) for v in slow if v is not None]))
    assert at_lead.ds == pytest.approx(100.0 * 0.60 * factor)  # completed: 100 x 1 x 0.60 x the min-speed factors
    on_bend = run_route(ConstantVelocity(), bend)
    assert on_bend.ds is not None and on_bend.ds < run_route(expert, bend).ds  # type: ignore[operator]
    assert on_bend.end == END_DEVIATED and on_bend.count("outside_route_lanes") == 1
    assert on_bend.count("collision_static") >= 1  # straight on past the bend into the scenery
    assert on_bend.completion is not None and on_bend.ds == pytest.approx(
        driving_score(on_bend.completion, [(i.kind, i.value) for i in on_bend.infractions]))


def test_a_planner_that_raises_leaves_its_run_unscored_and_widens_the_bounds(routes: dict[int, Route]) -> None:
    pair = [routes[0], routes[2]]
    cell = run_cell(RaisesOn(pair[1].name), pair)
    bad = cell.runs[1]
    assert (bad.ds, bad.completion, bad.end, bad.steps) == (None, None, END_UNSCORED, 0)
    assert "RuntimeError: boom" in bad.error
    good = cell.runs[0].ds
    assert good is not None and cell.unscored == 1
    assert cell.mean == good and cell.std == 0.0
    assert cell.bounds == pytest.approx((good / 2, (good + 100.0) / 2))
    clean = run_cell(ConstantVelocity(), pair)
    assert clean.bounds[0] == clean.bounds[1] == clean.mean


def test_a_bad_plan_is_unscored_never_zero(routes: dict[int, Route]) -> None:
    class Nan(ConstantVelocity):
        def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
            return np.full((6, 2), np.nan)

    run = run_route(Nan(), routes[0])
    assert run.ds is None and run.end == END_UNSCORED and "step 0" in run.error


def test_the_same_run_twice_is_bit_identical(routes: dict[int, Route]) -> None:
    route = routes[LEAD]
    corruption = Corruption("gaussian_noise", 3)
    first, second = (run_route(FrontReader(), route, corruption, seed=5) for _ in range(2))
    assert first.ds == second.ds and first.end == second.end
    assert first.trace.tobytes() == second.trace.tobytes()
    other = run_route(FrontReader(), route, Corruption("gaussian_noise", 3), seed=6)
    assert other.trace.tobytes() != first.trace.tobytes()  # the seed reaches the images, hence the path


def test_the_planner_gets_the_six_cameras_view_and_the_route_steps_context(routes: dict[int, Route]) -> None:
    """As in the open loop, `images` names all six cameras; only the declared one is rendered up front (the
    others on a read: `closedloop.view`)."""
    from pytest_drivedegrade.constants import CAMERAS

    planner = FrontReader()
    run = run_route(planner, routes[0])
    assert [s[0] for s in planner.seen] == [CAMERAS] * run.steps
    assert [s[1] for s in planner.seen] == list(range(run.steps))
    for k, ctx in enumerate(planner.contexts):
        x, y, _ = run.trace[5 * k]  # the pose the planner was called at: every fifth 10 Hz state
        assert ctx.ego2global[:2, 3] == pytest.approx([x, y])


def test_cell_bounds_and_moments_on_known_runs() -> None:
    def run(ds: float | None) -> RunResult:
        return RunResult("r", 0, ds, None if ds is None else ds / 100, "x", (), np.zeros((1, 3)))

    cell = CellResult.of("closed-clean", [run(40.0), run(80.0), run(None), run(None)])
    assert cell.mean == 60.0 and cell.std == 20.0 and cell.unscored == 2
    assert cell.bounds == (30.0, 80.0)
    assert cell.completion == pytest.approx(0.6)


def test_at_the_logged_state_the_planner_gets_what_the_reader_gives(world: Path) -> None:
    """Ego status, command and frame context of the simulated state equal the data's at the logged poses."""
    route = load_routes(world)[0]
    ego = route.scene.ego
    frames = [f for f in NuScenesReader(world).frames() if f.scene_name == route.name]
    for k in (0, 3, 12, 25):
        frame, t = frames[k], 5 * k
        pose = (float(ego.xy[t, 0]), float(ego.xy[t, 1]), float(ego.yaw[t]))
        history = [(float(ego.xy[5 * j, 0]), float(ego.xy[5 * j, 1]), float(ego.yaw[5 * j])) for j in range(k)]
        status = ego_status(history, pose, float(ego.speed[t]), float(ego.accel[t]),
                            float((ego.yaw[t + 1] - ego.yaw[t]) / 0.1))
        assert status.velocity == pytest.approx(frame.ego.velocity, abs=0.05)
        assert status.acceleration == pytest.approx(frame.ego.acceleration, abs=0.15)
        assert status.yaw_rate == pytest.approx(frame.ego.yaw_rate, abs=0.01)
        assert status.past_xy == pytest.approx(frame.ego.past_xy, abs=0.05)
        assert route_command(route, pose, float(ego.speed[t])) == frame.command
        ours, theirs = frame_context(route, k, pose, status), FrameContext.of(frame)
        assert (ours.index, ours.timestamp, ours.scene_name) == (theirs.index, theirs.timestamp, theirs.scene_name)
        assert ours.ego2global == pytest.approx(theirs.ego2global, abs=1e-6)
        for cam, cal in theirs.calibration.items():
            assert ours.calibration[cam].image_size == cal.image_size
            assert ours.calibration[cam].sensor2ego == pytest.approx(cal.sensor2ego, abs=1e-6)
            assert ours.calibration[cam].intrinsic == pytest.approx(cal.intrinsic, abs=1e-6)


class Stop:
    """Plans to stand still."""

    cameras: tuple[str, ...] = ()

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        return np.zeros((6, 2))


def test_standing_still_ends_blocked_and_a_rear_end_by_the_follower_is_not_at_fault(routes: dict[int, Route]) -> None:
    """NAVSIM's rule (the at_fault option) does not count the follower's rear end; the leaderboard's (the
    default) counts it once, as the ego was still rolling (CollisionTest ignores only an ego below 0.1 m/s)."""
    route = routes[0]
    assert "follower" in [a.role for a in route.scene.agents]
    run = run_route(Stop(), route, rules=Rules("at_fault"))
    assert run.end == END_BLOCKED and run.infractions == ()
    assert run.ds is not None and run.completion is not None and run.ds == pytest.approx(100 * run.completion)
    assert run.ds < 20
    every = run_route(Stop(), route)
    assert [(i.kind, i.what) for i in every.infractions] == [("collision_vehicle", "follower")]
    assert every.completion == run.completion and every.ds == pytest.approx(0.60 * run.ds)
    contacts = []
    for t in range(len(run.trace)):
        x, y, yaw = run.trace[t]
        pose = judge.Pose(float(x), float(y), float(yaw), 0.0, 0.0)
        contacts += judge.collisions(route, pose, t, False)
    assert contacts and all(route.scene.agents[who].role == "follower" for _, who, _ in contacts)


@given(st.lists(st.one_of(st.none(), st.floats(0.0, 100.0)), min_size=1, max_size=12), st.floats(0.0, 1.0))
@settings(max_examples=60, deadline=None)
def test_the_bounds_hold_every_assignment_of_the_unscored_runs(ds: list[float | None], fill: float) -> None:
    cell = CellResult.of("c", [RunResult("r", 0, d, None, "x", (), np.zeros((1, 3))) for d in ds])
    assigned = float(np.mean([100.0 * fill if d is None else d for d in ds]))
    lo, hi = cell.bounds
    assert lo - 1e-9 <= assigned <= hi + 1e-9
    assert hi - lo == pytest.approx(100.0 * ds.count(None) / len(ds))
