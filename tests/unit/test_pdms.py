"""The PDMS-like score (spec 3) on hand-made frames with known answers, its building blocks against
references, the expert on the world, and properties over random frames."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pytest_drivedegrade.constants import EGO_LENGTH
from pytest_drivedegrade.data.frame import AgentBoxes
from pytest_drivedegrade.data.maps import DrivableArea, MapPolygon
from pytest_drivedegrade.metrics import pdms as P  # noqa: N812 - P for the score module, as in the paper

T = np.arange(1, 7) * 0.5  # waypoint times
CAR = (4.5, 1.9)


def path(x, y=None) -> np.ndarray:
    return np.stack([np.asarray(x, float), np.zeros(6) if y is None else np.asarray(y, float)], 1)


def braking(v: float, a: float) -> np.ndarray:
    """Distance along x at the waypoint times, from speed v with constant acceleration a (stopping at 0)."""
    ts = np.minimum(T, v / -a) if a < 0 else T
    return v * ts + 0.5 * a * ts**2


def agents(*tracks) -> list[AgentBoxes]:
    """Per waypoint time, the boxes of the given tracks; a track is (x(t), y(t), yaw, size, category) with x, y
    arrays over the six times (NaN: not annotated then)."""
    out = []
    for k in range(6):
        rows = [(x[k], y[k], yaw, size, cat) for x, y, yaw, size, cat in tracks if np.isfinite(x[k])]
        if not rows:
            out.append(AgentBoxes.empty())
            continue
        out.append(AgentBoxes(np.array([[r[0], r[1]] for r in rows]), np.array([r[3] for r in rows], float),
                              np.array([r[2] for r in rows], float), tuple(r[4] for r in rows)))
    return out


def moving(x0, y0, vx, vy=0.0, size=CAR, category="vehicle", yaw=None):
    yaw = float(np.arctan2(vy, vx)) if yaw is None else yaw
    return (x0 + vx * T, y0 + vy * T, yaw, size, category)


#: A two-lane road in the map's frame around an ego standing at (100, 50) heading 0.7 rad: the ego lane
#: (y in [-1.75, 1.75] of the ego frame), the oncoming lane to its left and a 1 m shoulder on the right.
POSE = (100.0, 50.0, 0.7)


def road_area() -> DrivableArea:
    corners = np.array([[-60.0, -2.75], [250.0, -2.75], [250.0, 5.25], [-60.0, 5.25]])
    x, y, yaw = POSE
    c, s = np.cos(yaw), np.sin(yaw)
    ring = np.stack([x + c * corners[:, 0] - s * corners[:, 1], y + s * corners[:, 0] + c * corners[:, 1]], 1)
    return DrivableArea("test-road", (MapPolygon(ring),))


def score(plan, expert, boxes=(), v=10.0, drivable="road"):
    area = road_area() if drivable == "road" else drivable
    return P.pdm_score(plan, expert, list(boxes), (v, 0.0), area, POSE if area is not None else None)


def weighted(r) -> float:
    return r.nc * r.dac * (5 * r.ep + 5 * r.ttc + 2 * r.comfort) / 12


# -- known answers ------------------------------------------------------------------------------------------

def test_the_experts_own_plan_on_a_clear_road_scores_one():
    expert = path(10.0 * T)
    traffic = agents(moving(60.0, 3.5, -10.0), moving(-30.0, 0.0, 10.0),  # oncoming; a car behind, keeping distance
                     (np.full(6, 25.0), np.full(6, -4.5), 0.0, (0.6, 0.6), "pedestrian"))  # on the sidewalk
    r = score(expert, expert, traffic)
    assert (r.nc, r.dac, r.ttc, r.ep, r.comfort, r.pdms) == (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    assert r.map_scored and r.progress_m == pytest.approx(30.0) and r.expert_progress_m == pytest.approx(30.0)


def test_leaving_the_road_zeroes_dac_and_pdms():
    expert = path(10.0 * T)
    plan = path(10.0 * T, [-0.2, -0.8, -1.8, -3.0, -4.2, -5.4])  # drifts right, over the shoulder
    r = score(plan, expert)
    assert r.dac == 0.0 and r.pdms == 0.0 and r.ep == 0.0  # progress counts times nc * dac
    assert r.nc == 1.0 and r.ttc == 1.0
    inside = score(path(10.0 * T, [-0.05, -0.1, -0.15, -0.2, -0.25, -0.3]), expert)  # stays on the asphalt
    assert inside.dac == 1.0


def tracked_end(plan, v: float) -> np.ndarray:
    """Where NAVSIM's tracker takes a plan by 3 s, from (v, 0) m/s."""
    return P.tracked_states(np.asarray(plan)[None], [P.initial_state((v, 0.0))])[0].xy[-1]


