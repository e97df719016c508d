"""Trust issue 20, numbered items 2-6 and M4: each test is named after the item it covers and fails on the code
before its fix."""

from __future__ import annotations

import json

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json  # noqa: E402

from pytest_drivedegrade.cells import record_digest  # noqa: E402
from pytest_drivedegrade.cli import main  # noqa: E402

pytest_plugins = ["plugin_support"]


def _strip_digest(path, *, shift: float) -> None:
    """Drop a stored cell's ``record_digest`` and move its first plan by `shift` m (a hand-made cell)."""
    data = json.loads(path.read_text())
    del data["record_digest"]
    data["record"]["plans"][0][0][0] += shift
    path.write_text(json.dumps(data))


def test_item2_a_stored_cell_without_record_digest_is_recomputed_not_trusted(dd):
    """Item 2: a stored cell without ``record_digest`` is a digest failure: recomputed (its plans back to the
    computed ones), named in the summary, not listed as reused; the certificate lists every cell's record digest,
    which the stored cell files hash to."""
    dd.write_planner()
    dd.run(families="jpeg", severities="1").assert_outcomes(passed=4)
    path = dd.folder() / "cells" / "jpeg-s1.json"
    original = json.loads(path.read_text())
    _strip_digest(path, shift=3.0)
    again = dd.run(families="jpeg", severities="1")
    again.assert_outcomes(passed=4)
    again.stdout.fnmatch_lines(["*reused 3 stored cell(s) (same run key, digest verified): blind, clean, null",
                                "*recomputed 1 stored cell(s) whose content digest failed*: jpeg-s1"])
    assert json.loads(path.read_text())["record"]["plans"] == original["record"]["plans"]
    cert = load_json(dd.folder() / "certificate.json")
    assert cert["cost"]["resumed_cells"] == ["blind", "clean", "null"]
    for cell in cert["cells"]:
        stored = json.loads((dd.folder() / "cells" / f"{cell['cell']}.json").read_text())
        assert cell["record_digest"] == stored["record_digest"] == record_digest(stored["record"])


def test_item2_merge_refuses_a_shard_cell_without_record_digest(dd, capsys):
    """Item 2, merge: a shard's cell file without ``record_digest`` is refused, naming the file, even with
    --allow-incomplete (it is not a missing cell that a merge may leave out)."""
    dd.write_planner()
    dd.run("--drivedegrade-shard", "1/1", families="jpeg", severities="1").assert_outcomes(passed=4)
    shard = dd.folder() / "shard-1-of-1"
    _strip_digest(shard / "cells" / "clean.json", shift=0.0)
    out = str(dd.pytester.path / "m")
    assert main(["merge", str(shard), "--out", out, "--allow-incomplete"]) == 2
    err = capsys.readouterr().err
    assert "clean.json" in err and "no record_digest" in err
    assert not (dd.pytester.path / "m" / "testplanner" / "certificate.json").exists()
