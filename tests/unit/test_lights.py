"""Traffic lights (spec 5, section 18): the light scenes leave every other scene as it was (sha256 over the default
world's scenes and the scenario scenes, frozen before lights existed), the expert stops at red, the cameras show
the light's state, the map's `traffic_light` layer round-trips, the closed loop counts a red light run as
RunningRedLightTest does (x 0.70, once per light) and the EPDMS traffic-light term has hand-worked answers."""

from __future__ import annotations

import hashlib
import math
from dataclasses import replace

import numpy as np
import pytest

from pytest_drivedegrade.closedloop import route_of, run_route
from pytest_drivedegrade.closedloop.camera import RouteCameras
from pytest_drivedegrade.closedloop.expert import WorldExpert
from pytest_drivedegrade.closedloop.judge import Pose, red_lights_run
from pytest_drivedegrade.closedloop.leaderboard import PENALTIES, driving_score
from pytest_drivedegrade.closedloop.routes import Route
from pytest_drivedegrade.constants import EGO_LENGTH
from pytest_drivedegrade.data.maps import parse_lane_map
from pytest_drivedegrade.data.world import render
from pytest_drivedegrade.data.world.agents import DT
from pytest_drivedegrade.data.world.expert import drive
from pytest_drivedegrade.data.world.export import map_expansion, timestamp
from pytest_drivedegrade.data.world.lights import HEAD_Z, RED, YELLOW_S, TrafficLight, segments_cross
from pytest_drivedegrade.data.world.scenarios import light_name, light_scene, ran_red, scenario_scene
from pytest_drivedegrade.data.world.scene import make_scene
from pytest_drivedegrade.metrics.pdms.extended import ExtendedTerms, epdms_score
from pytest_drivedegrade.metrics.pdms.lights import RedArea, convex_intersect, traffic_light_compliance
from pytest_drivedegrade.metrics.pdms.motion import EgoStates
from pytest_drivedegrade.metrics.pdms.prepared import PreparedFrame

SEED = 0
#: sha256 of `_world_digest` over the default world's scenes 0, 7, ..., 98 and of the 18 scenario scenes of the
#: default slice, computed on the code before traffic lights existed (branch main at cc76a03).
OPEN_LOOP_SHA = "888be6da2ba0efac6c105f759a62d70b99c46338cebfa139df119a9198293907"
SCENARIO_SHA = "6053bdf3b9047f5a2e2e5a354771313835571084a6a1eb3b43a9e7f3cd8b0879"


