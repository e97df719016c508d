"""The other road users: one `AgentBoxes` per waypoint time, matched into tracks across keyframes (the boxes
carry no instance ids) with their velocities, and which boxes an ego box touches."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ...constants import HORIZON_STEPS, STEP_SECONDS
from ...data.frame import AgentBoxes
from ..trajectory import overlap_pairs
from .constants import EGO_SIZE, MAX_AGENT_SPEED, SIZE_MATCH_M


def agent_steps(agents: Sequence[AgentBoxes], count: int = HORIZON_STEPS) -> list[AgentBoxes]:
    """Exactly one `AgentBoxes` per waypoint time (`count` of them): extra steps dropped, missing ones empty."""
    steps = list(agents)[:count]
    return steps + [AgentBoxes.empty()] * (count - len(steps))


def _match(prev: AgentBoxes, boxes: AgentBoxes, prev_ids: np.ndarray, cur: np.ndarray) -> None:
    """Give the boxes of one keyframe (`cur`, -1 where unmatched, in place) the track ids of the previous
    keyframe's boxes they continue: same category, sizes within SIZE_MATCH_M, a move that fits
    MAX_AGENT_SPEED, pairs taken nearest first."""
    cat_p, cat_c = np.asarray(prev.category, dtype=object), np.asarray(boxes.category, dtype=object)
    dist = np.linalg.norm(np.asarray(prev.center)[:, None] - np.asarray(boxes.center)[None], axis=-1)
    size_gap = np.abs(np.asarray(prev.size)[:, None] - np.asarray(boxes.size)[None]).max(-1)
    ok = (cat_p[:, None] == cat_c[None]) & (size_gap <= SIZE_MATCH_M) & (dist <= MAX_AGENT_SPEED * STEP_SECONDS)
    used_p = np.zeros(len(prev), dtype=bool)
    pi, ci = np.nonzero(ok)
    for j in np.argsort(dist[pi, ci], kind="stable"):
        p, c = pi[j], ci[j]
        if not used_p[p] and cur[c] < 0:
            used_p[p], cur[c] = True, prev_ids[p]


def _track_ids(steps: list[AgentBoxes]) -> list[np.ndarray]:
    """Per step the track id of each box (N,): matched to the previous keyframe's box, or a fresh id."""
    ids: list[np.ndarray] = []
    next_id = 0
    for k, boxes in enumerate(steps):
        cur = np.full(len(boxes), -1, dtype=np.int64)
        if k and len(boxes) and len(steps[k - 1]):
            _match(steps[k - 1], boxes, ids[k - 1], cur)
        fresh = cur < 0
        cur[fresh] = np.arange(next_id, next_id + int(fresh.sum()))
        next_id += int(fresh.sum())
        ids.append(cur)
    return ids


def _track_velocities(steps: list[AgentBoxes], ids: list[np.ndarray]) -> list[np.ndarray]:
    """Per step the velocity (N, 2) m/s of each box: the central difference of its track's centres where it is
    seen at both neighbouring keyframes, else the one-sided one, NaN when seen only once."""
    where = [{int(t): i for i, t in enumerate(step_ids)} for step_ids in ids]
    velocities = []
    for k, boxes in enumerate(steps):
        vel = np.full((len(boxes), 2), np.nan)
        centers = np.asarray(boxes.center, dtype=np.float64).reshape(-1, 2)
        for i, t in enumerate(ids[k]):
            before = where[k - 1].get(int(t)) if k else None
            after = where[k + 1].get(int(t)) if k + 1 < len(steps) else None
            a = np.asarray(steps[k - 1].center, dtype=np.float64)[before] if before is not None else centers[i]
            b = np.asarray(steps[k + 1].center, dtype=np.float64)[after] if after is not None else centers[i]
            span = STEP_SECONDS * ((before is not None) + (after is not None))
            if span:
                vel[i] = (b - a) / span
        velocities.append(vel)
    return velocities


def agent_tracks(agents: Sequence[AgentBoxes]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Identities and velocities of the boxes of consecutive keyframes (AgentBoxes carry no instance ids).

    Boxes of neighbouring keyframes are the same agent when category and size agree (within SIZE_MATCH_M: an
    annotated instance keeps its size) and the move fits MAX_AGENT_SPEED; pairs are taken nearest first.
    Returns per step the track id of each box (N,) and its velocity (N, 2) m/s: the central difference where
    the agent is seen at both neighbouring keyframes, else the one-sided one, NaN when seen only once.
    """
    steps = agent_steps(agents, max(len(agents), HORIZON_STEPS))  # six steps, or a 4 s plan's eight
    ids = _track_ids(steps)
    return ids, _track_velocities(steps, ids)


def hits(center: np.ndarray, heading: float, boxes: AgentBoxes, size: np.ndarray = EGO_SIZE) -> np.ndarray:
    """Indices of the agent boxes an ego-sized box (or `size`) at (center, heading) overlaps or touches."""
    n = len(boxes)
    if not n:
        return np.zeros(0, dtype=np.int64)
    centers = np.asarray(boxes.center, dtype=np.float64).reshape(-1, 2)
    sizes = np.asarray(boxes.size, dtype=np.float64).reshape(-1, 2)
    over = overlap_pairs(np.broadcast_to(center, (n, 2)), np.broadcast_to(size, (n, 2)), np.full(n, heading),
                         centers, sizes, np.asarray(boxes.yaw, dtype=np.float64).reshape(-1))
    return np.flatnonzero(over)


def first_seen(ids: list[np.ndarray], velocities: list[np.ndarray]) -> list[np.ndarray]:
    """Per step the velocity (N, 2) of each box's track where the track is first seen: NAVSIM judges whether an
    agent stands still by its track's first-seen object (`unique_objects`), not by its speed at the collision."""
    first: dict[int, np.ndarray] = {}
    for step_ids, step_velocities in zip(ids, velocities):
        for track, velocity in zip(step_ids.tolist(), step_velocities):
            first.setdefault(int(track), velocity)
    return [np.array([first[int(t)] for t in step_ids.tolist()], dtype=np.float64).reshape(-1, 2)
            for step_ids in ids]
