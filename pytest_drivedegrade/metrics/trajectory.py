"""Per-frame planning metrics and their aggregation conventions.

Every function here is pure and numpy-only. A plan and a ground truth are ``(6, 2)`` arrays of waypoints at
t = 0.5 .. 3.0 s in the current ego frame (x forward, y left, metres); the ego sits at the origin at t = 0.

Conventions (SPEC section 5):

- L2 per step is the Euclidean distance between planned and ground-truth waypoints.
- Collision per step places the 4.084 m x 1.85 m ego box at each planned waypoint, heading along the step
  direction, and tests it against the annotated agent boxes of the same future keyframe with an exact
  separating-axis test. A step counts only where the ground-truth trajectory's own box does not collide (an
  annotation artefact, or a collision the expert itself "had", is not the planner's fault).
- Horizons 1 / 2 / 3 s are steps 1 / 3 / 5. ``stp3`` averages the steps up to and including the horizon step;
  ``uniad`` takes the value at the horizon step.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np

from ..constants import EGO_LENGTH, EGO_WIDTH, HORIZON_STEPS, REPORT_HORIZONS_S, STEP_SECONDS, VRU_CATEGORIES
from ..data.frame import AgentBoxes, Frame

#: Step index (0-based, into the six waypoints) of each reported horizon: 1 s -> 1, 2 s -> 3, 3 s -> 5.
HORIZON_INDEX: tuple[int, ...] = tuple(int(round(h / STEP_SECONDS)) - 1 for h in REPORT_HORIZONS_S)
#: The aggregation conventions ``at_horizons`` understands.
CONVENTIONS: tuple[str, ...] = ("stp3", "uniad")
#: A step shorter than this (metres) carries no reliable direction; the previous heading is kept.
MIN_STEP_M: float = 1e-3
#: Slack (metres) on the separating-axis test, so that boxes which touch exactly still count after rounding.
TOUCH_EPS_M: float = 1e-9

# Number of 1 bits in every byte value, for the energy proxy.
_POPCOUNT_U8 = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1).astype(np.uint8)


def _as_plan(traj: Any, name: str) -> np.ndarray:
    arr = np.asarray(traj, dtype=np.float64)
    if arr.shape != (HORIZON_STEPS, 2):
        raise ValueError(f"{name} must have shape ({HORIZON_STEPS}, 2), got {arr.shape}")
    return arr


def l2_per_step(pred: Any, gt: Any) -> np.ndarray:
    """Euclidean distance (m) between planned and ground-truth waypoints, one per step: shape (6,)."""
    return np.linalg.norm(_as_plan(pred, "pred") - _as_plan(gt, "gt"), axis=1)


def step_headings(traj: Any) -> np.ndarray:
    """Heading (rad) of each waypoint from its step direction p_i - p_{i-1}, with p_{-1} the origin.

    A step shorter than ``MIN_STEP_M`` (a stopped ego) keeps the previous heading; 0 (straight ahead) when no
    step before it moved.
    """
    pts = _as_plan(traj, "trajectory")
    steps = np.diff(np.vstack([np.zeros((1, 2)), pts]), axis=0)
    headings = np.zeros(len(pts))
    current = 0.0
    for i, (dx, dy) in enumerate(steps):
        if np.hypot(dx, dy) >= MIN_STEP_M:
            current = float(np.arctan2(dy, dx))
        headings[i] = current
    return headings


def _overlap_pairs(c0: np.ndarray, size0: np.ndarray, yaw0: np.ndarray, c1: np.ndarray, size1: np.ndarray,
                   yaw1: np.ndarray) -> np.ndarray:
    """Exact separating-axis test for N pairs of oriented boxes (all arrays with a leading N), shape (N,)."""
    u0 = np.stack([np.cos(yaw0), np.sin(yaw0)], axis=1)
    v0 = np.stack([-u0[:, 1], u0[:, 0]], axis=1)
    u1 = np.stack([np.cos(yaw1), np.sin(yaw1)], axis=1)
    v1 = np.stack([-u1[:, 1], u1[:, 0]], axis=1)
    h0, h1 = size0 / 2.0, size1 / 2.0
    delta = c1 - c0
    separated = np.zeros(len(c0), dtype=bool)

    def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.abs(np.sum(a * b, axis=1))

    for axis in (u0, v0, u1, v1):
        r0 = h0[:, 0] * dot(axis, u0) + h0[:, 1] * dot(axis, v0)
        r1 = h1[:, 0] * dot(axis, u1) + h1[:, 1] * dot(axis, v1)
        separated |= dot(delta, axis) > r0 + r1 + TOUCH_EPS_M
    return ~separated


def boxes_overlap(
    center: Any, size: Any, yaw: float, centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray
) -> np.ndarray:
    """Whether one oriented box overlaps each of N oriented boxes: exact separating-axis test, shape (N,) bool.

    Boxes are (length along heading, width). Two rectangles are disjoint iff their projections on one of the
    four edge normals are disjoint; boxes that merely touch (share an edge or a corner) count as overlapping.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    n = len(centers)
    if n == 0:
        return np.zeros(0, dtype=bool)
    return _overlap_pairs(np.broadcast_to(np.asarray(center, np.float64), (n, 2)),
                          np.broadcast_to(np.asarray(size, np.float64), (n, 2)), np.full(n, float(yaw)),
                          centers, np.asarray(sizes, np.float64).reshape(-1, 2),
                          np.asarray(yaws, np.float64).reshape(-1))


