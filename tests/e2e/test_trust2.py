"""Trust issue 20, numbered items 2-6 and M4: each test is named after the item it covers and fails on the code
before its fix."""

from __future__ import annotations

import json

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json  # noqa: E402

from pytest_drivedegrade.cli import main  # noqa: E402
from pytest_drivedegrade.payload import record_digest  # noqa: E402

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
    assert sorted(cert["record_digests"]) == sorted(c["cell"] for c in cert["cells"])
    for cell, digest in cert["record_digests"].items():
        stored = json.loads((dd.folder() / "cells" / f"{cell}.json").read_text())
        assert digest == stored["record_digest"] == record_digest(stored["record"])


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


@pytest.mark.parametrize("narrow", [("-k", "not blackout"), ("-k", "clean"), ("--drivedegrade-families", "jpeg")])
def test_item3_a_narrowed_gated_run_fails_naming_what_it_did_not_compute(dd, narrow):
    """Item 3: a gated run narrowed by ``-k`` or a shorter family list fails the gate, naming the baseline's
    cells it did not compute, unless --drivedegrade-baseline-partial (which names them too)."""
    dd.write_planner()
    dd.run(families="jpeg,blackout", severities="5").assert_outcomes(passed=5)
    baseline = dd.pytester.path / "baseline.json"
    baseline.write_text((dd.folder() / "certificate.json").read_text())
    families = "jpeg,blackout" if narrow[0] == "-k" else narrow[1]
    args = narrow if narrow[0] == "-k" else ()
    narrowed = dd.run("--drivedegrade-baseline", str(baseline), *args, families=families, severities="5",
                      report="fresh")  # a fresh checkout: no stored cells of the baseline's run to fill the gaps
    assert narrowed.ret == 1
    narrowed.stdout.fnmatch_lines(["*baseline: FAILED: not compared: * cell(s) of the baseline were not computed "
                                   "by this run: *blackout-s5*"])
    partial = dd.run("--drivedegrade-baseline", str(baseline), "--drivedegrade-baseline-partial", *args,
                     families=families, severities="5", report="fresh2")
    assert partial.ret == 0
    partial.stdout.fnmatch_lines(["*baseline (--drivedegrade-baseline-partial): not compared: *blackout-s5*"])


#: A front-camera planner without reset that tracks scenes through ``context.scene_token`` (item 4): its plan
#: drifts with the number of frames of the scene it has seen, so a skipped call changes later plans. `declare`
#: is a class-body line (``deterministic = True`` for a planner that claims what it is not), `context` whether
#: predict takes the context (without it the planner counts every call it ever had).
TRACKER = '''
import numpy as np
import pytest

T = 0.5 * np.arange(1, 7)


class Tracker:
    cameras = ("CAM_FRONT",)
    name = "tracker"
    {declare}

    def __init__(self):
        self.at, self.seen = None, 0

    def predict(self, images, ego, cmd{context}):
        at = {at}  # a new track at another scene, or back at an earlier keyframe (the next cell's pass)
        self.seen = self.seen + 1 if self.at is not None and at[0] == self.at[0] and at[1] > self.at[1] else 1
        self.at = at
        plan = np.zeros((6, 2))
        plan[:, 0] = max(ego.velocity[0], 0.0) * T
        plan[:, 1] = float(images["CAM_FRONT"][::8, ::8].mean()) / 255.0 + 0.01 * self.seen
        return plan


@pytest.fixture(scope="session")
def planner():
    return Tracker()
'''


def _tracker(dd, *extra, declare="", context=True, report):
    dd.pytester.makepyfile(tracker=TRACKER.format(declare=declare, context=", context" if context else "",
                                                  at="(context.scene_token, context.index)" if context
                                                  else "(0, self.seen)"))
    return dd.run("-p", "no:xdist", *extra, planner="tracker.py", report=report,
                  families="blackout,frame_dropout", severities="1,3")


