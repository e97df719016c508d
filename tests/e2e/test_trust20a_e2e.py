"""Issue 20 end to end, the verify / compare / gate items: the PDMS-metric gate in a real run (M13), a signed
baseline required and a rejected baseline refused at start-up (M14), an overflowing number in a shard's files
(M10) and merge's missing-cell advice (L7). Each test is named after its item and fails on the code before it."""

from __future__ import annotations

import json
import shutil

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, no_traceback  # noqa: E402

from pytest_drivedegrade.certificate import seal as cf  # noqa: E402
from pytest_drivedegrade.cli import main  # noqa: E402

pytest_plugins = ["plugin_support"]


def reseal(path, change) -> None:
    """Edit a certificate and reseal it as a forger would (`seal` recomputes the section digests and digest)."""
    data = json.loads(path.read_text())
    change(data)
    path.write_text(cf.certificate_text(cf.seal({k: v for k, v in data.items()
                                                 if k not in ("digest", "section_digests")})))


def test_m13_a_pdms_regression_fails_a_pdms_metric_gate_end_to_end(dd):
    """M13: under --drivedegrade-metric pdms the cell item gates the PDMS retention: a baseline whose jpeg-s1
    PDMS retention is 0.1 higher (its L2 retention unchanged) fails that cell, naming the PDMS retention (before:
    the gate compared L2 retention whatever the verdict's metric, and passed)."""
    dd.write_planner()
    first = dd.run("--drivedegrade-metric", "pdms", families="jpeg", severities="1")
    first.assert_outcomes(passed=4)
    cert = dd.folder() / "certificate.json"
    base = dd.pytester.path / "baseline.json"
    shutil.copy(cert, base)
    jpeg = next(c for c in load_json(cert)["cells"] if c["cell"] == "jpeg-s1")
    assert jpeg["pdms_retention"] is not None

    def lift(d: dict) -> None:
        next(c for c in d["cells"] if c["cell"] == "jpeg-s1")["pdms_retention"] += 0.1
    reseal(base, lift)
    assert main(["verify", str(base)]) == 0  # a consistent baseline: only its PDMS retention is higher
    gated = dd.run("--drivedegrade-metric", "pdms", "--drivedegrade-baseline", str(base), families="jpeg",
                   severities="1")
    gated.assert_outcomes(passed=3, failed=1)
    gated.stdout.fnmatch_lines(["retention regressed beyond --drivedegrade-tolerance 0.02: jpeg-s1: PDMS retention "
                                "* vs baseline * (drop 0.100)"])
    no_traceback(gated)


def test_m14_an_unsigned_or_rejected_baseline_fails_the_run_saying_why(dd):
    """M14: --drivedegrade-baseline-public-key with an unsigned baseline fails before any cell runs, saying it is
    unsigned; a resealed baseline whose arithmetic does not add up is refused naming the field; the key without
    a baseline is a usage error naming both options."""
    dd.write_planner()
    dd.run(families="jpeg", severities="1").assert_outcomes(passed=4)
    base = dd.pytester.path / "baseline.json"
    shutil.copy(dd.folder() / "certificate.json", base)
    assert main(["keygen", str(dd.pytester.path / "issuer")]) == 0
    pub = str(dd.pytester.path / "issuer.pub")
    unsigned = dd.run("--drivedegrade-baseline", str(base), "--drivedegrade-baseline-public-key", pub,
                      families="jpeg", severities="1")
    assert unsigned.ret == pytest.ExitCode.USAGE_ERROR
    unsigned.stderr.fnmatch_lines(["*--drivedegrade-baseline (--drivedegrade-baseline-public-key): *baseline.json: "
                                   "the certificate is unsigned*"])
    lone = dd.run("--drivedegrade-baseline-public-key", pub, families="jpeg", severities="1")
    assert lone.ret == pytest.ExitCode.USAGE_ERROR
    lone.stderr.fnmatch_lines(["*--drivedegrade-baseline-public-key: a public key to check the baseline with, but no "
                               "--drivedegrade-baseline*"])
    reseal(base, lambda d: next(c for c in d["cells"] if c["cell"] == "blind").update(retention=1.5))
    rejected = dd.run("--drivedegrade-baseline", str(base), families="jpeg", severities="1")
    assert rejected.ret == pytest.ExitCode.USAGE_ERROR
    rejected.stderr.fnmatch_lines(["*baseline.json: refused: the digest verifies but the arithmetic does not add up "
                                   "(cells.blind.retention: certificate says 1.500000*"])


@pytest.fixture
def shard(dd):
    """One finished shard folder (1/1) of jpeg S1."""
    dd.write_planner()
    dd.run("--drivedegrade-shard", "1/1", families="jpeg", severities="1").assert_outcomes(passed=4)
    return dd.folder() / "shard-1-of-1"


def test_m10_an_overflowing_number_in_a_shard_file_is_a_clear_merge_error(dd, shard, capsys):
    """M10, merge: 1e999 in a shard's cell file or manifest is an error naming the file, the field and that it
    overflows (before: read as infinity, then an edited-cell error or a crash on writing)."""
    cell = shard / "cells" / "jpeg-s1.json"
    original = cell.read_text()
    cell.write_text(original.replace('"plans": [[[', '"plans": [[[1e999, ', 1))
    out = str(dd.pytester.path / "m")
    assert main(["merge", str(shard), "--out", out]) == 2
    err = capsys.readouterr().err
    assert "jpeg-s1.json: malformed: a 1e999 literal at record.plans[0][0][0] (it overflows a double)" in err
    assert "Traceback" not in err
    cell.write_text(original)
    manifest = shard / "shard.json"
    data = json.loads(manifest.read_text())
    manifest.write_text(manifest.read_text().replace('"floor_l2": [', '"floor_l2": [1e999, ', 1)
                        if data.get("floor_l2") else manifest.read_text().replace('"frames": ', '"frames": 1e999, '
                                                                                  '"was": ', 1))
    assert main(["merge", str(shard), "--out", out]) == 2
    err = capsys.readouterr().err
    assert "shard.json: malformed: a 1e999 literal at " in err and "overflows a double" in err
    assert not (dd.pytester.path / "m" / "testplanner" / "certificate.json").exists()


def test_l7_merge_says_which_shard_lacks_which_cells_and_what_to_do(dd, shard, capsys):
    """L7: a shard that lacks a cell (its file gone) merges as incomplete, and the summary names the shard, the
    cell, and says to rerun that shard and then the merge, not "the same command"."""
    (shard / "cells" / "jpeg-s1.json").unlink()
    assert main(["merge", str(shard), "--out", str(dd.pytester.path / "m"), "--allow-incomplete"]) == 0
    out = capsys.readouterr().out
    assert f"missing cells (1): jpeg-s1; shard 1/1 ({shard}) lacks jpeg-s1: rerun each such shard with its own " \
           "command (--drivedegrade-shard I/N; its finished cells are reused), then run this merge again" in out
    assert "rerun the same command" not in out
