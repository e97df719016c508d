"""The reference closed-loop driver (planners/closed_driver.py): its committed weights load without a download,
it plans six finite waypoints from the front camera, the same input gives the same plan bit for bit, its plan
depends on the camera (a black front camera stops it), its outputs read as the percept they were trained on, and
its recipe (planners/train_closed_driver.py) is deterministic and does not depend on how many processes drive."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pytest_drivedegrade.closedloop import load_routes, route_of
from pytest_drivedegrade.closedloop.camera import RouteCameras
from pytest_drivedegrade.closedloop.loop_io import ego_status, route_command
from pytest_drivedegrade.closedloop.percept import BEND_AHEAD, FAR_M, LANE_AHEAD, Percept
from pytest_drivedegrade.constants import EGO_LENGTH
from pytest_drivedegrade.data.world.scenarios import scenario_scene
from pytest_drivedegrade.floor import FEATURE_SIZE
from pytest_drivedegrade.planning import EgoStatus

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "planners"))
from closed_driver import (  # noqa: E402
    OUTPUT_SIZE,
    PROFILE_M,
    WEIGHTS,
    ClosedDriver,
    PerceptEnsemble,
    PerceptNet,
    percept_of,
    preprocess,
    profile_distance,
    targets,
)
from train_closed_driver import gather, train, training_routes, training_specs  # noqa: E402

#: Farthest the driver may plan to move in 3 s standing behind a vehicle that stands in its lane (m).
STOPPED_REACH_M = 2.0


@pytest.fixture(scope="module")
def inputs():
    route = route_of(scenario_scene(0, 1))
    ego = route.scene.ego
    pose = (float(ego.xy[0, 0]), float(ego.xy[0, 1]), float(ego.yaw[0]))
    images = RouteCameras(route, ("CAM_FRONT",)).images(pose, 0)
    status = ego_status([], pose, float(ego.speed[0]), float(ego.accel[0]), 0.0)
    return images, status, route_command(route, pose, float(ego.speed[0]))


def test_the_committed_weights_plan_six_finite_waypoints_deterministically(inputs) -> None:
    images, status, cmd = inputs
    a = ClosedDriver().predict(images, status, cmd)
    b = ClosedDriver().predict(images, status, cmd)
    assert a.shape == (6, 2) and np.isfinite(a).all()
    assert a.tobytes() == b.tobytes()
    assert WEIGHTS.is_file() and WEIGHTS.with_suffix(".json").is_file()


def test_a_black_front_camera_reads_an_obstacle_close_ahead_and_stops_the_driver(inputs) -> None:
    """Measured on the committed weights, at the start of scenario 1 (a lead 12.0 m ahead at 10.4 m/s, the ego at
    6.2 m/s): the driver reads the lead 10.0 m ahead and plans 17.6 m in 3 s; with a black front camera it reads
    the corridor blocked at once (0.1 m) and plans to stop within 4.1 m (the blackout S5 cell's 6 DS)."""
    images, status, cmd = inputs
    driver = ClosedDriver()
    dark = {"CAM_FRONT": np.zeros_like(images["CAM_FRONT"])}
    assert preprocess(images).shape == (6, 45, 80)
    seen, blind = driver.percept(images, status, cmd), driver.percept(dark, status, cmd)
    assert abs(seen.gap - 12.0) < 3.0 and blind.gap < 2.0
    ahead, stopped = driver.predict(images, status, cmd)[-1, 0], driver.predict(dark, status, cmd)[-1, 0]
    assert stopped < 4.5 and ahead > stopped + 5.0


def _frame(route, t: int):
    """The front camera, ego status and command at log step `t` of `route`, the ego at its logged pose and speed
    with its logged past (what the closed loop gives the driver when it drives as the log did)."""
    ego = route.scene.ego
    pose = (float(ego.xy[t, 0]), float(ego.xy[t, 1]), float(ego.yaw[t]))
    past = [(float(ego.xy[t - 5 * j, 0]), float(ego.xy[t - 5 * j, 1]), float(ego.yaw[t - 5 * j]))
            for j in range(4, 0, -1) if t - 5 * j >= 0]
    status = ego_status(past, pose, float(ego.speed[t]), float(ego.accel[t]), 0.0)
    images = RouteCameras(route, ("CAM_FRONT",)).images(pose, t)
    return images, status, route_command(route, pose, float(ego.speed[t]))


def test_the_committed_weights_see_a_standing_bus_and_brake_for_it() -> None:
    """Scenario 2: the logged expert brakes from step 100 and stands behind a broken-down bus from step 140 to 180.
    Placed on the log, the driver plans over 15 m in 3 s at step 40 (the bus far ahead, 7.8 m/s; measured 23.8 m)
    and under 8 m at step 120 (close behind it, 4.7 m/s; the log 3.7 m; measured 3.2 m), reading the bus no farther
    than it is and less than 3 m short of it (measured 6.0 m, the bus 6.5 m ahead)."""
    route = route_of(scenario_scene(0, 2))
    assert [a.kind for a in route.scene.agents if a.role == "stopped"] == ["bus"]
    driver = ClosedDriver()
    assert driver.predict(*_frame(route, 40))[-1, 0] > 15.0
    frame = _frame(route, 120)
    driver.reset("scenario-0002-blocked")  # a call 8 s later is not the next call: no gap to track
    assert driver.predict(*frame)[-1, 0] < 8.0
    ego = route.scene.ego
    bus = next(a for a in route.scene.agents if a.role == "stopped")
    gap = float(route.lane.project(bus.xy[120][None])[0][0]) - bus.size[0] / 2 - float(ego.s[120]) - EGO_LENGTH / 2
    assert gap - 3.0 < driver.percept(*frame).gap <= gap


def test_the_driver_stays_put_behind_a_standing_bus() -> None:
    """Scenario 2, standing behind the bus (log steps 145-175, 4.1 m behind it), called every 0.5 s as the loop
    calls it: the plan stays put at every call (measured: 0.0 to 0.7 m in 3 s; a frame alone reads the bus moving
    at 0.7-1.2 m/s, the weights before this recipe's at 3.3-3.6)."""
    route = route_of(scenario_scene(0, 2))
    driver = ClosedDriver()
    driver.reset("scenario-0002-blocked")
    reach = [float(driver.predict(*_frame(route, t))[-1, 0]) for t in range(145, 180, 5)]
    assert max(reach) < STOPPED_REACH_M, reach


class _Reads(ClosedDriver):
    """The driver with its network's reading replaced by `readings`, one per call (the planning half alone)."""

    def __init__(self, readings: list[Percept]) -> None:
        super().__init__()
        self.readings = iter(readings)

    def percept(self, images, ego, cmd) -> Percept:
        return next(self.readings)


def test_a_lead_read_as_moving_whose_gap_does_not_change_is_planned_as_standing(inputs) -> None:
    """What the committed driver before this one did behind the bus: each frame read the gap (4.1 m) and the bus
    moving at 3.5 m/s, so the rule planned 7 m in 3 s and the driver crept up to it. The gap's change over the last
    call gives the lead's speed: 0 while neither moves, so from the second call the plan stays put; a lead whose
    gap opens is planned at the (slower) speed read; after reset() the first call has nothing to track."""
    images, _, cmd = inputs
    lane = np.stack([np.asarray(LANE_AHEAD), np.zeros(len(LANE_AHEAD))], axis=1)
    bend = np.full(len(BEND_AHEAD), 20.0)
    standing = EgoStatus((0.0, 0.0), (0.0, 0.0), 0.0)
    bus = Percept(lane, bend, 4.1, 3.5)
    driver = _Reads([bus] * 3 + [bus] * 2)
    driver.reset("a")
    reach = [float(driver.predict(images, standing, cmd)[-1, 0]) for _ in range(3)]
    assert reach[0] > 5.0 and max(reach[1:]) < STOPPED_REACH_M, reach
    driver.reset("b")
    assert float(driver.predict(images, standing, cmd)[-1, 0]) == pytest.approx(reach[0])
    moving = EgoStatus((8.0, 0.0), (0.0, 0.0), 0.0)

    def second_plan(gap: float) -> tuple[float, float]:
        """The second call's reach after a first reading (12 m, 8 m/s), and a fresh driver's on the same reading."""
        tracked = _Reads([Percept(lane, bend, 12.0, 8.0), Percept(lane, bend, gap, 8.0)])
        tracked.predict(images, moving, cmd)
        fresh = _Reads([Percept(lane, bend, gap, 8.0)])
        return float(tracked.predict(images, moving, cmd)[-1, 0]), float(fresh.predict(images, moving, cmd)[-1, 0])

    assert second_plan(14.0)[0] == second_plan(14.0)[1]  # opening (12 m/s tracked): the 8 m/s read is kept
    closing, unaware = second_plan(9.0)  # closing at 6 m/s: the lead moves at 2 m/s, not 8
    assert closing < unaware - 3.0


def test_a_profile_reads_as_the_distance_it_was_trained_on() -> None:
    """Targets of a world percept, read back by `percept_of`: a hard profile gives the bin's lower edge (within one
    bin of the truth), nothing within 50 m gives FAR_M, red and yellow come back, and the lead's speed is learnt only
    where an obstacle is within 40 m."""
    lane = np.stack([np.asarray(LANE_AHEAD), np.linspace(0.0, 2.0, len(LANE_AHEAD))], axis=1)
    bend = np.linspace(20.0, 9.0, len(BEND_AHEAD))
    truth = [Percept(lane, bend, 17.0, 5.0, 9.0, True, False), Percept(lane, bend), Percept(lane, bend, 45.0, 3.0,
                                                                                            30.0, False, True)]
    wanted, learn = targets(truth)
    assert wanted.shape == (3, OUTPUT_SIZE) and learn.tolist() == [1.0, 0.0, 0.0]
    read = [percept_of(row) for row in wanted]
    assert (read[0].gap, read[0].line, read[0].red, read[0].yellow) == (16.0, 8.0, True, False)
    assert (read[1].gap, read[1].line, read[1].red, read[1].yellow) == (FAR_M, FAR_M, False, False)
    assert (read[2].gap, read[2].line, read[2].red, read[2].yellow) == (40.0, 25.0, False, True)
    assert read[0].lane == pytest.approx(lane) and read[0].bend == pytest.approx(bend) and read[0].lead_speed == 5.0
    soft = np.full(len(PROFILE_M), 0.5)
    soft[:3] = 1.0  # sure up to 6 m, then a coin: 6 + half the rest up to 50
    assert profile_distance(soft) == pytest.approx(6.0 + 0.5 * (50.0 - 6.0))
    assert profile_distance(np.array([1.0, 0.2, 0.9] + [0.0] * 9)) == pytest.approx(2.0 + 0.2 * 2 + 0.2 * 2)


def test_the_training_routes_are_not_the_slices(small_world: Path) -> None:
    """Training drives the train scenes, scenarios and light scenes numbered from 1000; the slice the val scenes,
    scenarios and light scenes from 0: no route, and no scene, in common; nor with the held-out scenes from 3000
    (benchmarks/closedloop.py --held-out), which the recipe refuses to reach."""
    train_ = training_routes(small_world, 6, 2 / 3, 0.0)
    names = [r.name for r in train_]
    assert names[:2] == ["scene-0001", "scene-0002"] and len(names) == 6
    assert all(n.startswith("scenario-10") for n in names[2:])
    mixed = [r.name for r in training_routes(small_world, 6, 1 / 3, 1 / 3)]
    assert len(mixed) == 6 and sum(n.startswith("scenario-10") for n in mixed) == 2
    assert [n for n in mixed if n.startswith("lights-")] == ["lights-1000", "lights-1001"]
    last = training_specs(small_world, 4000, 0.5, 0.5)  # 2000 of each: scenes 1000 .. 2999
    assert max(index for _, _, index, _ in last) == 2999
    with pytest.raises(ValueError, match="held-out scenes numbered from 3000"):
        training_specs(small_world, 4002, 0.5, 0.5)  # 2001 of each would reach scenario 3000
    with pytest.raises(ValueError, match="train scenes"):
        training_routes(small_world, 9, 1 / 3, 1 / 3)
    slice_names = {r.name for r in load_routes(small_world)}
    assert any(n.startswith("lights-") for n in slice_names)
    assert not (set(names) | set(mixed)) & slice_names


def test_the_gathered_data_do_not_depend_on_the_number_of_processes(small_world: Path) -> None:
    """A round's data, driven by the perturbed bound and by a learner, are the same bit for bit in one process or
    two (each route's draws are seeded by its index; the data come back in route order)."""
    specs = training_specs(small_world, 3, 1 / 3, 1 / 3)
    one, two = gather(specs, None, 1.0, 7, 1), gather(specs, None, 1.0, 7, 2)
    assert one[0].tobytes() == two[0].tobytes() and one[1].tobytes() == two[1].tobytes()
    assert targets(one[2])[0].tobytes() == targets(two[2])[0].tobytes()
    torch.manual_seed(0)
    net = PerceptEnsemble(1)
    learner = [gather(specs, net, 0.2, 8, w) for w in (1, 2)]
    assert learner[0][0].tobytes() == learner[1][0].tobytes()
    assert len(one[2]) == len(one[0]) > 20


def test_training_is_deterministic_for_a_seed() -> None:
    """The recipe's training step on the same data and seed gives the same weights, tensor for tensor."""
    rng = np.random.default_rng(3)
    pix = rng.integers(0, 256, (40, 6, 45, 80), dtype=np.uint8)
    feats = rng.normal(size=(40, FEATURE_SIZE)).astype(np.float32)
    lane = np.stack([np.asarray(LANE_AHEAD), np.zeros(len(LANE_AHEAD))], axis=1)
    labels = [Percept(lane, np.full(len(BEND_AHEAD), 15.0), float(g), 3.0, float(d), bool(g < 20), False)
              for g, d in zip(rng.uniform(0, 70, 40), rng.uniform(0, 70, 40))]
    torch.manual_seed(0)
    start = PerceptNet().state_dict()
    nets = [PerceptNet(), PerceptNet()]
    for net in nets:
        net.load_state_dict(start)
        train(net, pix, feats, labels, 2, seed=5)
    first, second = (n.state_dict() for n in nets)
    assert all(torch.equal(first[k], second[k]) for k in first)
    assert not torch.equal(first["head.4.weight"], start["head.4.weight"])


def test_the_initial_network_is_the_same_in_every_process() -> None:
    """torch seeds its default generator at random per process; the recipe seeds it before drawing the network, so
    two fresh interpreters draw the same initial weights (the cause of the old recipe's irreproducible reruns)."""
    code = ("import hashlib, sys; sys.path.insert(0, 'planners'); import torch; "
            "from train_closed_driver import initial_network; "
            "print(torch.initial_seed(), hashlib.sha256(b''.join(v.numpy().tobytes() for v in "
            "initial_network(3).state_dict().values())).hexdigest())")
    root = Path(__file__).resolve().parents[2]
    procs = [subprocess.Popen([sys.executable, "-c", code], cwd=root, stdout=subprocess.PIPE, text=True)
             for _ in range(2)]
    runs = [p.communicate(timeout=120)[0].split() for p in procs]
    assert [p.returncode for p in procs] == [0, 0]
    assert runs[0][1] == runs[1][1]
    assert runs[0][0] != runs[1][0]  # the unseeded generator did differ between the two processes


def test_edited_weights_change_the_planner_fingerprint_and_foreign_weights_are_refused(tmp_path, inputs) -> None:
    """A hostile edit of the committed weights (one number) changes the planner's fingerprint, so no stored cell of
    the committed driver is reused for it; a file of other weights (two networks) is refused naming the file, not
    loaded half-way."""
    from pytest_drivedegrade.planning import planner_fingerprint

    path = Path(__file__).resolve().parents[2] / "planners" / "closed_driver.py"
    state = torch.load(WEIGHTS, map_location="cpu", weights_only=True)
    key = next(k for k in state if k.endswith("weight"))
    state[key] = state[key].clone()
    state[key].view(-1)[0] += 1e-3
    edited = tmp_path / "edited.pt"
    torch.save(state, edited)
    honest, tampered = ClosedDriver(), ClosedDriver(edited)
    assert planner_fingerprint(honest, path) != planner_fingerprint(tampered, path)
    assert planner_fingerprint(honest, path) == planner_fingerprint(ClosedDriver(), path)
    other = tmp_path / "other.pt"
    torch.save(PerceptEnsemble(2).state_dict(), other)
    with pytest.raises(ValueError, match="other.pt: not weights of this driver"):
        ClosedDriver(other)