def test_item4_a_temporal_planner_that_sees_the_stream_is_not_reused(dd):
    """Item 4: a planner whose predict takes the context and that does not declare ``deterministic = True`` may
    track scenes by ``context.scene_token``: its frames are never reused, so its cells equal those of a run with
    --drivedegrade-no-reuse (reuse would skip calls and certify other numbers)."""
    on = _tracker(dd, report="on")
    on.assert_outcomes(passed=7)
    off = _tracker(dd, "--drivedegrade-no-reuse", report="off")
    off.assert_outcomes(passed=7)
    a = load_json(dd.folder("tracker", report="on") / "certificate.json")
    b = load_json(dd.folder("tracker", report="off") / "certificate.json")
    assert a["cost"]["reused"] == 0
    assert a["cells"] == b["cells"] and a["axes"] == b["axes"]


@pytest.mark.parametrize("context", [True, False], ids=["declares-deterministic", "no-context"])
def test_item4_the_reuse_control_fails_a_planner_whose_reused_plans_differ(dd, context):
    """Item 4, the reuse control: a planner that reuse applies to (it declares ``deterministic = True``, or its
    predict takes no context) but whose plans depend on its call history is predicted on a sample of the reused
    frames; a plan that differs bit for bit from the reused one fails the cell loudly, saying why."""
    result = _tracker(dd, declare="deterministic = True" if context else "", context=context, report="r")
    assert result.ret == 1
    result.stdout.fnmatch_lines(["*reuse control failed: predict() on inputs equal to the clean cell's returned "
                                 "another plan than clean's*"])


def test_item6_reproduce_checks_the_arithmetic_the_planner_and_draws_a_fresh_sample(dd, capsys):
    """Item 6: `reproduce` refuses a resealed certificate whose verdict contradicts its cells before any rerun,
    refuses another planner (its name here) unless --any-planner, and draws its default sample from fresh
    randomness, naming the seed so that --seed draws the same cells again."""
    from pytest_drivedegrade.certificate.reproduce import sample_cells
    from pytest_drivedegrade.certificate.seal import seal, verify, write_certificate

    planner = dd.write_planner()
    dd.run("-p", "no:xdist", families="jpeg,blackout", severities="2,5").assert_outcomes(passed=7)
    cert_path = dd.folder() / "certificate.json"
    cert = verify(cert_path)
    forged = dict(cert)
    forged["verdict"] = {**cert["verdict"], "label": "not-shown-to-use-cameras"
                         if cert["verdict"]["label"] != "not-shown-to-use-cameras" else "uses-cameras"}
    forged_path = dd.pytester.path / "forged.json"
    write_certificate(forged_path, seal(forged))
    capsys.readouterr()
    assert main(["reproduce", str(forged_path), str(planner)]) == 2
    out, err = capsys.readouterr()
    assert "contradict its own cells" in err and "verdict" in err and "sample seed" not in out

    seeds = []
    for _ in range(2):
        assert main(["reproduce", str(cert_path), str(planner), "--cells", "1"]) == 0
        out, _err = capsys.readouterr()
        line = next(x for x in out.splitlines() if x.startswith("reproduce: sample seed "))
        assert "(fresh randomness; --seed" in line
        seed = line.split()[3]
        seeds.append(seed)
        cells = line.split(": ", 2)[2].split(", ")
        assert cells == sample_cells([c["cell"] for c in cert["cells"]], cert["digest"], 1, salt=seed)
    assert seeds[0] != seeds[1]  # 1 in 2**31 to collide

    planner.write_text(planner.read_text().replace("name = 'testplanner'", "name = 'another'"))
    assert main(["reproduce", str(cert_path), str(planner), "--cells", "0", "--seed", "1"]) == 2
    err = capsys.readouterr().err
    assert "the planner is not the certificate's (name 'another' here, 'testplanner' in the certificate" in err
    assert main(["reproduce", str(cert_path), str(planner), "--cells", "0", "--seed", "1", "--any-planner"]) == 0


#: A planner whose model lives in a module beside it (item 5): the plan's offset comes from `trust2_model`.
MODEL_PLANNER = '''
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from trust2_model import OFFSET  # noqa: E402


class Modelled:
    cameras = ("CAM_FRONT",)
    name = "modelled"

    def predict(self, images, ego, cmd):
        plan = np.zeros((6, 2))
        plan[:, 0] = max(ego.velocity[0], 0.0) * 0.5 * np.arange(1, 7) + OFFSET
        plan[:, 1] = float(images["CAM_FRONT"][::8, ::8].mean()) / 255.0
        return plan


@pytest.fixture(scope="session")
def planner():
    return Modelled()
'''


