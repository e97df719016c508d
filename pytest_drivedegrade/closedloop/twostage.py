"""NAVSIM v2's two-stage pseudo-simulation on the embedded world (issue 39), for one cell's plans.

Stage one is the cell itself: each frame's plan, scored as the cell scored it (its EPDMS). Stage two starts where
the stage-one plan ends in time (the keyframe `poses` x 0.5 s later: 3 s, or 4 s for an 8-pose planner), from
start poses around the logged ego there (`STAGE_TWO_STARTS`). At each start the cameras are rendered by the world
at that pose (`camera.images_at`: NAVSIM renders its synthetic scenes in advance by Gaussian
splatting, the world renders them exactly) and corrupted with the cell's operator; the planner plans from the
logged state there seen from the new pose, and the plan is scored against that keyframe's logged future, agents
and map, all seen from the start pose. The stage-two scenes are weighted by how close their start lies to where
the stage-one plan ended, and stage one's EPDMS is multiplied by the weighted mean of stage two's
(`metrics.pdms.two_stage`, NAVSIM's aggregation).

Not part of a certification yet: a library function and `benchmarks/navsim_two_stage.py` (docs/explanation/
navsim.md says what is missing).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from ..cells import CellRecord
from ..constants import CAMERAS
from ..corruptions.api import corrupt_sample
from ..data import geometry as geo
from ..data.context import FrameContext
from ..data.frame import AgentBoxes, EgoStatus, Frame
from ..metrics.pdms import PreparedFrame, tracked_states
from ..metrics.pdms.constants import EGO_BOXES
from ..metrics.pdms.extended import epdms_score
from ..metrics.pdms.two_stage import group_score, stage_two_weights, weighted_average
from ..planning import Planner, call_style, planner_cameras, validate_output
from .camera import images_at
from .routes import Route, load_routes

if TYPE_CHECKING:
    from ..run import RunContext

#: The stage-two start poses, (forward m, left m, yaw rad) from the logged ego pose in its own frame: the logged
#: pose, half a metre to each side, a metre ahead and behind, 5 degrees to each side. NAVSIM's come from its
#: synthetic-scene data set (navhard_two_stage), which the suite does not have: an adaptation.
STAGE_TWO_STARTS: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, -0.5, 0.0), (1.0, 0.0, 0.0), (-1.0, 0.0, 0.0),
    (0.0, 0.0, math.radians(5.0)), (0.0, 0.0, -math.radians(5.0)))


def start_poses(pose: tuple[float, float, float],
                offsets: tuple[tuple[float, float, float], ...] = STAGE_TWO_STARTS) -> list[tuple[float, float, float]]:
    """The world poses (x, y, yaw) of `offsets` (forward, left, yaw) from the ego pose `pose`."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return [(x + c * f - s * left, y + s * f + c * left, yaw + turn) for f, left, turn in offsets]


def _rotate(v: tuple[float, float], angle: float) -> tuple[float, float]:
    c, s = math.cos(angle), math.sin(angle)
    return (c * v[0] - s * v[1], s * v[0] + c * v[1])


def _boxes(boxes: AgentBoxes, to_new: Callable[[np.ndarray], np.ndarray], turn: float) -> AgentBoxes:
    if not len(boxes):
        return boxes
    return AgentBoxes(to_new(np.asarray(boxes.center, dtype=np.float64).reshape(-1, 2)), boxes.size,
                      geo.wrap_angle(np.asarray(boxes.yaw, dtype=np.float64) + turn), boxes.category)


def stage_two_frame(frame: Frame, pose: tuple[float, float, float], index: int) -> Frame:
    """Logged keyframe `frame` as the ego at world `pose` sees it: its future, agents and past in the frame of
    `pose`, its velocity and acceleration turned with it (the logged state, moved); a token of its own. No
    history comfort (no past motion of the moved ego)."""
    if frame.pose is None:
        raise ValueError(f"frame {frame.token} has no global pose: it cannot be moved")
    turn = float(frame.pose[2] - pose[2])

    def to_new(xy: np.ndarray) -> np.ndarray:
        return geo.se2_to_ego(frame.to_global(xy), np.array(pose[:2]), pose[2])

    ego = frame.ego
    moved = EgoStatus(_rotate(ego.velocity, turn), _rotate(ego.acceleration, turn), ego.yaw_rate,
                      to_new(np.asarray(ego.past_xy, dtype=np.float64)))
    tail = to_new(frame.future_tail) if frame.future_tail is not None and len(frame.future_tail) else \
        frame.future_tail
    height = frame.ego_pose[1][2] if len(frame.ego_pose[1]) > 2 else 0.0
    return replace(frame, token=f"{frame.token}~stage2~{index}", ego=moved, gt_future=to_new(frame.gt_future),
                   agents=tuple(_boxes(b, to_new, turn) for b in frame.agents),
                   pose=(float(pose[0]), float(pose[1]), float(pose[2])),
                   ego_pose=(geo.yaw_to_quat(pose[2]), (float(pose[0]), float(pose[1]), float(height))),
                   past_motion=None, future_tail=tail,
                   agents_tail=tuple(_boxes(b, to_new, turn) for b in frame.agents_tail))


