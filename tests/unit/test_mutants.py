"""Issue 20, "Tests that would not notice": single-point changes to last round's code that left the whole suite
passing. Each test here is a known answer that one of those changes breaks (the change is named in its
docstring); none restates the code it checks.

The PDMS tests stay on the functions whose contract does not depend on how a plan becomes states (comfort on
given states, TTC and fault on given boxes, the DAC footprint), so they hold whatever tracker makes the states.
"""

from __future__ import annotations

import numpy as np
import pytest

from pytest_drivedegrade.constants import EGO_LENGTH, EGO_WIDTH
from pytest_drivedegrade.corruptions.ego import perturb
from pytest_drivedegrade.data.frame import AgentBoxes, EgoStatus
from pytest_drivedegrade.metrics import pdms as P  # noqa: N812 - as in test_pdms
from pytest_drivedegrade.metrics.pdms import reference as R  # noqa: N812
from pytest_drivedegrade.metrics.pdms.motion import EgoStates
from pytest_drivedegrade.metrics.pdms.rules import Contact, ttc_score
from pytest_drivedegrade.scoring import intervals as iv
from pytest_drivedegrade.scoring.analyse import run_verdict
from pytest_drivedegrade.scoring.records import Axes

T = np.arange(1, 7) * 0.5
CAR = (4.5, 1.9)
IN_LANE = np.zeros(P.N_STATES, dtype=bool)


def path(x, y=None) -> np.ndarray:
    return np.stack([np.asarray(x, float), np.zeros(6) if y is None else np.asarray(y, float)], 1)


def boxes_over_time(x0: float, vx: float, y: float = 0.0, size=CAR) -> list[AgentBoxes]:
    """One vehicle driving along x at `vx`, annotated at the six waypoint times."""
    return [AgentBoxes(np.array([[x0 + vx * t, y]]), np.array([size], float), np.array([0.0]), ("vehicle",))
            for t in T]


# -- PDMS: comfort ----------------------------------------------------------------------------------------------

def lateral_states(jerk: float) -> EgoStates:
    """10 m/s straight ahead, with a lateral acceleration flipping sign every state and growing by `jerk` m/s^3:
    its fitted lateral acceleration stays small (the flips cancel), its magnitude grows at `jerk` m/s^3, and
    nothing else moves (no longitudinal acceleration, no yaw)."""
    t, n = P.TIMES, P.N_STATES
    ay = (-1.0) ** np.arange(n) * jerk * t
    return EgoStates(np.stack([10 * t, np.zeros(n)], 1), np.stack([np.full(n, 10.0), np.zeros(n)], 1),
                     np.stack([np.zeros(n), ay], 1), np.zeros(n), np.full(n, 10.0))


def test_a_jerk_of_10_m_per_s3_is_uncomfortable_and_5_is_not():
    """Mutant: the jerk bound 8.37 -> 83.7. The acceleration's magnitude growing at 10 m/s^3 (every other comfort
    signal inside its bound) fails comfort on the jerk alone; at 5 m/s^3 it is comfortable."""
    fast, slow = P.comfort_terms(lateral_states(10.0)), P.comfort_terms(lateral_states(5.0))
    assert fast["jerk"].min() > 9.0 and fast["jerk"].max() < 11.0
    assert np.abs(fast["lat_accel"]).max() < 4.89 and np.abs(fast["lon_jerk"]).max() == 0.0
    assert P.is_comfortable(lateral_states(10.0)) == 0.0
    assert P.is_comfortable(lateral_states(5.0)) == 1.0 and slow["jerk"].max() < 5.5


# -- PDMS: TTC on given states and boxes ----------------------------------------------------------------------