_EGO_SIZE = np.array([EGO_LENGTH, EGO_WIDTH])
_EGO_RADIUS = float(np.hypot(EGO_LENGTH, EGO_WIDTH) / 2)


def _flatten(agents: Sequence[AgentBoxes]) -> tuple[np.ndarray, ...] | None:
    """All agents of the six steps as flat arrays (step, center, size, yaw, category) or None when empty."""
    steps = list(agents[:HORIZON_STEPS])
    counts = [len(b) for b in steps]
    if not sum(counts):
        return None

    def cat(b: Any) -> np.ndarray:
        return np.asarray(b, np.float64)

    return (np.repeat(np.arange(len(steps)), counts),
            np.concatenate([cat(b.center).reshape(-1, 2) for b in steps]),
            np.concatenate([cat(b.size).reshape(-1, 2) for b in steps]),
            np.concatenate([cat(b.yaw).reshape(-1) for b in steps]),
            np.array([c for b in steps for c in b.category], dtype=object))


def _agent_hits(traj: np.ndarray, flat: tuple[np.ndarray, ...] | None) -> np.ndarray:
    """Per flattened agent: does the ego box at that agent's step waypoint overlap it. A bounding-circle test
    first leaves the exact separating-axis test to the few agents near the ego."""
    if flat is None:
        return np.zeros(0, dtype=bool)
    step, centers, sizes, yaws, _ = flat
    ego = traj[step]
    near = np.linalg.norm(centers - ego, axis=1) <= _EGO_RADIUS + np.hypot(sizes[:, 0], sizes[:, 1]) / 2 + 1e-6
    hits = np.zeros(len(step), dtype=bool)
    if near.any():
        k = np.flatnonzero(near)
        hits[k] = _overlap_pairs(ego[k], np.broadcast_to(_EGO_SIZE, (len(k), 2)), step_headings(traj)[step[k]],
                                 centers[k], sizes[k], yaws[k])
    return hits


def _per_step(hits: np.ndarray, flat: tuple[np.ndarray, ...] | None, keep: np.ndarray | None = None) -> np.ndarray:
    out = np.zeros(HORIZON_STEPS, dtype=bool)
    if flat is not None and hits.any():
        chosen = hits if keep is None else hits & keep
        out[np.unique(flat[0][chosen])] = True
    return out


def _select(flat: tuple[np.ndarray, ...] | None, categories: Collection[str] | None) -> np.ndarray | None:
    if flat is None or categories is None:
        return None
    return np.isin(flat[4], list(categories))


def collision_per_step(
    pred: Any, gt: Any, agents: Sequence[AgentBoxes], *, categories: Collection[str] | None = None
) -> np.ndarray:
    """Per step (6,) bool: the planned ego box hits an agent box of `categories` while the GT ego box does not.

    `agents` holds one ``AgentBoxes`` per future step (the same future time as the waypoint); `categories`
    None means every agent. Headings come from the step direction (see ``step_headings``). Touching boxes
    count as a collision (within ``TOUCH_EPS_M``). Missing steps (fewer than six ``AgentBoxes``) never collide.
    """
    pred_arr, gt_arr = _as_plan(pred, "pred"), _as_plan(gt, "gt")
    flat = _flatten(agents)
    keep = _select(flat, categories)
    return _per_step(_agent_hits(pred_arr, flat), flat, keep) & ~_per_step(_agent_hits(gt_arr, flat), flat, keep)


