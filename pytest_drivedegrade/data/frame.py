"""The frame model: what the reader yields for one keyframe, and the types planners receive.

Everything here is plain data. Arrays are numpy; coordinates are in the *current ego frame* (x forward,
y left, metres) unless a field says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from ..constants import COMMAND_THRESHOLD_M, HORIZON_STEPS, PAST_STEPS


class Command(IntEnum):
    """High-level driving command, in UniAD's order."""

    RIGHT = 0
    LEFT = 1
    STRAIGHT = 2


def command_from_future(future_xy: np.ndarray, threshold: float = COMMAND_THRESHOLD_M) -> Command:
    """The 2 m rule: LEFT / RIGHT when the final future waypoint lies at least `threshold` to that side."""
    lateral = float(np.asarray(future_xy, dtype=float)[-1, 1])
    if lateral >= threshold:
        return Command.LEFT
    if lateral <= -threshold:
        return Command.RIGHT
    return Command.STRAIGHT


@dataclass(frozen=True)
class EgoStatus:
    """Ego status at the current keyframe, in the current ego frame.

    `past_xy` holds the last `PAST_STEPS` keyframe positions (2 s), oldest first, as (x, y) in the current
    ego frame (so the most recent past point lies behind the ego, x < 0 when driving forward).
    """

    velocity: tuple[float, float]  # (vx, vy) m/s
    acceleration: tuple[float, float]  # (ax, ay) m/s^2
    yaw_rate: float  # rad/s, positive turning left
    past_xy: np.ndarray = field(default_factory=lambda: np.zeros((PAST_STEPS, 2)))

    def as_vector(self) -> np.ndarray:
        """A fixed-order float32 feature vector: vx, vy, ax, ay, yaw_rate, then past (x, y) oldest first."""
        head = np.array([*self.velocity, *self.acceleration, self.yaw_rate], dtype=np.float32)
        return np.concatenate([head, np.asarray(self.past_xy, dtype=np.float32).reshape(-1)])

    @staticmethod
    def vector_size() -> int:
        return 5 + 2 * PAST_STEPS


@dataclass(frozen=True)
class CameraInfo:
    """One camera of a keyframe: where its image is and how it is mounted.

    `intrinsic` is the 3x3 camera matrix for the image as stored; `rotation` (w, x, y, z quaternion) and
    `translation` (m) map camera coordinates to the ego frame, as nuScenes' calibrated_sensor does.
    """

    name: str
    path: str
    width: int
    height: int
    intrinsic: np.ndarray
    rotation: tuple[float, float, float, float]
    translation: tuple[float, float, float]
    sample_token: str = ""  # the keyframe (sample) this image belongs to, for error messages


@dataclass(frozen=True)
class AgentBoxes:
    """Annotated agents at one future keyframe, as oriented boxes in the current ego frame."""

    center: np.ndarray  # (N, 2) x, y
    size: np.ndarray  # (N, 2) length (along heading), width
    yaw: np.ndarray  # (N,) heading rad, in the current ego frame
    category: tuple[str, ...]  # coarse class per box: vehicle, pedestrian, cyclist, other

    @staticmethod
    def empty() -> AgentBoxes:
        return AgentBoxes(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0,)), ())

    def __len__(self) -> int:
        return len(self.category)


