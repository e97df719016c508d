"""Scene shards (SPEC section 9): a deterministic partition of the scored frames into N scene-contiguous shards
balanced by frame count, so a job array or a CI matrix runs shard I of N and `drivedegrade merge` joins them.

Whole scenes stay together (a temporal planner's stream is never cut), and shard order is scene order, so the
merged frames are in exactly the order of an unsharded run.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from .data.frame import Frame
from .errors import DriveDegradeError

_SPEC = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")


@dataclass(frozen=True)
class Shard:
    """Shard `index` (1-based) of `count`."""

    index: int
    count: int

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    @property
    def label(self) -> str:
        """A folder-safe name, e.g. ``shard-2-of-8``."""
        return f"shard-{self.index}-of-{self.count}"

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``I/N`` with 1 <= I <= N; DriveDegradeError saying what is wrong otherwise."""
        found = _SPEC.match(str(text))
        if not found:
            raise DriveDegradeError(f"expected I/N (e.g. 2/8), got {text!r}")
        index, count = int(found.group(1)), int(found.group(2))
        if count < 1 or not 1 <= index <= count:
            raise DriveDegradeError(f"shard {index}/{count}: I must be between 1 and N (1-based)")
        return cls(index, count)


def scene_runs(frames: list[Frame]) -> list[list[Frame]]:
    """The frames grouped into runs of one scene each, in order."""
    runs: list[list[Frame]] = []
    for frame in frames:
        if runs and runs[-1][0].scene_token == frame.scene_token:
            runs[-1].append(frame)
        else:
            runs.append([frame])
    return runs


def partition(frames: list[Frame], count: int) -> list[list[Frame]]:
    """`count` scene-contiguous shards balanced by frame count.

    Shard k ends at the scene boundary closest to k/count of the frames (never empty: each shard keeps at least
    one scene). A DriveDegradeError when there are fewer scenes than shards.
    """
    runs = scene_runs(frames)
    if count > len(runs):
        raise DriveDegradeError(f"cannot split {len(runs)} scene(s) into {count} shards: use at most "
                                f"{len(runs)} shards (a scene is never split)")
    sizes = [len(r) for r in runs]
    total = sum(sizes)
    bounds: list[int] = []  # index of the first scene of shards 2..count
    cumulative = [sum(sizes[:i]) for i in range(len(sizes) + 1)]
    for k in range(1, count):
        ideal = total * k / count
        low = (bounds[-1] if bounds else 0) + 1  # at least one scene in the shard before
        high = len(runs) - (count - k)  # and at least one in each shard after
        best = min(range(low, high + 1), key=lambda b: (abs(cumulative[b] - ideal), b))
        bounds.append(best)
    edges = [0, *bounds, len(runs)]
    return [[f for run in runs[a:b] for f in run] for a, b in zip(edges[:-1], edges[1:])]


def shard_frames(frames: list[Frame], shard: Shard) -> list[Frame]:
    """The frames of one shard."""
    return partition(frames, shard.count)[shard.index - 1]
