"""`drivedegrade reproduce CERT PLANNER` end to end (SPEC section 11): certify a small planner, rerun its clean,
null and sampled cells through pytest and find them bit-identical; a planner that moves one waypoint by 1e-9 m is
reported DIFFERENT with the frame; an edited certificate is refused before anything runs."""

from __future__ import annotations

import json

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json  # noqa: E402

from pytest_drivedegrade.certificate.reproduce import sample_cells  # noqa: E402
from pytest_drivedegrade.cli import main  # noqa: E402

pytest_plugins = ["plugin_support"]

FAMILIES = "jpeg,gaussian_noise,blackout"


def test_reproduce_identical_then_different_then_tampered(dd, capsys):
    planner = dd.write_planner()
    result = dd.run("-p", "no:xdist", "--drivedegrade-frames", "6", families=FAMILIES, severities="2,5")
    result.assert_outcomes(passed=9)
    cert_path = dd.folder() / "certificate.json"
    cert = load_json(cert_path)
    assert all(len(c["plans_digest"]) == 64 for c in cert["cells"])
    assert cert["dataset"]["frames_requested"] == 6 and cert["tool"]["versions"]["opencv"]
    expected = sample_cells([c["cell"] for c in cert["cells"]], cert["digest"], 2, salt="0")
    assert expected[:2] == ["clean", "null"] and len(expected) == 4
    capsys.readouterr()

    assert main(["reproduce", str(cert_path), str(planner), "--cells", "2", "--seed", "0"]) == 0
    out, err = capsys.readouterr()
    lines = [line for line in out.splitlines() if line.startswith("[")]
    assert sorted(line.split("] ")[1] for line in lines) == sorted(f"{c}: identical" for c in expected), out + err
    assert "all 4 cell(s) identical" in out
    assert "NOTE" not in err, err  # same machine, same planner, same data: nothing to warn about
    # its progress line, in a log (no terminal here): the closing count only, the verdict lines say each cell
    progress = [line for line in err.splitlines() if line.startswith("drivedegrade reproduce")]
    assert len(progress) == 1 and progress[0].startswith("drivedegrade reproduce: 4 cells in "), err

    source = planner.read_text()
    planner.write_text(source.replace("        return plan\n\n    def misbehave",
                                      "        plan[2, 0] += 1e-9\n        return plan\n\n    def misbehave"))
    # another planner file: refused unless --any-planner (trust issue item 6), then compared frame by frame
    assert main(["reproduce", str(cert_path), str(planner), "--cells", "2", "--seed", "0", "--any-planner"]) == 1
    out, err = capsys.readouterr()
    first = cert_path.parent / "cells" / "clean.json"
    token = json.loads(first.read_text())["record"]["frames"][0]
    for cell in expected:
        assert f"] {cell}: DIFFERENT (first differing frame {token}, 6 frame(s) differ, max plan difference 1e-09 m)" \
            in out, out
    assert "the planner fingerprint differs" in err
    assert "4 of 4 cell(s) DIFFERENT" in out

    cert["cells"][3]["retention"] = 0.5  # tampered: refused before any rerun
    cert_path.write_text(json.dumps(cert))
    assert main(["reproduce", str(cert_path), str(planner)]) == 2
    out, err = capsys.readouterr()
    assert "digest mismatch" in err and "edited section(s): cells" in err and not out
