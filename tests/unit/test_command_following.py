"""Issue 40 (command cells, the measure): junction frames from a lane map and the command-following figure, with
hidden-behaviour planners (ignores the command, follows it, follows it only when the cameras show the junction)
and the privileged expert. Known answers on a hand-built junction."""

from __future__ import annotations

import numpy as np
import pytest

from pytest_drivedegrade.data.frame import Command
from pytest_drivedegrade.data.junctions import alternative, ego_lane, manoeuvre
from pytest_drivedegrade.data.maps import Lane, LaneMap
from pytest_drivedegrade.scoring.command import command_label, following, frame_sums, from_sums

STEPS = np.arange(1, 7) * 0.5


def _straight(x0: float, x1: float, y: float = 0.0) -> np.ndarray:
    x = np.arange(x0, x1 + 1e-9, 0.5)
    return np.stack([x, np.full_like(x, y), np.zeros_like(x)], axis=1)


def _left_arc(x0: float, radius: float = 10.0) -> np.ndarray:
    a = np.linspace(0, np.pi / 2, 40)
    return np.stack([x0 + radius * np.sin(a), radius - radius * np.cos(a), a], axis=1)


def junction_map() -> LaneMap:
    """A lane along y = 0 up to x = 10, then a straight connector and a left-turn connector (radius 10 m), each
    with its lane after it."""
    up = _left_arc(10.0)
    after_left = np.stack([np.full(61, 20.0), np.linspace(10, 40, 61), np.full(61, np.pi / 2)], axis=1)
    lanes = (Lane("a", None, _straight(-20, 10), outgoing=("s", "l")),
             Lane("s", None, _straight(10, 30), connector=True, incoming=("a",), outgoing=("s2",)),
             Lane("l", None, up, connector=True, incoming=("a",), outgoing=("l2",)),
             Lane("s2", None, _straight(30, 60), incoming=("s",)), Lane("l2", None, after_left, incoming=("l",)))
    return LaneMap("test", lanes, (), (), (), (), None)  # type: ignore[arg-type]  # no drivable area needed


def straight_future(speed: float = 5.0) -> np.ndarray:
    return np.stack([speed * STEPS, np.zeros(6)], axis=1)


def test_the_map_names_the_manoeuvres_and_the_alternative_is_the_other_one() -> None:
    m = junction_map()
    assert [manoeuvre(lane) for lane in m.lanes if lane.connector] == [Command.STRAIGHT, Command.LEFT]
    assert ego_lane(m, (0.0, 0.0, 0.0))[0].token == "a"
    assert ego_lane(m, (0.0, 0.0, np.pi)) is None  # driving against the lane: not on it
    alt = alternative(m, (0.0, 0.0, 0.0), straight_future(), Command.STRAIGHT)
    assert alt is not None and alt.command == Command.LEFT
    # the expert's path: the logged arc lengths (2.5 .. 15 m) along the lane, then 2.5 and 5 m into the arc
    np.testing.assert_allclose(alt.path[:4], straight_future()[:4], atol=1e-6)
    angle = np.array([0.25, 0.5])
    np.testing.assert_allclose(alt.path[4:], np.stack([10 + 10 * np.sin(angle), 10 - 10 * np.cos(angle)], 1),
                               atol=0.02)
    # the logged future turned left: the other manoeuvre is straight on, along the logged arc lengths
    back = alternative(m, (0.0, 0.0, 0.0), alt.path, Command.LEFT)
    assert back is not None and back.command == Command.STRAIGHT and abs(back.path[:, 1]).max() < 1e-6
    # told left with a future that went straight: the straight manoeuvre does not part from it, nothing to score
    assert alternative(m, (0.0, 0.0, 0.0), straight_future(), Command.LEFT) is None


def test_frames_away_from_the_junction_are_not_scored() -> None:
    m = junction_map()
    assert alternative(m, (-20.0, 0.0, 0.0), straight_future(2.0), Command.STRAIGHT) is None  # too far to part
    assert alternative(m, (0.0, 8.0, 0.0), straight_future(), Command.STRAIGHT) is None  # not on a lane
    assert alternative(None, (0.0, 0.0, 0.0), straight_future(), Command.STRAIGHT) is None
    assert alternative(m, None, straight_future(), Command.STRAIGHT) is None


