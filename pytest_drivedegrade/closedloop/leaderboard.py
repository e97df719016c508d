"""The Driving Score as the CARLA leaderboard computes it (leaderboard 2.x `utils/statistics_manager.py` and
scenario_runner's `atomic_criteria.py`; spec/leaderboard.md lists every infraction and what the world does with it).

DS = 100 x route completion x the product of every infraction's penalty factor. Fixed factors: collision with a
pedestrian 0.50, a vehicle 0.60, a static object 0.65, red light 0.70, stop sign 0.80, scenario timeout 0.70, not
yielding to an emergency vehicle 0.70. Percentage factors: outside route lanes (coefficient 0, "increases": the
factor is 1 - p/100 where p is the share of the driven route covered outside the driving lanes or in an oncoming
lane) and minimum speed (coefficient 0.7, "decreases": 1 - 0.3 (1 - p/100) per route checkpoint whose mean ego
speed p is below 100 % of the surrounding traffic's). Pure numbers only; `simulate` tracks the run.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

#: Fixed penalty factors (statistics_manager.PENALTY_VALUE_DICT).
PENALTIES: dict[str, float] = {
    "collision_pedestrian": 0.50, "collision_vehicle": 0.60, "collision_static": 0.65, "red_light": 0.70,
    "stop_sign": 0.80, "scenario_timeout": 0.70, "yield_emergency_vehicle": 0.70}
#: Percentage penalties (statistics_manager.PENALTY_PERC_DICT): kind -> (coefficient, direction).
PERCENT_PENALTIES: dict[str, tuple[float, str]] = {"outside_route_lanes": (0.0, "increases"),
                                                   "min_speed": (0.7, "decreases")}
#: Collision rules: every collision counts (the leaderboard's CollisionTest, the default), or only the at-fault
#: ones by NAVSIM's PDMS rule (`metrics.pdms.rules.at_fault`).
COLLISION_RULES = ("all", "at_fault")
#: CollisionTest: a collision while the ego is slower than this (m/s) is not counted; a second contact with the
#: same actor within COLLISION_ID_S, or any within COLLISION_RADIUS_M of the last counted one, is the same one.
COLLISION_EPSILON, COLLISION_ID_S, COLLISION_RADIUS_M = 0.1, 5.0, 5.0
#: OutsideRouteLanesTest: the ego's centre farther than this (m) beyond a driving or parking lane's half width.
ALLOWED_OUT_M = 0.5
#: InRouteTest (offroad_max=30 as the leaderboard sets it): the run ends this far (m) from the route; also once the
#: route covered farther than half of it from the route exceeds this share of the route's length.
DEVIATION_M, DEVIATION_SHARE = 30.0, 0.30
#: ActorBlockedTest (min_speed 0.1 m/s, max_time 180 s as the leaderboard sets them).
BLOCKED_SPEED, BLOCKED_S = 0.1, 180.0
#: RunningRedLightTest.DISTANCE_LIGHT: a light farther than this (m) from the ego is not checked.
RED_LIGHT_DISTANCE_M = 15.0
#: MinimumSpeedRouteTest(checkpoints=4); the last checkpoint is recorded when over 95 % of the route is done.
MIN_SPEED_CHECKPOINTS, MIN_SPEED_LAST = 4, 0.95


@dataclass(frozen=True)
class Limits:
    """The ends of a run on one route: route deviation (m) and blocked time (s). The leaderboard's 180 s blocked
    limit is longer than a world scene, so it is scaled to half the scene's duration (and only counts while the
    road ahead is free, so that a legitimate wait behind a stopped vehicle is not cut short)."""

    deviation_m: float
    blocked_s: float

    @staticmethod
    def of(scene_s: float) -> Limits:
        return Limits(DEVIATION_M, min(BLOCKED_S, scene_s / 2.0))


def check_rule(rule: str) -> str:
    """`rule` if it is a COLLISION_RULES value; ValueError naming the valid ones otherwise."""
    if rule not in COLLISION_RULES:
        raise ValueError(f"collision rule {rule!r}: expected {' or '.join(COLLISION_RULES)}")
    return rule


def percent_factor(kind: str, percentage: float) -> float:
    """The factor of one percentage infraction (statistics_manager.set_score_penalty)."""
    coefficient, direction = PERCENT_PENALTIES[kind]
    if direction == "decreases":
        return 1.0 - (1.0 - coefficient) * (1.0 - percentage / 100.0)
    return 1.0 - (1.0 - coefficient) * percentage / 100.0


def penalty(infractions: Iterable[tuple[str, float | None]]) -> float:
    """The product of the factors of (kind, percentage) infractions (kinds without a penalty count 1)."""
    out = 1.0
    for kind, value in infractions:
        if kind in PENALTIES:
            out *= PENALTIES[kind]
        elif kind in PERCENT_PENALTIES and value is not None:
            out *= percent_factor(kind, value)
    return out


def driving_score(completion: float, infractions: Iterable[tuple[str, float | None]]) -> float:
    """DS 0..100: 100 x completion (0..1) x penalty, never below 0 (statistics_manager: score_composed)."""
    return max(100.0 * completion * penalty(infractions), 0.0)


@dataclass
class CollisionFilter:
    """CollisionTest's de-duplication: the last counted collision's actor, time (s) and place."""

    last_id: int | None = None
    last_time: float = 0.0
    last_xy: np.ndarray | None = None

    def update(self, xy: np.ndarray, time_s: float) -> None:
        """Forget the last collision's place once the ego is COLLISION_RADIUS_M from it, its actor after
        COLLISION_ID_S (CollisionTest.update, every tick)."""
        if self.last_xy is not None and float(np.hypot(*(xy - self.last_xy))) > COLLISION_RADIUS_M:
            self.last_xy = None
        if self.last_id is not None and time_s - self.last_time > COLLISION_ID_S:
            self.last_id = None

    def counts(self, actor: int | None, xy: np.ndarray, speed: float, time_s: float) -> bool:
        """Whether a contact with `actor` (None: a static object, the leaderboard's id 0) counts, and if so
        remember it (CollisionTest._count_collisions)."""
        if actor is not None and actor == self.last_id:
            return False
        if self.last_xy is not None and float(np.hypot(*(xy - self.last_xy))) <= COLLISION_RADIUS_M:
            return False
        if speed < COLLISION_EPSILON:
            return False
        self.last_time, self.last_xy = time_s, np.array(xy, dtype=np.float64)
        if actor is not None:
            self.last_id = actor
        return True


@dataclass
class MinSpeed:
    """MinimumSpeedRouteTest: the route cut into MIN_SPEED_CHECKPOINTS pieces; over each, the ego's mean speed as
    a percentage of the surrounding traffic's mean speed (100 when there is no traffic). Returns a checkpoint's
    percentage when it is below 100 (an infraction)."""

    length: float
    done_m: float = 0.0
    ego: float = 0.0
    traffic: float = 0.0
    points: int = 0

    def tick(self, progress: float, ego_speed: float, traffic_speed: float | None) -> float | None:
        """One tick at route `progress` (m); the failing checkpoint's percentage, if one closes here."""
        out = None
        if progress - self.done_m > self.length / MIN_SPEED_CHECKPOINTS:
            out = self._close()
            self.done_m = progress
        if traffic_speed is not None:
            self.ego, self.traffic, self.points = self.ego + ego_speed, self.traffic + traffic_speed, self.points + 1
        return out

    def finish(self, progress: float) -> float | None:
        """The last checkpoint, recorded when over MIN_SPEED_LAST of the route is done (terminate)."""
        return self._close() if progress / max(self.length, 1e-9) > MIN_SPEED_LAST else None

    def _close(self) -> float | None:
        value = 100.0
        if self.points > 0 and self.traffic > 0:
            value = round(self.ego / self.traffic * 100.0, 2)
        self.ego = self.traffic = 0.0
        self.points = 0
        return value if value < 100.0 else None
