"""Known answers and properties of the planning metrics (pytest_drivedegrade.metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.constants import EGO_LENGTH, EGO_WIDTH
from pytest_drivedegrade.data.frame import AgentBoxes, Command, EgoStatus, Frame
from pytest_drivedegrade.metrics import trajectory as metrics
from pytest_drivedegrade.metrics.trajectory import _ones

STRAIGHT = np.stack([np.arange(1, 7) * 2.0, np.zeros(6)], axis=1)  # 4 m/s straight ahead


def boxes(*rows: tuple[float, float, float, float, float, str]) -> AgentBoxes:
    """AgentBoxes from (x, y, length, width, yaw, category) rows."""
    arr = np.array([r[:5] for r in rows], dtype=float).reshape(-1, 5)
    return AgentBoxes(arr[:, :2], arr[:, 2:4], arr[:, 4], tuple(r[5] for r in rows))


def at_every_step(agent: AgentBoxes) -> tuple[AgentBoxes, ...]:
    return (agent,) * 6


def make_frame(gt: np.ndarray, agents: tuple[AgentBoxes, ...]) -> Frame:
    ego = EgoStatus((4.0, 0.0), (0.0, 0.0), 0.0, np.array([[-8.0, 0], [-6, 0], [-4, 0], [-2, 0]]))
    return Frame("tok", "scene", 0, {}, ego, Command.STRAIGHT, gt, np.ones(6, bool), agents)


# --- L2 and the horizon conventions ----------------------------------------------------------------------


def test_ground_truth_as_prediction_scores_zero() -> None:
    agents = at_every_step(boxes((10.0, 3.0, 4.0, 2.0, 0.3, "vehicle"), (6.0, -2.0, 0.8, 0.8, 0.0, "pedestrian")))
    out = metrics.frame_metrics(STRAIGHT, make_frame(STRAIGHT, agents))
    assert out["l2"] == [0.0] * 6
    assert out["collision"] == [0] * 6 and out["collision_vru"] == [0] * 6
    assert metrics.l2_avg(np.array(out["l2"])) == 0.0


def test_l2_per_step_known_answer() -> None:
    pred = STRAIGHT + np.array([[3.0, 4.0]] * 6) * np.arange(1, 7)[:, None] / 6
    np.testing.assert_allclose(metrics.l2_per_step(pred, STRAIGHT), 5.0 * np.arange(1, 7) / 6)


def test_conventions_on_hand_computed_example() -> None:
    per_step = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    # stp3: mean(1,2)=1.5, mean(1..4)=2.5, mean(1..6)=3.5; uniad: steps 1, 3, 5 -> 2, 4, 6.
    np.testing.assert_allclose(metrics.at_horizons(per_step, "stp3"), [1.5, 2.5, 3.5])
    np.testing.assert_allclose(metrics.at_horizons(per_step, "uniad"), [2.0, 4.0, 6.0])
    assert metrics.l2_avg(per_step) == pytest.approx(2.5)
    assert metrics.l2_avg(per_step, "uniad") == pytest.approx(4.0)


def test_conventions_broadcast_over_frames() -> None:
    per_step = np.array([[1.0, 2, 3, 4, 5, 6], [0, 0, 0, 0, 0, 6]])
    np.testing.assert_allclose(metrics.at_horizons(per_step, "stp3"), [[1.5, 2.5, 3.5], [0, 0, 1]])
    np.testing.assert_allclose(metrics.l2_avg(per_step, "uniad"), [4.0, 2.0])


def test_unknown_convention_names_the_valid_ones() -> None:
    with pytest.raises(ValueError, match="stp3, uniad"):
        metrics.at_horizons(np.zeros(6), "vad")


def test_wrong_shapes_are_rejected() -> None:
    with pytest.raises(ValueError, match=r"\(6, 2\)"):
        metrics.l2_per_step(np.zeros((5, 2)), STRAIGHT)
    with pytest.raises(ValueError):
        metrics.at_horizons(np.zeros(5), "stp3")


# --- box geometry ------------------------------------------------------------------------------------------

HALF_L = EGO_LENGTH / 2
DIAMOND_REACH = math.sqrt(2.0)  # a 2 m x 2 m square rotated 45 degrees reaches sqrt(2) from its centre


@pytest.mark.parametrize(
    ("dx", "expected"),
    [(-0.01, True), (0.0, True), (0.01, False)],
    ids=["overlap", "touch", "miss"],
)
def test_rotated_diamond_against_ego_front(dx: float, expected: bool) -> None:
    """A 45-degree square whose corner reaches the ego's front face: overlaps, touches, misses."""
    centre = (HALF_L + DIAMOND_REACH + dx, 0.3)
    hit = metrics.boxes_overlap((0.0, 0.0), (EGO_LENGTH, EGO_WIDTH), 0.0, [centre], [(2.0, 2.0)], [math.pi / 4])
    assert hit.tolist() == [expected]