def at_horizons(per_step: Any, convention: str) -> np.ndarray:
    """Aggregate per-step values (..., 6) to the 1 / 2 / 3 s horizons (..., 3).

    ``stp3``: mean of the steps up to and including the horizon step; ``uniad``: the value at the horizon step.
    """
    arr = np.asarray(per_step, dtype=np.float64)
    if arr.shape[-1:] != (HORIZON_STEPS,):
        raise ValueError(f"per-step values must end in a dimension of {HORIZON_STEPS}, got shape {arr.shape}")
    if convention == "stp3":
        return np.stack([arr[..., : i + 1].mean(axis=-1) for i in HORIZON_INDEX], axis=-1)
    if convention == "uniad":
        return arr[..., list(HORIZON_INDEX)]
    raise ValueError(f"unknown convention {convention!r}; valid conventions are {', '.join(CONVENTIONS)}")


def l2_avg(per_step: Any, convention: str = "stp3") -> float | np.ndarray:
    """Mean over the three horizons of ``at_horizons``: a float for one frame (6,), an array for (..., 6)."""
    value = at_horizons(per_step, convention).mean(axis=-1)
    return float(value) if np.ndim(value) == 0 else value


def jerk(plan: Any) -> float:
    """Mean absolute jerk (m/s^3) of a plan: the mean norm of its third finite difference.

    The origin (0, 0) is prepended as the t = 0 position, giving seven positions 0.5 s apart; velocity,
    acceleration and jerk are successive differences divided by 0.5 s, leaving four jerk vectors whose
    Euclidean norms are averaged. A constant-acceleration plan has zero jerk.
    """
    pts = np.vstack([np.zeros((1, 2)), _as_plan(plan, "plan")])
    third = np.diff(pts, n=3, axis=0) / STEP_SECONDS**3
    return float(np.linalg.norm(third, axis=1).mean())


def endpoint_shift(plan: Any, reference_plan: Any) -> float:
    """Distance (m) between the 3 s waypoints of a plan and a reference plan (the clean one)."""
    return float(np.linalg.norm(_as_plan(plan, "plan")[-1] - _as_plan(reference_plan, "reference_plan")[-1]))


def _ones(raw: np.ndarray) -> int:
    """Number of 1 bits in a flat uint8 array: a hardware popcount over 64-bit words (numpy >= 2), the
    remaining bytes through a 256-entry table."""
    words = raw.size // 8 * 8 if hasattr(np, "bitwise_count") else 0
    ones = int(np.bitwise_count(raw[:words].view(np.uint64)).sum()) if words else 0
    return ones + int(_POPCOUNT_U8[raw[words:]].sum(dtype=np.int64))


def bit1_density(images: Mapping[str, np.ndarray]) -> float:
    """Fraction of 1 bits among all bytes of all images: the energy proxy (divide by clean's for relative).

    About 0.15 ms for an 800 x 450 image. Returns 0.0 when there are no bytes.
    """
    ones = 0
    total = 0
    for image in images.values():
        raw = np.ascontiguousarray(image).view(np.uint8).reshape(-1)
        ones += _ones(raw)
        total += raw.size * 8
    return ones / total if total else 0.0


def frame_metrics(pred: Any, frame: Frame) -> dict[str, Any]:
    """Every per-frame metric of one plan, as plain builtins (safe to cross the xdist boundary).

    Returns ``{"l2": [6 floats], "collision": [6 ints], "collision_vru": [6 ints], "jerk": float}``.
    """
    pred_arr = _as_plan(pred, "pred")
    gt = _as_plan(frame.gt_future, "gt_future")
    flat = _flatten(tuple(frame.agents))
    vru = _select(flat, VRU_CATEGORIES)
    pred_hits, gt_hits = _agent_hits(pred_arr, flat), _agent_hits(gt, flat)
    collision = _per_step(pred_hits, flat) & ~_per_step(gt_hits, flat)
    collision_vru = _per_step(pred_hits, flat, vru) & ~_per_step(gt_hits, flat, vru)
    return {
        "l2": [float(v) for v in l2_per_step(pred_arr, gt)],
        "collision": [int(v) for v in collision],
        "collision_vru": [int(v) for v in collision_vru],
        "jerk": jerk(pred_arr),
    }