def test_ttc_fails_on_the_0_9_s_projection_alone():
    """Mutant: TTC projections (0, .3, .6, .9) -> (0, .3, .6). The ego brakes at 2 m/s^2 from 10 m/s behind a
    lead at 6 m/s and keeps 0.6 m at its closest (t = 2 s). Projected on at constant speed for d seconds from the
    state d earlier, it overshoots its true position by d^2 m: 0.81 m at 0.9 s (a hit), 0.36 m at 0.6 s (none).
    So the only contact is the one projected 0.9 s from t = 1.1 s, and TTC fails on it alone."""
    states = P.interpolate(path(10.0 * T - T**2), (10.0, 0.0))
    lead = boxes_over_time(8.89, 6.0)
    ids, velocities = P.agent_tracks(lead)
    contacts = list(R.projections(states, lead, ids))
    assert [c.state for c in contacts] == [11]  # t = 1.1 s, projected onto the 2.0 s boxes
    assert ttc_score(states, contacts, IN_LANE) == 0.0
    assert P.no_at_fault_collisions(states, lead, ids, velocities, IN_LANE) == 1.0  # it never touches the lead
    farther = boxes_over_time(9.89, 6.0)  # 1.6 m at the closest: beyond every projection
    assert list(R.projections(states, farther, P.agent_tracks(farther)[0])) == []


# -- PDMS: fault --------------------------------------------------------------------------------------------------

def moving_contact(x: float, velocity=(5.0, 0.0), state: int = 10) -> Contact:
    return Contact(state, 1, np.array([x, 0.0]), np.array(CAR), 0.0, "vehicle", np.asarray(velocity, float))


def test_the_egos_front_bumper_into_a_moving_car_is_at_fault():
    """Mutant: a front-bumper contact with a moving agent no longer at fault (at_fault without its front-contact
    clause; both the reference form and the prepared frame judge through it). The ego at 10 m/s, in its lane,
    runs its nose into a car ahead driving at 5 m/s: at fault, NC 0, in both forms; a car alongside, its rear half
    over the ego's side and clear of the nose (a side contact in lane), is not."""
    ego = P.interpolate(path(10.0 * T), (10.0, 0.0))
    nose_in = 10.0 + EGO_LENGTH / 2 + CAR[0] / 2 - 0.2  # the car's rear 0.2 m inside the ego's nose at t = 1 s
    assert P.at_fault(ego, moving_contact(nose_in), IN_LANE, static=False)
    beside = Contact(10, 1, np.array([9.0, (EGO_WIDTH + CAR[1]) / 2 - 0.1]), np.array(CAR), 0.0, "vehicle",
                     np.array([10.0, 0.0]))
    assert not P.at_fault(ego, beside, IN_LANE, static=False)
    slower = boxes_over_time(nose_in - 5.0 * 1.0, 5.0)  # at t = 1 s it is where `moving_contact` put it
    ids, velocities = P.agent_tracks(slower)
    assert np.allclose(velocities[1], [5.0, 0.0])  # tracked as moving: not the standing-agent rule
    assert P.no_at_fault_collisions(ego, slower, ids, velocities, IN_LANE) == 0.0
    prepared = P.PreparedFrame.prepare(path(10.0 * T), slower, (10.0, 0.0))
    contacts = list(prepared.collisions(ego))
    assert contacts and P.collision_score(ego, contacts, IN_LANE) == 0.0


# -- PDMS: the DAC footprint --------------------------------------------------------------------------------------

def test_the_dac_footprint_is_the_whole_ego_box():
    """Mutant: the footprint's front-right corner moved to the box's centre line. At the origin heading 0 the
    corners are (+-L/2, +-W/2) in the order front-left, rear-left, rear-right, front-right; a road with a notch
    cut at the front right (x > 0, y < -W/4) puts that corner alone off the road."""
    half = np.array([EGO_LENGTH, EGO_WIDTH]) / 2
    corners = P.box_corners(np.zeros((1, 2)), np.zeros(1))[0]
    np.testing.assert_allclose(corners, [[half[0], half[1]], [-half[0], half[1]], [-half[0], -half[1]],
                                         [half[0], -half[1]]], atol=1e-12)
    standing = P.interpolate(np.zeros((6, 2)), (0.0, 0.0))

    def notched(p: np.ndarray) -> np.ndarray:
        return ~((p[:, 0] > 0) & (p[:, 1] < -EGO_WIDTH / 4))

    assert P.off_road(standing, notched).all()
    assert not P.off_road(standing, lambda p: np.ones(len(p), bool)).any()


# -- intervals ------------------------------------------------------------------------------------------------------