@pytest.mark.parametrize(
    ("gap", "expected"), [(-0.05, True), (0.0, True), (0.05, False)], ids=["overlap", "touch", "miss"]
)
def test_rotated_ego_against_axis_aligned_box(gap: float, expected: bool) -> None:
    """The ego turned 90 degrees: its length now runs along y, so a box beside it touches at half the length."""
    centre = (0.0, HALF_L + 0.5 + gap)  # agent 1 m x 1 m, its near edge at HALF_L + gap
    hit = metrics.boxes_overlap((0.0, 0.0), (EGO_LENGTH, EGO_WIDTH), math.pi / 2, [centre], [(1.0, 1.0)], [0.0])
    assert hit.tolist() == [expected]


def test_corner_gap_that_bounding_boxes_would_miss() -> None:
    """Two 45-degree boxes near the ego's corner: axis-aligned bounds overlap, the oriented boxes do not."""
    # Diamond of half-diagonal sqrt(2) placed diagonally off the ego's front-left corner.
    corner = np.array([HALF_L, EGO_WIDTH / 2])
    centre = corner + np.array([1.0, 1.0]) * (DIAMOND_REACH / math.sqrt(2) + 0.05) + np.array([0.3, 0.3])
    args = ((0.0, 0.0), (EGO_LENGTH, EGO_WIDTH), 0.0, [centre], [(2.0, 2.0)], [math.pi / 4])
    assert not metrics.boxes_overlap(*args)[0]
    aabb_half = DIAMOND_REACH
    assert abs(centre[0]) < HALF_L + aabb_half and abs(centre[1]) < EGO_WIDTH / 2 + aabb_half


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-8, 8), y=st.floats(-8, 8), yaw0=st.floats(-4, 4), yaw1=st.floats(-4, 4),
    length=st.floats(0.3, 6), width=st.floats(0.3, 3),
)
def test_overlap_is_symmetric_and_agrees_with_sampling(x, y, yaw0, yaw1, length, width) -> None:
    """Swapping the two boxes gives the same answer; a point of one inside the other implies overlap."""
    a = metrics.boxes_overlap((0, 0), (EGO_LENGTH, EGO_WIDTH), yaw0, [(x, y)], [(length, width)], [yaw1])[0]
    b = metrics.boxes_overlap((x, y), (length, width), yaw1, [(0, 0)], [(EGO_LENGTH, EGO_WIDTH)], [yaw0])[0]
    assert a == b
    # Sample points of box 1 and test them against box 0 directly.
    s, t = np.meshgrid(np.linspace(-0.5, 0.5, 9), np.linspace(-0.5, 0.5, 9))
    u = np.array([math.cos(yaw1), math.sin(yaw1)])
    v = np.array([-u[1], u[0]])
    pts = np.array([x, y]) + (s.ravel() * length)[:, None] * u + (t.ravel() * width)[:, None] * v
    c, sn = math.cos(yaw0), math.sin(yaw0)
    local = pts @ np.array([[c, -sn], [sn, c]])
    inside = (np.abs(local[:, 0]) < HALF_L - 1e-6) & (np.abs(local[:, 1]) < EGO_WIDTH / 2 - 1e-6)
    if inside.any():
        assert a


