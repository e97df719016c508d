"""A finished run: what the end of a run needs, whoever assembled it.

The pytest controller builds one from this session's and the stored cells, `drivedegrade merge` from shard
folders; `report.publish.publish` analyses it and writes its outputs, the same way for both, so a merge of
shards writes exactly what the unsharded run writes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..cells import CellRecord
from ..scoring.records import finite_mean
from ..scoring.retention import retention
from ..settings import RunSettings
from .seal import Provenance

if TYPE_CHECKING:
    from .closed import ClosedRun


@dataclass(frozen=True)
class FloorFigures:
    """The ego-only floor as the analysis takes it: its clean mean L2 (None when no floor ran) and, when the
    ego cells ran, its ego_blind retention (``{"ego_removal": ...}``, for the reliance chart); its clean L2 per
    frame for the blind-equals-clean check (M12)."""

    l2: float | None = None
    extra: Mapping[str, float] = field(default_factory=dict)
    per_frame: tuple[float, ...] | None = None  #: the clean L2 per scored frame, in the run's frame order

    @classmethod
    def of(cls, clean: Sequence[float] | np.ndarray | None,
           ego_blind: Sequence[float] | np.ndarray | None = None) -> FloorFigures:
        """From the floor's per-frame clean and ego_blind L2 (joined in scene order when sharded)."""
        if clean is None:
            return cls()
        l2 = finite_mean(np.asarray(clean, dtype=float))
        per_frame = tuple(float(v) for v in clean)
        if ego_blind is None:
            return cls(l2, per_frame=per_frame)
        return cls(l2, {"ego_removal": float(retention(l2, finite_mean(np.asarray(ego_blind, dtype=float))))},
                   per_frame)


@dataclass(frozen=True)
class FinishedRun:
    """One run's cells and everything around them that its outputs say.

    `settings`: the run's settings (a merge's: the first shard's, its shard left out).
    `front`: (token, image) of the first scored frame's front camera, the report's figure (None when unreadable).
    `resumed_cells`: the stored cells this run took instead of computing them (None where the run cannot tell,
    a merge). `notes`: lines the assembly said (cells reused, a skipped floor), printed after the summary.
    `adaptive`: --drivedegrade-adaptive's section (`scoring.sequential.adaptive_section`), else None.
    """

    records: Mapping[str, CellRecord]
    provenance: Provenance
    settings: RunSettings
    floor: FloorFigures
    gt: Mapping[str, np.ndarray]
    front: tuple[str, np.ndarray] | None
    missing_cells: tuple[str, ...] = ()
    missing_shards: tuple[int, ...] = ()
    missing_advice: str = ""  #: what to do about the missing cells (a merge: which shard to rerun); "" the default
    resumed_cells: tuple[str, ...] | None = None
    notes: tuple[str, ...] = ()
    closed: ClosedRun | None = None  #: the closed-loop cells (SPEC section 13), when the run drove any
    adaptive: Mapping[str, object] | None = None  #: the certificate's ``adaptive`` section (adaptive runs only)
    #: a merge of adaptive shards: each cell's stored file in the shard that owns it, copied into the merged
    #: report's cells/ (where `verify` recomputes the stops from the per-frame results)
    cell_files: Mapping[str, Path] | None = None
    #: cell -> its record's `payload.record_digest` where already known (checked when the payload was read), so
    #: the certificate's ``record_digests`` does not hash those records again; the others are hashed
    digests: Mapping[str, str] | None = None
    #: frame token -> its scene token: the scene-cluster intervals' basis (None: unknown, frames independent)
    scenes: Mapping[str, str] | None = None