def test_stopping_short_scores_progress_against_the_expert():
    expert = path(6.0 * T)  # 18 m
    plan = path(braking(6.0, -3.0))  # stops after 6 m
    r = score(plan, expert, v=6.0)
    stop = tracked_end(plan, 6.0)[0]  # the tracker looks 1 s ahead and lags: it stops late, as NAVSIM's does
    assert 6.0 < stop < 8.5 and r.progress_m == pytest.approx(stop)
    assert r.expert_progress_m == pytest.approx(18.0) and r.ep == pytest.approx(stop / 18.0)
    assert (r.nc, r.dac, r.ttc, r.comfort) == (1.0, 1.0, 1.0, 1.0)
    assert r.pdms == pytest.approx((5 * stop / 18.0 + 5 + 2) / 12)
    overshoot = score(path(braking(6.0, 1.0)), expert, v=6.0)  # farther than the expert: the top, 1
    assert overshoot.ep == 1.0


def test_the_5m_rule_gives_full_progress_when_the_expert_barely_moves():
    creep = path(1.5 * T)  # 4.5 m in 3 s: below the 5 m threshold
    stop = score(path(braking(1.5, -1.5)), creep, v=1.5)
    assert stop.progress_m < 2.0 and stop.expert_progress_m < 5.0 and stop.ep == 1.0
    standing = score(np.zeros((6, 2)), np.zeros((6, 2)), v=0.0)
    assert standing.ep == 1.0 and standing.pdms == 1.0
    off = score(path(1.5 * T, -np.linspace(0.6, 3.6, 6)), creep, v=1.5)  # creeps off the road: nc * dac = 0
    assert off.dac == 0.0 and off.ep == 0.0


def test_swerving_into_a_car_in_the_next_lane_is_an_at_fault_collision():
    expert = path(10.0 * T)
    beside = moving(0.0, 3.5, 10.0)  # alongside in the left lane, same speed
    plan = path(10.0 * T, [0.4, 1.4, 2.6, 3.3, 3.5, 3.5])
    r = score(plan, expert, agents(beside))
    assert r.nc == 0.0 and r.pdms == 0.0 and r.dac == 1.0  # on the road, but across the lane line into it
    assert score(expert, expert, agents(beside)).nc == 1.0  # keeping its lane, nothing happens


def test_running_into_a_car_ahead_is_at_fault_and_fails_ttc():
    expert = path(braking(10.0, -4.0))  # stops 12.5 m on
    lead = (np.full(6, 21.0), np.zeros(6), 0.0, CAR, "vehicle")  # stopped in the lane
    r = score(path(10.0 * T), expert, agents(lead))
    assert r.nc == 0.0 and r.ttc == 0.0 and r.pdms == 0.0
    ok = score(expert, expert, agents(lead))
    assert ok.nc == 1.0 and ok.ttc == 1.0


