"""Scene shards (SPEC section 9): a deterministic partition of the scored frames into N scene-contiguous shards
balanced by frame count, so a job array or a CI matrix runs shard I of N and `drivedegrade merge` joins them.

Whole scenes stay together (a temporal planner's stream is never cut), and shard order is scene order, so the
merged frames are in exactly the order of an unsharded run.

An adaptive run (spec 14) is sharded by cells instead (`adaptive_owned`): a cell's stopping rule draws units from
every scene in one seeded order, so each shard scores every frame and owns whole families' sequential runs.
"""

from __future__ import annotations

from collections.abc import Sequence

from .data.frame import Frame
from .errors import DriveDegradeError
from .settings import Shard

#: Shard lives with the settings
__all__ = ["Shard", "adaptive_groups", "adaptive_owned", "partition", "scene_runs", "shard_frames"]


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


#: The cells an adaptive shard keeps with clean: blind and the null control compare with clean's whole record.
WITH_CLEAN = ("clean", "blind", "null")


def adaptive_groups(cells: Sequence[tuple[str, int]]) -> list[list[tuple[str, int]]]:
    """An adaptive run's cells in the groups a shard owns whole: clean with blind and the null control, then one
    group per family in run order (a family's severity schedule reads every visited severity's outcome)."""
    groups: dict[str, list[tuple[str, int]]] = {}
    for family, severity in cells:
        groups.setdefault("clean" if family in WITH_CLEAN else family, []).append((family, severity))
    return list(groups.values())


def adaptive_owned(cells: Sequence[tuple[str, int]], shard: Shard) -> list[tuple[str, int]]:
    """The cells shard I of N owns in an adaptive run: group g (`adaptive_groups`) goes to shard g mod N + 1.
    Each owned cell runs exactly its unsharded sequential run: every shard scores every frame, and the stopping
    rule reads only the seeded draw order, clean's units and the run's cell count. A DriveDegradeError when there
    are fewer groups than shards."""
    groups = adaptive_groups(cells)
    if shard.count > len(groups):
        raise DriveDegradeError(f"an adaptive run is sharded by whole families (a cell's stopping rule reads units "
                                f"of every scene), and this one has {len(groups)} group(s) (clean with blind and "
                                f"the null control, then one per family): use at most {len(groups)} shards")
    return [c for g, group in enumerate(groups) if g % shard.count + 1 == shard.index for c in group]
