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

A cell mode (``--drivedegrade-two-stage``): `RunContext.run_cell` adds stage two to every open-loop cell it runs
whole (`add_stage_two`: the record's ``epdms_stage2`` and ``epdms2``), through the cell's own stream (`stream`:
the loader corrupts each rendered camera with the cell's operator under the per-frame seed rule, keyed by the
stage-two frame's own token; the ego and command cells perturb its inputs as they do a logged frame's; every
call checked and timed as stage one's). Each stage-two start is a scene of its own: no state, no frame_dropout
hold and no extended comfort crosses from one start to another (a planner with ``reset()``, which would need the
stage-one history replayed before each start, is refused by the pre-flight check).
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import stream
from ..cells import CellRecord
from ..data import geometry as geo
from ..data.context import FrameContext
from ..data.frame import AgentBoxes, EgoStatus, Frame
from ..data.junctions import Alternative
from ..data.nuscenes import WORLD_MANIFEST
from ..data.world.rig import Rig
from ..data.world.scene import make_scene
from ..errors import DataError
from ..metrics.pdms import PreparedFrame, tracked_states
from ..metrics.pdms.two_stage import STAGE_TWO_STARTS, group_score, stage_two_weights, weighted_average
from ..metrics.trajectory import FrameTruth
from ..planning import Planner
from ..settings import RunSettings
from .camera import images_at
from .routes import Route, route_of

if TYPE_CHECKING:
    from ..run import RunContext



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
    `pose`, its velocity and acceleration turned with it (the logged state, moved); a token and a scene token of
    its own (each start is a scene of one frame). No history comfort (no past motion of the moved ego)."""
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
    token = f"{frame.token}~stage2~{index}"
    scene = f"{frame.scene_token}~stage2~{frame.index}~{index}"
    return replace(frame, token=token, scene_token=scene, ego=moved, gt_future=to_new(frame.gt_future),
                   agents=tuple(_boxes(b, to_new, turn) for b in frame.agents),
                   pose=(float(pose[0]), float(pose[1]), float(pose[2])),
                   ego_pose=(geo.yaw_to_quat(pose[2]), (float(pose[0]), float(pose[1]), float(height))),
                   past_motion=None, future_tail=tail,
                   agents_tail=tuple(_boxes(b, to_new, turn) for b in frame.agents_tail))


@dataclass(frozen=True)
class StageTwo:
    """A cell's two-stage figures per frame (NaN where a frame has no stage two: its stage-two keyframe lacks
    the future to score, or a plan of either stage failed): stage two's weighted EPDMS, and stage one's times it;
    the stage-two frames' failures (each message names its frame's stage-two token)."""

    stage_two: np.ndarray
    two_stage: np.ndarray
    starts: int
    errors: tuple[str, ...] = ()
    data_errors: tuple[str, ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)  #: stage two's cost (`stream.run_cell`'s seconds)
    calls: int = 0  #: stage-two frames the planner was given (frames with a stage two x starts)

    @property
    def frames(self) -> int:
        """Frames with a stage two."""
        return int(np.isfinite(self.two_stage).sum())


#: Rendered stage-two images a process keeps for the next cells (every cell renders the same poses): fill once,
#: never evict, like the decode cache; past it an image is rendered again, to the same pixels.
RENDER_CACHE_BYTES = 512 * 2**20


def require_world(root: Path) -> None:
    """DataError unless `root` is a world the suite can render (its manifest): the two-stage mode's data check."""
    if not (Path(root) / WORLD_MANIFEST).is_file():
        raise DataError(f"--drivedegrade-two-stage needs the embedded world (a data root with {WORLD_MANIFEST}), "
                        f"and {root} is not one: stage two renders the cameras at start poses the car never drove, "
                        "and real logs (nuScenes) hold images only where it drove. Drop --drivedegrade-data (the "
                        "default world) or --drivedegrade-two-stage")


@dataclass
class StageTwoWorld:
    """What stage two reads in one process, built once and shared by its cells: the routes (one per scene, for
    rendering), the keyframes stage two starts at, and the rendered images (`RENDER_CACHE_BYTES`)."""

    routes: dict[str, Route]
    keyframes: dict[tuple[str, int], Frame]
    rendered: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    rendered_bytes: int = 0
    #: the prefetch thread and the planner's thread may both render: one at a time (the pixels are the same)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @classmethod
    def of(cls, context: RunContext) -> StageTwoWorld:
        root = Path(context.reader.root)
        require_world(root)
        manifest = json.loads((root / WORLD_MANIFEST).read_text())
        names = [*manifest["splits"]["train"], *manifest["splits"]["val"]]
        rig = Rig.nuscenes_like(bool(manifest.get("full_size", False)))
        wanted = sorted({f.scene_name for f in context.frames}, key=names.index)
        routes = {n: route_of(make_scene(int(manifest["seed"]), names.index(n), n), rig) for n in wanted}
        keyframes = {(f.scene_name, f.index): f for f in context.reader.scorable_frames() if f.scene_name in routes}
        return cls(routes, keyframes)

    def render(self, frame: Frame, pose: tuple[float, float, float], camera: str) -> np.ndarray:
        """`camera` at world `pose` at keyframe `frame` of its scene (read-only; cached within the budget)."""
        key = (frame.token, camera)
        with self.lock:
            found = self.rendered.get(key)
            if found is None:
                found = images_at(self.routes[frame.scene_name], (camera,), pose, frame.index)[camera]
                found.setflags(write=False)
                if self.rendered_bytes + found.nbytes <= RENDER_CACHE_BYTES:
                    self.rendered[key], self.rendered_bytes = found, self.rendered_bytes + found.nbytes
        return found


