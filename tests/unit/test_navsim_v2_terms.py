"""EPDMS terms against known NAVSIM v2.2 outputs (issue 39): each case's expected value worked out by hand from
NAVSIM's own definitions (`pdm_scorer.py`, `pdm_score.py`, `metric_cache_processor.py`), written beside it.

- history comfort's past: NAVSIM's ``get_ego_past_trajectory(0, 1.5)`` (the keyframes 1.5, 1.0, 0.5 s back and
  this one) linearly interpolated every 0.1 s from the first, the last sample dropped; HC 1 without a past; the
  human scored without a past, so HC is never filtered;
- driving direction: a centre in no on-route lane is oncoming, off every lane (a shoulder) included;
- lane keeping: the distance to the route's centreline (a same-direction lane change fails);
- TTC's intersection clause and "in multiple lanes" from the lane polygons.
"""

from __future__ import annotations

import numpy as np
import pytest

from pytest_drivedegrade.data.frame import AgentBoxes, EgoStatus
from pytest_drivedegrade.data.maps import DrivableArea, Lane, LaneMap, MapPolygon
from pytest_drivedegrade.metrics import pdms as P  # noqa: N812 - as test_pdms has it
from pytest_drivedegrade.metrics.pdms import extended as X  # noqa: N812
from pytest_drivedegrade.metrics.pdms.lanes import LaneView, astray
from pytest_drivedegrade.metrics.pdms.motion import box_corners
from pytest_drivedegrade.metrics.pdms.route import route_centreline

TIMES = np.arange(P.N_STATES) * P.SIM_DT
T = np.arange(1, 7) * 0.5
EGO = EgoStatus((10.0, 0.0), (0.0, 0.0), 0.0, np.stack([-10.0 * np.arange(4, 0, -1) * 0.5, np.zeros(4)], 1))


def straight(speed: float, y: float = 0.0, heading: float = 0.0) -> P.EgoStates:
    """States along a line through (0, y) at `heading` and constant speed."""
    d = np.array([np.cos(heading), np.sin(heading)])
    return P.EgoStates(np.array([0.0, y]) + (speed * TIMES)[:, None] * d, np.tile(speed * d, (P.N_STATES, 1)),
                       np.zeros((P.N_STATES, 2)), np.full(P.N_STATES, heading), np.full(P.N_STATES, speed))


def moved(states: P.EgoStates, y: np.ndarray) -> P.EgoStates:
    xy = states.xy.copy()
    xy[:, 1] = y
    return P.EgoStates(xy, states.velocity, states.accel, states.heading, states.speed)


