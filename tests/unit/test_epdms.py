"""EPDMS (spec 4.1, NAVSIM v2): known answers per term on synthetic lanes and hand-made motions, the human filter
and the aggregate, and the prepared frame's terms against the ones built from the reference form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pytest_drivedegrade.data.frame import EgoStatus
from pytest_drivedegrade.metrics import pdms as P  # noqa: N812 - as test_pdms has it
from pytest_drivedegrade.metrics.pdms import extended as X  # noqa: N812
from pytest_drivedegrade.metrics.pdms.lanes import LaneView

TIMES = np.arange(P.N_STATES) * P.SIM_DT
T = np.arange(1, 7) * 0.5


def straight(speed: float, y: float = 0.0, heading: float = 0.0, accel: float = 0.0) -> P.EgoStates:
    """States along a line through (0, y) at `heading`, speed `speed` + `accel` t (not below 0)."""
    v = np.maximum(speed + accel * TIMES, 0.0)
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * P.SIM_DT)])
    d = np.array([np.cos(heading), np.sin(heading)])
    a = np.where(v > 0, accel, 0.0)
    return P.EgoStates(np.array([0.0, y]) + s[:, None] * d, v[:, None] * d, a[:, None] * d,
                       np.full(P.N_STATES, heading), v)


def two_lanes(intersection: bool = False) -> LaneView:
    """A road along x: the ego's lane (centreline y = 0, driving +x) and the oncoming lane (y = 3.5, driving -x),
    3.5 m wide each; optionally an intersection square over x in [-10, 60]."""
    x = np.linspace(-50.0, 150.0, 401)
    own, other = np.stack([x, np.zeros_like(x)], 1), np.stack([x[::-1], np.full_like(x, 3.5)], 1)
    box = lambda y0, y1: np.array([[-50.0, y0], [150.0, y0], [150.0, y1], [-50.0, y1]])  # noqa: E731
    junction = [np.array([[-10.0, -5.0], [60.0, -5.0], [60.0, 10.0], [-10.0, 10.0]])] if intersection else []
    return LaneView.of_centrelines([own, other], [box(-1.75, 1.75), box(1.75, 5.25)], junction)


# -- ddc -------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("speed,expected", [(10.0, 0.0), (3.0, 0.5), (1.0, 1.0)])
def test_driving_in_the_oncoming_lane_scores_ddc_by_the_distance_in_any_second(speed, expected):
    # 1 s window: 11 states, 10 steps: 10 m, 3 m, 1 m driven against the lane
    assert X.driving_direction(straight(speed, y=3.5), two_lanes()) == expected


def test_ddc_is_met_in_the_own_lane_in_intersections_and_not_scored_without_lanes():
    assert X.driving_direction(straight(10.0), two_lanes()) == 1.0
    assert X.driving_direction(straight(10.0, y=3.5, heading=np.pi), two_lanes()) == 1.0  # with that lane's flow
    assert X.driving_direction(straight(10.0, y=3.5), two_lanes(intersection=True)) == 1.0  # 0 .. 30 m: inside
    assert math.isnan(X.driving_direction(straight(10.0), None))


# -- lk --------------------------------------------------------------------------------------------------------

def test_lane_keeping_fails_after_two_seconds_off_the_centreline():
    lanes = two_lanes()
    assert X.lane_keeping(straight(10.0, y=0.3), lanes) == 1.0
    assert X.lane_keeping(straight(10.0, y=0.8), lanes) == 0.0  # 31 states 0.8 m off: 20 in a row
    drift = straight(10.0)
    xy = drift.xy.copy()
    xy[:19, 1] = 0.8  # 19 states off, then back: not 2 s
    assert X.lane_keeping(P.EgoStates(xy, drift.velocity, drift.accel, drift.heading, drift.speed), lanes) == 1.0
    assert X.lane_keeping(straight(10.0, y=0.8), two_lanes(intersection=True)) == 1.0  # 0 .. 30 m skipped
    assert math.isnan(X.lane_keeping(straight(10.0), None))
    # against the oncoming lane's direction its centreline does not count: the ego lane's is 3.2 m away
    assert X.lane_keeping(straight(10.0, y=3.2), lanes) == 0.0


# -- hc and ec --------------------------------------------------------------------------------------------------

def test_history_comfort_pads_the_plan_with_the_past():
    # keyframes 1.5, 1.0, 0.5 s back, as NAVSIM reads them (times us, heading, ax, ay); the -2 s row is unread
    steady = X.history(np.array([[-2e6, 0, 0, 0], [-1.5e6, 0, 0, 0], [-1e6, 0, 0, 0], [-0.5e6, 0, 0, 0]]))
    assert len(steady[0]) == 14 and np.allclose(steady, 0.0, atol=1e-12)
    assert X.history_comfort(straight(10.0), steady) == 1.0
    assert X.history_comfort(straight(10.0, accel=-6.0), steady) == 0.0  # braking beyond -4.05 m/s^2
    # a hard stop in the past is still in the padded window: the plan alone would pass (NAVSIM: 1 without a past)
    stop = X.history(np.array([[-2e6, 0, -6, 0], [-1.5e6, 0, -6, 0], [-1e6, 0, -6, 0], [-0.5e6, 0, -6, 0]]))
    assert X.history_comfort(straight(0.5), None) == 1.0 and X.history_comfort(straight(0.5), stop) == 0.0


def test_extended_comfort_compares_consecutive_plans_over_their_overlap():
    assert math.isnan(X.extended_comfort(straight(10.0), None))
    assert X.extended_comfort(straight(10.0), straight(10.0)) == 1.0
    assert X.extended_comfort(straight(10.0, accel=-3.0), straight(10.0)) == 0.0  # acceleration RMS 3 > 0.7
    assert X.extended_comfort(straight(10.0, accel=-0.5), straight(10.0)) == 1.0


# -- the aggregate and the human filter ------------------------------------------------------------------------

def test_the_aggregate_multiplies_and_weighs_only_scored_terms():
    ones = X.ExtendedTerms(1.0, 1.0, 1.0, math.nan, 1.0, 1.0, 1.0, 1.0)
    assert X.epdms_score(ones, 1.0) == 1.0
    half_ep = X.ExtendedTerms(1.0, 1.0, 0.5, math.nan, 0.5, 1.0, 1.0, 1.0)
    assert X.epdms_score(half_ep, 1.0) == pytest.approx(0.5 * (5 * 0.5 + 5 + 2 + 2 + 2) / 16)
    assert X.epdms_score(half_ep, math.nan) == pytest.approx(0.5 * (5 * 0.5 + 5 + 2 + 2) / 14)  # no ec
    assert X.epdms_score(X.ExtendedTerms(0.0, 1.0, 1.0, math.nan, 1.0, 1.0, 1.0, 1.0), 1.0) == 0.0


def test_the_human_filter_drops_a_rule_the_expert_broke_too():
    plan = X.ExtendedTerms(0.0, 1.0, 0.5, math.nan, 0.7, 0.0, 0.0, 1.0)
    human = X.ExtendedTerms(0.0, 1.0, 0.5, math.nan, 1.0, 1.0, 0.0, 1.0)
    kept = plan.filtered(human)
    assert (kept.nc, kept.ddc, kept.ttc, kept.lk) == (1.0, 0.5, 0.0, 1.0)  # 0 only: a 0.5 is not filtered
    assert X.epdms_score(kept, 1.0) == pytest.approx(0.5 * (5 * 0.7 + 0 + 2 + 2 + 2) / 16)


def test_ep_v2_clips_raw_progress_against_the_multiplied_top():
    assert X.ep_v2(20.0, 0.5, 15.0, 1.0) == 1.0  # v1 would give 10 / 15
    assert X.ep_v2(10.0, 1.0, 20.0, 1.0) == 0.5
    assert X.ep_v2(3.0, 0.0, 4.0, 1.0) == 1.0  # below 5 m: 1 even multiplied by 0 (v1: 0)


# -- the prepared frame ----------------------------------------------------------------------------------------

def test_the_prepared_frames_terms_equal_the_reference_forms():
    ego = EgoStatus((10.0, 0.0), (0.0, 0.0), 0.0, np.stack([-10.0 * np.arange(4, 0, -1) * 0.5, np.zeros(4)], 1))
    lanes, expert = two_lanes(), np.stack([10.0 * T, np.zeros(6)], 1)
    prepared = P.PreparedFrame.prepare(expert, [], ego, lanes=lanes)
    assert prepared.human == X.ExtendedTerms(1.0, 1.0, 1.0, prepared.human.tlc, 1.0, 1.0, 1.0, 1.0)
    change = np.stack([10.0 * T, [0.5, 1.5, 2.8, 3.4, 3.5, 3.5]], 1)  # into the oncoming lane, and held
    for plan in (expert, change, np.stack([6.0 * T, np.zeros(6)], 1)):
        ps = P.tracked_states(plan[None], [P.initial_state(ego)])[0]
        ref = P.pdm_score(plan, expert, [], ego)
        terms = prepared.extended(ps, prepared.score(plan))
        ddc = X.driving_direction(ps, lanes)
        assert terms == X.ExtendedTerms(ref.nc, ref.dac, ddc, terms.tlc, X.ep_v2(ref.progress_m, ref.nc * ddc,
                                        ref.expert_progress_m, 1.0), ref.ttc, X.lane_keeping(ps, lanes),
                                        X.history_comfort(ps, prepared.past))
        assert math.isnan(terms.tlc)
        if plan is change:
            assert terms.ddc < 1.0 and terms.lk == 0.0
