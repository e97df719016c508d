"""NAVSIM's rules, written once: whose fault a collision is, when a projected contact fails TTC, how progress is
normalised and how the terms combine into the PDMS. The reference form (`reference`) and the prepared frame
(`prepared`) differ only in how they find the contacts they hand to these functions."""

from __future__ import annotations

from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ...data.frame import AgentBoxes
from .agents import hits
from .constants import (
    AHEAD_DEG,
    BEHIND_DEG,
    COMFORT_WEIGHT,
    EGO_SIZE,
    EP_WEIGHT,
    PROGRESS_DISTANCE_THRESHOLD,
    STATIC_CATEGORIES,
    STOPPED_SPEED,
    TTC_WEIGHT,
    PDMSResult,
)
from .motion import EgoStates


@dataclass(frozen=True)
class Contact:
    """An ego box that touches an agent box: the ego state it is judged from (for TTC, the state the box was
    projected from), the agent's track and its box and velocity at that waypoint time."""

    state: int  # index of the 10 Hz ego state
    track: int
    center: np.ndarray  # (2,) m
    size: np.ndarray  # (2,) length along its heading, width
    yaw: float  # rad
    category: str
    velocity: np.ndarray  # (2,) m/s, NaN when unknown

    @classmethod
    def of(cls, state: int, boxes: AgentBoxes, j: int, ids: np.ndarray,
           velocities: np.ndarray | None = None) -> Contact:
        """The contact with box `j` of one waypoint time's `boxes`, given that time's track ids and velocities
        (None: not tracked, the velocity is unknown)."""
        velocity = np.full(2, np.nan) if velocities is None else velocities[j]
        return cls(state, int(ids[j]), np.asarray(boxes.center, dtype=np.float64).reshape(-1, 2)[j],
                   np.asarray(boxes.size, dtype=np.float64).reshape(-1, 2)[j],
                   float(np.asarray(boxes.yaw, dtype=np.float64).reshape(-1)[j]), boxes.category[j], velocity)


def relative_angle(xy: np.ndarray, heading: float, other: np.ndarray) -> float:
    """Angle (rad, 0..pi) between the ego heading and the direction from the ego to `other` (0 when they
    coincide), as nuPlan's get_agent_relative_angle."""
    d = np.asarray(other, dtype=np.float64) - xy
    norm = float(np.hypot(d[0], d[1]))
    if norm < 1e-9:
        return 0.0
    return float(np.arccos(np.clip((d[0] * np.cos(heading) + d[1] * np.sin(heading)) / norm, -1.0, 1.0)))


def front_contact(xy: np.ndarray, heading: float, contact: Contact, size: np.ndarray = EGO_SIZE) -> bool:
    """Whether the ego's front edge (a box of no length across the nose of an ego box of `size`) touches the
    contact's box."""
    nose = xy + 0.5 * float(size[0]) * np.array([np.cos(heading), np.sin(heading)])
    single = AgentBoxes(contact.center[None], contact.size[None], np.array([contact.yaw]), (contact.category,))
    return len(hits(nose, heading, single, np.array([0.0, float(size[1])]))) > 0


def at_fault(states: EgoStates, contact: Contact, astray: np.ndarray, static: bool,
             size: np.ndarray = EGO_SIZE) -> bool:
    """NAVSIM's get_collision_type for one collision: ego stopped -> not at fault; agent stopped (or `static`)
    -> at fault; agent behind (> BEHIND_DEG) -> not at fault; the ego's front edge touches it -> at fault; else
    (a side contact) at fault only while the ego is `astray` (off the road or out of its lane, per state)."""
    i = contact.state
    if states.speed[i] <= STOPPED_SPEED:
        return False  # the ego stands still
    agent_speed = float(np.hypot(*contact.velocity))  # NaN when unknown: moving
    if static or agent_speed <= STOPPED_SPEED:
        return True  # it hits a standing agent
    xy, heading = states.xy[i], float(states.heading[i])
    if relative_angle(xy, heading, contact.center) > np.deg2rad(BEHIND_DEG):
        return False  # hit from behind
    return front_contact(xy, heading, contact, size) or bool(astray[i])


def collision_score(states: EgoStates, collisions: Iterable[Contact], astray: np.ndarray,
                    ignore: Collection[int] = (), static_categories: Sequence[str] = STATIC_CATEGORIES,
                    size: np.ndarray = EGO_SIZE) -> float:
    """NC in {0, 0.5, 1} from the plan's collisions at the waypoint times, in time order: per track not
    ignored, an at-fault collision scores 0 (1/2 with a static object); a not-at-fault track is ignored from
    then on."""
    ignored = set(ignore)
    score = 1.0
    for contact in collisions:
        if contact.track in ignored:
            continue
        static = contact.category in static_categories
        if at_fault(states, contact, astray, static, size):
            score = min(score, 0.5 if static else 0.0)
        else:
            ignored.add(contact.track)
    return score


def ttc_fails(states: EgoStates, contact: Contact, astray: np.ndarray) -> bool:
    """Whether a projected contact fails TTC: the agent is ahead (< AHEAD_DEG off the heading of the state it
    was projected from), or not behind (<= BEHIND_DEG) while the ego is `astray`."""
    i = contact.state
    angle = relative_angle(states.xy[i], float(states.heading[i]), contact.center)
    return bool(angle < np.deg2rad(AHEAD_DEG) or (astray[i] and angle <= np.deg2rad(BEHIND_DEG)))


def ttc_score(states: EgoStates, projections: Iterable[Contact], astray: np.ndarray,
              ignore: Collection[int] = ()) -> float:
    """TTC in {0, 1} from the contacts of the projected ego boxes, in NAVSIM's order (`TTC_SCHEDULE`): 0 at the
    first contact that `ttc_fails` on a track not ignored; any other track is ignored from then on."""
    ignored = set(ignore)
    for contact in projections:
        if contact.track in ignored:
            continue
        if ttc_fails(states, contact, astray):
            return 0.0
        ignored.add(contact.track)
    return 1.0


def ego_progress(plan_m: float, plan_multiplier: float, expert_m: float, expert_multiplier: float) -> float:
    """NAVSIM's normalised progress of the plan against the expert (PDM-Closed there): raw progress (at least 0)
    times the multiplicative metrics, over the larger of the two; 1 (0 for a plan multiplied by 0) when that
    larger value is at most PROGRESS_DISTANCE_THRESHOLD."""
    plan_raw = max(plan_m, 0.0) * plan_multiplier
    top = max(plan_raw, max(expert_m, 0.0) * expert_multiplier)
    if top > PROGRESS_DISTANCE_THRESHOLD:
        return plan_raw / top
    return 1.0 if plan_multiplier > 0 else 0.0


def pdms_result(nc: float, dac: float, ttc: float, comfort: float, plan_m: float, expert_m: float,
                expert_multiplier: float, map_scored: bool) -> PDMSResult:
    """The terms combined: progress times nc * dac against the expert's, then
    ``pdms = nc * dac * (5 ep + 5 ttc + 2 comfort) / 12``."""
    ep = ego_progress(plan_m, nc * dac, expert_m, expert_multiplier)
    weighted = (EP_WEIGHT * ep + TTC_WEIGHT * ttc + COMFORT_WEIGHT * comfort) / (EP_WEIGHT + TTC_WEIGHT
                                                                                   + COMFORT_WEIGHT)
    return PDMSResult(nc, dac, ttc, ep, comfort, nc * dac * weighted, map_scored, max(plan_m, 0.0),
                      max(expert_m, 0.0))
