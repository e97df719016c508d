"""The documentation's reference pages are generated from the code (docs/gen_reference.py): an option or a
cells.csv column added without a place there fails here, and the certificate's schema fits a real certificate."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[2] / "docs"


@pytest.fixture(scope="module")
def gen():
    spec = importlib.util.spec_from_file_location("gen_reference", DOCS / "gen_reference.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["gen_reference"] = module
    spec.loader.exec_module(module)
    return module


def test_every_option_has_its_place_in_the_options_reference(gen):
    from pytest_drivedegrade.plugin.options import OPTIONS

    placed = [flag for flags in gen.SECTIONS.values() for flag in flags]
    flags = [spec.flag for spec in OPTIONS]
    missing = sorted(set(flags) - set(placed))
    assert not missing, f"option(s) without docs: {missing}; add each to a section of SECTIONS in docs/gen_reference.py"
    assert sorted(placed) == sorted(flags), "a flag in SECTIONS that is no option, or one placed twice"
    assert all(spec.help.strip() for spec in OPTIONS)


def test_every_cells_csv_column_is_described(gen):
    from pytest_drivedegrade.report.columns import CSV

    missing = [name for name in CSV if not gen.column_description(name)]
    assert not missing, f"cells.csv column(s) without docs: {missing}; describe them in COLUMNS of " \
        "docs/gen_reference.py"
    assert gen.column_description("collision_2s_uniad") == ("share of frames whose plan collides with an annotated "
                                                             "box at 2 s, UniAD convention (the value at the horizon "
                                                             "step)")


def test_the_generated_pages_hold_every_option_column_and_subcommand(gen, tmp_path):
    from pytest_drivedegrade.cli import build_parser
    from pytest_drivedegrade.plugin.options import OPTIONS
    from pytest_drivedegrade.report.columns import CSV

    pages = {p.name: p.read_text() for p in gen.generate(tmp_path)}
    assert all(f"`{spec.flag}" in pages["options.md"] and f"`{spec.dest}`" in pages["options.md"] for spec in OPTIONS)
    assert all(f"| `{name}` |" in pages["cells-csv.md"] for name in CSV)
    subs = next(a for a in build_parser()._actions if hasattr(a, "choices") and isinstance(a.choices, dict))
    assert all(f"## drivedegrade {name}" in pages["cli.md"] for name in subs.choices)
    assert "usage: drivedegrade verify" in pages["cli.md"]


def _fits(value, schema) -> bool:
    """The subset of JSON Schema the generated schema uses: type, const, required, properties, items."""
    kinds = schema.get("type")
    if kinds is not None:
        names = kinds if isinstance(kinds, list) else [kinds]
        ok = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None)}
        if not any((k == "number" and isinstance(value, (int, float)) and not isinstance(value, bool)) or
                   (k == "integer" and isinstance(value, int) and not isinstance(value, bool)) or
                   (k in ok and isinstance(value, ok[k])) for k in names):
            return False
    if "const" in schema and value != schema["const"]:
        return False
    if isinstance(value, dict):
        if any(k not in value for k in schema.get("required", ())):
            return False
        return all(_fits(value[k], s) for k, s in schema.get("properties", {}).items() if k in value)
    if isinstance(value, list) and "items" in schema:
        return all(_fits(v, schema["items"]) for v in value)
    return True


def test_the_schema_fits_a_sealed_certificate_and_not_an_edited_one(gen, tmp_path):
    sys.path.insert(0, str(Path(__file__).parent))
    from test_analysis import GROUPS, synthetic_run

    from pytest_drivedegrade.certificate import seal as cf
    from pytest_drivedegrade.scoring.analyse import analyse_run

    recs, _ = synthetic_run(16, damage=lambda f, s: 0.1 * s)
    prov = cf.Provenance("a", "sha256:planner", "sha256:data", "val", "1.0.0", seed=0, frames=12)
    path = tmp_path / "certificate.json"
    cf.write_certificate(path, cf.build_certificate(analyse_run(recs, groups=GROUPS, n_resamples=20), prov))
    cert = json.loads(path.read_text())
    schema = gen.certificate_schema()
    assert _fits(cert, schema)
    assert not _fits({**cert, "schema": "other/1"}, schema)
    assert not _fits({k: v for k, v in cert.items() if k != "verdict"}, schema)
    broken = {**cert, "cells": [{**cert["cells"][0], "retention": "0.9"}]}
    assert not _fits(broken, schema)