# --- collision per step ------------------------------------------------------------------------------------


def test_collision_only_where_ground_truth_is_clear() -> None:
    """A car parked 1 m left of the path: swerving into it collides; the GT that drives through it does not count."""
    car = boxes((6.0, 2.0, 4.0, 1.8, 0.0, "vehicle"))
    swerve = STRAIGHT + np.array([0.0, 2.0])
    hits = metrics.collision_per_step(swerve, STRAIGHT, at_every_step(car))
    # The swerving ego (y = 2) overlaps the car while |x - 6| <= 2.042 + 2: waypoints x = 2 .. 10, not 12.
    assert hits.tolist() == [True, True, True, True, True, False]
    # Ground truth that itself collides everywhere cancels every step.
    assert not metrics.collision_per_step(swerve, swerve, at_every_step(car)).any()


def test_collision_uses_agents_of_the_same_future_step() -> None:
    ped_at_step_2 = tuple(
        boxes((6.0, 0.0, 0.6, 0.6, 0.0, "pedestrian")) if i == 2 else AgentBoxes.empty() for i in range(6)
    )
    hits = metrics.collision_per_step(STRAIGHT, STRAIGHT + np.array([0, 5.0]), ped_at_step_2)
    assert hits.tolist() == [False, False, True, False, False, False]


def test_vru_filter_ignores_vehicles() -> None:
    agents = at_every_step(boxes((6.0, 0.0, 4.0, 1.8, 0.0, "vehicle")))
    far = STRAIGHT + np.array([0.0, 10.0])
    assert metrics.collision_per_step(STRAIGHT, far, agents).any()
    assert not metrics.collision_per_step(STRAIGHT, far, agents, categories=("pedestrian", "cyclist")).any()
    out = metrics.frame_metrics(STRAIGHT, make_frame(far, agents))
    assert sum(out["collision"]) > 0 and out["collision_vru"] == [0] * 6


def test_heading_from_step_direction_and_held_when_stopped() -> None:
    plan = np.array([[0.0, 1.0], [0.0, 2.0], [0.0, 2.0], [1.0, 2.0], [1.0, 2.0005], [1.0, 2.0005]])
    np.testing.assert_allclose(metrics.step_headings(plan), [math.pi / 2] * 3 + [0.0] * 3)
    assert metrics.step_headings(np.zeros((6, 2))).tolist() == [0.0] * 6


def test_heading_matters_for_collision() -> None:
    """A sideways plan turns the ego box 90 degrees, so a box that a forward-facing ego would clip is missed."""
    plan = np.stack([np.zeros(6), np.arange(1, 7) * 0.5], axis=1)  # driving left, heading +90 deg
    agent = boxes((1.6, 1.5, 0.5, 0.5, 0.0, "vehicle"))  # beside the left-moving ego's flank
    assert not metrics.collision_per_step(plan, plan + np.array([0, 30.0]), at_every_step(agent))[2]
    hit_if_forward = metrics.boxes_overlap(plan[2], (EGO_LENGTH, EGO_WIDTH), 0.0, [(1.6, 1.5)], [(0.5, 0.5)], [0.0])
    assert hit_if_forward[0]


