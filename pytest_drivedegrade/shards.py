"""Scene shards (SPEC section 9): a deterministic partition of the scored frames into N scene-contiguous shards
balanced by frame count, so a job array or a CI matrix runs shard I of N and `drivedegrade merge` joins them.

Whole scenes stay together (a temporal planner's stream is never cut), and shard order is scene order, so the
merged frames are in exactly the order of an unsharded run.
"""

from __future__ import annotations

from .data.frame import Frame
from .errors import DriveDegradeError
from .settings import Shard

__all__ = ["Shard", "partition", "scene_runs", "shard_frames"]  # Shard lives with the settings


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

    The cuts lie on scene boundaries, as close as they can be to k/count of the frames: the largest distance of a
    cut from its ideal position is the smallest possible (then their sum), found by dynamic programming over the
    boundaries (a greedy cut can be forced far off later on). Never empty: each shard keeps at least one scene.
    A DriveDegradeError when there are fewer scenes than shards.
    """
    runs = scene_runs(frames)
    if count > len(runs):
        raise DriveDegradeError(f"cannot split {len(runs)} scene(s) into {count} shards: use at most "
                                f"{len(runs)} shards (a scene is never split)")
    n, total = len(runs), len(frames)
    cumulative = [0]
    for run in runs:
        cumulative.append(cumulative[-1] + len(run))
    # cost[b]: the best (largest deviation, summed deviation) of the cuts so far with the last one at boundary b
    cost: dict[int, tuple[float, float]] = {0: (0.0, 0.0)}
    came_from: list[dict[int, int]] = []
    for k in range(1, count):
        ideal = total * k / count
        earlier = sorted(cost)
        best: tuple[tuple[float, float], int] | None = None  # the best cut k - 1 before boundary b
        nxt: dict[int, tuple[float, float]] = {}
        back: dict[int, int] = {}
        j = 0
        for b in range(k, n - (count - k) + 1):
            while j < len(earlier) and earlier[j] < b:
                if best is None or cost[earlier[j]] < best[0]:
                    best = (cost[earlier[j]], earlier[j])
                j += 1
            assert best is not None  # boundary k - 1 (or 0) is always earlier
            (worst, summed), before = best
            off = abs(cumulative[b] - ideal)
            nxt[b], back[b] = (max(worst, off), summed + off), before
        cost = nxt
        came_from.append(back)
    bounds: list[int] = []
    if count > 1:
        at = min(cost, key=lambda b: (cost[b], b))
        for back in reversed(came_from):
            bounds.append(at)
            at = back[at]
        bounds.reverse()
    edges = [0, *bounds, n]
    return [[f for run in runs[a:b] for f in run] for a, b in zip(edges[:-1], edges[1:])]


def shard_frames(frames: list[Frame], shard: Shard) -> list[Frame]:
    """The frames of one shard."""
    return partition(frames, shard.count)[shard.index - 1]
