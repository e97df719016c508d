"""`drivedegrade merge SHARD_DIR... --out DIR`: join the cell results of scene shards into the outputs of one run.

Each shard run (`--drivedegrade-shard I/N`) leaves `<report>/<planner>/shard-I-of-N/` with `shard.json` (what the
shard scored, its run key, the floor's per-frame L2, the ground truth for the trajectory panels) and `cells/`.
The merge reads every shard's per-frame results, checks that the shards belong to one run and that none is
missing, joins each cell's records in shard order (scene order, the order of an unsharded run; `CellRecord.concat`,
as the Ray pool joins its scene groups) and returns the `FinishedRun` an unsharded run builds, which
`report.publish` writes exactly as it writes that run's. A missing shard is an error naming it, unless
`allow_incomplete`, when the certificate says `completeness: false`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, cast

import numpy as np

from ..cells import CellRecord
from ..errors import DriveDegradeError
from ..payload import CellPayload, RecordDigestMismatch
from ..progress import Progress, Sink
from ..scoring.sequential import summary_line
from ..settings import RunSettings
from .closed import ClosedRun
from .finished import FinishedRun, FloorFigures
from .seal import CertificateError, Provenance, read_strict_json, run_provenance

#: 2: the run's settings in one ``settings`` object (`RunSettings.to_builtins`) rather than spread over the manifest.
SHARD_SCHEMA = "drivedegrade-shard/2"
MANIFEST = "shard.json"
#: Manifest fields besides the settings (`RunSettings.same_run`) that every shard of one run shares.
SAME_RUN = ("planner", "planner_fingerprint", "dataset_fingerprint", "spec_version", "count", "frames_total", "cells")

#: The manifest fields the merge reads, with their JSON types (checked before any is used).
MANIFEST_TYPES: dict[str, type] = {"index": int, "count": int, "frames_total": int, "cells": list, "key": dict,
                                   "planner": str, "settings": dict}


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


def read_manifest(folder: Path) -> ShardResult:
    """A shard folder's checked manifest and settings, its cells not yet read (`load_cells`); DriveDegradeError
    naming what is wrong with it."""
    path = find_manifest(Path(folder))
    try:
        manifest = cast("dict[str, Any]", read_strict_json(path, constants=True))  # its shape is checked below
    except CertificateError as exc:  # names the file, and the overflowing number or duplicate key and where
        raise DriveDegradeError(f"unreadable shard manifest: {exc}") from None
    if not isinstance(manifest, dict) or manifest.get("schema") != SHARD_SCHEMA:
        older = isinstance(manifest, dict) and str(manifest.get("schema", "")).startswith("drivedegrade-shard/")
        raise DriveDegradeError(f"{path}: " + (f"a shard manifest of another version ({manifest['schema']}, this "
                                               f"version reads {SHARD_SCHEMA}): rerun the shard with this version "
                                               "(its finished cells are reused)" if older else
                                               f"not a drivedegrade shard manifest (schema {SHARD_SCHEMA})"))
    bad = [k for k, kind in MANIFEST_TYPES.items() if not isinstance(manifest.get(k), kind)
           or isinstance(manifest.get(k), bool)]
    if bad or not all(isinstance(c, str) for c in manifest["cells"]):
        raise DriveDegradeError(f"{path}: a malformed shard manifest ({', '.join(bad or ['cells'])} missing or of "
                                "the wrong type): rerun that shard (its finished cells are reused)")
    try:
        settings = RunSettings.from_builtins(manifest["settings"])
    except (KeyError, TypeError, DriveDegradeError) as exc:
        raise DriveDegradeError(f"{path}: the shard manifest's settings are unreadable ({exc})") from None
    return ShardResult(path.parent, manifest, settings, {})


def load_cells(shard: ShardResult, bar: Progress | None = None) -> ShardResult:
    """`shard` (from `read_manifest`) with the cells it finished, read and digest-checked (`bar` advanced per
    cell file)."""
    path, manifest = shard.folder / MANIFEST, shard.manifest
    payloads: dict[str, CellPayload] = {}
    for cell in manifest["cells"]:
        if bar is not None:
            bar.advance(note=f"shard {manifest['index']}/{manifest['count']}")
        file = path.parent / "cells" / f"{cell}.json"
        if not file.is_file():
            continue  # a cell this shard did not finish: reported as a missing cell of this shard
        try:
            payload = CellPayload.from_builtins(cast("Mapping[str, Any]", read_strict_json(file, constants=True)))
        except RecordDigestMismatch as exc:  # edited, or without a digest: never merged, never silently skipped
            raise DriveDegradeError(f"{file}: {exc}; rerun that shard (its other cells are reused)") from None
        except CertificateError as exc:  # an overflowing number, a duplicate key: named, never skipped
            raise DriveDegradeError(f"{exc}; rerun that shard (its other cells are reused)") from None
        except (OSError, ValueError):
            continue  # a missing or broken cell file: reported as a missing cell of this shard
        if dict(payload.key) == manifest["key"] and payload.cell == cell:
            payloads[cell] = payload
    return replace(shard, payloads=payloads)


def _records(shards: Sequence[ShardResult], cells: Sequence[str]) -> dict[str, CellRecord]:
    """Each cell's record over the shards in order (scene order), for the cells every given shard has: the
    per-shard records joined by `CellRecord.concat`, as the Ray pool joins its scene groups."""
    records = {}
    for cell in cells:
        parts = [s.payloads[cell].record for s in shards if cell in s.payloads]
        if parts and len(parts) == len(shards):
            records[cell] = CellRecord.concat(parts)
    return records


def shard_frames(shard: ShardResult) -> list[str]:
    """The frame tokens a shard scored (every cell of it has the same), as its cell records say."""
    seen = {tuple(p.record.frames) for p in shard.payloads.values()}
    if len(seen) > 1:
        raise DriveDegradeError(f"{shard.folder}: its cells hold different frames; rerun that shard "
                                "(--drivedegrade-no-resume)")
    return list(seen.pop()) if seen else []


def check_frames(shards: Sequence[ShardResult], *, complete: bool) -> None:
    """The shards' frames are disjoint and, when every shard is there, are the run's `frames_total` (issue 20
    M5: a copy of one shard relabelled as another would otherwise count its frames twice and merge as complete)."""
    owner: dict[str, int] = {}
    for s in shards:
        index = s.manifest["index"]
        for token in shard_frames(s):
            if token in owner:
                raise DriveDegradeError(f"shards {owner[token]} and {index} both hold frame {token} (is one a copy "
                                        f"of the other, relabelled?): shards of one run are disjoint; rerun shard "
                                        f"{index} (--drivedegrade-shard {index}/{s.manifest['count']})")
            owner[token] = index
    total = shards[0].manifest["frames_total"]
    if complete and any(s.manifest["cells"] for s in shards) and len(owner) != total:  # a closed-only run: no frame
        raise DriveDegradeError(f"the shards hold {len(owner)} frame(s) but the run scores {total}: a shard is "
                                "truncated or not of this run; rerun the shards and merge again")


def _joined(parts: Sequence[Any]) -> np.ndarray | None:
    """The shards' per-frame values joined in order (None when a shard has none)."""
    if not parts or any(p is None for p in parts):
        return None
    return np.concatenate([np.asarray(p, dtype=float) for p in parts])


