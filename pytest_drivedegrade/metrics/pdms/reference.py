"""The reference form of the PDMS-like score: every contact found literally, one waypoint time (or TTC
projection) and one ego box at a time, as NAVSIM loops over its states. The tests hold `prepared.PreparedFrame`
to it; both judge their contacts with the same `rules`."""

from __future__ import annotations

from collections.abc import Collection, Iterator, Sequence
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ...data.frame import AgentBoxes, EgoStatus, Frame
from .agents import agent_steps, agent_tracks, first_seen, hits
from .constants import (
    EGO_SIZE,
    KEY_STATES,
    STATIC_CATEGORIES,
    TTC_SCHEDULE,
    TTC_STOPPED_SPEED,
    DrivableQuery,
    PDMSResult,
)
from .lanes import LaneView, astray
from .motion import (
    EgoPose,
    EgoStates,
    expert_path,
    is_comfortable,
    off_road,
    progress_along,
    waypoints,
)
from .rules import Contact, collision_score, pdms_result, ttc_score
from .tracked import initial_state, tracked_states

if TYPE_CHECKING:  # `tracking` imports this package: its names are read through `tracked` at run time
    from ..tracking import InitialState


def collisions(states: EgoStates, agents: Sequence[AgentBoxes], ids: list[np.ndarray],
               velocities: list[np.ndarray], size: np.ndarray = EGO_SIZE) -> Iterator[Contact]:
    """The ego box at each waypoint time against that time's agent boxes: every contact, in time order."""
    steps = agent_steps(agents)
    for k, i in enumerate(KEY_STATES.tolist()):
        for j in hits(states.xy[i], float(states.heading[i]), steps[k], size):
            yield Contact.of(i, steps[k], int(j), ids[k], velocities[k])


def projections(states: EgoStates, agents: Sequence[AgentBoxes], ids: list[np.ndarray],
                size: np.ndarray = EGO_SIZE) -> Iterator[Contact]:
    """For every (state, projection d, waypoint time) of TTC_SCHEDULE, the ego box moved on at the state's speed
    along its heading for d seconds against that time's agent boxes (states slower than TTC_STOPPED_SPEED
    skipped): every contact, in NAVSIM's order."""
    steps = agent_steps(agents)
    for i, d, k in TTC_SCHEDULE:
        speed = float(states.speed[i])
        if speed < TTC_STOPPED_SPEED:
            continue
        xy, heading = states.xy[i], float(states.heading[i])
        moved = xy + speed * d * np.array([np.cos(heading), np.sin(heading)])
        for j in hits(moved, heading, steps[k], size):
            yield Contact.of(i, steps[k], int(j), ids[k])  # TTC does not read the agent's velocity


def no_at_fault_collisions(states: EgoStates, agents: Sequence[AgentBoxes], ids: list[np.ndarray],
                           velocities: list[np.ndarray], astray: np.ndarray, ignore: Collection[int] = (),
                           static_categories: Sequence[str] = STATIC_CATEGORIES, size: np.ndarray = EGO_SIZE) -> float:
    """NC in {0, 0.5, 1}: NAVSIM's collision classification (`rules.at_fault`) at each waypoint time."""
    return collision_score(states, collisions(states, agents, ids, velocities, size), astray, ignore,
                           static_categories, size)


def time_to_collision_within_bound(states: EgoStates, agents: Sequence[AgentBoxes], ids: list[np.ndarray],
                                   astray: np.ndarray, ignore: Collection[int] = (),
                                   size: np.ndarray = EGO_SIZE) -> float:
    """TTC in {0, 1}: the projected ego boxes' contacts judged by `rules.ttc_fails`."""
    return ttc_score(states, projections(states, agents, ids, size), astray, ignore)


def pdm_score(plan: npt.ArrayLike, expert: npt.ArrayLike, agents: Sequence[AgentBoxes],
              ego: EgoStatus | InitialState | npt.ArrayLike = (0.0, 0.0), drivable: DrivableQuery | None = None,
              ego_pose: EgoPose | None = None, *,
              static_categories: Sequence[str] = STATIC_CATEGORIES, lanes: LaneView | None = None,
              ego_size: npt.ArrayLike = EGO_SIZE) -> PDMSResult:
    """The PDMS of one plan (see the package docstring and spec/README.md) on its tracked states.

    plan, expert: (6, 2) waypoints in the ego frame, each tracked alone from `ego` (the frame's `EgoStatus`,
    an `InitialState`, or a bare (vx, vy) m/s at t = 0); agents: one AgentBoxes per waypoint time (missing
    steps are empty); drivable: a vectorised query points (K, 2) -> bool in the map's frame, or None (no map:
    dac 1, `map_scored` False); ego_pose: the ego's (x, y, yaw) in the map's frame (None: the query takes
    ego-frame points); lanes: the lanes around the ego (`PreparedFrame`'s), which decide "in multiple lanes"
    and TTC's intersection clause (None: the former stand-in, half a lane from the expert's path); ego_size:
    the ego box (length, width), m.
    """
    size = np.array(ego_size, dtype=np.float64).reshape(2)
    plan_arr, expert_arr = waypoints(plan, "plan"), waypoints(expert, "expert")
    steps = agent_steps(agents)
    ids, velocities = agent_tracks(steps)
    seen = first_seen(ids, velocities)
    start = initial_state(ego)
    ps, es = tracked_states(plan_arr[None], [start])[0], tracked_states(expert_arr[None], [start])[0]
    path = expert_path(expert_arr, float(es.heading[-1]))
    plan_off, expert_off = off_road(ps, drivable, ego_pose, size), off_road(es, drivable, ego_pose, size)
    side, ttc_side = astray(ps, plan_off, path, lanes, size)  # off the road or in two lanes: side contacts count
    nc = no_at_fault_collisions(ps, steps, ids, seen, side, static_categories=static_categories, size=size)
    ttc = time_to_collision_within_bound(ps, steps, ids, ttc_side, size=size)
    dac = 0.0 if plan_off.any() else 1.0
    expert_nc = no_at_fault_collisions(es, steps, ids, seen, astray(es, expert_off, path, lanes, size)[0],
                                       static_categories=static_categories, size=size)
    return pdms_result(nc, dac, ttc, is_comfortable(ps), progress_along(path, ps.xy[-1]),
                       progress_along(path, es.xy[-1]), expert_nc * (0.0 if expert_off.any() else 1.0),
                       drivable is not None)


def frame_pdms(plan: npt.ArrayLike, frame: Frame, drivable: DrivableQuery | None = None, *,
               static_categories: Sequence[str] = STATIC_CATEGORIES) -> PDMSResult:
    """`pdm_score` of a plan on a reader frame: its ground truth, agents, ego status and global pose; pass the
    frame's `reader.drivable_area(frame)` (or None) as `drivable`."""
    return pdm_score(plan, frame.gt_future, frame.agents, frame.ego, drivable, frame.pose,
                     static_categories=static_categories)
