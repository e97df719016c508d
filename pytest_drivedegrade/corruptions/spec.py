"""The ladder as data: `drivedegrade spec` renders it as YAML, JSON or a table, from the registry itself."""

from __future__ import annotations

import json
from typing import Any

from ..constants import CAMERAS, REFERENCE_WIDTH
from ..errors import InvalidInput
from .ladder import FAMILIES, SPEC_VERSION

SEEDING = "numpy PCG64 seeded with int(blake2b(f'{seed}|{frame}|{camera}|{family}|{severity}').digest())"


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def _first_line(doc: str | None) -> str:
    """The operator's summary: its docstring up to the first blank line, on one line."""
    return " ".join((doc or "").strip().split("\n\n")[0].split())


def spec_dict() -> dict[str, Any]:
    """The whole ladder: version, conventions and each family's declaration, in SPEC order."""
    return {
        "spec_version": SPEC_VERSION,
        "reference_width_px": REFERENCE_WIDTH,
        "cameras": list(CAMERAS),
        "seeding": SEEDING,
        "diagnostic_cells": {"clean": "severity 0, the decoded image", "blind": "all six cameras zero"},
        "families": [
            {
                "name": f.name, "group": f.group, "axis": f.axis, "core": f.core, "parameter": f.parameter,
                "unit": f.unit, "random": f.random, "scope": f.scope, "scales_with_width": f.spatial,
                "operator": _first_line(f.op.__doc__),
                "values": {f"S{i + 1}": _plain(v) for i, v in enumerate(f.values)},
            }
            for f in FAMILIES.values()
        ],
    }


def _table() -> str:
    rows: list[tuple[str, ...]] = [
        ("family", "group", "axis", "parameter (unit)", "S1", "S2", "S3", "S4", "S5", "random")]
    for f in FAMILIES.values():
        values = ["+".join(c.replace("CAM_", "") for c in v) if isinstance(v, tuple) else str(v) for v in f.values]
        rows.append((f.name, f.group, f.axis, f"{f.parameter} ({f.unit})", *values, "yes" if f.random else "no"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return f"DriveDegrade ladder, spec version {SPEC_VERSION}\n" + "\n".join(lines) + "\n"


def render_spec(fmt: str = "yaml") -> str:
    """The ladder as text in `fmt` ("yaml", "json" or "table")."""
    if fmt == "yaml":
        import yaml

        header = ("# The DriveDegrade corruption ladder, emitted by `drivedegrade spec --format yaml` from the\n"
                  "# injector's own tables. Do not edit: change the code and re-emit.\n")
        return header + yaml.safe_dump(spec_dict(), sort_keys=False, default_flow_style=None, width=110)
    if fmt == "json":
        return json.dumps(spec_dict(), indent=2) + "\n"
    if fmt == "table":
        return _table()
    raise InvalidInput(f"unknown spec format {fmt!r}; valid formats: yaml, json, table")