@dataclass(frozen=True)
class StageTwo:
    """A cell's two-stage figures per frame (NaN where a frame has no stage two: its stage-two keyframe lacks
    the future to score, or its stage-one plan failed): stage two's weighted EPDMS, and stage one's times it."""

    stage_two: np.ndarray
    two_stage: np.ndarray
    starts: int

    @property
    def frames(self) -> int:
        """Frames with a stage two."""
        return int(np.isfinite(self.two_stage).sum())


def _scene_images(images: dict[str, np.ndarray], shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Six cameras: the rendered ones, the cameras the planner does not read black (it never looks at them)."""
    return {cam: images.get(cam, np.zeros(shape, np.uint8)) for cam in CAMERAS}


def stage_two_scores(context: RunContext, planner: Planner, later: Frame, poses: int, family: str, severity: int, *,
                     seed: int, starts: list[tuple[float, float, float]], route: Route) -> list[float]:
    """The planner's stage-two EPDMS from each start pose at keyframe `later` under the cell's operator."""
    style, cameras = call_style(planner), planner_cameras(planner)
    out = []
    for n, pose in enumerate(starts):
        moved = stage_two_frame(later, pose, n)
        rendered = images_at(route, cameras, pose, later.index)
        shape = next(iter(rendered.values())).shape if rendered else (1, 1, 3)
        images = corrupt_sample(_scene_images(rendered, shape), family, severity, seed=seed, frame=moved.token) \
            if family != "clean" else _scene_images(rendered, shape)
        for image in images.values():
            image.setflags(write=False)
        view = MappingProxyType(images)
        if style.takes_context:
            raw = planner.predict(view, moved.ego, moved.command, context=FrameContext.of(moved))  # type: ignore[call-arg]
        else:
            raw = planner.predict(view, moved.ego, moved.command)
        plan = validate_output(raw, moved.token, poses)
        prepared = PreparedFrame.of(moved, context.reader.drivable_area(later), lane_map=context.reader.lane_map(later),
                                    ego_size=EGO_BOXES[context.settings.ego_box], poses=poses)
        _, terms = prepared.judged(plan, tracked_states(plan[None], [prepared.initial])[0])
        out.append(epdms_score(terms.filtered(prepared.human) if prepared.human is not None else terms, math.nan))
    return out


def stage_two_cell(context: RunContext, planner: Planner, record: CellRecord, *, seed: int | None = None,
                   offsets: tuple[tuple[float, float, float], ...] = STAGE_TWO_STARTS) -> StageTwo:
    """Stage two of every frame of the cell `record` (run by `context` on `planner`): see the module."""
    poses = int(record.plans.shape[1])
    routes = {r.name: r for r in load_routes(context.reader.root)}
    later_of = {(f.scene_name, f.index): f for f in context.reader.scorable_frames()}
    stage_two, two_stage = (np.full(len(record.frames), np.nan) for _ in range(2))
    for i, frame in enumerate(context.frames):
        later = later_of.get((frame.scene_name, frame.index + poses))
        plan = record.plans[i]
        if later is None or later.pose is None or frame.scene_name not in routes or not np.isfinite(plan).all():
            continue
        first = context.pdms_frame(frame, poses)
        end = frame.to_global(tracked_states(plan[None], [first.initial])[0].xy[-1])
        starts = start_poses(later.pose, offsets)
        scores = stage_two_scores(context, planner, later, poses, record.family, record.severity,
                                  seed=context.seed if seed is None else seed, starts=starts,
                                  route=routes[frame.scene_name])
        weights = stage_two_weights(end, [p[:2] for p in starts])
        stage_two[i] = weighted_average(scores, weights)
        two_stage[i] = group_score(float(record.epdms[i]), scores, weights)
    return StageTwo(stage_two, two_stage, len(offsets))