def _world_digest(scenes) -> str:
    h = hashlib.sha256()
    for scene in scenes:
        for a in scene.agents:
            h.update(np.ascontiguousarray(a.xy).tobytes() + np.ascontiguousarray(a.speed).tobytes()
                     + np.ascontiguousarray(a.yaw).tobytes() + repr((a.kind, a.role, a.size)).encode())
        for arr in (scene.ego.xy, scene.ego.speed, scene.ego.s, scene.ego.react):
            h.update(np.ascontiguousarray(arr).tobytes())
        h.update(repr((scene.name, scene.events, scene.crosswalks, scene.v_cruise)).encode())
        h.update(np.ascontiguousarray(scene.lane.xy).tobytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def routes() -> list[Route]:
    return [route_of(light_scene(SEED, i)) for i in range(6)]


def test_lights_leave_the_open_loop_world_and_the_scenario_scenes_byte_identical() -> None:
    light_scene(SEED, 0)
    assert _world_digest(make_scene(SEED, i, f"s{i}") for i in range(0, 100, 7)) == OPEN_LOOP_SHA
    assert _world_digest(scenario_scene(SEED, i) for i in range(18)) == SCENARIO_SHA
    assert all(not make_scene(SEED, i, "x").lights for i in range(3))


def test_a_light_scene_is_deterministic_and_its_expert_stops_at_red(routes: list[Route]) -> None:
    again = light_scene(SEED, 2)
    assert _world_digest([again]) == _world_digest([routes[2].scene]) and again.name == light_name(2)
    for route in routes:
        scene, (light,) = route.scene, route.scene.lights
        assert light.t_red == pytest.approx(light.t_yellow + YELLOW_S) and light.t_green > light.t_red
        assert not ran_red(scene.lane, light, scene.net, scene.ego), scene.name
        s_stop = float(scene.lane.project(light.stop_line(scene.net).mean(0)[None])[0][0])
        red = np.array([light.state_at(t * DT) == RED for t in range(len(scene.ego.s))])
        assert (scene.ego.s[red] + EGO_LENGTH / 2 <= s_stop).all(), scene.name  # never past the line while red
        assert ((scene.ego.speed < 0.3) & red).any(), scene.name  # halts at it
        assert scene.ego.s[-1] + EGO_LENGTH / 2 > s_stop + 10.0  # and drives on at green


def test_a_light_ignoring_driver_would_run_it(routes: list[Route]) -> None:
    """The scenes are ones where the light matters: the same drive without the light crosses the line at red."""
    ran = 0
    for route in routes:
        scene = route.scene
        blind = drive(scene.lane, [a for a in scene.agents if a.role != "follower"], scene.v_cruise,
                      float(scene.ego.speed[0]), float(scene.ego.s[0]))
        ran += ran_red(scene.lane, scene.lights[0], scene.net, blind)
    assert ran >= 4


def _project(route: Route, pose, world_xyz) -> tuple[int, int]:
    w2c, _ = render.world_to_camera(route.rig, "CAM_FRONT", pose)
    cam = route.rig.cameras["CAM_FRONT"]
    pc = w2c[:3, :3] @ np.asarray(world_xyz) + w2c[:3, 3]
    uv = cam.intrinsic @ (pc / pc[2])
    return int(round(uv[0])), int(round(uv[1]))


def _lamp(route: Route, which: int) -> np.ndarray:
    """The world centre of lamp `which` (0 red, 1 yellow, 2 green) on the head's face."""
    hx, hy, hyaw = route.scene.lights[0].head(route.scene.net)
    step = (HEAD_Z[1] - HEAD_Z[0]) / 3
    return np.array([hx + 0.22 * np.cos(hyaw), hy + 0.22 * np.sin(hyaw), HEAD_Z[0] + (2.5 - which) * step])


def test_the_front_camera_shows_the_lit_lamp_in_its_colour(routes: list[Route]) -> None:
    route = routes[0]
    light, net = route.scene.lights[0], route.scene.net
    s_stop = float(route.lane.project(light.stop_line(net).mean(0)[None])[0][0])
    x, y, yaw = route.lane.at(s_stop - 12.0)  # on the ego's lane 12 m before the line: the head 24 m ahead
    pose = (float(x), float(y), float(yaw))
    cams = RouteCameras(route, ("CAM_FRONT",))
    for when, lit in ((light.t_red + 0.5, 0), (light.t_green + 0.5, 2), (light.t_yellow + 0.5, 1)):
        img = cams.images(pose, int(round(when / DT)))["CAM_FRONT"].astype(int)
        for which in range(3):
            u, v = _project(route, pose, _lamp(route, which))
            r, g, b = np.median(img[v - 2:v + 3, u - 2:u + 3].reshape(-1, 3), axis=0)
            bright = max(r, g) > 150
            assert bright == (which == lit), (when, which, (r, g, b))
            if which == lit == 0:
                assert r > 150 and g < 90
            if which == lit == 2:
                assert g > 150 and r < 90
            if which == lit == 1:
                assert r > 150 and g > 110 and b < 90


def test_the_map_traffic_light_layer_round_trips(routes: list[Route]) -> None:
    scene = routes[1].scene
    data = map_expansion(scene, SEED)
    assert len(data["traffic_light"]) == len(data["stop_line"]) == 1
    assert data["stop_line"][0]["stop_line_type"] == "TRAFFIC_LIGHT"
    lane_map = parse_lane_map(data, "x")
    (light,), (mine,) = lane_map.lights, scene.lights
    np.testing.assert_allclose(light.line, mine.stop_line(scene.net), atol=1e-4)
    np.testing.assert_allclose(light.area.exterior, mine.area(scene.net), atol=1e-4)
    steps = np.arange(0, 245, 3)
    stamps = timestamp(scene, 0) + steps * 100_000
    assert list(light.status_at(stamps)) == [mine.state_at(t * DT).upper() for t in steps]
    assert not parse_lane_map(map_expansion(make_scene(SEED, 3, "scene-0003"), SEED), "y").lights


def test_red_lights_run_is_the_tail_crossing_the_stop_line_at_red(routes: list[Route]) -> None:
    route = routes[0]
    light, net = route.scene.lights[0], route.scene.net
    x, y, yaw = (float(v) for v in route.lane.at(float(route.lane.project(light.stop_line(net).mean(0)[None])[0][0])))
    # the tail segment spans 0.8 to 1.0 half lengths + 1 m behind the centre: put its middle on the line
    back = 0.9 * EGO_LENGTH / 2 + 0.5
    on_line = Pose(x + back * np.cos(yaw), y + back * np.sin(yaw), yaw, 8.0, 0.0)
    red_step, green_step = int(math.ceil((light.t_red + 0.1) / DT)), int(light.t_green / DT) + 2
    assert red_lights_run(route, on_line, red_step) == [0]
    assert red_lights_run(route, on_line, green_step) == []
    assert red_lights_run(route, on_line, int(light.t_yellow / DT) + 1) == []  # yellow is not red
    ahead = Pose(x + 6.0 * np.cos(yaw), y + 6.0 * np.sin(yaw), yaw, 8.0, 0.0)  # the tail already past
    assert red_lights_run(route, ahead, red_step) == []
    reversed_ = Pose(on_line.x, on_line.y, yaw + np.pi, 8.0, 0.0)
    assert red_lights_run(route, reversed_, red_step) == []


class RedRunner(WorldExpert):
    """A hidden behaviour: drives the expert's log of the same scene without the light (it runs the red)."""

    name = "red_runner"

    def __init__(self, routes: list[Route]) -> None:
        blind = []
        for r in routes:
            s = r.scene
            ego = drive(s.lane, [a for a in s.agents if a.role != "follower"], s.v_cruise, float(s.ego.speed[0]),
                        float(s.ego.s[0]))
            blind.append(replace(r, scene=replace(s, ego=ego)))
        super().__init__(blind)


def test_the_closed_loop_counts_a_red_light_once_for_a_runner_and_never_for_the_expert(routes) -> None:
    expert, runner = WorldExpert(routes), RedRunner(routes)
    counted = 0
    for route in routes:
        run = run_route(expert, route)
        assert run.ds is not None and run.ds >= 95.0 and run.end == "complete", route.name
        assert not [i for i in run.infractions if i.kind == "red_light"]
        bad = run_route(runner, route)
        reds = [i for i in bad.infractions if i.kind == "red_light"]
        assert len(reds) <= 1
        if reds:
            counted += 1
            assert bad.ds == pytest.approx(driving_score(bad.completion, [(i.kind, i.value)
                                                                          for i in bad.infractions]))
            assert bad.ds <= 100.0 * PENALTIES["red_light"] + 1e-9
    assert counted >= 4


def test_segments_cross_known_answers() -> None:
    a = np.array([[0.0, 0.0], [2.0, 0.0]])
    assert segments_cross(a, np.array([[1.0, -1.0], [1.0, 1.0]]))
    assert segments_cross(a, np.array([[2.0, -1.0], [2.0, 1.0]]))  # touching the end
    assert not segments_cross(a, np.array([[2.1, -1.0], [2.1, 1.0]]))
    assert not segments_cross(a, np.array([[0.0, 1.0], [2.0, 1.0]]))  # parallel


# --- EPDMS traffic-light compliance -----------------------------------------------------------------------------

def _straight(speed: float = 10.0, n: int = 31) -> EgoStates:
    """The ego driving along +x at `speed` from the origin, SIM_DT apart."""
    x = speed * 0.1 * np.arange(n)
    return EgoStates(np.stack([x, np.zeros(n)], 1), np.tile([speed, 0.0], (n, 1)), np.zeros((n, 2)), np.zeros(n),
                     np.full(n, speed))


#: The controlled area: x from 20 to 30 m, y from -2 to 2 m.
AREA = np.array([[20.0, -2.0], [30.0, -2.0], [30.0, 2.0], [20.0, 2.0]])
#: The first state whose box reaches it: front x = i + EGO_LENGTH / 2 >= 20 at 10 m/s (i = 18 with 4.084 m).
FIRST = int(math.ceil(20.0 - EGO_LENGTH / 2))


def test_tlc_known_answers() -> None:
    states = _straight()
    assert FIRST == 18
    red = np.zeros(31, bool)
    assert math.isnan(traffic_light_compliance(states, None))
    assert traffic_light_compliance(states, [RedArea(AREA, red)]) == 1.0  # green throughout
    red[:FIRST] = True
    assert traffic_light_compliance(states, [RedArea(AREA, red)]) == 1.0  # red only until the box gets there
    red[FIRST] = True
    assert traffic_light_compliance(states, [RedArea(AREA, red)]) == 0.0  # red when the box enters: violation
    stopping = _straight(5.0)  # 5 m/s: front at 15 + 2.04 m after 3 s, never in the area
    assert traffic_light_compliance(stopping, [RedArea(AREA, np.ones(31, bool))]) == 1.0
    wide = RedArea(AREA + [0.0, 2.0 + 1.85 / 2 + 0.01], np.ones(31, bool))  # beside the ego's box, 1 cm off
    assert traffic_light_compliance(states, [wide]) == 1.0
    assert convex_intersect(AREA, AREA[::-1] + [10.0, 0.0])  # either orientation, edges touching
    assert not convex_intersect(AREA, AREA[::-1] + [10.01, 0.0])


def test_tlc_multiplies_the_epdms_and_nan_leaves_it_as_before() -> None:
    terms = dict(nc=1.0, dac=1.0, ddc=1.0, ep=0.8, ttc=1.0, lk=1.0, hc=1.0)
    base = epdms_score(ExtendedTerms(tlc=math.nan, **terms), 1.0)
    assert base == pytest.approx((5 * 0.8 + 5 + 2 + 2 + 2) / 16)
    assert epdms_score(ExtendedTerms(tlc=1.0, **terms), 1.0) == base
    assert epdms_score(ExtendedTerms(tlc=0.0, **terms), 1.0) == 0.0


def test_a_prepared_frame_scores_tlc_with_the_human_filter() -> None:
    expert = np.array([[2.5 * (k + 1), 0.0] for k in range(6)])  # 5 m/s: stops short of the area
    fast = np.array([[5.0 * (k + 1), 0.0] for k in range(6)])  # 10 m/s: into it by 3 s
    red = RedArea(AREA, np.ones(31, bool))
    frame = PreparedFrame.prepare(expert, [], (5.0, 0.0), red_areas=[red])
    assert frame.human is not None and frame.human.tlc == 1.0
    from pytest_drivedegrade.metrics.pdms.tracked import tracked_states

    ps = tracked_states(fast[None], [frame.initial])[0]
    assert frame.judged(fast, ps)[1].tlc == 0.0
    plain = PreparedFrame.prepare(expert, [], (5.0, 0.0))
    assert math.isnan(plain.judged(fast, ps)[1].tlc)  # no lights: not scored, as before
    through = PreparedFrame.prepare(fast, [], (10.0, 0.0), red_areas=[red])
    assert through.human is not None and through.human.tlc == 0.0  # the human ran it: the plan's 0 is filtered
    assert through.judged(fast, ps)[1].filtered(through.human).tlc == 1.0


def test_a_light_stop_line_spans_the_lanes_of_its_direction() -> None:
    scene = light_scene(SEED, 3)
    light: TrafficLight = scene.lights[0]
    line = light.stop_line(scene.net)
    assert float(np.hypot(*(line[1] - line[0]))) == pytest.approx(light.lanes * 3.5, abs=1e-6)
    _, d = scene.net.route.center.project(line)
    assert d[0] == pytest.approx(0.0, abs=0.2) and d[1] == pytest.approx(-light.lanes * 3.5, abs=0.2)


def test_tlc_reads_the_lights_from_the_map_in_the_frame_of_the_ego(routes: list[Route]) -> None:
    """The map's light, moved into the ego frame at a keyframe where the expert waits at the red: a plan that
    drives on at 10 m/s enters the controlled lanes while red (tlc 0), the expert's standstill does not (1)."""
    from pytest_drivedegrade.metrics.pdms.lights import red_areas
    from pytest_drivedegrade.metrics.pdms.tracked import initial_state, tracked_states

    scene = routes[0].scene
    light = scene.lights[0]
    lane_map = parse_lane_map(map_expansion(scene, SEED), "x")
    waiting = [k for k in range(40) if scene.ego.speed[5 * k] < 0.3 and light.state_at(
        (5 * k + 30) * DT) == RED]
    assert waiting, "the expert waits at the red for at least 3 s at some keyframe"
    step = 5 * waiting[0]
    pose = (float(scene.ego.xy[step, 0]), float(scene.ego.xy[step, 1]), float(scene.ego.yaw[step]))
    areas = red_areas(lane_map, pose, timestamp(scene, waiting[0]), 6)
    assert areas is not None and len(areas) == 1 and areas[0].red.all()
    assert 0.0 < float(areas[0].polygon[:, 0].min()) < 5.0  # the controlled lanes start just ahead of the ego
    start = initial_state((0.0, 0.0))
    go = tracked_states(np.array([[[5.0 * (k + 1), 0.0] for k in range(6)]]), [initial_state((10.0, 0.0))])[0]
    wait = tracked_states(np.array([[[0.0, 0.0]] * 6]), [start])[0]
    assert traffic_light_compliance(go, areas) == 0.0 and traffic_light_compliance(wait, areas) == 1.0
    assert red_areas(parse_lane_map(map_expansion(make_scene(SEED, 3, "s"), SEED), "y"), pose, 0, 6) is None