@dataclass(frozen=True)
class Frame:
    """One scorable (or not) keyframe: images to decode, ego status, command and ground-truth future."""

    token: str
    scene_token: str
    timestamp: int  # microseconds, nuScenes convention
    cameras: dict[str, CameraInfo]
    ego: EgoStatus
    command: Command
    gt_future: np.ndarray  # (HORIZON_STEPS, 2) in the current ego frame
    gt_valid: np.ndarray  # (HORIZON_STEPS,) bool
    agents: tuple[AgentBoxes, ...] = ()  # one per future step, len HORIZON_STEPS when scorable
    scene_name: str = ""
    index: int = 0  #: position of this keyframe in its scene (0 = the scene's first keyframe)
    #: ego_pose at this keyframe: (rotation (w, x, y, z), translation (x, y, z) m), ego -> global.
    ego_pose: tuple[tuple[float, ...], tuple[float, ...]] = ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    #: LIDAR_TOP's calibrated_sensor (rotation, translation), lidar -> ego; None when the data set has none.
    lidar: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    #: The CAN bus pose message at or before this keyframe (accel, rotation_rate, vel; 3 values each), or None.
    can: dict[str, tuple[float, ...]] | None = None
    location: str = ""  # the log's location, which names its map ("" when the data has no log table)
    pose: tuple[float, float, float] | None = None  # global (x, y, yaw) of the ego at this keyframe
    lidar_file: str = ""  # the keyframe's LIDAR_TOP sweep (.pcd.bin), "" when the data set has none
    #: The past keyframes' logged motion, for NAVSIM's history comfort (scoring only, never a planner input):
    #: (PAST_STEPS, 4) oldest first, each (time relative to this keyframe in microseconds, heading relative to
    #: this keyframe's (rad), that keyframe's own acceleration (ax, ay) m/s^2 in its body frame, as its
    #: `EgoStatus` has it). A keyframe before the scene's first repeats the first's motion 0.5 s further back.
    #: None where the data give no past (a closed-loop frame).
    past_motion: np.ndarray | None = None
    #: A non-finite planner input of the data set (`data.faults.input_fault`), set for a run's scored frames by
    #: `RunContext.open`: the frame is then a data fault in every cell. "" when there is none.
    input_fault: str = ""
    #: The future keyframes beyond the sixth, on data with more than 3 s of future (a world generated with
    #: ``--future 4``): their positions (T, 2) in the current ego frame and their agent boxes, for a planner of
    #: NAVSIM's eight poses (`future`, `future_agents`); None and () elsewhere.
    future_tail: np.ndarray | None = None
    agents_tail: tuple[AgentBoxes, ...] = ()
    #: The future keyframes a scored frame of its data holds (2 x the data's future seconds): 6, or 8.
    future_needed: int = HORIZON_STEPS

    def future(self, poses: int = HORIZON_STEPS) -> np.ndarray:
        """The logged future of `poses` waypoints (the first six are `gt_future`); ValueError when the data hold
        fewer future keyframes here."""
        if poses == HORIZON_STEPS:
            return self.gt_future
        tail = self.future_tail if self.future_tail is not None else np.zeros((0, 2))
        if len(tail) < poses - HORIZON_STEPS:
            raise ValueError(f"frame {self.token} holds {HORIZON_STEPS + len(tail)} future keyframes, not {poses}")
        return np.concatenate([self.gt_future, tail[: poses - HORIZON_STEPS]])

    def future_agents(self, poses: int = HORIZON_STEPS) -> tuple[AgentBoxes, ...]:
        """The agent boxes of `poses` future keyframes (the first six are `agents`)."""
        if poses == HORIZON_STEPS:
            return self.agents
        return tuple(self.agents) + tuple(self.agents_tail[: poses - HORIZON_STEPS])

    def to_global(self, xy: np.ndarray) -> np.ndarray:
        """Points (..., 2) of the current ego frame in global metres (the map's frame); needs `pose`."""
        if self.pose is None:
            raise ValueError(f"frame {self.token} has no global ego pose")
        x, y, yaw = self.pose
        pts = np.asarray(xy, dtype=float)
        c, s = np.cos(yaw), np.sin(yaw)
        return np.stack([x + c * pts[..., 0] - s * pts[..., 1], y + s * pts[..., 0] + c * pts[..., 1]], axis=-1)

    @property
    def scorable(self) -> bool:
        """True when all six future keyframes exist (the VAD-style valid-planning subset), and on data with 4 s of
        future (`future_needed` 8) the two after them too."""
        tail = 0 if self.future_tail is None else len(self.future_tail)
        return bool(np.asarray(self.gt_valid).all()) and len(self.gt_valid) == HORIZON_STEPS and \
            HORIZON_STEPS + tail >= self.future_needed