def test_the_joint_bootstrap_pairs_each_cell_with_clean_on_the_same_frames():
    """Mutant: the joint bootstrap unpaired (clean's resample taken from another row). Clean's errors vary over
    frames (0.2 .. 2.2 m) and the cell's are exactly 1.25 x clean's on every frame, so every paired resample
    gives retention 0.8 exactly; an unpaired one would scatter around it."""
    clean = np.linspace(0.2, 2.2, 40)
    res = iv.resample_cells(clean, {"fog-s5": [clean * 1.25]}, n_resamples=300, seed=3)
    np.testing.assert_allclose(res.retention["fog-s5"], 0.8, rtol=0, atol=1e-12)


def test_a_verdict_with_92_percent_confidence_is_borderline():
    """Mutant: the borderline cut 0.95 -> 0.90. 92 of 100 resamples keep the label (quality above the flat
    line in 92): borderline; 97 of 100: not."""
    axes = Axes(quality=0.97, removal=0.99, gap=-0.02, mean=0.98)
    for above, borderline in ((92, True), (97, False)):
        quality = np.r_[np.full(above, 0.97), np.full(100 - above, 0.90)]
        per = iv.AxisResamples(quality=quality, removal=np.full(100, 0.99))
        v = run_verdict(axes, per, metric="l2", flat=0.95)
        assert v.label == "not-shown-to-use-cameras" and v.confidence == pytest.approx(above / 100)
        assert v.borderline is borderline and ("Borderline" in v.text) is borderline


# -- the ego ladder -------------------------------------------------------------------------------------------------

def test_ego_noise_moves_past_positions_by_its_own_sigma():
    """Mutant: past positions drawn with the yaw-rate sigma (5x smaller). Over 300 frames x 4 points x 2
    coordinates the past-position noise at S5 has a standard deviation of 0.8 m (within 6 %), at S1 0.05 m."""
    ego = EgoStatus((5.0, 0.0), (0.0, 0.0), 0.0, np.zeros((4, 2)))
    for severity, sigma in ((5, 0.8), (1, 0.05)):
        moved = np.stack([perturb(ego, None, "ego_noise", severity, seed=0, frame=f"f{i}")[0].past_xy
                          for i in range(300)])
        assert moved.std() == pytest.approx(sigma, rel=0.06)


# -- the comfort filters ------------------------------------------------------------------------------------------

def test_savitzky_golay_known_answers():
    """The comfort filters without scipy: the textbook 5-point quadratic smoothing weights (-3, 12, 17, 12, -3) /
    35 and derivative weights (-2, -1, 0, 1, 2) / (10 dt) in the interior, and exactness on polynomials up to the
    fit's order at every sample, the ends included (mode 'interp')."""
    y = np.random.default_rng(0).normal(size=P.N_STATES)
    mid = np.arange(2, P.N_STATES - 2)
    window = np.stack([y[mid + k] for k in range(-2, 3)], 1)
    np.testing.assert_allclose(P.savgol(y, 5, 2)[mid], window @ np.array([-3, 12, 17, 12, -3]) / 35, atol=1e-12)
    np.testing.assert_allclose(P.savgol(y, 5, 2, 1)[mid], window @ np.array([-2, -1, 0, 1, 2]) / (10 * P.SIM_DT),
                               atol=1e-9)
    t = P.TIMES
    cubic = 1.0 - 2.0 * t + 0.5 * t**2 + 0.3 * t**3
    np.testing.assert_allclose(P.savgol(cubic, 5, 3, 2), t * 1.8 + 1.0, atol=1e-8)
    def quadratic(at: np.ndarray) -> np.ndarray:
        return 2.0 + 3.0 * at - 0.7 * at**2

    for window_size in (5, 15, P.N_STATES):
        np.testing.assert_allclose(P.savgol(quadratic(t), window_size, 2), quadratic(t), atol=1e-9)
        np.testing.assert_allclose(P.savgol(quadratic(t), window_size, 2, 1), 3.0 - 1.4 * t, atol=1e-8)
    # an even window's middle lies half a sample on: its interior gives the polynomial there, the ends the fit
    inner = slice(4, P.N_STATES - 4)
    np.testing.assert_allclose(P.savgol(quadratic(t), 8, 2)[inner], quadratic(t + P.SIM_DT / 2)[inner], atol=1e-9)
    np.testing.assert_allclose(P.savgol(quadratic(t), 8, 2)[:4], quadratic(t)[:4], atol=1e-9)
