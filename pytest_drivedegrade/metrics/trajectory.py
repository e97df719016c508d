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
- Jerk is the mean norm of the plan's third finite difference; the bit-1 density of the delivered images is
  the energy proxy.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TypedDict

import cv2
import numpy as np
import numpy.typing as npt

from ..constants import EGO_LENGTH, EGO_WIDTH, HORIZON_STEPS, REPORT_HORIZONS_S, STEP_SECONDS, VRU_CATEGORIES
from ..corruptions.derived import derived
from ..data.frame import AgentBoxes, Frame

#: Step index (0-based, into the six waypoints) of each reported horizon: 1 s -> 1, 2 s -> 3, 3 s -> 5.
HORIZON_INDEX: tuple[int, ...] = tuple(int(round(h / STEP_SECONDS)) - 1 for h in REPORT_HORIZONS_S)
#: The aggregation conventions ``at_horizons`` understands.
CONVENTIONS: tuple[str, ...] = ("stp3", "uniad")
#: A step shorter than this (metres) carries no reliable direction; the previous heading is kept.
MIN_STEP_M: float = 1e-3
#: Slack (metres) on the separating-axis test, so that boxes which touch exactly still count after rounding.
TOUCH_EPS_M: float = 1e-9

#: The ego box (length, width) and its half diagonal, the radius of the bounding-circle pre-test.
_EGO_SIZE = np.array([EGO_LENGTH, EGO_WIDTH])
_EGO_RADIUS = float(np.hypot(EGO_LENGTH, EGO_WIDTH) / 2)
# Number of 1 bits in every byte value, for the energy proxy.
_POPCOUNT_U8 = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1).astype(np.uint8)


