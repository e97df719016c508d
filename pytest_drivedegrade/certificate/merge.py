"""`drivedegrade merge SHARD_DIR... --out DIR`: join the cell results of scene shards into the outputs of one run.

Each shard run (`--drivedegrade-shard I/N`) leaves `<report>/<planner>/shard-I-of-N/` with `shard.json` (what the
shard scored, its run key, the floor's per-frame L2, the ground truth for the trajectory panels) and `cells/`.
The merge reads every shard's per-frame results, checks that the shards belong to one run and that none is
missing, joins each cell's records in shard order (scene order, the order of an unsharded run; `CellRecord.concat`,
as the Ray pool joins its scene groups) and
computes and writes exactly what an unsharded run writes. A missing shard is an error naming it, unless
`allow_incomplete`, when the certificate says `completeness: false`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..cells import CellPayload, CellRecord
from ..errors import DriveDegradeError
from ..scoring.records import finite_mean
from ..scoring.retention import retention
from ..settings import RunSettings
from .seal import Provenance

#: 2: the run's settings in one ``settings`` object (`RunSettings.to_builtins`) rather than spread over the manifest.
SHARD_SCHEMA = "drivedegrade-shard/2"
MANIFEST = "shard.json"
#: Manifest fields besides the settings (`RunSettings.same_run`) that every shard of one run shares.
SAME_RUN = ("planner", "planner_fingerprint", "dataset_fingerprint", "spec_version", "count", "frames_total", "cells")


@dataclass(frozen=True)
class ShardResult:
    folder: Path
    manifest: dict[str, Any]
    settings: RunSettings
    payloads: dict[str, CellPayload]


def find_manifest(folder: Path) -> Path:
    """`folder/shard.json`, or the one shard folder below `folder` (a planner's report folder)."""
    direct = folder / MANIFEST
    if direct.is_file():
        return direct
    found = sorted(folder.glob(f"shard-*-of-*/{MANIFEST}"))
    if len(found) == 1:
        return found[0]
    if not found:
        raise DriveDegradeError(f"{folder}: no {MANIFEST}: pass the folders that --drivedegrade-shard runs wrote "
                                "(reports/<planner>/shard-I-of-N)")
    raise DriveDegradeError(f"{folder} holds several shards ({', '.join(str(p.parent.name) for p in found)}): "
                            "pass each shard folder")


def load_shard(folder: Path) -> ShardResult:
    path = find_manifest(Path(folder))
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DriveDegradeError(f"{path}: unreadable shard manifest ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("schema") != SHARD_SCHEMA:
        older = isinstance(manifest, dict) and str(manifest.get("schema", "")).startswith("drivedegrade-shard/")
        raise DriveDegradeError(f"{path}: " + (f"a shard manifest of another version ({manifest['schema']}, this "
                                               f"version reads {SHARD_SCHEMA}): rerun the shard with this version "
                                               "(its finished cells are reused)" if older else
                                               f"not a drivedegrade shard manifest (schema {SHARD_SCHEMA})"))
    try:
        settings = RunSettings.from_builtins(manifest["settings"])
    except (KeyError, TypeError, DriveDegradeError) as exc:
        raise DriveDegradeError(f"{path}: the shard manifest's settings are unreadable ({exc})") from None
    payloads: dict[str, CellPayload] = {}
    for cell in manifest["cells"]:
        file = path.parent / "cells" / f"{cell}.json"
        try:
            payload = CellPayload.from_builtins(json.loads(file.read_text()))
        except (OSError, ValueError):
            continue  # a missing or broken cell file: reported as a missing cell of this shard
        if dict(payload.key) == manifest["key"] and payload.cell == cell:
            payloads[cell] = payload
    return ShardResult(path.parent, manifest, settings, payloads)


def _records(shards: Sequence[ShardResult], cells: Sequence[str]) -> dict[str, CellRecord]:
    """Each cell's record over the shards in order (scene order), for the cells every given shard has: the
    per-shard records joined by `CellRecord.concat`, as the Ray pool joins its scene groups."""
    records = {}
    for cell in cells:
        parts = [s.payloads[cell].record for s in shards if cell in s.payloads]
        if parts and len(parts) == len(shards):
            records[cell] = CellRecord.concat(parts)
    return records


@dataclass(frozen=True)
class Merged:
    records: dict[str, CellRecord]
    provenance: Provenance
    key: dict[str, Any]
    floor_l2: float | None
    gt: dict[str, np.ndarray]
    flat: float
    missing_cells: list[str]
    missing_shards: list[int]
    data_root: str
    front: tuple[str, str] | None  #: (token, CAM_FRONT image path) of the first shard's first frame
    floor_extra: dict[str, float]  #: the floor's ego_removal, when the shards ran the ego cells
    settings: RunSettings  #: the run's (the first shard's, its shard left out)


def write_merged(merged: Merged, out: Path, signing_key: Any = None) -> list[str]:
    """Analyse the merged records and write cells.csv, certificate.json and report.html into `out/<planner>/`
    (the certificate signed with `signing_key` when given); the lines to print."""
    from ..report.outputs import montage_of, write_outputs
    from ..scoring.verdict import analyse_run

    analysis = analyse_run(merged.records.values(), flat=merged.flat, seed=merged.provenance.seed,
                           floor_l2=merged.floor_l2, metric=merged.settings.metric)
    analysis.floor.update(merged.floor_extra)
    analysis.settings.update(merged.settings.certificate_settings())
    montage = None
    if merged.front is not None and Path(merged.front[1]).is_file():
        from ..data.images import decode_rgb

        try:
            montage = montage_of(decode_rgb(merged.front[1], merged.front[0]), merged.front[0],
                                 merged.provenance.seed)
        except DriveDegradeError:
            montage = None
    extra: dict[str, Any] = {"complete": False, "missing_shards": merged.missing_shards} \
        if merged.missing_shards else {}
    from ..scoring.records import cost_ledger

    _, written = write_outputs(out, merged.provenance, merged.records, analysis, merged.missing_cells, gt=merged.gt,
                               montage=montage, completeness=extra, cost=cost_ledger(merged.records.values()),
                               signing_key=signing_key)
    from ..report.terminal import summary_lines

    lines = summary_lines(analysis, merged.missing_cells)
    if merged.missing_shards:
        lines.append(f"INCOMPLETE: shard(s) {', '.join(map(str, merged.missing_shards))} missing; the certificate "
                     "says completeness: false")
    return [*lines, written]


def _joined_mean(parts: Sequence[Any]) -> float | None:
    """The mean over the shards' per-frame values joined in order (None when a shard has none)."""
    if not parts or any(p is None for p in parts):
        return None
    return finite_mean(np.concatenate([np.asarray(p, dtype=float) for p in parts]))


def merge_shards(folders: Sequence[Path], *, allow_incomplete: bool = False, command: str = "") -> Merged:
    """Join shard folders into one run's records; DriveDegradeError when they are not one run or a shard is
    missing (unless `allow_incomplete`)."""
    if not folders:
        raise DriveDegradeError("no shard folders given")
    shards = sorted((load_shard(Path(f)) for f in folders), key=lambda s: s.manifest["index"])
    first, settings = shards[0].manifest, replace(shards[0].settings, shard=None)
    for s in shards[1:]:
        diff = [k for k in SAME_RUN if s.manifest.get(k) != first.get(k)] + \
            [d.name for d in shards[0].settings.same_run(s.settings)]
        if diff:
            raise DriveDegradeError(f"{s.folder} is not from the same run as {shards[0].folder}: they differ in "
                                    f"{', '.join(diff)}")
    indices = [s.manifest["index"] for s in shards]
    if len(set(indices)) != len(indices):
        raise DriveDegradeError(f"shard(s) given twice: {sorted(i for i in set(indices) if indices.count(i) > 1)}")
    missing_shards = sorted(set(range(1, first["count"] + 1)) - set(indices))
    if missing_shards and not allow_incomplete:
        names = ", ".join(f"{i}/{first['count']}" for i in missing_shards)
        raise DriveDegradeError(f"missing shard(s) {names}: run them (--drivedegrade-shard I/N) and merge again, or "
                                "pass --allow-incomplete to write a certificate that says completeness: false")
    if settings.seeds > 1:
        raise DriveDegradeError("these shards ran with --drivedegrade-seeds above 1: merging multi-seed shards is "
                                "not supported yet; run the shards with one seed, or the whole run unsharded")
    cells = list(first["cells"])
    records = _records(shards, cells)
    if "clean" not in records:
        raise DriveDegradeError("the clean cell is missing from at least one shard: retention needs it; rerun that "
                                "shard (finished cells are reused)")
    floor = _joined_mean([s.manifest.get("floor_l2") for s in shards])
    floor_blind = _joined_mean([s.manifest.get("floor_ego_blind_l2") for s in shards])
    floor_extra = {} if floor is None or floor_blind is None else \
        {"ego_removal": float(retention(floor, floor_blind))}
    frames = len(records["clean"].frames)
    prov = Provenance(planner_name=first["planner"], planner_fingerprint=first["planner_fingerprint"],
                      dataset_fingerprint=first["dataset_fingerprint"], split=settings.split,
                      spec_version=first["spec_version"], seed=settings.seed, frames=frames,
                      frames_unscored=first.get("frames_unscored"), data_source=settings.data_source,
                      command=command, tool_version=first.get("tool_version", ""),
                      frames_requested=settings.frames, timeout=settings.timeout,
                      versions=first.get("versions") or {},
                      planner_file=str(first.get("planner_file", "")))
    gt = {t: np.asarray(v, dtype=float) for s in shards for t, v in s.manifest.get("gt", {}).items()}
    key = {k: v for k, v in first["key"].items() if k != "frames_key"}
    front = shards[0].manifest.get("front")
    return Merged(records, prov, key, floor, gt, settings.flat, [c for c in cells if c not in records],
                  missing_shards, str(first.get("data_root", "")), (front[0], front[1]) if front else None,
                  floor_extra, settings)


def shard_manifest(*, index: int, count: int, planner: str, key: Mapping[str, Any], provenance: Provenance,
                   settings: RunSettings, frames_total: int, cells: Sequence[str], missing: Sequence[str],
                   floor_l2: Sequence[float] | None, floor_ego_blind_l2: Sequence[float] | None,
                   gt: Mapping[str, Any], data_root: str,
                   front: tuple[str, str] | None = None) -> dict[str, Any]:
    """What a shard run writes beside its cells for the merge (the settings as `RunSettings.to_builtins`; the
    provenance's split, seed, data source, frames asked for and timeout are settings, read back from there)."""
    return {"schema": SHARD_SCHEMA, "index": index, "count": count, "planner": planner, "key": dict(key),
            "planner_fingerprint": provenance.planner_fingerprint,
            "dataset_fingerprint": provenance.dataset_fingerprint, "spec_version": provenance.spec_version,
            "settings": settings.to_builtins(),
            "frames": provenance.frames, "frames_total": frames_total, "frames_unscored": provenance.frames_unscored,
            "tool_version": provenance.tool_version, "versions": dict(provenance.versions),
            "planner_file": provenance.planner_file, "cells": list(cells), "missing_cells": list(missing),
            "floor_l2": None if floor_l2 is None else [float(v) for v in floor_l2],
            "floor_ego_blind_l2": None if floor_ego_blind_l2 is None else [float(v) for v in floor_ego_blind_l2],
            "gt": {t: np.asarray(v, dtype=float).tolist() for t, v in gt.items()}, "data_root": data_root,
            "front": list(front) if front else None}
