"""The nuScenes tables: which the reader needs, the fields it uses from each table's rows with their JSON types,
and the checked loading that names a malformed table by its file and the offending row's token (a data error,
never a KeyError later), and file names confined to the data root."""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..errors import DataError

REQUIRED_TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor",
                   "sample_annotation", "instance", "category")
OPTIONAL_TABLES = ("log", "visibility", "attribute", "map")


#: The fields the reader uses from each table's rows, with their JSON types (checked at start-up, so a malformed
#: row is named by its table file and token rather than failing later as a KeyError or a TypeError).
_TOKEN: dict[str, type | tuple[type, ...]] = {"token": str}
_POSE: dict[str, type | tuple[type, ...]] = {"translation": list, "rotation": list}
ROW_FIELDS: dict[str, dict[str, type | tuple[type, ...]]] = {
    "scene": {**_TOKEN, "name": str, "first_sample_token": str},
    "sample": {**_TOKEN, "timestamp": int},
    "sample_data": {**_TOKEN, "sample_token": str, "calibrated_sensor_token": str, "ego_pose_token": str,
                    "filename": str, "width": int, "height": int},
    "ego_pose": {**_TOKEN, **_POSE, "timestamp": int},
    "calibrated_sensor": {**_TOKEN, **_POSE, "sensor_token": str, "camera_intrinsic": list},
    "sensor": {**_TOKEN, "channel": str},
    "sample_annotation": {**_TOKEN, **_POSE, "sample_token": str, "instance_token": str, "size": list},
    "instance": {**_TOKEN, "category_token": str},
    "category": {**_TOKEN, "name": str},
    "log": _TOKEN,
}


def _row_problem(row: object, fields: dict[str, type | tuple[type, ...]]) -> str:
    """What is wrong with one table row ("" when nothing): not an object, a missing field, a wrong type."""
    if not isinstance(row, dict):
        return f"is a JSON {type(row).__name__}, not an object"
    for key, kind in fields.items():
        if key not in row:
            return f"lacks the field {key!r}"
        value = row[key]
        if not isinstance(value, kind) or isinstance(value, bool):
            want = kind.__name__ if isinstance(kind, type) else " or ".join(k.__name__ for k in kind)
            return f"has {key}={value!r:.60} ({type(value).__name__}), expected {want}"
    return ""


def _allowed(kind: type | tuple[type, ...]) -> set[type]:
    return {kind} if isinstance(kind, type) else set(kind)


def check_rows(path: Path, rows: object, fields: dict[str, type | tuple[type, ...]]) -> list[dict]:
    """`rows` when the table is a list of objects with every field in `fields` of its type; else a DataError
    naming the table file and the offending row's token (or its position when it has no token)."""
    if not isinstance(rows, list):
        raise DataError(f"nuScenes table {path} is a JSON {type(rows).__name__}, not a list of records; "
                        "re-extract or regenerate the data")
    try:  # the fast path: one set of types per field (about 0.1 s per million rows), no message built
        if all({type(row[k]) for row in rows} <= _allowed(t) for k, t in fields.items()):
            return rows
    except (KeyError, TypeError, AttributeError):
        pass
    for i, row in enumerate(rows):
        problem = _row_problem(row, fields)
        if problem:
            token = row.get("token") if isinstance(row, dict) else None
            which = f"the record with token {token!r}" if isinstance(token, str) else f"record {i}"
            raise DataError(f"nuScenes table {path}: {which} {problem}; re-extract or regenerate the data")
    return rows


def load_table(path: Path) -> list[dict]:
    """A table file's rows, checked against `ROW_FIELDS` (a DataError naming the file otherwise)."""
    if not path.is_file():
        raise DataError(f"missing nuScenes table {path}: the data root must hold every table of the version "
                        f"folder ({', '.join(REQUIRED_TABLES)})")
    try:
        rows = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"unreadable nuScenes table {path}: {exc}; re-extract or regenerate the data") from exc
    return check_rows(path, rows, ROW_FIELDS.get(path.stem, {}))


def confined(root: Path, name: str, where: str) -> Path:
    """``root / name`` when `name` is a relative path that stays inside `root` after normalising ``..`` away;
    else a DataError naming `where` (the table row). The check is on the name, not on resolved links, so a data
    root whose ``samples/`` is a symbolic link to another disk (a common nuScenes install) still works."""
    normal = os.path.normpath(name)
    if not name.strip() or Path(name).is_absolute() or Path(name).drive or Path(normal).parts[:1] == ("..",):
        raise DataError(f"{where}: filename {name!r} leaves the data root {root}; file names in sample_data must "
                        "be relative paths inside it")
    return root / normal
