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


def read_json(path: Path, what: str, todo: str = "re-extract or regenerate the data") -> object:
    """The JSON value in `path`; a DataError naming `what` and the file for bytes that are not UTF-8, text that
    is not JSON, or JSON nested deeper than the parser can follow (a RecursionError, not a traceback)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        raise DataError(f"unreadable {what} {path}: {exc}; {todo}") from None
    except RecursionError:
        raise DataError(f"unreadable {what} {path}: JSON nested too deeply to parse; {todo}") from None


def load_table(path: Path) -> list[dict]:
    """A table file's rows, checked against `ROW_FIELDS` and `LIST_SHAPES` (a DataError naming the file
    otherwise)."""
    if not path.is_file():
        raise DataError(f"missing nuScenes table {path}: the data root must hold every table of the version "
                        f"folder ({', '.join(REQUIRED_TABLES)})")
    rows = check_rows(path, read_json(path, "nuScenes table"), ROW_FIELDS.get(path.stem, {}))
    return check_lists(path, rows, {k: v for k, v in LIST_SHAPES.items() if k in ROW_FIELDS.get(path.stem, {})})


#: The numeric lists the reader indexes: a field's (length, length of each element or 0 for a number).
LIST_SHAPES: dict[str, tuple[int, int]] = {"translation": (3, 0), "rotation": (4, 0), "size": (3, 0),
                                           "camera_intrinsic": (3, 3)}


def _list_problem(value: list, shape: tuple[int, int]) -> bool:
    """True when `value` is not a list of `shape[0]` numbers (or of lists of `shape[1]` numbers; an empty list
    there too: nuScenes' camera_intrinsic of a lidar or radar)."""
    length, inner = shape
    if inner and not value:
        return False
    if len(value) != length:
        return True
    items = value if not inner else [v for row in value if isinstance(row, list) and len(row) == inner for v in row]
    return len(items) != length * max(inner, 1) or any(type(v) not in (int, float) for v in items)


def check_lists(path: Path, rows: list[dict], shapes: dict[str, tuple[int, int]]) -> list[dict]:
    """`rows` when each field of `shapes` is a list of that many numbers; else a DataError naming the table file,
    the row's token and the field (an IndexError or a string in a pose would otherwise surface much later)."""
    for key, shape in shapes.items():
        for row in rows:
            if _list_problem(row[key], shape):
                what = f"{shape[0]} numbers" if not shape[1] else f"{shape[0]} lists of {shape[1]} numbers"
                raise DataError(f"nuScenes table {path}: the record with token {row.get('token')!r} has "
                                f"{key}={row[key]!r:.80}, expected {what}; re-extract or regenerate the data")
    return rows


#: The fields the reader takes from each CAN bus pose record (`can_bus/<scene>_pose.json`).
CAN_FIELDS = ("vel", "accel", "rotation_rate")


def load_can_bus(path: Path) -> list[dict]:
    """The records of a CAN bus pose file: a list of objects with an integer ``utime`` and three numbers in each of
    `CAN_FIELDS`; else a DataError naming the file and the record (fix the file, or delete it: without it ego
    status comes from ego_pose differences)."""
    todo = "fix or delete the file (without it ego status comes from ego_pose differences)"
    records = read_json(path, "CAN bus file", todo)
    if not isinstance(records, list):
        raise DataError(f"CAN bus file {path} is a JSON {type(records).__name__}, not a list of records; {todo}")
    for i, rec in enumerate(records):
        bad = (not isinstance(rec, dict) or type(rec.get("utime")) is not int
               or any(not isinstance(rec.get(k), list) or len(rec[k]) < 3 or
                      any(type(v) not in (int, float) for v in rec[k][:3]) for k in CAN_FIELDS))
        if bad:
            raise DataError(f"CAN bus file {path}: record {i} ({rec!r:.80}) is not an object with an integer utime "
                            f"and three numbers in each of {', '.join(CAN_FIELDS)}; {todo}")
    return records


def load_manifest(path: Path) -> dict | None:
    """The embedded world's manifest (None when there is none), checked for what the reader uses: its
    ``fingerprint`` (a string) and ``splits`` (split name -> list of scene names)."""
    if not path.is_file():
        return None
    todo = "regenerate the world (drivedegrade world), or delete the file to read the folder as nuScenes"
    data = read_json(path, "world manifest", todo)
    splits = data.get("splits") if isinstance(data, dict) else None
    if not isinstance(data, dict) or not isinstance(data.get("fingerprint"), str) or not isinstance(splits, dict) \
            or not all(isinstance(v, list) and all(isinstance(n, str) for n in v) for v in splits.values()):
        raise DataError(f"malformed world manifest {path}: expected an object with a string fingerprint and "
                        f"splits mapping each split to a list of scene names; {todo}")
    return data


def confined(root: Path, name: str, where: str) -> Path:
    """``root / name`` when `name` is a relative path that stays inside `root` after normalising ``..`` away;
    else a DataError naming `where` (the table row). The check is on the name, not on resolved links, so a data
    root whose ``samples/`` is a symbolic link to another disk (a common nuScenes install) still works."""
    if "\x00" in name or not name.isprintable() or _not_utf8(name):
        raise DataError(f"{where}: filename {name!r} holds a NUL, a control character or bytes that are not UTF-8; "
                        "file names in sample_data must be printable UTF-8: re-extract or regenerate the data")
    normal = Path(os.path.normpath(name))  # normpath keeps a root and a drive: they are tested on it
    if not name.strip() or normal.is_absolute() or normal.drive or normal.parts[:1] == ("..",):
        raise DataError(f"{where}: filename {name!r} leaves the data root {root}; file names in sample_data must "
                        "be relative paths inside it")
    return root / normal


def _not_utf8(name: str) -> bool:
    """True for a name with lone surrogates (how Python carries bytes that are not UTF-8)."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return True
    return False
