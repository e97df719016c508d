"""`drivedegrade merge` of an adaptive run's shards (spec 14). An adaptive shard scores every frame and owns whole
families' cells (`shards.adaptive_owned`), so a cell is taken from the one shard that owns it, never joined
across shards; the run's unit plan comes from the manifests, and the certificate's ``adaptive`` section is
computed as the unsharded run computes it (`scoring.sequential.adaptive_section`): the same bit for bit.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ..cells import CellRecord, cell_id
from ..data.frame import Frame
from ..errors import DriveDegradeError
from ..scoring import sequential
from ..settings import RunSettings, Shard
from ..shards import adaptive_owned

if TYPE_CHECKING:
    from .merge import ShardResult


def adaptive_manifest(run_cells: Sequence[tuple[str, int]], shard: Shard, frames: Sequence[Frame],
                      seed: int, fingerprint: str) -> dict[str, object]:
    """What an adaptive shard's manifest adds for the merge: the cells it owns, the run's cells (the union bound
    counts them) and the unit plans a run of these frames may use (single frames, windows: `UnitPlan.matching`
    picks by clean's unit count)."""
    plans = tuple(sequential.UnitPlan.drawn(frames, seed, fingerprint, None, temporal=t, scenes=s)
                  for t, s in ((False, False), (True, False), (False, True)))
    return {"owned": [cell_id(f, s) for f, s in adaptive_owned(run_cells, shard)],
            "run_cells": [[f, s] for f, s in run_cells], "plans": [p.to_builtins() for p in plans]}


def _part(shard: ShardResult) -> Mapping[str, object]:
    part = shard.manifest.get("adaptive")
    if not isinstance(part, Mapping) or not isinstance(part.get("owned"), list):
        raise DriveDegradeError(f"{shard.folder}: an adaptive run's shard manifest without the cells it owns; "
                                "rerun that shard with this version (its finished cells are reused)")
    return part


def _owned(shard: ShardResult) -> list[str]:
    owned = _part(shard)["owned"]
    return [str(c) for c in owned] if isinstance(owned, list) else []


def owners(shards: Sequence[ShardResult]) -> dict[str, ShardResult]:
    """cell -> the shard that owns it; a DriveDegradeError when two shards claim one cell or a shard's frames are
    not every frame of the run (each adaptive shard scores them all)."""
    found: dict[str, ShardResult] = {}
    for s in shards:
        for cell in _owned(s):
            if cell in found:
                raise DriveDegradeError(f"shards {found[cell].manifest['index']} and {s.manifest['index']} both own "
                                        f"cell {cell}: shards of one adaptive run own disjoint families")
            found[cell] = s
        frames = {f for p in s.payloads.values() for f in p.record.frames}
        if frames and len(frames) != s.manifest["frames_total"]:
            raise DriveDegradeError(f"{s.folder}: an adaptive shard scores every frame of the run, and this one holds "
                                    f"{len(frames)} of {s.manifest['frames_total']}; rerun that shard")
    return found


def adaptive_records(shards: Sequence[ShardResult],
                     cells: Sequence[str]) -> tuple[dict[str, CellRecord], dict[str, Path]]:
    """Each cell's record from the shard that owns it (cells of missing shards are missing), and its stored file
    (copied beside the merged certificate, where `verify` reads the per-frame results)."""
    own = owners(shards)
    frames = {tuple(p.record.frames) for s in shards for p in s.payloads.values()}
    if len(frames) > 1:
        raise DriveDegradeError("the adaptive shards' cells hold different frames: rerun the shards "
                                "(--drivedegrade-no-resume) and merge again")
    got = {c: own[c] for c in cells if c in own and c in own[c].payloads}
    return ({c: s.payloads[c].record for c, s in got.items()},
            {c: s.folder / "cells" / f"{c}.json" for c, s in got.items()})


def merged_section(shards: Sequence[ShardResult], records: Mapping[str, CellRecord],
                   settings: RunSettings) -> dict[str, object] | None:
    """The merged run's ``adaptive`` section, as the unsharded run's controller computes it (None without clean)."""
    if "clean" not in records:
        return None
    from ..scoring.verdict import FamilyGroups

    part = _part(shards[0])
    raw = part.get("plans")
    plans = [sequential.UnitPlan.from_builtins(p) for p in raw if isinstance(p, Mapping)] if isinstance(raw, list) \
        else []
    units = int(records["clean"].units or 0)
    plan = next((p for p in plans if p.population == units), plans[min(1, len(plans) - 1)] if plans else None)
    run_cells = part.get("run_cells")
    if plan is None or not isinstance(run_cells, list):
        raise DriveDegradeError(f"{shards[0].folder}: the shard manifest lacks the run's unit plans; rerun it "
                                "with this version (its finished cells are reused)")
    groups = FamilyGroups.from_registry()
    return sequential.adaptive_section(records, plan, [(str(f), int(s)) for f, s in run_cells],
                                       alpha=settings.alpha, flat=settings.flat, quality=groups.quality,
                                       removal=groups.removal, rule="certify")