def _front_image(front: Sequence[str] | None) -> tuple[str, np.ndarray] | None:
    """(token, image) of the first shard's first front-camera frame, the report's figure; None when the image
    is not on this machine or cannot be read."""
    if not front or not Path(front[1]).is_file():
        return None
    from ..data.images import decode_rgb

    try:
        return front[0], decode_rgb(front[1], front[0])
    except DriveDegradeError:
        return None


def merge_shards(folders: Sequence[Path], *, allow_incomplete: bool = False, command: str = "",
                 root: Path | None = None, progress: Sink | None = None) -> FinishedRun:
    """Join shard folders into one finished run (`report.publish.publish` writes its outputs); DriveDegradeError
    when they are not one run or a shard is missing (unless `allow_incomplete`). With `root`, the data set's
    path is recorded relative to it. Reading the cell files (the long part) is one progress line on `progress`
    (None: none)."""
    if not folders:
        raise DriveDegradeError("no shard folders given")
    heads = [read_manifest(Path(f)) for f in folders]
    with Progress("drivedegrade merge", sum(len(h.manifest["cells"]) for h in heads), unit="cell files",
                  sink=progress or Sink.silent()) as bar:
        shards = sorted((load_cells(h, bar) for h in heads), key=lambda s: s.manifest["index"])
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
    adaptive, files = None, None
    if settings.adaptive:  # shards own whole families on every frame (`adaptive_merge`), not scenes
        from .adaptive_merge import adaptive_records, merged_section

        records, files = adaptive_records(shards, cells)
        adaptive = merged_section(shards, records, settings)
    else:
        check_frames(shards, complete=not missing_shards)
        records = _records(shards, cells)
    closed = closed_of_shards(shards, settings)
    if "clean" not in records and (cells or closed is None):
        raise DriveDegradeError("the clean cell is missing from at least one shard: retention needs it; rerun that "
                                "shard (finished cells are reused)")
    floored = shards[:1] if settings.adaptive else shards  # an adaptive shard's floor is of every frame
    floor = FloorFigures.of(_joined([s.manifest.get("floor_l2") for s in floored]),
                            _joined([s.manifest.get("floor_ego_blind_l2") for s in floored]))
    prov = run_provenance(settings, planner_name=first["planner"], key=first["key"],
                          frames=len(records["clean"].frames) if "clean" in records else 0,
                          frames_unscored=first.get("frames_unscored"),
                          command=command, planner_file=str(first.get("planner_file", "")), recorded=first,
                          root=root)
    if isinstance(first.get("data_source"), str):  # as the shard's run recorded it, relative to its rootdir
        prov = replace(prov, data_source=first["data_source"])
    gt = {t: np.asarray(v, dtype=float) for s in shards for t, v in s.manifest.get("gt", {}).items()}
    return FinishedRun(records, prov, settings, floor, gt, _front_image(shards[0].manifest.get("front")),
                       scenes=_scenes(shards), missing_cells=tuple(c for c in cells if c not in records),
                       missing_shards=tuple(missing_shards), missing_advice=missing_advice(shards, cells),
                       closed=closed, adaptive=adaptive, cell_files=files,
                       notes=(summary_line(adaptive),) if adaptive is not None else ())