def _as_plan(traj: npt.ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(traj, dtype=np.float64)
    if arr.shape != (HORIZON_STEPS, 2):
        raise ValueError(f"{name} must have shape ({HORIZON_STEPS}, 2), got {arr.shape}")
    return arr


def l2_per_step(pred: npt.ArrayLike, gt: npt.ArrayLike) -> np.ndarray:
    """Euclidean distance (m) between planned and ground-truth waypoints, one per step: shape (6,)."""
    return np.linalg.norm(_as_plan(pred, "pred") - _as_plan(gt, "gt"), axis=1)


def step_headings(traj: npt.ArrayLike) -> np.ndarray:
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


def overlap_pairs(c0: np.ndarray, size0: np.ndarray, yaw0: np.ndarray, c1: np.ndarray, size1: np.ndarray,
                  yaw1: np.ndarray) -> np.ndarray:
    """Whether box i of the first set overlaps box i of the second, for N pairs at once: shape (N,) bool.

    Centres (N, 2), sizes (N, 2) as (length along heading, width) and yaws (N,) rad, in one frame. The exact
    separating-axis test: two rectangles are disjoint iff their projections on one of the four edge normals
    are, with ``TOUCH_EPS_M`` of slack so that touching boxes overlap. Shared by the collision metric here and
    the PDMS contacts (`metrics.pdms`). Written per coordinate: each |a . b| is a_x b_x + a_y b_y, the sum over
    the length-2 axis it once was, in the same order, so the same bits at twice the speed
    (tests/unit/test_metrics.py checks it against the vector form).
    """
    u0x, u0y = np.cos(yaw0), np.sin(yaw0)  # each box's heading u and its normal v = (-u_y, u_x)
    u1x, u1y = np.cos(yaw1), np.sin(yaw1)
    h0x, h0y = size0[:, 0] / 2.0, size0[:, 1] / 2.0
    h1x, h1y = size1[:, 0] / 2.0, size1[:, 1] / 2.0
    dx, dy = c1[:, 0] - c0[:, 0], c1[:, 1] - c0[:, 1]
    separated = np.zeros(len(c0), dtype=bool)
    for ax, ay in ((u0x, u0y), (-u0y, u0x), (u1x, u1y), (-u1y, u1x)):
        r0 = h0x * np.abs(ax * u0x + ay * u0y) + h0y * np.abs(ax * -u0y + ay * u0x)
        r1 = h1x * np.abs(ax * u1x + ay * u1y) + h1y * np.abs(ax * -u1y + ay * u1x)
        separated |= np.abs(dx * ax + dy * ay) > r0 + r1 + TOUCH_EPS_M
    return ~separated


def boxes_overlap(
    center: npt.ArrayLike, size: npt.ArrayLike, yaw: float, centers: npt.ArrayLike, sizes: npt.ArrayLike,
    yaws: npt.ArrayLike
) -> np.ndarray:
    """Whether one oriented box overlaps each of N oriented boxes: exact separating-axis test, shape (N,) bool.

    Boxes are (length along heading, width). Two rectangles are disjoint iff their projections on one of the
    four edge normals are disjoint; boxes that merely touch (share an edge or a corner) count as overlapping.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    n = len(centers)
    if n == 0:
        return np.zeros(0, dtype=bool)
    return overlap_pairs(np.broadcast_to(np.asarray(center, np.float64), (n, 2)),
                         np.broadcast_to(np.asarray(size, np.float64), (n, 2)), np.full(n, float(yaw)),
                         centers, np.asarray(sizes, np.float64).reshape(-1, 2),
                         np.asarray(yaws, np.float64).reshape(-1))


@dataclass(frozen=True)
class FlatAgents:
    """The agent boxes of the six future steps as flat arrays, in (step, box) order: one test for all of them."""

    step: np.ndarray  # (M,) waypoint index 0..5 of each box
    centers: np.ndarray  # (M, 2)
    sizes: np.ndarray  # (M, 2)
    yaws: np.ndarray  # (M,)
    categories: np.ndarray  # (M,) object: the coarse class of each box
    count: int = HORIZON_STEPS  # the steps (waypoint times) the boxes belong to: 6, or 8 for a 4 s plan

    @classmethod
    def of(cls, agents: Sequence[AgentBoxes], count: int = HORIZON_STEPS) -> FlatAgents:
        """All agents of the first `count` steps (none: empty arrays)."""
        steps = list(agents[:count])
        counts = [len(b) for b in steps]
        if not sum(counts):
            return cls(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, object),
                       count)
        return cls(np.repeat(np.arange(len(steps)), counts),
                   np.concatenate([np.asarray(b.center, np.float64).reshape(-1, 2) for b in steps]),
                   np.concatenate([np.asarray(b.size, np.float64).reshape(-1, 2) for b in steps]),
                   np.concatenate([np.asarray(b.yaw, np.float64).reshape(-1) for b in steps]),
                   np.array([c for b in steps for c in b.category], dtype=object), count)

    @cached_property
    def step_start(self) -> np.ndarray:
        """(count + 1,) where each step's boxes start in the flat arrays (they are in step order)."""
        return np.concatenate([[0], np.cumsum(np.bincount(self.step, minlength=self.count))])

    def pairs(self, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every (query, box) pair of queries at waypoint `step` (Q,) and that step's boxes, in (query, box)
        order: what ``np.nonzero(step[:, None] == self.step[None, :])`` finds, without the Q x M comparison."""
        start = self.step_start
        first = start[step]
        counts = start[step + 1] - first
        total = int(counts.sum())
        query = np.repeat(np.arange(len(step)), counts)
        box = np.arange(total) + np.repeat(first - (np.cumsum(counts) - counts), counts)
        return query, box

    @cached_property
    def reach(self) -> np.ndarray:
        """(M,) the distance within which a box's centre may touch the ego box: both half diagonals."""
        return _EGO_RADIUS + np.hypot(self.sizes[:, 0], self.sizes[:, 1]) / 2 + 1e-6

    def hits(self, traj: np.ndarray) -> np.ndarray:
        """Per box (M,) bool: the ego box at that box's step waypoint of `traj` overlaps it. A bounding-circle
        test first leaves the exact separating-axis test to the few boxes near the ego (the distance written per
        coordinate: `np.linalg.norm`'s sum over the length-2 axis, the same bits)."""
        ego = traj[self.step]
        dx, dy = self.centers[:, 0] - ego[:, 0], self.centers[:, 1] - ego[:, 1]
        near = np.sqrt(dx * dx + dy * dy) <= self.reach
        hits = np.zeros(len(self.step), dtype=bool)
        if near.any():
            k = np.flatnonzero(near)
            hits[k] = overlap_pairs(ego[k], np.broadcast_to(_EGO_SIZE, (len(k), 2)),
                                    step_headings(traj)[self.step[k]], self.centers[k], self.sizes[k], self.yaws[k])
        return hits

    def of_categories(self, categories: Collection[str] | None) -> np.ndarray | None:
        """Per box (M,) bool: its class is one of `categories` (None: every box, no mask)."""
        return None if categories is None else np.isin(self.categories, list(categories))

    def per_step(self, hits: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
        """Per step (6,) bool: some box of that step is hit (and kept by the mask `keep`)."""
        out = np.zeros(HORIZON_STEPS, dtype=bool)
        if hits.any():
            chosen = hits if keep is None else hits & keep
            out[np.unique(self.step[chosen])] = True
        return out



def collision_per_step(
    pred: npt.ArrayLike, gt: npt.ArrayLike, agents: Sequence[AgentBoxes], *, categories: Collection[str] | None = None
) -> np.ndarray:
    """Per step (6,) bool: the planned ego box hits an agent box of `categories` while the GT ego box does not.

    `agents` holds one ``AgentBoxes`` per future step (the same future time as the waypoint); `categories`
    None means every agent. Headings come from the step direction (see ``step_headings``). Touching boxes
    count as a collision (within ``TOUCH_EPS_M``). Missing steps (fewer than six ``AgentBoxes``) never collide.
    """
    pred_arr, gt_arr = _as_plan(pred, "pred"), _as_plan(gt, "gt")
    flat = FlatAgents.of(agents)
    keep = flat.of_categories(categories)
    return flat.per_step(flat.hits(pred_arr), keep) & ~flat.per_step(flat.hits(gt_arr), keep)


def at_horizons(per_step: npt.ArrayLike, convention: str) -> np.ndarray:
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


def l2_avg(per_step: npt.ArrayLike, convention: str = "stp3") -> float | np.ndarray:
    """Mean over the three horizons of ``at_horizons``: a float for one frame (6,), an array for (..., 6)."""
    value = at_horizons(per_step, convention).mean(axis=-1)
    return float(value) if np.ndim(value) == 0 else value


def jerk(plan: npt.ArrayLike) -> float:
    """Mean absolute jerk (m/s^3) of a plan: the mean norm of its third finite difference.

    The origin (0, 0) is prepended as the t = 0 position, giving seven positions 0.5 s apart; velocity,
    acceleration and jerk are successive differences divided by 0.5 s, leaving four jerk vectors whose
    Euclidean norms are averaged. A constant-acceleration plan has zero jerk.
    """
    pts = np.vstack([np.zeros((1, 2)), _as_plan(plan, "plan")])
    third = np.diff(pts, n=3, axis=0) / STEP_SECONDS**3
    return float(np.linalg.norm(third, axis=1).mean())


def endpoint_shift(plan: npt.ArrayLike, reference_plan: npt.ArrayLike) -> float:
    """Distance (m) between the 3 s waypoints of a plan and a reference plan (the clean one)."""
    return float(np.linalg.norm(_as_plan(plan, "plan")[-1] - _as_plan(reference_plan, "reference_plan")[-1]))


def _ones(raw: np.ndarray) -> int:
    """Number of 1 bits in a flat uint8 array: a hardware popcount over 64-bit words (numpy >= 2), summed by
    OpenCV (integer counts, exact in its double: 2x faster than numpy's sum of the uint8 counts), the remaining
    bytes through a 256-entry table."""
    words = raw.size // 8 * 8 if hasattr(np, "bitwise_count") else 0
    ones = int(cv2.sumElems(np.bitwise_count(raw[:words].view(np.uint64)).reshape(1, -1))[0]) if words else 0
    return ones + (int(_POPCOUNT_U8[raw[words:]].sum(dtype=np.int64)) if words < raw.size else 0)


def bit1_density(images: Mapping[str, np.ndarray]) -> float:
    """Fraction of 1 bits among all bytes of all images: the energy proxy (divide by clean's for relative).

    About 0.15 ms for an 800 x 450 image. Returns 0.0 when there are no bytes.
    """
    ones = 0
    total = 0
    for image in images.values():
        arr = np.ascontiguousarray(image)  # the array itself when it is one: a registered image stays itself
        ones += derived(arr, "ones", _image_ones)  # a decoded clean image's count is kept (`corruptions.derived`)
        total += arr.nbytes * 8
    return ones / total if total else 0.0


def _image_ones(image: np.ndarray) -> int:
    return _ones(image.view(np.uint8).reshape(-1))


class FrameMetrics(TypedDict):
    """`frame_metrics`' result: plain builtins, safe to cross the xdist boundary."""

    l2: list[float]  # per step (6), metres
    collision: list[int]  # per step (6), 0 / 1
    collision_vru: list[int]  # per step (6), 0 / 1, pedestrians and cyclists only
    jerk: float  # m/s^3


@dataclass(frozen=True)
class FrameTruth:
    """What `frame_metrics` derives from the frame alone (its logged future, its agents as flat boxes, which are
    vulnerable road users, which steps the logged ego itself touches), made once per frame and process."""

    gt: np.ndarray
    flat: FlatAgents
    vru: np.ndarray | None
    gt_steps: np.ndarray  #: (6,) bool: the logged future touches some box at that step
    gt_vru_steps: np.ndarray  #: (6,) bool: ... some pedestrian or cyclist

    @classmethod
    def of(cls, frame: Frame) -> FrameTruth:
        gt = _as_plan(frame.gt_future, "gt_future")
        flat = FlatAgents.of(tuple(frame.agents))
        vru = flat.of_categories(VRU_CATEGORIES)
        gt_hits = flat.hits(gt)
        return cls(gt, flat, vru, flat.per_step(gt_hits), flat.per_step(gt_hits, vru))


def frame_metrics(pred: npt.ArrayLike, frame: Frame, truth: FrameTruth | None = None) -> FrameMetrics:
    """Every per-frame metric of one plan: L2 and collisions (all agents, VRUs) per step, and the jerk. `truth`:
    the frame's `FrameTruth` where the caller keeps it (made here otherwise)."""
    pred_arr = _as_plan(pred, "pred")
    t = truth if truth is not None else FrameTruth.of(frame)
    pred_hits = t.flat.hits(pred_arr)
    collision = t.flat.per_step(pred_hits) & ~t.gt_steps
    collision_vru = t.flat.per_step(pred_hits, t.vru) & ~t.gt_vru_steps
    return {
        "l2": [float(v) for v in l2_per_step(pred_arr, t.gt)],
        "collision": [int(v) for v in collision],
        "collision_vru": [int(v) for v in collision_vru],
        "jerk": jerk(pred_arr),
    }