def test_hitting_a_static_object_halves_nc():
    expert = path(braking(10.0, -3.6))  # stops 13.9 m on, 3.8 m before the barrier
    barrier = (np.full(6, 20.0), np.zeros(6), np.pi / 2, (0.5, 2.0), "other")
    r = score(path(10.0 * T), expert, agents(barrier))
    assert r.nc == 0.5 and r.ttc == 0.0 and r.dac == 1.0
    # 30 m halved against the tracked expert's stop (it stops late: 16 m, not 13.9)
    assert 15.0 < r.expert_progress_m < 17.0 and r.ep == pytest.approx(15.0 / r.expert_progress_m)
    assert r.pdms == pytest.approx(0.5 * (5 * r.ep + 5 * 0.0 + 2 * 1.0) / 12)
    truck = (np.full(6, 20.0), np.zeros(6), 0.0, (7.5, 2.4), "vehicle")  # a standing truck is a vehicle: 0
    assert score(path(10.0 * T), expert, agents(truck)).nc == 0.0
    chosen = P.pdm_score(path(10.0 * T), expert, agents(truck), (10.0, 0.0), static_categories=("vehicle",))
    assert chosen.nc == 0.5  # unless the caller counts standing vehicles as static objects


def test_braking_harder_than_the_comfort_bounds_is_uncomfortable():
    hard = score(path(braking(20.0, -6.0)), path(20.0 * T), v=20.0)  # -6 m/s^2 < -4.05
    assert hard.comfort == 0.0 and hard.nc == 1.0 and hard.dac == 1.0
    assert hard.pdms == pytest.approx(weighted(hard)) and hard.pdms < 1.0
    terms = P.comfort_terms(P.interpolate(path(braking(20.0, -6.0)), (20.0, 0.0)))
    np.testing.assert_allclose(terms["lon_accel"], -6.0, atol=1e-6)
    firm = score(path(braking(20.0, -3.0)), path(20.0 * T), v=20.0)  # -3 m/s^2: within the bounds
    assert firm.comfort == 1.0
    swerve = P.interpolate(path(10.0 * T, [0.5, 2.0, 4.0, 4.5, 3.0, 1.0]), (10.0, 0.0))  # a fast S at 10 m/s
    assert P.is_comfortable(swerve) == 0.0 and P.comfort_terms(swerve)["lat_accel"].max() > 4.89


@pytest.mark.parametrize("radius,rate,comfortable", [(2.5, 1.2, 0.0), (4.0, 0.8, 1.0)])
def test_turning_faster_than_the_yaw_rate_bound_is_uncomfortable(radius, rate, comfortable):
    """Slow tight turns: only the yaw rate (0.95 rad/s) separates them; the lateral acceleration stays low."""
    states = P.interpolate(path(radius * np.sin(rate * T), radius * (1 - np.cos(rate * T))), (radius * rate, 0.0))
    terms = P.comfort_terms(states)
    assert P.is_comfortable(states) == comfortable
    assert np.abs(terms["yaw_rate"]).max() == pytest.approx(rate, abs=0.05)
    assert np.abs(terms["lat_accel"]).max() < 4.0


def test_being_run_into_from_behind_is_not_the_egos_fault():
    expert = path(6.0 * T + 0.5 * 2.0 * T**2)  # accelerates away from the follower
    x = np.where(T <= 1.5, -17.75 + 16.0 * T - 2.25, np.nan)  # a fast follower, annotated for 1.5 s
    follower = (x, np.zeros(6), 0.0, CAR, "vehicle")
    plan = path(braking(6.0, -3.0))  # brakes; at 1.5 s the follower's nose is in its rear
    r = score(plan, expert, agents(follower), v=6.0)
    assert r.nc == 1.0
    # (TTC fails here, as in NAVSIM: projected from 0.6 s, the ego meets the overtaking follower, whose centre
    # at 1.5 s lies ahead of where the ego was at 0.6 s)
    ahead = (np.full(6, 12.0), np.zeros(6), 0.0, CAR, "vehicle")  # driving on into a car ahead instead
    assert score(path(10.0 * T), plan, agents(ahead), v=6.0).nc == 0.0