def _scenes(shards: Sequence[ShardResult]) -> dict[str, str] | None:
    """Each frame's scene over the shards (the scene-cluster intervals' basis); None when a shard's manifest is
    from before the scenes were written (the merged run then says its intervals treat frames as independent)."""
    out: dict[str, str] = {}
    for s in shards:
        got = s.manifest.get("scenes")
        if not isinstance(got, Mapping):
            return None
        out.update({str(t): str(v) for t, v in got.items()})
    return out


def missing_advice(shards: Sequence[ShardResult], cells: Sequence[str]) -> str:
    """What to do about the cells some shard lacks, naming which shard lacks which (a merge's missing cells are
    finished by rerunning that shard, not the merge); empty when none lacks any."""
    parts = []
    for s in shards:
        mine = s.manifest.get("adaptive", {}).get("owned", cells) if s.settings.adaptive else cells
        lacking = [c for c in cells if c in mine and c not in s.payloads]
        if lacking:
            shown = ", ".join(lacking[:8]) + (f" and {len(lacking) - 8} more" if len(lacking) > 8 else "")
            parts.append(f"shard {s.manifest['index']}/{s.manifest['count']} ({s.folder}) lacks {shown}")
    if not parts:
        return ""
    return ("; ".join(parts) + ": rerun each such shard with its own command (--drivedegrade-shard I/N; its "
            "finished cells are reused), then run this merge again")