def box(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def road(left_way: float, route: bool = True, intersection: bool = False) -> LaneView:
    """Two 3.5 m lanes along x: the ego's (centre y = 0, driving +x) and a left one (centre y = 3.5) driving +x
    (`left_way` 1) or -x (-1); the route is the ego lane's centreline; optionally a junction over x in
    [-10, 60]."""
    x = np.linspace(-50.0, 150.0, 401)
    own = np.stack([x, np.zeros_like(x)], 1)
    left = np.stack([x[::int(left_way)], np.full_like(x, 3.5)], 1)
    junction = [box(-10.0, 60.0, -5.0, 10.0)] if intersection else []
    view = LaneView.of_centrelines([own, left], [box(-50, 150, -1.75, 1.75), box(-50, 150, 1.75, 5.25)], junction)
    return LaneView(view.start, view.end, view.yaw, view.lane, view.polygons, view.intersections,
                    own if route else None)


# -- history comfort: its past, as NAVSIM builds it ---------------------------------------------------------

def test_history_is_the_three_past_keyframes_and_this_one_interpolated_every_tenth_less_the_last_sample():
    # keyframes at -1.5, -1.0, -0.5 s (heading 0.15, 0.10, 0.05; ax -3, -2, -1) and now (0, ax 0): heading(t) =
    # -0.1 t and ax(t) = 2 t on [-1.5, 0]; samples -1.5, -1.4, .., -0.2 (arange to 0 is 15, less the last: 14)
    past = np.array([[-2.0e6, 0.2, -9.0, 9.0], [-1.5e6, 0.15, -3.0, 0.0], [-1.0e6, 0.1, -2.0, 0.0],
                     [-0.5e6, 0.05, -1.0, 0.0]])
    heading, lon, lat = X.history(past, (0.0, 0.0))
    t = np.arange(-15, -1) * 0.1
    assert len(heading) == 14
    np.testing.assert_allclose(heading, -0.1 * t, atol=1e-12)
    np.testing.assert_allclose(lon, 2.0 * t, atol=1e-12)
    np.testing.assert_array_equal(lat, np.zeros(14))  # the -2 s keyframe (ay 9) is not NAVSIM's


def test_history_takes_the_keyframes_real_times():
    # keyframes 1.55 s, 1.02 s and 0.49 s back: samples -1.55, -1.45, .., -0.05 (16), less the last: 15
    past = np.array([[-2.0e6, 0.0, 0.0, 0.0], [-1.55e6, 0.0, 1.0, 0.0], [-1.02e6, 0.0, 1.0, 0.0],
                     [-0.49e6, 0.0, 1.0, 0.0]])
    _, lon, _ = X.history(past, (0.0, 0.0))
    assert len(lon) == 15
    assert lon[-1] == pytest.approx(1.0 - 0.34 / 0.49)  # at -0.15 s, between 1 (at -0.49) and 0 (now)
    with pytest.raises(ValueError, match="do not increase"):
        X.history(np.array([[-2e6, 0, 0, 0], [-1e6, 0, 0, 0], [-1.5e6, 0, 0, 0], [-0.5e6, 0, 0, 0]]))


BRAKING = np.array([[-2.0e6, 0.0, -5.0, 0.0], [-1.5e6, 0.0, -5.0, 0.0], [-1.0e6, 0.0, -5.0, 0.0],
                    [-0.5e6, 0.0, -5.0, 0.0]])


@pytest.mark.parametrize("past,expected", [
    (None, 1.0),  # NAVSIM: no past, HC 1
    (np.array([[-2e6, 0, 0, 0], [-1.5e6, 0, 0, 0], [-1e6, 0, 0, 0], [-0.5e6, 0, 0, 0]]), 1.0),
    # -5 m/s^2 held from -1.5 s: the first smoothed samples are -5 < -4.05 (savgol of a constant is the constant)
    (BRAKING, 0.0),
])
def test_history_comfort_known_answers(past, expected):
    history = None if past is None else X.history(past, (-5.0 if past is BRAKING else 0.0, 0.0))
    assert X.history_comfort(straight(10.0), history) == expected


def test_the_human_is_scored_without_a_past_so_history_comfort_is_never_filtered():
    # the expert braked hard in the past: its HC with a past would be 0 and the old filter set the plan's to 1;
    # NAVSIM's human run has no past (HC 1), so the plan keeps its 0
    ego = EgoStatus((10.0, 0.0), (-5.0, 0.0), 0.0, EGO.past_xy)
    expert = np.stack([10.0 * T, np.zeros(6)], 1)
    prepared = P.PreparedFrame.prepare(expert, [], ego, lanes=road(1.0), past_motion=BRAKING)
    ps = P.tracked_states(expert[None], [prepared.initial])[0]
    terms = prepared.extended(ps, prepared.score(expert))
    assert terms.hc == 0.0 and prepared.human is not None and prepared.human.hc == 1.0
    assert terms.filtered(prepared.human).hc == 0.0


# -- driving direction compliance ---------------------------------------------------------------------------

@pytest.mark.parametrize("states,lanes,expected", [
    (straight(10.0), road(-1.0), 1.0),  # in its own (on-route) lane
    (straight(10.0, y=3.5), road(-1.0), 0.0),  # 10 m in 1 s in the oncoming lane (>= 6 m)
    (straight(3.0, y=3.5), road(-1.0), 0.5),  # 3 m (2 .. 6 m)
    (straight(10.0, y=-3.5), road(-1.0), 0.0),  # the shoulder: in no on-route lane, oncoming (10 m)
    (straight(3.0, y=-3.5), road(-1.0), 0.5),
    (straight(1.0, y=-3.5), road(-1.0), 1.0),  # 1 m < 2 m
    (straight(10.0, y=3.5, heading=np.pi), road(-1.0), 0.0),  # turned round in the other lane: not on route
    (straight(10.0, y=3.5), road(1.0), 1.0),  # a same-direction neighbour is on the route's roadblock
    (straight(10.0, y=-3.5), road(-1.0, intersection=True), 1.0),  # 0 .. 30 m inside the junction: skipped
])
def test_driving_direction_known_answers(states, lanes, expected):
    assert X.driving_direction(states, lanes) == expected


# -- lane keeping -----------------------------------------------------------------------------------------------

def lane_change(hold_from: int) -> np.ndarray:
    """y of a change into the left lane: 0 until 0.1 s, 3.5 from state `hold_from`, linear between."""
    return np.interp(np.arange(P.N_STATES), [1, hold_from], [0.0, 3.5])


@pytest.mark.parametrize("y,expected", [
    (np.full(P.N_STATES, 0.3), 1.0),  # 0.3 m from the route: within 0.5
    (np.full(P.N_STATES, 3.5), 0.0),  # centred in the same-direction neighbour: 3.5 m off for 3 s
    (lane_change(10), 0.0),  # a change completed in 1 s, then held: 20+ states off
    (np.where(np.arange(P.N_STATES) < 19, 0.8, 0.0), 1.0),  # 19 states off (< 20 = ceil(2 / 0.1)), then back
    (np.where(np.arange(P.N_STATES) < 20, 0.8, 0.0), 0.0),  # 20 states off
])
def test_lane_keeping_is_measured_against_the_route_centreline(y, expected):
    assert X.lane_keeping(moved(straight(10.0), y), road(1.0)) == expected


def test_lane_keeping_in_the_junction_is_skipped_and_without_a_route_the_nearest_same_way_lane_stands_in():
    assert X.lane_keeping(moved(straight(10.0), np.full(P.N_STATES, 3.5)), road(1.0, intersection=True)) == 1.0
    assert X.lane_keeping(moved(straight(10.0), np.full(P.N_STATES, 3.5)), road(1.0, route=False)) == 1.0


def straight_lane(token: str, x0: float, x1: float, y: float, outgoing: tuple[str, ...] = ()) -> Lane:
    xs = np.linspace(x0, x1, 21)
    line = np.stack([xs, np.full_like(xs, y), np.zeros_like(xs)], 1)
    return Lane(token, MapPolygon(box(x0, x1, y - 1.75, y + 1.75)), line, outgoing=outgoing)


def turn_lane(token: str) -> Lane:
    a = np.linspace(-np.pi / 2, 0.0, 21)  # a quarter circle of radius 20 about (40, 20): (40, 0) to (60, 20)
    line = np.stack([40.0 + 20.0 * np.cos(a), 20.0 + 20.0 * np.sin(a), a + np.pi / 2], 1)
    return Lane(token, None, line, connector=True)


def test_the_route_follows_the_ego_lanes_successors_the_logged_future_takes():
    lanes = (straight_lane("a", 0.0, 40.0, 0.0, ("b", "c")), straight_lane("b", 40.0, 80.0, 0.0),
             turn_lane("c"), straight_lane("d", 0.0, 80.0, 3.5))
    lane_map = LaneMap("x", lanes, (), (), (), (), DrivableArea("x"))
    ahead = np.stack([10.0 * T, np.zeros(6)], 1)
    route = route_centreline(lane_map, (10.0, 0.0, 0.0), ahead)
    assert route is not None and route[:, 1].max() == 0.0 and route[-1, 0] == 70.0  # a then b, ego frame
    turning = route_centreline(lane_map, (10.0, 0.0, 0.0), [[10.0, 0.0], [25.0, 0.0], [40.0, 5.0], [48.0, 15.0]])
    assert turning is not None and turning[-1].tolist() == pytest.approx([50.0, 20.0])  # a then c
    other = route_centreline(lane_map, (10.0, 3.5, 0.0), ahead)
    assert other is not None and other[:, 1].max() == 0.0 and other[0, 0] == -10.0  # d, from its start
    assert route_centreline(lane_map, (10.0, 0.0, np.pi), ahead) is None  # no lane runs that way
    assert route_centreline(lane_map, (10.0, 9.0, 0.0), ahead) is None  # off every lane


# -- NC / TTC: multiple lanes and the intersection clause -------------------------------------------------------

@pytest.mark.parametrize("y,expected", [
    (0.0, False),  # every corner in the ego lane
    (1.75, True),  # across the lane line: corners in two lanes, none holding all four
    (-1.75, False),  # half on the shoulder: one lane holds corners (non-drivable is DAC's business)
    (3.5, False),  # inside the left lane
])
def test_in_multiple_lanes_known_answers(y, expected):
    s = straight(10.0, y=y)
    assert road(1.0).multiple_lanes(box_corners(s.xy, s.heading)).tolist() == [expected] * P.N_STATES


def alongside(offset: float) -> list[AgentBoxes]:
    """An agent seen at 0.5 s only, `offset` m behind the ego's centre then and 1.6 m to its left (the boxes
    overlap)."""
    return [AgentBoxes(np.array([[5.0 + offset, 1.6]]), np.array([[4.0, 1.8]]), np.zeros(1), ("vehicle",)),
            *[AgentBoxes.empty()] * 5]


@pytest.mark.parametrize("junction,expected_ttc", [(False, 1.0), (True, 0.0)])
def test_ttc_intersection_clause(junction, expected_ttc):
    # the first projected contact (NAVSIM's order: state, then projection) is the state at 0.2 s projected 0.3 s
    # onto the agent at 0.5 s: 2 m on and 1.6 m aside of the state, 38.7 degrees off the heading: neither ahead
    # (< 30) nor behind (> 150). NAVSIM: at fault only when the ego is in multiple lanes, off the road, or in an
    # intersection; else the track is ignored from then on. NC: the side contact is not at fault either way.
    expert = np.stack([10.0 * T, np.zeros(6)], 1)
    lanes = road(1.0, intersection=junction)
    result = P.PreparedFrame.prepare(expert, alongside(-1.0), EGO, lanes=lanes).score(expert)
    assert (result.nc, result.ttc) == (1.0, expected_ttc)
    assert P.pdm_score(expert, expert, alongside(-1.0), EGO, lanes=lanes) == result
    s = straight(10.0)
    side, ttc_side = astray(s, np.zeros(P.N_STATES, bool), expert, lanes)
    assert not side.any() and ttc_side.all() == junction


def test_the_readers_past_motion_is_each_past_keyframes_own_logged_state(small_world):
    from pytest_drivedegrade.data import geometry as geo
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    frames = list(NuScenesReader(small_world, split="all").frames(agents=False))
    by_scene: dict[str, list] = {}
    for f in frames:
        by_scene.setdefault(f.scene_token, []).append(f)
    checked = 0
    for scene in by_scene.values():
        for k, f in enumerate(scene):
            assert f.past_motion is not None and f.past_motion.shape == (4, 2 + 2)
            for n in range(1, 5):
                row = f.past_motion[4 - n]
                i = max(k - n, 0)
                assert row[0] == (scene[i].timestamp - f.timestamp) - (n - (k - i)) * 500_000
                assert row[1] == pytest.approx(float(geo.wrap_angle(scene[i].pose[2] - f.pose[2])), abs=1e-12)
                assert tuple(row[2:]) == scene[i].ego.acceleration
                checked += 1
    assert checked >= 4 * 20


# -- the ego box as a scoring setting ----------------------------------------------------------------------------

def parked(y: float) -> list[AgentBoxes]:
    """A car standing at (10, y), 4 m x 1.8 m, at every waypoint time."""
    return [AgentBoxes(np.array([[10.0, y]]), np.array([[4.0, 1.8]]), np.zeros(1), ("vehicle",)) for _ in T]


@pytest.mark.parametrize("box,expected", [("nuscenes", (1.0, 1.0)), ("pacifica", (0.0, 0.0))])
def test_the_ego_box_is_a_scoring_setting(box, expected):
    # a car parked with its near side 1.1 m from the ego's path: the nuScenes box (half width 0.925 m) passes it,
    # NAVSIM's Pacifica (half width 1.1485 m) scrapes it; a standing agent is always the ego's fault (NC 0) and
    # the projected boxes meet it ahead (TTC 0)
    from pytest_drivedegrade.metrics.pdms.constants import EGO_BOXES

    expert = np.stack([10.0 * T, np.zeros(6)], 1)
    size = EGO_BOXES[box]
    result = P.PreparedFrame.prepare(expert, parked(2.0), EGO, ego_size=size).score(expert)
    assert (result.nc, result.ttc) == expected
    assert P.pdm_score(expert, expert, parked(2.0), EGO, ego_size=size) == result
    assert P.PreparedFrame.prepare(expert, parked(2.0), EGO).score(expert) == \
        P.PreparedFrame.prepare(expert, parked(2.0), EGO, ego_size=EGO_BOXES["nuscenes"]).score(expert)


@pytest.mark.parametrize("seed", range(20))
def test_the_route_fit_over_nearby_segments_equals_the_fit_over_all(seed):
    rng = np.random.default_rng(seed)
    route = np.cumsum(rng.normal(0.0, 4.0, (rng.integers(2, 200), 2)), axis=0)
    pts = rng.uniform(-30.0, 30.0, (31, 2)) * rng.choice([0.1, 1.0, 5.0])
    view = road(1.0)
    view = LaneView(view.start, view.end, view.yaw, view.lane, view.polygons, view.intersections, route)
    got = view._route_fit(pts)
    want = LaneView._segments_fit(pts, route[:-1], route[1:])
    assert got[0].tobytes() == want[0].tobytes() and got[1].tobytes() == want[1].tobytes()


# -- checked against NAVSIM v2.2's own scorer (benchmarks/navsim_reference.py) ---------------------------------

def test_centre_lon_accel_is_navsims_shift_to_the_pacificas_centre():
    # get_acceleration_shifted with displacement (1.461, 0): a_x + 1.461 w^2 + 1.461 alpha, a_y unchanged; NAVSIM's
    # t = 0 state has no yaw rate, so w = (0, 0.5, 0.5) and alpha = (0, 5, 0) whatever the tracker's w[0]
    lon = np.array([1.0, 1.0, 1.0])
    got = X.centre_lon_accel(lon, np.array([0.3, 0.5, 0.5]))
    np.testing.assert_allclose(got, [1.0, 1.0 + 1.461 * 0.25 + 1.461 * 5.0, 1.0 + 1.461 * 0.25], rtol=0, atol=1e-12)
    assert X.HC_CENTRE_M == 1.461


def _turning(base: float, rate_per_state: float) -> P.EgoStates:
    """Straight states (heading 0, as the test needs only the accelerations) with longitudinal acceleration
    `base` and the tracker's yaw rate growing by `rate_per_state` each state."""
    s = straight(10.0)
    accel = np.zeros((P.N_STATES, 2))
    accel[:, 0] = base
    return P.EgoStates(s.xy, s.velocity, accel, s.heading, s.speed, rate_per_state * np.arange(P.N_STATES))


@pytest.mark.parametrize("rate,expected", [
    (0.0, 1.0),  # no turn: 1 m/s^2 throughout
    (0.02, 1.0),  # w up to 0.6 rad/s, alpha 0.2: at most 1 + 1.461 (0.36 + 0.2) = 1.82 < 2.40 m/s^2
    (0.04, 0.0),  # w up to 1.2 rad/s, alpha 0.4: 1 + 1.461 (1.44 + 0.4) = 3.69 > 2.40 (the code before: 1)
])
def test_history_comfort_reads_the_longitudinal_acceleration_at_navsims_centre(rate, expected):
    past = np.array([[-2e6, 0, 1.0, 0], [-1.5e6, 0, 1.0, 0], [-1e6, 0, 1.0, 0], [-0.5e6, 0, 1.0, 0]])
    assert X.history_comfort(_turning(1.0, rate), X.history(past, (1.0, 0.0))) == expected


def test_tracked_states_carry_the_trackers_yaw_rate():
    from pytest_drivedegrade.metrics import tracking

    plan = np.stack([10.0 * T, 0.3 * T**2], 1)
    start = tracking.InitialState(10.0)
    ps = P.tracked_states(plan[None], [start])[0]
    assert ps.yaw_rate is not None
    np.testing.assert_array_equal(ps.yaw_rate, tracking.track_plans(plan[None], [start]).yaw_rate[0])


def test_epdms_ttc_looks_only_at_states_whose_longest_projection_ends_in_the_horizon():
    # NAVSIM v2.2: n_proposal_steps_to_evaluate = num_poses - 9: states 0 .. 21 of six poses' 31, 0 .. 31 of 41
    def contact(state: int) -> P.Contact:
        return P.Contact(state, state, np.array([12.0 + state, 0.0]), np.array([4.0, 1.8]), 0.0, "vehicle",
                         np.array([5.0, 0.0]))

    contacts = [contact(i) for i in (0, 21, 22, 30)]
    assert [c.state for c in X.ttc_v2_window(contacts, 31)] == [0, 21]
    assert [c.state for c in X.ttc_v2_window(contacts, 41)] == [0, 21, 22, 30]
    # an agent ahead met only from state 22 on: NAVSIM v1.1 (the PDMS) fails TTC, v2.2 (the EPDMS) does not
    s, late = straight(10.0), [contact(22)]
    ahead = np.zeros(P.N_STATES, bool)
    assert P.ttc_score(s, late, ahead) == 0.0
    assert P.ttc_score(s, X.ttc_v2_window(late, P.N_STATES), ahead) == 1.0


def test_route_progress_known_answers():
    from pytest_drivedegrade.metrics.pdms.route import route_progress

    route = np.array([[-5.0, 0.0], [10.0, 0.0], [10.0, 10.0]])  # 15 m along x, then 10 m along y
    assert route_progress(route, np.zeros(2), np.array([11.0, 5.0])) == pytest.approx(15.0)  # 20 - 5
    assert route_progress(route, np.zeros(2), np.array([-9.0, 0.0])) == 0.0  # behind: clamped, at least 0
    assert route_progress(route, np.zeros(2), np.array([10.0, 30.0])) == pytest.approx(20.0)  # clamped at the end
    repeated = np.array([[-5.0, 0.0], [0.0, 0.0], [0.0, 0.0], [10.0, 0.0]])  # a repeated point: no NaN
    assert route_progress(repeated, np.zeros(2), np.array([4.0, 1.0])) == pytest.approx(4.0)


def test_epdms_progress_is_measured_along_the_route_centreline():
    # the expert drives straight on; the route bends left after 10 m (a junction's connector): NAVSIM measures the
    # plan's and the expert's progress along the route, so a plan following the bend makes full progress
    expert = np.stack([5.0 * T, np.zeros(6)], 1)
    x = np.linspace(-20.0, 10.0, 31)
    bend = np.array([[10.0 + 10 * np.sin(a), 10 - 10 * np.cos(a)] for a in np.linspace(0, np.pi / 2, 20)[1:]])
    route = np.vstack([np.stack([x, np.zeros_like(x)], 1), bend])
    view = road(1.0)
    lanes = LaneView(view.start, view.end, view.yaw, view.lane, view.polygons, view.intersections, route)
    ego = EgoStatus((5.0, 0.0), (0.0, 0.0), 0.0, EGO.past_xy)
    prepared = P.PreparedFrame.prepare(expert, [], ego, lanes=lanes)
    ps = P.tracked_states(expert[None], [prepared.initial])[0]
    from pytest_drivedegrade.metrics.pdms.route import route_progress

    assert prepared.route_expert_m == pytest.approx(route_progress(route, ps.xy[0], ps.xy[-1]))
    assert prepared.extended(ps, prepared.score(expert)).ep == 1.0  # the expert against itself
    plan = np.stack([5.0 * T, 0.4 * T**2], 1)  # drifting left into the bend: more progress along the route
    pp = P.tracked_states(plan[None], [prepared.initial])[0]
    result = prepared.score(plan)
    on_route = route_progress(route, pp.xy[0], pp.xy[-1])
    assert prepared.extended(pp, result).ep == pytest.approx(min(on_route / prepared.route_expert_m, 1.0))
    assert prepared.extended(pp, result).ep != pytest.approx(min(result.progress_m / result.expert_progress_m, 1.0))