def test_ttc_projects_the_ego_at_constant_velocity():
    # the ego brakes at 2 m/s^2 behind a slower lead and keeps 0.3 m (tracked: it brakes a little late): no
    # collision, but projected on for 0.9 s at its speed, it would have hit the lead
    plan = path(10.0 * T - T**2)
    lead = moving(9.26, 0.0, 6.0)
    r = score(plan, plan, agents(lead))
    assert r.nc == 1.0 and r.ttc == 0.0
    far = moving(10.26, 0.0, 6.0)  # 1 m more: the projection falls short
    assert score(plan, plan, agents(far)).ttc == 1.0


def test_a_standing_ego_is_never_at_fault():
    states = P.interpolate(np.zeros((6, 2)), (0.0, 0.0))
    crossing = agents(moving(0.0, -8.0, 0.0, 8.0))  # crosses through the standing ego
    ids, vel = P.agent_tracks(crossing)
    assert P.no_at_fault_collisions(states, crossing, ids, vel, np.zeros(P.N_STATES, bool)) == 1.0
    moving_ego = P.interpolate(path(1.0 * T), (1.0, 0.0))
    side = agents(moving(1.5, -8.0, 0.0, 8.0))  # the same car into the side of a creeping ego
    ids, vel = P.agent_tracks(side)
    astray = np.ones(P.N_STATES, bool)
    assert P.no_at_fault_collisions(moving_ego, side, ids, vel, ~astray) == 1.0  # a side contact in lane
    assert P.no_at_fault_collisions(moving_ego, side, ids, vel, astray) == 0.0  # ... while astray


def test_without_a_map_dac_is_not_scored():
    expert = path(10.0 * T)
    plan = path(10.0 * T, [-0.2, -0.8, -1.8, -3.0, -4.2, -5.4])
    r = score(plan, expert, drivable=None)
    assert r.dac == 1.0 and not r.map_scored
    assert r.ep == pytest.approx(30.0 / 30.0, abs=0.05)  # still measured, along the expert's path
    assert score(plan, expert).map_scored


def test_tracks_the_expert_touches_are_not_ignored_as_in_navsim_v1():
    """NAVSIM v1 scores every track (its metric cache starts with no collided tracks): a box overlapping the
    logged ego all along is a collision for the expert's own plan too, and the expert's multiplier is 0."""
    expert = path(10.0 * T)
    ghost = (10.0 * T + 1.0, np.zeros(6), 0.0, CAR, "vehicle")
    r = score(expert, expert, agents(ghost))
    assert r.nc == 0.0 and r.pdms == 0.0 and r.ep == 0.0


# -- building blocks ------------------------------------------------------------------------------------------