def test_heading_is_the_step_direction_not_the_bearing_of_the_waypoint() -> None:
    """Waypoints (4, 0), (5, 1), (6, 2), ..: the first step heads 0, every later one 45 degrees, while the third
    waypoint's bearing from the ego is atan(2 / 6) = 18.4 degrees. At (6, 2), heading 45 degrees, the ego box
    (4.084 x 1.85) reaches 2.042 m along the heading and 0.925 m across it: a 0.5 m box turned with it 2.2 m
    ahead touches (2.2 < 2.042 + 0.25), one 1.2 m to the side does not (1.2 > 0.925 + 0.25), though an ego
    facing 0 or 18.4 degrees would hit it."""
    plan = np.array([[4.0, 0.0], [5.0, 1.0], [6.0, 2.0], [7.0, 3.0], [8.0, 4.0], [9.0, 5.0]])
    np.testing.assert_allclose(metrics.step_headings(plan), [0.0] + [math.pi / 4] * 5, atol=1e-12)
    along, across = np.array([1.0, 1.0]) / math.sqrt(2), np.array([-1.0, 1.0]) / math.sqrt(2)
    far = plan + np.array([0.0, 40.0])  # the ground truth is nowhere near the agents
    for offset, expected in ((2.2 * along, True), (1.2 * across, False)):
        centre = tuple(plan[2] + offset)
        agents = tuple(boxes((*centre, 0.5, 0.5, math.pi / 4, "vehicle")) if i == 2 else AgentBoxes.empty()
                       for i in range(6))
        assert metrics.collision_per_step(plan, far, agents).tolist() == [False, False, expected, False, False, False]
    side = [tuple(plan[2] + 1.2 * across)]
    for wrong in (0.0, math.atan2(2.0, 6.0)):
        assert metrics.boxes_overlap(plan[2], (EGO_LENGTH, EGO_WIDTH), wrong, side, [(0.5, 0.5)], [math.pi / 4])[0]


# --- jerk, endpoint shift, energy ----------------------------------------------------------------------------


def test_jerk_of_constant_acceleration_is_zero() -> None:
    t = np.arange(1, 7) * 0.5
    plan = np.stack([3.0 * t + 0.5 * 1.7 * t**2, -0.2 * t + 0.5 * 0.4 * t**2], axis=1)
    assert metrics.jerk(plan) == pytest.approx(0.0, abs=1e-9)


def test_jerk_known_answer() -> None:
    t = np.arange(1, 7) * 0.5
    plan = np.stack([t**3 / 6.0 * 2.0, np.zeros(6)], axis=1)  # x = j t^3 / 6 with j = 2 m/s^3
    assert metrics.jerk(plan) == pytest.approx(2.0)


def test_endpoint_shift() -> None:
    other = STRAIGHT.copy()
    other[-1] += (3.0, -4.0)
    other[0] += (100.0, 0.0)  # earlier waypoints do not matter
    assert metrics.endpoint_shift(other, STRAIGHT) == pytest.approx(5.0)


def test_bit1_density_known_answers() -> None:
    zeros = np.zeros((4, 5, 3), np.uint8)
    ones = np.full((4, 5, 3), 255, np.uint8)
    assert metrics.bit1_density({"A": zeros}) == 0.0
    assert metrics.bit1_density({"A": ones}) == 1.0
    assert metrics.bit1_density({"A": zeros, "B": ones}) == 0.5
    assert metrics.bit1_density({"A": np.full((2, 2, 3), 0b0000_0111, np.uint8)}) == pytest.approx(3 / 8)
    assert metrics.bit1_density({}) == 0.0


@settings(max_examples=60, deadline=None)
@given(st.binary(min_size=1, max_size=3000))
def test_bit1_density_matches_unpackbits(data: bytes) -> None:
    """Exactly: the popcount of whole 64-bit words summed by OpenCV, the tail bytes by table."""
    arr = np.frombuffer(data, np.uint8)
    assert _ones(arr) == int(np.unpackbits(arr).sum(dtype=np.int64))
    assert metrics.bit1_density({"A": arr}) == np.unpackbits(arr).mean()


def test_bit1_count_of_a_full_size_saturated_frame_is_exact() -> None:
    frame = np.full((900, 1600, 3), 255, np.uint8)
    assert _ones(frame.reshape(-1)) == frame.size * 8 and metrics.bit1_density({"A": frame}) == 1.0


