"""A changed ladder value needs a new spec version: the values table is pinned by a hash per version."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import yaml

from pytest_drivedegrade import FAMILIES, SPEC_VERSION
from pytest_drivedegrade.corruptions.spec import render_spec

ROOT = Path(__file__).resolve().parents[2]

#: spec version -> SHA-256 of its values table. Versions that changed only operators share a table.
#: Add a line when a value changes (and bump SPEC_VERSION: a new value is at least a minor version).
VALUES_TABLE_SHA256 = {
    "1.0.0": "3c2d1ec18a417af15cca4dca270f0d8e9d87b9f6436bc71681c544eb4792e569",
    "2.0.0": "3c2d1ec18a417af15cca4dca270f0d8e9d87b9f6436bc71681c544eb4792e569",
    "3.0.0": "3c2d1ec18a417af15cca4dca270f0d8e9d87b9f6436bc71681c544eb4792e569",
    "4.0.0": "3c2d1ec18a417af15cca4dca270f0d8e9d87b9f6436bc71681c544eb4792e569",
    "4.1.0": "3c2d1ec18a417af15cca4dca270f0d8e9d87b9f6436bc71681c544eb4792e569",
    "4.2.0": "3c2d1ec18a417af15cca4dca270f0d8e9d87b9f6436bc71681c544eb4792e569",
    "5.0.0": "3c2d1ec18a417af15cca4dca270f0d8e9d87b9f6436bc71681c544eb4792e569",
    "5.1.0": "3c2d1ec18a417af15cca4dca270f0d8e9d87b9f6436bc71681c544eb4792e569",
}


def values_table(families: list[dict]) -> list[dict]:
    """What a spec version pins: each family's name, parameter, unit, five values, randomness, spatial."""
    return [{k: f[k] for k in ("name", "parameter", "unit", "values", "random", "scales_with_width")}
            for f in families]


def table_hash(table: list[dict]) -> str:
    return hashlib.sha256(json.dumps(table, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def test_values_table_hash_is_pinned_for_this_spec_version():
    table = values_table(yaml.safe_load(render_spec("yaml"))["families"])
    digest = table_hash(table)
    assert SPEC_VERSION in VALUES_TABLE_SHA256, (
        f"spec version {SPEC_VERSION} has no pinned values table: add {SPEC_VERSION!r}: {digest!r} to "
        "VALUES_TABLE_SHA256 in tests/test_spec_version.py")
    assert digest == VALUES_TABLE_SHA256[SPEC_VERSION], (
        f"the ladder's values changed but SPEC_VERSION is still {SPEC_VERSION}: bump SPEC_VERSION in "
        f"corruptions/registry.py, re-emit spec/ladder.yaml and add the hash: '<new version>': {digest!r}")


def test_committed_ladder_has_the_same_values_table():
    committed = yaml.safe_load((ROOT / "spec" / "ladder.yaml").read_text())
    assert committed["spec_version"] == SPEC_VERSION
    assert table_hash(values_table(committed["families"])) == VALUES_TABLE_SHA256.get(SPEC_VERSION)


def test_values_table_covers_every_family_and_field():
    table = values_table(yaml.safe_load(render_spec("yaml"))["families"])
    assert [f["name"] for f in table] == list(FAMILIES)
    gaussian_blur = table[0]
    assert gaussian_blur == {"name": "gaussian_blur", "parameter": "defocus sigma", "unit": "px",
                             "values": {"S1": 0.5, "S2": 1.0, "S3": 2.0, "S4": 3.5, "S5": 6.0}, "random": False,
                             "scales_with_width": True}
    changed = [dict(f) for f in table]
    changed[1] = {**changed[1], "values": {**changed[1]["values"], "S3": changed[1]["values"]["S3"] + 1}}
    assert table_hash(changed) != table_hash(table)