def test_interpolation_passes_the_waypoints_and_keeps_constant_acceleration_exact():
    plan = path(8.0 * T + 0.5 * 1.2 * T**2, 0.3 * T)
    s = P.interpolate(plan, (8.0, 0.3))
    np.testing.assert_allclose(s.xy[P.KEY_STATES], plan, atol=1e-9)
    np.testing.assert_allclose(s.xy[0], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(s.velocity[:, 0], 8.0 + 1.2 * P.TIMES, atol=1e-9)
    np.testing.assert_allclose(s.accel, np.tile([1.2, 0.0], (P.N_STATES, 1)), atol=1e-9)
    turn = P.interpolate(path(10.0 * np.sin(T / 2) * 2, 20 * (1 - np.cos(T / 2))), (10.0, 0.0))  # r = 20 m
    assert np.abs(P.comfort_terms(turn)["lat_accel"][5:-5] - 5.0).max() < 0.3  # v^2 / r


@pytest.mark.parametrize("window,poly,deriv", [(31, 2, 0), (8, 2, 0), (5, 2, 1), (5, 3, 2), (31, 2, 1), (15, 2, 1)])
def test_savitzky_golay_matches_scipy(window, poly, deriv):
    from scipy import signal  # in the test extras: the comparison runs, never skipped
    y = np.random.default_rng(window + poly).normal(size=P.N_STATES).cumsum()
    np.testing.assert_allclose(P.savgol(y, window, poly, deriv),
                               signal.savgol_filter(y, window, poly, deriv=deriv, delta=P.SIM_DT), atol=1e-9)


def test_agent_tracks_match_boxes_across_keyframes():
    a = moving(10.0, 0.0, 8.0)
    b = moving(14.0, 3.5, -6.0, size=(4.8, 1.8))
    walker = (np.array([5.0, np.nan, 5.2, 5.4, 5.6, 5.8]), np.full(6, -4.0), 0.0, (0.6, 0.6), "pedestrian")
    boxes = agents(b, walker, a)
    ids, vel = P.agent_tracks(boxes)
    assert ids[0][2] == ids[5][2] and ids[0][0] == ids[5][0] and ids[0][0] != ids[0][2]
    np.testing.assert_allclose(vel[2][-1], [8.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(vel[3][0], [-6.0, 0.0], atol=1e-9)
    assert ids[0][1] != ids[2][1]  # the walker missed one keyframe: a new track, seen first at 1.5 s
    assert np.isnan(vel[0][1]).all()  # seen once: unknown speed
    np.testing.assert_allclose(vel[3][1], [0.4, 0.0], atol=1e-9)


def test_expert_on_the_world_scores_full_marks(tmp_path):
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import write_world

    reader = NuScenesReader(write_world(tmp_path / "w", scenes=2, seed=7, val_images=False), split="all")
    frames = reader.scorable_frames()
    results = [P.frame_pdms(f.gt_future, f, reader.drivable_area(f)) for f in frames]
    assert all(r.map_scored and (r.nc, r.dac, r.ttc, r.ep) == (1.0, 1.0, 1.0, 1.0) for r in results)
    # tracked, as NAVSIM scores it, the expert is comfortable everywhere (on raw waypoints 0.85: spec/README)
    assert all(r.comfort == 1.0 for r in results)
    assert not P.frame_pdms(frames[0].gt_future, frames[0]).map_scored


def contact(x, y, *, track=1, state=10, velocity=(5.0, 0.0), category="vehicle", size=CAR):
    """A contact of the ego state `state` with an agent box centred at (x, y), heading along x."""
    return P.Contact(state, track, np.array([x, y], float), np.array(size, float), 0.0, category,
                     np.array(velocity, float))


def test_the_rules_decide_fault_and_ttc_as_navsim():
    """`rules` on hand-placed contacts of an ego at 10 m/s, at (10, 0) heading 0 at state 10 (t = 1 s)."""
    ego = P.interpolate(path(10.0 * T), (10.0, 0.0))
    standing = P.interpolate(np.zeros((6, 2)), (0.0, 0.0))
    lane, astray = np.zeros(P.N_STATES, bool), np.ones(P.N_STATES, bool)
    front = contact(10.0 + EGO_LENGTH / 2 + 2.25 - 0.1, 0.0)  # its rear in the ego's nose
    side = contact(10.0, 2.0, velocity=(10.0, 0.0))  # alongside, its right edge over the ego's left
    behind = contact(10.0 - 4.4, 0.0)
    assert P.at_fault(ego, front, lane, static=False) and not P.at_fault(standing, front, lane, static=False)
    assert P.at_fault(ego, contact(5.6, 0.0, velocity=(0.0, 0.0)), lane, static=False)  # behind, but standing
    assert P.at_fault(ego, behind, lane, static=True) and not P.at_fault(ego, behind, astray, static=False)
    assert not P.at_fault(ego, side, lane, static=False) and P.at_fault(ego, side, astray, static=False)
    unknown = contact(10.0, 2.0, velocity=(np.nan, np.nan))  # seen once: moving, so a side contact
    assert not P.at_fault(ego, unknown, lane, static=False)
    # a not-at-fault track is ignored from then on; a static object halves NC
    assert P.collision_score(ego, [side, contact(15.0, 0.5, state=15)], lane) == 1.0
    assert P.collision_score(ego, [side, contact(15.0, 0.5, state=15, track=2)], lane) == 0.0
    assert P.collision_score(ego, [contact(15.0, 0.5, state=15, category="other")], lane) == 0.5
    assert P.collision_score(ego, [front], lane, ignore={1}) == 1.0
    # TTC: ahead fails; beside only while astray; behind never
    assert P.ttc_fails(ego, contact(20.0, 0.0), lane)
    assert not P.ttc_fails(ego, side, lane) and P.ttc_fails(ego, side, astray)
    assert not P.ttc_fails(ego, behind, astray)
    assert P.ttc_score(ego, [side, contact(20.0, 0.0)], lane) == 1.0  # the track was ignored at its first contact
    assert P.ttc_score(ego, [side, contact(20.0, 0.0, track=2)], lane) == 0.0


# -- properties -----------------------------------------------------------------------------------------------

coord = st.floats(-40.0, 40.0, allow_nan=False, allow_infinity=False)
waypoints = hnp.arrays(np.float64, (6, 2), elements=coord)
categories = st.sampled_from(["vehicle", "pedestrian", "cyclist", "other"])


@st.composite
def agent_steps(draw):
    n = draw(st.integers(0, 4))
    base = draw(hnp.arrays(np.float64, (n, 2), elements=st.floats(-30.0, 30.0)))
    vel = draw(hnp.arrays(np.float64, (n, 2), elements=st.floats(-10.0, 10.0)))
    size = draw(hnp.arrays(np.float64, (n, 2), elements=st.floats(0.3, 12.0)))
    yaw = draw(hnp.arrays(np.float64, (n,), elements=st.floats(-3.2, 3.2)))
    cats = tuple(draw(st.lists(categories, min_size=n, max_size=n)))
    present = draw(hnp.arrays(np.bool_, (6, n)))
    out = []
    for k in range(6):
        keep = present[k]
        out.append(AgentBoxes(base[keep] + vel[keep] * T[k], size[keep], yaw[keep],
                              tuple(c for c, p in zip(cats, keep) if p)))
    return out


maps = st.one_of(st.none(), st.floats(1.0, 30.0).map(lambda w: (lambda p: np.abs(p[:, 1]) < w)))


@settings(max_examples=150, deadline=None)
@given(waypoints, waypoints, agent_steps(), st.tuples(st.floats(-2.0, 20.0), st.floats(-2.0, 2.0)), maps)
def test_scores_are_bounded_and_multiplicative(plan, expert, boxes, v, drivable):
    r = P.pdm_score(plan, expert, boxes, v, drivable)
    assert r.nc in (0.0, 0.5, 1.0) and r.dac in (0.0, 1.0) and r.ttc in (0.0, 1.0) and r.comfort in (0.0, 1.0)
    assert 0.0 <= r.ep <= 1.0 and 0.0 <= r.pdms <= 1.0
    assert r.pdms == pytest.approx(weighted(r))
    if r.nc == 0.0 or r.dac == 0.0:
        assert r.pdms == 0.0
    assert r.map_scored == (drivable is not None)
    if drivable is None:
        assert r.dac == 1.0


@settings(max_examples=60, deadline=None)
@given(waypoints, agent_steps(), st.tuples(st.floats(0.0, 20.0), st.floats(-1.0, 1.0)), maps)
def test_the_expert_makes_full_progress_unless_multiplied_by_zero(expert, boxes, v, drivable):
    r = P.pdm_score(expert, expert, boxes, v, drivable)
    assert r.ep == (1.0 if r.nc * r.dac > 0 else 0.0)
    assert r.progress_m == r.expert_progress_m


def test_bad_plans_are_refused():
    with pytest.raises(ValueError, match="shape"):
        P.pdm_score(np.zeros((5, 2)), np.zeros((6, 2)), [])
    with pytest.raises(ValueError, match="non-finite"):
        P.pdm_score(np.full((6, 2), np.nan), np.zeros((6, 2)), [])
    assert EGO_LENGTH == pytest.approx(4.084)


# -- the fast path (PreparedFrame): equal to pdm_score -------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(waypoints, waypoints, agent_steps(), st.tuples(st.floats(-2.0, 20.0), st.floats(-2.0, 2.0)), maps)
def test_prepared_frame_scores_exactly_as_pdm_score(plan, expert, boxes, v, drivable):
    assert P.PreparedFrame.prepare(expert, boxes, v, drivable).score(plan) == P.pdm_score(plan, expert, boxes, v,
                                                                                          drivable)


@settings(max_examples=150, deadline=None)
@given(waypoints, agent_steps(), st.tuples(st.floats(-2.0, 20.0), st.floats(-2.0, 2.0)), maps)
def test_the_prepared_experts_own_judgement_is_the_references(expert, boxes, v, drivable):
    """`prepare` judges the expert with the frame's vectorised contacts: the NC and multiplier `pdm_score`
    (contacts found literally) gives the expert as a plan, and the EPDMS's TTC (NAVSIM v2.2's window) of the expert
    judged as a plan."""
    frame = P.PreparedFrame.prepare(expert, boxes, v, drivable)
    as_plan = P.pdm_score(expert, expert, boxes, v, drivable)
    assert frame.human is not None
    assert (frame.human.nc, frame.human.dac) == (as_plan.nc, as_plan.dac)
    arr = np.asarray(expert, dtype=np.float64)
    ps = P.tracked_states(arr[None], [frame.initial])[0]
    assert frame.human.ttc == frame.extended(ps, frame.score_tracked(arr, ps)).ttc
    assert frame.expert_multiplier == as_plan.nc * as_plan.dac


def test_prepared_frame_equals_pdm_score_on_the_world_with_a_local_map(tmp_path):
    """Every frame of a small world, the expert and noisy plans (some leaving the road, some hitting agents):
    the prepared frame (agents flattened, the map cut to the ego's surroundings) gives pdm_score's result."""
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import write_world

    reader = NuScenesReader(write_world(tmp_path / "w", scenes=2, seed=3, val_images=False), split="all")
    rng = np.random.default_rng(0)
    checked = set()
    frames, plans, refs = [], [], []
    for frame in reader.scorable_frames():
        area = reader.drivable_area(frame)
        prepared = P.PreparedFrame.of(frame, area)
        assert isinstance(prepared.drivable, P.LocalDrivable)
        for scale in (0.0, 0.5, 3.0):
            plan = frame.gt_future + rng.normal(0.0, scale, (6, 2))
            fast, ref = prepared.score(plan), P.frame_pdms(plan, frame, area)
            assert fast == ref
            checked.add((fast.nc, fast.dac, fast.ttc))
            frames.append(prepared), plans.append(plan), refs.append(ref)
    assert len(checked) > 1  # not only full marks
    # a cell's plans tracked in one batch (as stream.run_cell scores them), or any part of it: bit-identical
    assert P.score_plans(frames, plans) == refs
    assert P.score_plans(frames[7:30], plans[7:30]) == refs[7:30]


def test_experts_tracked_in_one_batch_prepare_each_frame_as_tracked_alone(tmp_path):
    """`tracked_experts` (every run frame's expert in one batch, as `RunContext.pdms_frame` prepares them) gives
    each frame the bits of tracking its expert alone, so the same preparation and the same judgement of any
    plan (PDMS and EPDMS terms); a frame whose expert cannot be tracked is left out, to raise on its own."""
    import dataclasses

    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import write_world

    reader = NuScenesReader(write_world(tmp_path / "w", scenes=2, seed=5, val_images=False), split="all")
    frames = reader.scorable_frames()
    broken = dataclasses.replace(frames[0], token="broken", gt_future=np.full((6, 2), np.nan))
    batch = P.tracked_experts([*frames, broken])
    assert list(batch) == [f.token for f in frames]
    with pytest.raises(ValueError, match="expert has non-finite waypoints"):
        P.PreparedFrame.of(broken, expert_states=batch.get("broken"))
    rng = np.random.default_rng(2)
    for frame in frames:
        alone = P.tracked_states(P.waypoints(frame.gt_future, "expert")[None], [P.initial_state(frame.ego)])[0]
        for name in ("xy", "velocity", "accel", "heading", "speed"):
            assert getattr(batch[frame.token], name).tobytes() == getattr(alone, name).tobytes(), name
        area, lanes = reader.drivable_area(frame), reader.lane_map(frame)
        single = P.PreparedFrame.of(frame, area, lane_map=lanes)
        shared = P.PreparedFrame.of(frame, area, lane_map=lanes, expert_states=batch[frame.token])
        assert repr((shared.expert_m, shared.expert_multiplier, shared.human, shared.path.tobytes())) == \
            repr((single.expert_m, single.expert_multiplier, single.human, single.path.tobytes()))
        plan = frame.gt_future + rng.normal(0.0, 1.5, (6, 2))
        states = P.tracked_states(plan[None], [single.initial])[0]
        assert repr(shared.judged(plan, states)) == repr(single.judged(plan, states))


def test_local_drivable_agrees_with_the_whole_map_inside_and_outside_its_window():
    area = road_area()
    local = P.LocalDrivable(area, POSE[:2], half=30.0)
    rng = np.random.default_rng(1)
    pts = np.array(POSE[:2]) + rng.uniform(-25, 25, (500, 2))  # inside the window
    np.testing.assert_array_equal(local(pts), area.contains(pts))
    far = np.array(POSE[:2]) + rng.uniform(-300, 300, (200, 2))  # mostly outside: the whole map answers
    np.testing.assert_array_equal(local(far), area.contains(far))


def test_local_drivable_keeps_holes_and_overlapping_polygons():
    square = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 40.0], [0.0, 40.0]])
    hole = np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]])
    area = DrivableArea("holes", (MapPolygon(square, (hole,)), MapPolygon(hole + 5.0)))
    pts = np.random.default_rng(2).uniform(-5, 45, (2000, 2))
    np.testing.assert_array_equal(P.LocalDrivable(area, (20.0, 20.0), half=60.0)(pts), area.contains(pts))
    row = np.column_stack([np.linspace(-5.0, 45.0, 101), np.full(101, 15.0)])  # one line of y: a narrow edge band
    np.testing.assert_array_equal(P.LocalDrivable(area, (20.0, 20.0), half=60.0)(row), area.contains(row))
    assert P.LocalDrivable(area, (20.0, 20.0), half=60.0)(np.zeros((0, 2))).shape == (0,)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 46), scale=st.sampled_from([0.5, 3.0, 6.0]),
       on_bounds=st.booleans())
def test_comfort_judged_stacked_equals_term_by_term(seed, n, scale, on_bounds):
    """`within_comfort` rounds the six signals stacked and compares them at once: the verdict of rounding and
    comparing each alone (as is_comfortable and the EPDMS' history comfort did), values on the bounds and on
    the rounding grid's half steps included."""
    from pytest_drivedegrade.metrics.pdms.motion import within_comfort

    rng = np.random.default_rng(seed)
    signals = {k: rng.normal(0.0, scale, n) for k in P.COMFORT_BOUNDS}
    if on_bounds:
        for k, (lo, hi) in P.COMFORT_BOUNDS.items():
            signals[k][rng.integers(0, n)] = rng.choice([lo, hi, lo + 5e-9, hi - 5e-9, hi + 4.9e-9])
    want = float(all(((np.round(v, 8) > P.COMFORT_BOUNDS[k][0]) & (np.round(v, 8) < P.COMFORT_BOUNDS[k][1])).all()
                     for k, v in signals.items()))
    assert within_comfort(signals) == want
