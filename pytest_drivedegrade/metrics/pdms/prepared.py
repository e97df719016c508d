"""The fast path: one frame prepared once (the expert's tracked states, path, multiplier and progress, agent
tracks, the map around the ego) and shared by every cell, its contacts found for all waypoint times and all
TTC projections in one vectorised separating-axis call, and the plans of many frames tracked in one batch
(`score_plans`). It judges them with the same `rules` as the reference form, and the tests hold it to
`reference.pdm_score` exactly."""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ...constants import HORIZON_STEPS
from ...data.frame import AgentBoxes, EgoStatus, Frame
from ...data.maps import DrivableArea, LaneMap
from ..trajectory import FlatAgents, overlap_pairs
from .agents import agent_steps, agent_tracks, first_seen
from .constants import (
    EGO_SIZE,
    FAR_MARGIN_M,
    KEY_STATES,
    STATIC_CATEGORIES,
    TTC_SCHEDULE,
    TTC_STOPPED_SPEED,
    DrivableQuery,
    PDMSResult,
    key_states,
    ttc_schedule,
)
from .extended import (
    ExtendedTerms,
    driving_direction,
    ep_v2,
    history,
    history_comfort,
    lane_keeping,
    lane_query,
)
from .lanes import LaneView, astray
from .lights import RedArea, red_areas, traffic_light_compliance
from .local_map import LocalDrivable
from .motion import (
    EgoPose,
    EgoStates,
    expert_path,
    is_comfortable,
    off_road,
    progress_along,
    waypoints,
)
from .route import route_centreline
from .rules import Contact, collision_score, pdms_result, ttc_score
from .tracked import initial_state, tracked_states

if TYPE_CHECKING:  # `tracking` imports this package: its names are read through `tracked` at run time
    from ..tracking import InitialState



