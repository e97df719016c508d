"""Issue 37: "A sharded run cannot be gated" (a baseline under a shard is refused, and nothing gated the merged
run): `drivedegrade merge --baseline BASE` gates the merged run, exit 1 on a regression, 0 without; and (low)
"merge exits 0 when a shard lacks a cell": refused unless --allow-incomplete."""

from __future__ import annotations

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import FRAGILE  # noqa: E402

from pytest_drivedegrade.cli import main  # noqa: E402

pytest_plugins = ["plugin_support"]

FAMILIES, SEVERITIES = "low_light,blackout", "5"


def test_a_merged_sharded_run_is_gated_against_a_baseline(dd, capsys):
    dd.write_planner()
    dd.run(families=FAMILIES, severities=SEVERITIES, report="base").assert_outcomes(passed=5)
    base = str(dd.folder(report="base") / "certificate.json")
    refused = dd.run("--drivedegrade-shard", "1/1", "--drivedegrade-baseline", base, families=FAMILIES,
                     severities=SEVERITIES, report="refused")
    assert refused.ret == pytest.ExitCode.USAGE_ERROR
    assert "drivedegrade merge SHARD_DIRS --out DIR --baseline BASE" in refused.stderr.str()
    dd.run("--drivedegrade-shard", "1/1", families=FAMILIES, severities=SEVERITIES, report="same")
    shard = str(dd.folder(report="same") / "shard-1-of-1")
    assert main(["merge", shard, "--out", str(dd.pytester.path / "m1"), "--baseline", base]) == 0
    assert "0 cell and 0 axis regression(s)" in capsys.readouterr().out
    dd.write_planner(scale=FRAGILE)
    dd.run("--drivedegrade-shard", "1/1", families=FAMILIES, severities=SEVERITIES, report="worse")
    shard = str(dd.folder(report="worse") / "shard-1-of-1")
    assert main(["merge", shard, "--out", str(dd.pytester.path / "m2"), "--baseline", base]) == 1
    out = capsys.readouterr().out
    assert "REGRESSION low_light-s5" in out, out
    assert (dd.pytester.path / "m2" / "testplanner" / "certificate.json").is_file()  # written, then gated
    edited = dd.pytester.path / "edited.json"
    text = (dd.folder(report="base") / "certificate.json").read_text()
    edited.write_text(text.replace('"label": "', '"label": "x', 1))
    assert main(["merge", shard, "--out", str(dd.pytester.path / "m3"), "--baseline", str(edited)]) == 2
    assert "--baseline: " in capsys.readouterr().err and not (dd.pytester.path / "m3").exists()


def test_merge_refuses_a_shard_that_lacks_a_cell_unless_allowed(dd, capsys):
    dd.write_planner()
    dd.run("--drivedegrade-shard", "1/1", families="jpeg", severities="1").assert_outcomes(passed=4)
    shard = dd.folder() / "shard-1-of-1"
    (shard / "cells" / "jpeg-s1.json").unlink()
    out = dd.pytester.path / "m"
    assert main(["merge", str(shard), "--out", str(out)]) == 2  # old code: 0, a certificate written
    err = capsys.readouterr().err
    assert "missing cell(s) jpeg-s1: shard 1/1" in err and "--allow-incomplete" in err, err
    assert not out.exists()
    assert main(["merge", str(shard), "--out", str(out), "--allow-incomplete"]) == 0


def test_compare_notes_a_mix_of_adaptive_and_full_certificates(dd, capsys):
    """Issue 37 (low): `compare` mixed adaptive and full certificates without a note; now a column says which
    each is, and the terminal and compare.html carry a note naming the adaptive ones."""
    import csv

    dd.write_planner()
    dd.run("-p", "no:xdist", families="jpeg", severities="1", report="full").assert_outcomes(passed=4)
    dd.run("-p", "no:xdist", "--drivedegrade-adaptive", families="jpeg", severities="1", report="ada")
    full, ada = (str(dd.folder(report=r) / "certificate.json") for r in ("full", "ada"))
    out = dd.pytester.path / "cmp"
    code = main(["compare", full, ada, "--out", str(out), "--force"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert "note: this comparison mixes adaptive and full certificates" in printed.out and ada in printed.out
    rows = list(csv.DictReader((out / "compare.csv").open()))
    assert [r["certification"] for r in rows] == ["full", "adaptive"]
    assert "Note: this comparison mixes adaptive and full certificates" in (out / "compare.html").read_text()
    # Issue 37 (low): the adaptive certificate copied without its cells/ is "cannot check, missing X" (exit 2),
    # not a failed arithmetic (exit 1); so is one cell file gone
    import shutil

    alone = dd.pytester.path / "alone"
    alone.mkdir()
    shutil.copyfile(ada, alone / "certificate.json")
    assert main(["verify", str(alone / "certificate.json")]) == 2
    err = capsys.readouterr().err
    assert f"these are missing: {alone / 'cells'}" in err and "copy the certificate together with" in err, err
    (dd.folder(report="ada") / "cells" / "jpeg-s1.json").unlink()
    assert main(["verify", ada]) == 2
    assert f"these are missing: {dd.folder(report='ada') / 'cells' / 'jpeg-s1.json'}" in capsys.readouterr().err
    assert main(["verify", full]) == 0