def test_item5_a_changed_imported_module_is_not_reused_and_no_resume_recomputes(dd):
    """Item 5: the planner fingerprint covers a module the planner file imports from beside it, so changing that
    module recomputes the stored cells (stale: planner_fingerprint) instead of reusing them; and
    --drivedegrade-no-resume recomputes every cell of an unchanged planner."""
    from pytest_drivedegrade.planning import covered_modules

    dd.pytester.makepyfile(modelled=MODEL_PLANNER, trust2_model="OFFSET = 0.0\n")
    planner = dd.pytester.path / "modelled.py"
    assert [p.name for p in covered_modules(planner)] == ["modelled.py", "trust2_model.py"]

    def certify(*extra):
        result = dd.run("-p", "no:xdist", *extra, planner="modelled.py", families="jpeg", severities="1")
        result.assert_outcomes(passed=4)
        return result, load_json(dd.folder("modelled") / "certificate.json")

    _, first = certify()
    again, second = certify()
    again.stdout.fnmatch_lines(["*reused 4 stored cell(s)*", "planner fingerprint covers modelled.py and 1 "
                                "module(s) it imports from outside site-packages: trust2_model.py"])
    (dd.pytester.path / "trust2_model.py").write_text("OFFSET = 0.25\n")
    changed, third = certify()
    assert third["planner"]["fingerprint"] != first["planner"]["fingerprint"]
    assert third["cost"]["resumed_cells"] == []
    changed.stdout.fnmatch_lines(["*not reused: 4 stored cell(s) recomputed because their run key differs in "
                                  "planner_fingerprint*"])
    fresh, fourth = certify("--drivedegrade-no-resume")
    assert fourth["cost"]["resumed_cells"] == [] and "stored cell(s)" not in fresh.stdout.str()
    assert fourth["planner"]["fingerprint"] == third["planner"]["fingerprint"]


def test_stop32_under_xdist_every_record_digest_is_its_files_and_a_forged_store_cell_is_caught(dd, capsys):
    """Issue 23's third pass sends each cell to the controller as its store text and seals the digest checked on
    receipt. Attacked under -n 2: (1) every certificate record digest equals the hash of the record in its cell
    file, computed cells and reused ones alike; (2) a store cell edited without its digest is recomputed, and the
    certificate then seals the recomputed file, not the edited one; (3) a forger who also rewrites the digest gets
    the cell reused (the seal is integrity only, and says so), but `drivedegrade reproduce` reruns it and names it
    DIFFERENT rather than report the run identical."""
    planner = dd.write_planner()

    def run_and_check(*extra: str) -> dict:
        result = dd.run("-n", "2", *extra, families="jpeg", severities="1")
        result.assert_outcomes(passed=4)
        cert = load_json(dd.folder() / "certificate.json")
        files = {p.stem: json.loads(p.read_text()) for p in (dd.folder() / "cells").glob("*.json")}
        assert sorted(cert["record_digests"]) == sorted(files) == ["blind", "clean", "jpeg-s1", "null"]
        for cell, stored in files.items():
            assert cert["record_digests"][cell] == record_digest(stored["record"]) == stored["record_digest"], cell
        assert main(["verify", str(dd.folder() / "certificate.json")]) == 0
        return files

    original = run_and_check()
    path = dd.folder() / "cells" / "jpeg-s1.json"
    edited = json.loads(path.read_text())
    edited["record"]["plans"][0][0][0] += 3.0
    path.write_text(json.dumps(edited))
    again = run_and_check()
    assert again["jpeg-s1"]["record"]["plans"] == original["jpeg-s1"]["record"]["plans"]

    forged = json.loads(path.read_text())
    forged["record"]["plans"][0][0][0] += 3.0
    forged["record_digest"] = record_digest(forged["record"])
    path.write_text(json.dumps(forged))
    reused = run_and_check()
    assert reused["jpeg-s1"]["record"]["plans"] == forged["record"]["plans"]  # resumed as stored: integrity only
    assert "jpeg-s1" in load_json(dd.folder() / "certificate.json")["cost"]["resumed_cells"]
    capsys.readouterr()
    assert main(["reproduce", str(dd.folder() / "certificate.json"), str(planner), "--seed", "0"]) == 1
    out = capsys.readouterr().out
    assert "] jpeg-s1: DIFFERENT" in out and "] clean: identical" in out, out