def frames(n: int = 20, seed: int = 0):
    """`n` junction frames: logged futures, the expert's paths for the other manoeuvre, whether the cameras show
    the junction (every third frame they do not: occluded), and a weak planner's own plans (noise about logged)."""
    rng = np.random.default_rng(seed)
    m = junction_map()
    logged, target = [], []
    for _ in range(n):
        speed = 5.5 + 2.5 * rng.random()  # far enough into the turn within 3 s for the manoeuvres to part
        fut = straight_future(speed)
        logged.append(fut)
        target.append(alternative(m, (0.0, 0.0, 0.0), fut, Command.STRAIGHT).path)
    logged, target = np.array(logged), np.array(target)
    shows = np.arange(n) % 3 != 2
    own = logged + rng.normal(scale=0.3, size=logged.shape)
    return logged, target, shows, own


def test_a_planner_that_ignores_the_command_scores_0_and_the_expert_1() -> None:
    logged, target, _, own = frames()
    ignores = following(own, own.copy(), logged, target, n_resamples=500)
    assert ignores.value == 0.0 and ignores.low == 0.0 and ignores.high == 0.0
    assert ignores.label == "command-insensitive" and ignores.frames == 20
    expert = following(logged, target, logged, target, n_resamples=500)
    assert expert.value == pytest.approx(1.0) and expert.low == pytest.approx(1.0)
    assert expert.label == "command-following"
    assert "0: ignores the command, 1: the privileged expert" in expert.text()


def test_a_planner_that_follows_only_when_the_cameras_show_the_junction() -> None:
    """It follows (90 % of the expert's change) where its cameras show the junction, else keeps its plan: with
    clean images it follows on 2 of 3 frames; with every camera off (blind) it never does."""
    logged, target, shows, own = frames(30)
    def plan(told_other: bool, sees: np.ndarray) -> np.ndarray:
        return own + (0.9 * (target - logged) * sees[:, None, None] if told_other else 0.0)
    clean = following(plan(False, shows), plan(True, shows), logged, target, n_resamples=500)
    blind = following(plan(False, np.zeros(30, bool)), plan(True, np.zeros(30, bool)), logged, target)
    den = ((target - logged) ** 2).sum(axis=(1, 2))
    assert clean.value == pytest.approx(0.9 * den[shows].sum() / den.sum())  # 0.9 x the frames it sees, weighted
    assert clean.label == "command-partial"  # 0.61, interval 0.43 .. 0.80: the command steers it, not shown half way
    always = following(plan(False, np.ones(30, bool)), plan(True, np.ones(30, bool)), logged, target)
    assert always.value == pytest.approx(0.9) and always.label == "command-following"
    assert blind.value == 0.0 and blind.label == "command-insensitive"
    turns_away = following(own, own - (target - logged), logged, target)
    assert turns_away.value == pytest.approx(-1.0) and turns_away.label == "command-insensitive"


@pytest.mark.parametrize("low, high, value, label", [
    (0.6, 0.9, 0.7, "command-following"), (0.5, 0.9, 0.7, "command-following"), (0.4, 0.9, 0.7, "command-partial"),
    (0.1, 0.3, 0.2, "command-partial"), (0.09, 0.3, 0.2, "undetermined"),
    (-0.2, 0.09, 0.0, "command-insensitive"), (-0.2, 0.1, 0.0, "undetermined"), (None, None, None, "undetermined"),
    (None, None, 0.8, "command-following"),
])
def test_each_label_excludes_the_other(low, high, value, label) -> None:
    assert command_label(low, high, value) == label


def test_one_junction_never_labels_a_planner() -> None:
    """Frames of one known scene are one junction: the figure and a frame interval are shown, the label is
    undetermined whatever they say (4 frames of one val scene are all the default world holds); the same frames
    spread over two scenes are labelled from the scene-cluster interval."""
    logged, target, _, own = frames(8)
    follows = own + 0.9 * (target - logged)
    one = from_sums(*frame_sums(own, follows, logged, target), scenes=[7] * 8)
    assert one.value == pytest.approx(0.9) and one.low is not None and one.label == "undetermined"
    two = from_sums(*frame_sums(own, follows, logged, target), scenes=[7] * 4 + [9] * 4)
    assert two.scenes == 2 and two.label == "command-following"


def test_no_scored_frame_is_not_measured() -> None:
    empty = np.zeros((0, 6, 2))
    got = following(empty, empty, empty, empty)
    assert got.value is None and got.label == "undetermined" and "not measured" in got.text()
