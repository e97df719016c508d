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

from .constants import EGO_LENGTH, EGO_WIDTH, HORIZON_STEPS, REPORT_HORIZONS_S, STEP_SECONDS, VRU_CATEGORIES
from .data.frame import AgentBoxes, Frame

#: Step index (0-based, into the six waypoints) of each reported horizon: 1 s -> 1, 2 s -> 3, 3 s -> 5.
HORIZON_INDEX: tuple[int, ...] = tuple(int(round(h / STEP_SECONDS)) - 1 for h in REPORT_HORIZONS_S)
#: The aggregation conventions ``at_horizons`` understands.
CONVENTIONS: tuple[str, ...] = ("stp3", "uniad")
#: A step shorter than this (metres) carries no reliable direction; the previous heading is kept.
MIN_STEP_M: float = 1e-3
#: Slack (metres) on the separating-axis test, so that boxes which touch exactly still count after rounding.
TOUCH_EPS_M: float = 1e-9

# Number of 1 bits in every byte value, for the energy proxy.
_POPCOUNT = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1).astype(np.int64)


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


def boxes_overlap(
    center: Any, size: Any, yaw: float, centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray
) -> np.ndarray:
    """Whether one oriented box overlaps each of N oriented boxes: exact separating-axis test, shape (N,) bool.

    Boxes are (length along heading, width). Two rectangles are disjoint iff their projections on one of the
    four edge normals are disjoint; boxes that merely touch (share an edge or a corner) count as overlapping.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    if len(centers) == 0:
        return np.zeros(0, dtype=bool)
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 2)
    yaws = np.asarray(yaws, dtype=np.float64).reshape(-1)
    # Unit axes (u along length, v along width) of the single box, shape (2,), and of the N boxes, (N, 2).
    u0 = np.array([np.cos(yaw), np.sin(yaw)])
    v0 = np.array([-u0[1], u0[0]])
    u1 = np.stack([np.cos(yaws), np.sin(yaws)], axis=1)
    v1 = np.stack([-u1[:, 1], u1[:, 0]], axis=1)
    h0 = np.asarray(size, dtype=np.float64) / 2.0
    h1 = sizes / 2.0
    delta = centers - np.asarray(center, dtype=np.float64)
    separated = np.zeros(len(centers), dtype=bool)
    for axis in (np.broadcast_to(u0, u1.shape), np.broadcast_to(v0, u1.shape), u1, v1):
        dist = np.abs(np.sum(delta * axis, axis=1))
        r0 = h0[0] * np.abs(axis @ u0) + h0[1] * np.abs(axis @ v0)
        r1 = h1[:, 0] * np.abs(np.sum(axis * u1, axis=1)) + h1[:, 1] * np.abs(np.sum(axis * v1, axis=1))
        separated |= dist > r0 + r1 + TOUCH_EPS_M
    return ~separated


def _select(agents: AgentBoxes, categories: Collection[str] | None) -> np.ndarray:
    if categories is None:
        return np.ones(len(agents), dtype=bool)
    wanted = set(categories)
    return np.array([c in wanted for c in agents.category], dtype=bool)


def _ego_hits(traj: np.ndarray, agents: Sequence[AgentBoxes], categories: Collection[str] | None) -> np.ndarray:
    """Per step: does the ego box at this trajectory's waypoint overlap any selected agent box of that step."""
    headings = step_headings(traj)
    ego_size = (EGO_LENGTH, EGO_WIDTH)
    hits = np.zeros(HORIZON_STEPS, dtype=bool)
    for i, boxes in enumerate(agents[:HORIZON_STEPS]):
        keep = _select(boxes, categories)
        if not keep.any():
            continue
        overlap = boxes_overlap(
            traj[i], ego_size, headings[i], boxes.center[keep], boxes.size[keep], boxes.yaw[keep]
        )
        hits[i] = bool(overlap.any())
    return hits


def collision_per_step(
    pred: Any, gt: Any, agents: Sequence[AgentBoxes], *, categories: Collection[str] | None = None
) -> np.ndarray:
    """Per step (6,) bool: the planned ego box hits an agent box of `categories` while the GT ego box does not.

    `agents` holds one ``AgentBoxes`` per future step (the same future time as the waypoint); `categories`
    None means every agent. Headings come from the step direction (see ``step_headings``). Touching boxes
    count as a collision (within ``TOUCH_EPS_M``). Missing steps (fewer than six ``AgentBoxes``) never collide.
    """
    pred_arr, gt_arr = _as_plan(pred, "pred"), _as_plan(gt, "gt")
    return _ego_hits(pred_arr, agents, categories) & ~_ego_hits(gt_arr, agents, categories)


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


def bit1_density(images: Mapping[str, np.ndarray]) -> float:
    """Fraction of 1 bits among all bytes of all images: the energy proxy (divide by clean's for relative).

    Bytes are counted with a 256-entry popcount table over a byte histogram, so a 6 x 800 x 450 sample costs
    a few milliseconds. Returns 0.0 when there are no bytes.
    """
    ones = 0
    total = 0
    for image in images.values():
        raw = np.ascontiguousarray(image).view(np.uint8).reshape(-1)
        ones += int(np.bincount(raw, minlength=256) @ _POPCOUNT)
        total += raw.size * 8
    return ones / total if total else 0.0


def frame_metrics(pred: Any, frame: Frame) -> dict[str, Any]:
    """Every per-frame metric of one plan, as plain builtins (safe to cross the xdist boundary).

    Returns ``{"l2": [6 floats], "collision": [6 ints], "collision_vru": [6 ints], "jerk": float}``.
    """
    pred_arr = _as_plan(pred, "pred")
    gt = _as_plan(frame.gt_future, "gt_future")
    agents = tuple(frame.agents)
    return {
        "l2": [float(v) for v in l2_per_step(pred_arr, gt)],
        "collision": [int(v) for v in collision_per_step(pred_arr, gt, agents)],
        "collision_vru": [int(v) for v in collision_per_step(pred_arr, gt, agents, categories=VRU_CATEGORIES)],
        "jerk": jerk(pred_arr),
    }