def stage_two_world(context: RunContext) -> StageTwoWorld:
    """The run's `StageTwoWorld` in this process (kept on the context: ``stage_two_cache``), built at first use."""
    found = context.stage_two_cache
    if not isinstance(found, StageTwoWorld):
        found = context.stage_two_cache = StageTwoWorld.of(context)
    return found


def enable(context: RunContext) -> RunContext:
    """`context` ready for the two-stage mode: its data checked (`require_world`) and its stage-two step set."""
    require_world(Path(context.reader.root))
    context.stage_two = add_stage_two
    return context


class StageTwoSource:
    """The run as a `stream.Source` whose frames are stage-two frames: their images rendered at their start pose
    (`StageTwoWorld.render`) instead of decoded; contexts, PDMS preparations and truths from the run's caches."""

    def __init__(self, context: RunContext, world: StageTwoWorld, poses: dict[str, tuple[float, float, float]]):
        self.context, self.world, self.poses = context, world, poses

    @property
    def settings(self) -> RunSettings:
        return self.context.settings

    def decode(self, frame: Frame, camera: str) -> np.ndarray:
        return self.world.render(frame, self.poses[frame.token], camera)

    def context_of(self, frame: Frame) -> FrameContext:
        return self.context.context_of(frame)

    def pdms_frame(self, frame: Frame, poses: int = 6) -> PreparedFrame:
        return self.context.pdms_frame(frame, poses)

    def frame_truth(self, frame: Frame) -> FrameTruth:
        return self.context.frame_truth(frame)

    def alternative_of(self, frame: Frame) -> Alternative | None:
        return self.context.alternative_of(frame)


def _stage_two_frames(context: RunContext, world: StageTwoWorld, record: CellRecord,
                      offsets: tuple[tuple[float, float, float], ...]
                      ) -> tuple[list[Frame], dict[str, tuple[float, float, float]], dict[int, np.ndarray]]:
    """Every cell frame's stage-two frames in order, their start poses by token, and each frame's stage-one plan
    end point (global) by frame index: only frames with a stage-two keyframe and a stage-one plan."""
    poses = int(record.plans.shape[1])
    moved: list[Frame] = []
    where: dict[str, tuple[float, float, float]] = {}
    ends: dict[int, np.ndarray] = {}
    for i, frame in enumerate(context.frames):
        later = world.keyframes.get((frame.scene_name, frame.index + poses))
        plan = record.plans[i]
        if later is None or later.pose is None or not np.isfinite(plan).all():
            continue
        first = context.pdms_frame(frame, poses)
        ends[i] = frame.to_global(tracked_states(plan[None], [first.initial])[0].xy[-1])
        for n, pose in enumerate(start_poses(later.pose, offsets)):
            moved.append(stage_two_frame(later, pose, n))
            where[moved[-1].token] = pose
    return moved, where, ends


def stage_two_cell(context: RunContext, planner: Planner, record: CellRecord, *, seed: int | None = None,
                   unread: tuple[str, ...] = (),
                   offsets: tuple[tuple[float, float, float], ...] = STAGE_TWO_STARTS) -> StageTwo:
    """Stage two of every frame of the cell `record` (run by `context` on `planner`, on all of its frames): see
    the module. `unread`: the cameras the null control blacks out."""
    if record.frames != [f.token for f in context.frames]:
        raise DataError(f"cell {record.cell!r}: stage two runs on a whole cell of the run's frames")
    world = stage_two_world(context)
    moved, where, ends = _stage_two_frames(context, world, record, offsets)
    stage = stream.run_cell(StageTwoSource(context, world, where), planner, record.family, record.severity, moved,
                            unread=unread, seed=context.seed if seed is None else seed)
    stage_two, two_stage = (np.full(len(record.frames), np.nan) for _ in range(2))
    k = len(offsets)
    for j, (i, end) in enumerate(ends.items()):
        scores = stage.epdms[j * k:(j + 1) * k]
        weights = stage_two_weights(end, [where[f.token][:2] for f in moved[j * k:(j + 1) * k]])
        stage_two[i] = weighted_average(scores, weights)
        two_stage[i] = group_score(float(record.epdms[i]), scores, weights)
    return StageTwo(stage_two, two_stage, k, tuple(stage.errors), tuple(stage.data_errors), dict(stage.seconds),
                    len(moved))


def add_stage_two(context: RunContext, planner: Planner, record: CellRecord, *, seed: int,
                  unread: tuple[str, ...]) -> CellRecord:
    """`record` with its stage two (`stage_two_cell`): ``epdms_stage2`` and ``epdms2`` per frame, the stage-two
    failures added to its own (prefixed ``stage two:``), so a planner failing there fails the cell's contract; its
    seconds added to the cell's (the cost ledger's parts and walls include stage two; ``stage_two_calls`` counts
    its planner calls)."""
    two = stage_two_cell(context, planner, record, seed=seed, unread=unread)
    seconds = {k: float(record.seconds.get(k, 0.0)) + float(two.seconds.get(k, 0.0))
               for k in (*record.seconds, *(k for k in two.seconds if k not in record.seconds))}
    record.seconds = {**seconds, "stage_two_calls": float(two.calls)}
    record.epdms_stage2, record.epdms2 = two.stage_two, two.two_stage
    record.errors = [*record.errors, *(f"stage two: {e}" for e in two.errors)]
    record.data_errors = [*record.data_errors, *(f"stage two: {e}" for e in two.data_errors)]
    return record