def closed_of_shards(shards: Sequence[ShardResult], settings: RunSettings) -> ClosedRun | None:
    """The closed-loop cells (SPEC 13) of the shards: each cell's runs joined in shard order (each shard drove
    its contiguous share of the (route, seed) runs); a cell some shard lacks is missing. None without any."""
    from ..closedloop.cells import ClosedPayload, ClosedRecord
    from ..errors import InvalidInput
    expected = list(shards[0].manifest.get("closed_cells") or [])
    if not expected:
        return None
    found: dict[str, list[ClosedPayload]] = {}
    for s in shards:
        for cell in expected:
            file = s.folder / "cells" / f"{cell}.json"
            if not file.is_file():
                continue  # a cell this shard did not finish: reported as missing
            try:
                payload = ClosedPayload.from_builtins(read_strict_json(file, constants=True))
            except InvalidInput as exc:
                raise DriveDegradeError(f"{file}: {exc}; rerun that shard (its other cells are reused)") from None
            except CertificateError as exc:  # an overflowing number, a duplicate key: named, never skipped
                raise DriveDegradeError(f"{exc}; rerun that shard (its other cells are reused)") from None
            except (OSError, ValueError):
                continue
            if payload.cell == cell and all(payload.key.get(k) == v for k, v in s.manifest["key"].items()
                                            if k in payload.key and k != "frames_key"):
                found.setdefault(cell, []).append(payload)
    joined = {c: ClosedPayload(ps[0].key, ps[0].planner, ClosedRecord.concat([p.record for p in ps]))
              for c, ps in found.items() if len(ps) == len(shards)}
    return ClosedRun({c: joined[c] for c in expected if c in joined}, settings,
                     tuple(c for c in expected if c not in joined)) if joined else None


def shard_manifest(*, index: int, count: int, planner: str, key: Mapping[str, Any], provenance: Provenance,
                   settings: RunSettings, frames_total: int, cells: Sequence[str], missing: Sequence[str],
                   floor_l2: Sequence[float] | None, floor_ego_blind_l2: Sequence[float] | None,
                   gt: Mapping[str, Any], data_root: str,
                   front: tuple[str, str] | None = None, scenes: Mapping[str, str] | None = None) -> dict[str, Any]:
    """What a shard run writes beside its cells for the merge (the settings as `RunSettings.to_builtins`; the
    provenance's split, seed, data source, frames asked for and timeout are settings, read back from there)."""
    return {"schema": SHARD_SCHEMA, "index": index, "count": count, "planner": planner, "key": dict(key),
            "planner_fingerprint": provenance.planner_fingerprint,
            "dataset_fingerprint": provenance.dataset_fingerprint, "spec_version": provenance.spec_version,
            "settings": settings.to_builtins(),
            "frames": provenance.frames, "frames_total": frames_total, "frames_unscored": provenance.frames_unscored,
            "tool_version": provenance.tool_version, "versions": dict(provenance.versions),
            "planner_file": provenance.planner_file, "data_source": provenance.data_source, "cells": list(cells),
            "missing_cells": list(missing),
            "floor_l2": None if floor_l2 is None else [float(v) for v in floor_l2],
            "floor_ego_blind_l2": None if floor_ego_blind_l2 is None else [float(v) for v in floor_ego_blind_l2],
            "gt": {t: np.asarray(v, dtype=float).tolist() for t, v in gt.items()}, "data_root": data_root,
            "front": list(front) if front else None,
            "scenes": None if scenes is None else {str(t): str(s) for t, s in scenes.items()}}