@functools.cache
def _ttc_arrays(poses: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`ttc_schedule(poses)` as arrays: the state each check projects from, the projection (s), the waypoint time
    it meets (for six poses: TTC_SCHEDULE's)."""
    schedule = TTC_SCHEDULE if poses == HORIZON_STEPS else ttc_schedule(poses)
    return (np.array([s[0] for s in schedule], dtype=np.int64), np.array([s[1] for s in schedule], dtype=np.float64),
            np.array([s[2] for s in schedule], dtype=np.int64))


#: Plans remembered per prepared frame (`PreparedFrame.judged`): more than a full ladder's cells, about 1 KB each.
MEMO_PLANS = 256


@dataclass(frozen=True)
class PreparedFrame:
    """What `pdm_score` derives from the frame alone, prepared once per frame and shared by every cell.

    ``score(plan)`` equals ``pdm_score(plan, expert, agents, ...)`` (tests/unit/test_pdms.py checks it on the
    world and on random frames); it tests all agent boxes of a waypoint time (and all TTC projections) in one
    vectorised separating-axis call, after dropping the pairs too far apart to touch.
    """

    expert: np.ndarray
    steps: tuple[AgentBoxes, ...]
    ids: tuple[np.ndarray, ...]
    velocities: tuple[np.ndarray, ...]  # per step, each box's track's first-seen velocity (`agents.first_seen`)
    initial: InitialState
    drivable: DrivableQuery | None
    ego_pose: EgoPose | None
    static_categories: tuple[str, ...]
    path: np.ndarray
    expert_m: float
    expert_multiplier: float
    boxes: FlatAgents  # every agent box of the six waypoint times, flat, in (time, index) order
    index: np.ndarray  # (M,) index of each box within its time's AgentBoxes
    reach: np.ndarray  # (M,) its half diagonal + the ego's + margin: farther centres cannot touch
    lanes: LaneView | None = None  # the lanes around the ego (EPDMS's ddc and lk; None: not scored)
    past: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # the ego's last 1.5 s (`extended.history`)
    human: ExtendedTerms | None = None  # the expert's own EPDMS terms (the human filter)
    ego_size: np.ndarray = field(default_factory=lambda: EGO_SIZE.copy())  # the ego box (length, width), m
    red_areas: tuple[RedArea, ...] | None = None  # the map's lights (EPDMS's tlc; None: no lights, not scored)
    #: plans judged on this frame (`judged`), by their bytes, up to MEMO_PLANS of them
    memo: dict[bytes, tuple[PDMSResult, ExtendedTerms]] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def prepare(cls, expert: npt.ArrayLike, agents: Sequence[AgentBoxes],
                ego: EgoStatus | InitialState | npt.ArrayLike = (0.0, 0.0), drivable: DrivableQuery | None = None,
                ego_pose: EgoPose | None = None, *, static_categories: Sequence[str] = STATIC_CATEGORIES,
                lanes: LaneView | None = None, expert_states: EgoStates | None = None,
                past_motion: npt.ArrayLike | None = None, ego_size: npt.ArrayLike = EGO_SIZE,
                red_areas: Sequence[RedArea] | None = None) -> PreparedFrame:
        """Prepare a frame from the arguments of `pdm_score` (less the plan); a whole map is cut to the
        polygons around the ego (`LocalDrivable`). The expert is tracked and judged once here: its progress
        and its multiplier (its own NC times DAC, as NAVSIM masks the reference's progress), and its EPDMS
        terms for the human filter (`lanes`: the lanes around the ego, in its frame). `expert_states`: the
        expert already tracked from this ego in a batch of frames (`tracked_experts`), the same states.
        `past_motion`: the past keyframes' motion (`Frame.past_motion`) for history comfort (None: hc 1).
        `ego_size`: the ego box (length, width) every box test of the plan and the expert uses (`EGO_BOXES`).
        `red_areas`: the lights' areas and red states (`lights.RedArea`) for tlc (None: not scored)."""
        size = np.array(ego_size, dtype=np.float64).reshape(2)
        expert_arr = waypoints(expert, "expert")
        steps = agent_steps(agents, len(expert_arr))
        ids, velocities = agent_tracks(steps)
        seen = first_seen(ids, velocities)
        start = initial_state(ego)
        if isinstance(drivable, DrivableArea) and ego_pose is not None:
            drivable = LocalDrivable(drivable, [float(ego_pose[0]), float(ego_pose[1])])
        es = tracked_states(expert_arr[None], [start])[0] if expert_states is None else expert_states
        expert_off = off_road(es, drivable, ego_pose, size)
        path = expert_path(expert_arr, float(es.heading[-1]))
        expert_astray, expert_ttc_astray = astray(es, expert_off, path, lanes, size)
        boxes = FlatAgents.of(steps, len(steps))
        index = np.concatenate([np.arange(len(b), dtype=np.int64) for b in steps])
        reach = 0.5 * np.hypot(boxes.sizes[:, 0], boxes.sizes[:, 1]) + 0.5 * math.hypot(*size) + FAR_MARGIN_M
        past = history(past_motion, ego.acceleration) if isinstance(ego, EgoStatus) and past_motion is not None \
            else None
        # the frame without the expert's own judgement, whose vectorised contacts then judge the expert as they
        # judge a plan (`score_tracked`): the reference's contacts in the reference's order, 6x cheaper
        bare = cls(expert_arr, tuple(steps), tuple(ids), tuple(seen), start, drivable, ego_pose,
                   tuple(static_categories), path, progress_along(path, es.xy[-1]), math.nan, boxes, index, reach,
                   lanes, past, None, size, None if red_areas is None else tuple(red_areas))
        expert_nc = collision_score(es, bare.collisions(es), expert_astray, static_categories=static_categories,
                                    size=size)
        dac = 0.0 if expert_off.any() else 1.0
        query = lane_query(es, lanes)
        tlc = traffic_light_compliance(es, bare.red_areas, size)
        human = ExtendedTerms(expert_nc, dac, driving_direction(es, lanes, query), tlc, 1.0,
                              ttc_score(es, bare.projections(es), expert_ttc_astray),
                              lane_keeping(es, lanes, query), 1.0)  # NAVSIM scores the human without a past
        return replace(bare, expert_multiplier=expert_nc * dac, human=human)

    @classmethod
    def of(cls, frame: Frame, drivable: DrivableQuery | None = None, *,
           static_categories: Sequence[str] = STATIC_CATEGORIES, lane_map: LaneMap | None = None,
           expert_states: EgoStates | None = None, ego_size: npt.ArrayLike = EGO_SIZE,
           poses: int = HORIZON_STEPS) -> PreparedFrame:
        """Prepare a reader frame, as `frame_pdms` scores it (`lane_map`: its location's lanes, for EPDMS;
        `expert_states`: its expert's from `tracked_experts`; `ego_size`: the ego box; `poses`: the horizon
        scored, 6 or 8 waypoints: `Frame.future` and `Frame.future_agents` of that many)."""
        expert, agents = frame.future(poses), frame.future_agents(poses)
        lanes = None
        if lane_map is not None and frame.pose is not None:
            logged = frame.gt_future[frame.gt_valid] if poses == HORIZON_STEPS else expert
            lanes = replace(LaneView.of_map(lane_map, frame.pose),
                            route=route_centreline(lane_map, frame.pose, logged))
        return cls.prepare(expert, agents, frame.ego, drivable, frame.pose,
                           static_categories=static_categories, lanes=lanes, expert_states=expert_states,
                           past_motion=frame.past_motion, ego_size=ego_size,
                           red_areas=red_areas(lane_map, frame.pose, frame.timestamp, poses))

    def _hit_pairs(self, xy: np.ndarray, heading: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego boxes at xy (Q, 2) / heading (Q,) against the agent boxes of waypoint `step` (Q,): the (query,
        flat agent) pairs that overlap or touch, in (query, agent) order."""
        b = self.boxes
        q, a = b.pairs(step)
        if len(q):
            near = np.hypot(*(b.centers[a] - xy[q]).T) <= self.reach[a]
            q, a = q[near], a[near]
        if not len(q):
            return q, a
        over = overlap_pairs(xy[q], np.broadcast_to(self.ego_size, (len(q), 2)), heading[q], b.centers[a],
                             b.sizes[a], b.yaws[a])
        return q[over], a[over]

    def _contact(self, state: int, flat: int, tracked: bool) -> Contact:
        """The contact of the ego state `state` with flat agent box `flat` (its velocity only when `tracked`)."""
        k = int(self.boxes.step[flat])
        return Contact.of(state, self.steps[k], int(self.index[flat]), self.ids[k],
                          self.velocities[k] if tracked else None)

    def collisions(self, states: EgoStates) -> Iterator[Contact]:
        """`reference.collisions`: the ego box at every waypoint time against its agents, all at once."""
        n = len(self.steps)
        keys = np.asarray(KEY_STATES) if n == HORIZON_STEPS else key_states(n)
        qs, ags = self._hit_pairs(states.xy[keys], states.heading[keys], np.arange(n))
        for q, flat in zip(qs.tolist(), ags.tolist()):
            yield self._contact(int(keys[q]), flat, tracked=True)

    def projections(self, states: EgoStates) -> Iterator[Contact]:
        """`reference.projections`: every (state, projection) pair of TTC_SCHEDULE at once."""
        ttc_state, ttc_seconds, ttc_step = _ttc_arrays(len(self.steps))
        speed = states.speed[ttc_state]
        moving = speed >= TTC_STOPPED_SPEED
        i_arr, d_arr, k_arr, speed = ttc_state[moving], ttc_seconds[moving], ttc_step[moving], speed[moving]
        heading = states.heading[i_arr]
        moved = states.xy[i_arr] + (speed * d_arr)[:, None] * np.stack([np.cos(heading), np.sin(heading)], 1)
        qs, ags = self._hit_pairs(moved, heading, k_arr)
        for q, flat in zip(qs.tolist(), ags.tolist()):
            yield self._contact(int(i_arr[q]), flat, tracked=False)

    def score(self, plan: npt.ArrayLike) -> PDMSResult:
        """The PDMS of one plan on this frame (equal to `pdm_score`)."""
        plan_arr = waypoints(plan, "plan")
        return self.score_tracked(plan_arr, tracked_states(plan_arr[None], [self.initial])[0])

    def score_tracked(self, plan: np.ndarray, ps: EgoStates) -> PDMSResult:
        """The PDMS of a plan (6, 2) whose tracked states `ps` are already simulated from `initial`."""
        plan_off = off_road(ps, self.drivable, self.ego_pose, self.ego_size)
        side, ttc_side = astray(ps, plan_off, self.path, self.lanes, self.ego_size)
        nc = collision_score(ps, self.collisions(ps), side, static_categories=self.static_categories,
                             size=self.ego_size)
        ttc = ttc_score(ps, self.projections(ps), ttc_side)
        dac = 0.0 if plan_off.any() else 1.0
        return pdms_result(nc, dac, ttc, is_comfortable(ps), progress_along(self.path, ps.xy[-1]),
                           self.expert_m, self.expert_multiplier, self.drivable is not None)


    def judged(self, plan: np.ndarray, ps: EgoStates) -> tuple[PDMSResult, ExtendedTerms]:
        """`score_tracked` and `extended` of a plan (6, 2) with its tracked states `ps`, remembered by the plan's
        bytes: a cell that plans as another did (the null control, frames that reused clean's plan, an ego-only
        planner's image cells) is judged once per process. Exact: the tracked states are a function of the plan
        and `initial` alone (whatever the batch), and so is everything judged from them."""
        key = np.ascontiguousarray(plan, dtype=np.float64).tobytes()
        found = self.memo.get(key)
        if found is None:
            result = self.score_tracked(plan, ps)
            found = (result, self.extended(ps, result))
            if len(self.memo) < MEMO_PLANS:
                self.memo[key] = found
        return found

    def extended(self, ps: EgoStates, result: PDMSResult) -> ExtendedTerms:
        """The plan's EPDMS terms before the human filter, from its tracked states and its PDMS `result`:
        ddc and lk on the lanes, NAVSIM v2's progress (against the expert's multiplied progress, the multiplier
        now with ddc), history comfort; tlc where the frame's map has traffic lights (`lights`)."""
        query = lane_query(ps, self.lanes)
        ddc = driving_direction(ps, self.lanes, query)
        expert_ddc = self.human.ddc if self.human is not None else float("nan")
        plan_mult = result.nc * result.dac * (1.0 if np.isnan(ddc) else ddc)
        expert_mult = self.expert_multiplier * (1.0 if np.isnan(expert_ddc) else expert_ddc)
        ep = ep_v2(result.progress_m, plan_mult, self.expert_m, expert_mult)
        lk = lane_keeping(ps, self.lanes, query)
        hc = history_comfort(ps, self.past)
        tlc = traffic_light_compliance(ps, self.red_areas, self.ego_size)
        return ExtendedTerms(result.nc, result.dac, ddc, tlc, ep, result.ttc, lk, hc)


def tracked_experts(frames: Sequence[Frame], poses: int = HORIZON_STEPS) -> dict[str, EgoStates]:
    """The experts (logged futures) of reader frames tracked from their egos in one batch, by frame token, for
    `PreparedFrame.of`: the tracker's cost is its 30 steps, nearly the same for 200 plans as for one, and a
    plan's states are bit-identical whichever plans share its batch. A frame whose expert or ego is not
    trackable is left out (its own preparation then raises what it raises)."""
    tokens, experts, starts = [], [], []
    for frame in frames:
        try:
            expert, start = waypoints(frame.future(poses), "expert"), initial_state(frame.ego)
        except (TypeError, ValueError):
            continue
        tokens.append(frame.token)
        experts.append(expert)
        starts.append(start)
    if not tokens:
        return {}
    return dict(zip(tokens, tracked_states(np.stack(experts), starts)))


def score_plans(frames: Sequence[PreparedFrame], plans: npt.ArrayLike) -> list[PDMSResult]:
    """The PDMS of plans (B, 6, 2) on their prepared frames (B of them, any frames), the plans tracked in one
    batch: the tracker's cost is its 30 steps, nearly the same for one plan as for a cell's worth."""
    arr = np.asarray(plans, dtype=np.float64)
    if len(frames) != len(arr):
        raise ValueError(f"{len(arr)} plans for {len(frames)} prepared frames")
    if not len(arr):
        return []
    checked = np.stack([waypoints(p, "plan") for p in arr])
    states = tracked_states(checked, [f.initial for f in frames])
    return [f.score_tracked(p, s) for f, p, s in zip(frames, checked, states)]