def test_frame_metrics_returns_plain_builtins() -> None:
    out = metrics.frame_metrics(STRAIGHT * 1.1, make_frame(STRAIGHT, at_every_step(AgentBoxes.empty())))
    assert set(out) == {"l2", "collision", "collision_vru", "jerk"}
    assert all(type(v) is float for v in out["l2"]) and all(type(v) is int for v in out["collision"])
    assert type(out["jerk"]) is float


def _overlap_vector_form(c0, size0, yaw0, c1, size1, yaw1):
    """`overlap_pairs` as it was written before issue 23 (dot products summed over a length-2 axis)."""
    u0 = np.stack([np.cos(yaw0), np.sin(yaw0)], axis=1)
    v0 = np.stack([-u0[:, 1], u0[:, 0]], axis=1)
    u1 = np.stack([np.cos(yaw1), np.sin(yaw1)], axis=1)
    v1 = np.stack([-u1[:, 1], u1[:, 0]], axis=1)
    h0, h1 = size0 / 2.0, size1 / 2.0
    delta = c1 - c0
    separated = np.zeros(len(c0), dtype=bool)
    for axis in (u0, v0, u1, v1):
        r0 = h0[:, 0] * np.abs(np.sum(axis * u0, axis=1)) + h0[:, 1] * np.abs(np.sum(axis * v0, axis=1))
        r1 = h1[:, 0] * np.abs(np.sum(axis * u1, axis=1)) + h1[:, 1] * np.abs(np.sum(axis * v1, axis=1))
        separated |= np.abs(np.sum(delta * axis, axis=1)) > r0 + r1 + metrics.TOUCH_EPS_M
    return ~separated


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 60), touching=st.booleans())
def test_overlap_pairs_per_coordinate_equals_the_vector_form(seed: int, n: int, touching: bool) -> None:
    """Random pairs, and pairs touching end to end (where the slack decides): the same answer for every pair."""
    rng = np.random.default_rng(seed)
    c0 = rng.normal(0, 5, (n, 2))
    s0, s1 = rng.uniform(0.3, 6, (n, 2)), rng.uniform(0.3, 6, (n, 2))
    y0, y1 = rng.uniform(-4, 4, n), rng.uniform(-4, 4, n)
    c1 = c0 + rng.normal(0, 3, (n, 2))
    if touching:
        y1 = y0.copy()
        c1 = c0 + ((s0[:, 0] + s1[:, 0]) / 2)[:, None] * np.stack([np.cos(y0), np.sin(y0)], axis=1)
    got = metrics.overlap_pairs(c0, s0, y0, c1, s1, y1)
    assert np.array_equal(got, _overlap_vector_form(c0, s0, y0, c1, s1, y1))
    if touching:
        assert got.all()  # end to end within the slack: touching counts


@settings(max_examples=200, deadline=None)
@given(counts=st.lists(st.integers(0, 9), min_size=0, max_size=6),
       steps=st.lists(st.integers(0, 5), min_size=0, max_size=60))
def test_the_pairs_by_step_are_those_of_the_full_comparison(counts, steps) -> None:
    """`FlatAgents.pairs` gives the (query, box) pairs, in order, of comparing every query's step with every
    box's (steps without boxes, and frames with fewer than six steps, included)."""
    agents = [AgentBoxes(center=np.zeros((n, 2)), size=np.ones((n, 2)), yaw=np.zeros(n), category=("car",) * n)
              for n in counts]
    flat = metrics.FlatAgents.of(agents)
    step = np.asarray(steps, dtype=np.int64)
    query, box = flat.pairs(step)
    want_q, want_b = np.nonzero(step[:, None] == flat.step[None, :])
    assert query.tolist() == want_q.tolist() and box.tolist() == want_b.tolist()
