"""Issue 20, the verify / compare / gate items (M1, M3, M10, M13, M14, L2, L7, L8, L10, the gate's digits) and
the "tests that would not notice" of verify and the seal: each test is named after its item and fails on the code
before its change (or, for a mutation, with that single change applied by hand)."""

from __future__ import annotations

import copy
import csv
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from test_analysis import GROUPS, record, synthetic_run

from pytest_drivedegrade.certificate import seal as cf
from pytest_drivedegrade.certificate import signing as sg
from pytest_drivedegrade.certificate.compare import CompareError, write_compare
from pytest_drivedegrade.certificate.consistency import check_consistency
from pytest_drivedegrade.cli import main
from pytest_drivedegrade.scoring import baseline as bl
from pytest_drivedegrade.scoring.analyse import analyse_run
from pytest_drivedegrade.scoring.verdict import ego_label

PROV = cf.Provenance("demo", "sha256:planner", "sha256:data", "val", "1.0.0", seed=0, frames=12)


def reseal(path: Path, change) -> None:
    """Edit and reseal as a forger would: the section digests and the digest recomputed with hashlib."""
    data = json.loads(path.read_text())
    change(data)

    def sha(obj) -> str:
        return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()

    body = {k: v for k, v in data.items() if k not in ("digest", "section_digests")}
    data["section_digests"] = {k: sha(v) for k, v in body.items()}
    data["digest"] = sha({k: v for k, v in data.items() if k != "digest"})
    path.write_text(json.dumps(data, indent=2))


def make_cert(tmp_path: Path, name: str = "certificate.json", *, null_wander: float = 0.0, ego: bool = False,
              prov: cf.Provenance = PROV) -> Path:
    """A sealed certificate of the synthetic run, with each cell's plans digest (and record digests)."""
    recs, truth = synthetic_run(12, null_wander=null_wander)
    for r in recs:  # a PDMS-like score that falls with the plan's error, so the PDMS axes have values
        r.pdms = 1.0 / (1.0 + r.l2.mean(axis=1))
    if ego:
        gt = np.stack([truth[f"tok{i:03d}"] for i in range(12)])
        clean = next(r for r in recs if r.cell == "clean")
        recs += [record("ego_noise-s5", "ego_noise", 5, clean.plans + 0.003, gt),
                 record("ego_blind", "ego_blind", 0, clean.plans + 2.0, gt)]
        for r in recs[-2:]:
            r.pdms = 1.0 / (1.0 + r.l2.mean(axis=1))
    analysis = analyse_run(recs, groups=GROUPS, n_resamples=50, floor_l2=5.0)
    return cf.write_certificate(tmp_path / name, cf.build_certificate(
        analysis, prov, created="2025-01-01T00:00:00+00:00", records={r.cell: r for r in recs}))


def _cell(data: dict, cell: str) -> dict:
    return next(c for c in data["cells"] if c["cell"] == cell)


# --- M1: retention against each cell's own figures, the null control against the plans digests ----------------

def test_m1_a_retention_its_own_l2_contradicts_fails_verify(tmp_path: Path, capsys) -> None:
    """M1: blind's retention is used by no threshold or axis, so only its own figures can catch an edit; a
    cell whose L2 was copied from clean (it looks undamaged) while its retention stays is caught too. The
    recomputed value is clean's l2_avg over the cell's (an error metric)."""
    path = make_cert(tmp_path)
    assert check_consistency(cf.verify(path)) == []
    reseal(path, lambda d: _cell(d, "blind").update(retention=0.999))
    cert = cf.verify(path)
    clean, blind = _cell(cert, "clean")["l2_avg"], _cell(cert, "blind")["l2_avg"]
    assert check_consistency(cert) == [f"cells.blind.retention: certificate says 0.999000, its l2_avg {blind:.6f} "
                                       f"against clean's {clean:.6f} gives {clean / blind:.6f}"]
    assert main(["verify", str(path)]) == 1
    assert "cells.blind.retention" in capsys.readouterr().err

    path = make_cert(tmp_path, "b.json")
    reseal(path, lambda d: _cell(d, "fog-s2").update(l2_avg=_cell(d, "clean")["l2_avg"]))
    problems = check_consistency(cf.verify(path))
    assert len(problems) == 1 and problems[0].startswith("cells.fog-s2.retention: certificate says ")
    assert problems[0].endswith("gives 1.000000")


def test_m1_a_failed_null_control_reported_as_passed_is_caught_by_the_plans_digests(tmp_path: Path) -> None:
    """M1: the null cell wandered (its plans digest differs from clean's, every frame planned in both), so the
    null control failed and the verdict is undetermined; a forger who says it passed and puts the computed label
    back leaves nothing else to catch."""
    path = make_cert(tmp_path, null_wander=0.01)
    cert = cf.verify(path)
    assert cert["null_control"]["passed"] is False and cert["verdict"]["label"] == "undetermined"
    assert _cell(cert, "null")["plans_digest"] != _cell(cert, "clean")["plans_digest"]
    assert check_consistency(cert) == []

    def say_passed(d: dict) -> None:
        d["null_control"].update(passed=True, max_abs_diff=0.0, max_l2_change=0.0, frames_changed=0)
        d["verdict"]["label"] = d["verdict"]["computed_label"]
    reseal(path, say_passed)
    problems = check_consistency(cf.verify(path))
    # since issue 40 the reliance section, read against the null's wander, no longer adds up either
    assert problems == ["null_control.passed: certificate says True, but the null cell's plans_digest differs from "
                        "clean's with every frame planned in both: its plans differ, so the control failed",
                        "reliance.wander: certificate says 0.014142, its null control gives 0.000000"]


def test_m1_a_passed_null_control_reported_as_failed_is_caught_by_the_plans_digests(tmp_path: Path) -> None:
    """M1, the other way: equal plans digests are bit-identical plans, so a null control reported failed (which
    would make any planner's verdict undetermined) contradicts the certificate's own cells."""
    path = make_cert(tmp_path)
    reseal(path, lambda d: (d["null_control"].update(passed=False, frames_changed=3),
                            d["verdict"].update(label="undetermined")))
    problems = check_consistency(cf.verify(path))
    assert problems == ["null_control.passed: certificate says False with 3 frame(s) changed, but the null cell's "
                        "plans_digest equals clean's: its plans are bit-identical, so the control passed"]


# --- M10: an overflowing number literal --------------------------------------------------------------------------

@pytest.mark.parametrize("literal", ["1e999", "-1e999", "1" * 5000], ids=["1e999", "-1e999", "5000-digits"])
@pytest.mark.parametrize("command", ["verify", "compare", "reproduce"])
def test_m10_an_overflowing_number_is_a_clear_error_naming_the_file(tmp_path: Path, capsys, command: str,
                                                                    literal: str) -> None:
    """M10: 1e999 (a double overflows to infinity) or a 5000-digit integer (past Python's conversion limit) in a
    certificate is a malformed file named with the field, exit 2, never a traceback."""
    path = make_cert(tmp_path)
    text = path.read_text()
    path.write_text(text.replace('"l2_avg": ', f'"l2_avg": {literal}, "was": ', 1))
    (tmp_path / "planner.py").write_text("class P:\n    pass\n")
    argv = {"verify": ["verify", str(path)], "compare": ["compare", str(path), "--out", str(tmp_path / "o")],
            "reproduce": ["reproduce", str(path), str(tmp_path / "planner.py")]}[command]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "Traceback" not in err
    assert "cells[0].l2_avg" in err and ("overflows a double" in err or "too long a number" in err)


def test_m10_cell_files_keep_their_nan_but_not_an_overflowing_number(tmp_path: Path) -> None:
    """M10: a cell file (and a shard manifest) holds NaN for failed frames, read as such; 1e999 is refused."""
    good = tmp_path / "cell.json"
    good.write_text('{"l2": [NaN, 1.5], "n": 3}')
    got = cf.read_strict_json(good, constants=True)
    assert isinstance(got, dict) and np.isnan(got["l2"][0]) and got["l2"][1] == 1.5 and got["n"] == 3
    good.write_text('{"l2": [NaN, 1e999]}')
    with pytest.raises(cf.CertificateError, match=r"cell\.json: malformed: a 1e999 literal at l2\[1\] \(it "
                                                  r"overflows a double\)"):
        cf.read_strict_json(good, constants=True)


# --- M3, L10, L2: compare ------------------------------------------------------------------------------------

def test_m3_compare_refuses_a_certificate_verify_rejects(tmp_path: Path, capsys) -> None:
    """M3: a resealed certificate whose arithmetic does not add up is refused by compare, even with --force."""
    good, bad = make_cert(tmp_path, "good.json"), make_cert(tmp_path, "bad.json")
    reseal(bad, lambda d: d["axes"].update(quality=0.999))
    with pytest.raises(CompareError, match=r"bad\.json: the digest verifies but the arithmetic does not add up "
                                           r"\(axes\.quality: certificate says 0\.999000"):
        write_compare([good, bad], tmp_path / "o", force=True)
    assert main(["compare", str(good), str(bad), "--out", str(tmp_path / "o"), "--force"]) == 2
    assert "refused" in capsys.readouterr().err
    assert not (tmp_path / "o" / "compare.csv").exists()


def test_m3_compare_marks_an_incomplete_certificate(tmp_path: Path, capsys) -> None:
    """M3: an incomplete certificate is compared but marked, in the table, the page and the terminal."""
    good, part = make_cert(tmp_path, "good.json"), make_cert(tmp_path, "part.json")
    reseal(part, lambda d: d.__setitem__("completeness", {"complete": False, "missing_cells": ["jpeg-s3"]}))
    _, html_path, df = write_compare([good, part], tmp_path / "o")
    assert list(df["status"]) == ["complete", "incomplete: missing cell(s): jpeg-s3"]
    assert "INCOMPLETE, compared as it is" in html_path.read_text()
    assert main(["compare", str(good), str(part), "--out", str(tmp_path / "p")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "INCOMPLETE" not in out[0] and out[1].endswith("INCOMPLETE (missing cell(s): jpeg-s3)")


def test_l10_compare_names_every_setting_that_differs(tmp_path: Path, capsys) -> None:
    """L10: certificates scored on other frames, with other seeds or under another OpenCV are not the same
    quantity: compare names each difference with both values and files; --force compares them with the warnings
    on the page."""
    a = make_cert(tmp_path, "a.json")
    b = make_cert(tmp_path, "b.json", prov=cf.Provenance("demo", "sha256:planner", "sha256:data", "val", "1.0.0",
                                                         seed=0, frames=16))

    def other(d: dict) -> None:
        d["settings"].update(seeds=3, seed_values=[0, 1, 2])
        d["tool"]["versions"]["opencv"] = "4.9.0"
    reseal(b, other)
    with pytest.raises(CompareError) as caught:
        write_compare([a, b], tmp_path / "o")
    text = str(caught.value)
    assert f"different scored frames: 12 in {a}; 16 in {b}" in text
    assert "different OpenCV version: " in text and f"'4.9.0' in {b}" in text
    assert f"different corruption seeds (--drivedegrade-seeds): 1 in {a}; 3 in {b}" in text
    assert "numpy" not in text and "spec version" not in text
    _, html_path, _ = write_compare([a, b], tmp_path / "o", force=True)
    assert "Compared with --force: different scored frames" in html_path.read_text()


def test_l2_compare_csv_neutralises_spreadsheet_formulas(tmp_path: Path) -> None:
    """L2: a planner named like a formula is written with a leading apostrophe (OWASP), numbers stay numbers."""
    from pytest_drivedegrade.certificate.compare import neutralise

    names = ["=HYPERLINK(\"http://x\")", "+1", "-2+3", "@SUM(A1)", "\tcmd", "plain"]
    paths = [make_cert(tmp_path, f"c{i}.json", prov=cf.Provenance(n, "sha256:planner", "sha256:data", "val",
                                                                   "1.0.0", seed=0, frames=12))
             for i, n in enumerate(names)]
    csv_path, _, df = write_compare(paths, tmp_path / "o")
    rows = list(csv.DictReader(csv_path.open(newline="")))
    assert [r["planner"] for r in rows] == ["'" + n for n in names[:5]] + ["plain"]
    assert list(df["planner"]) == names  # the table itself keeps the names
    assert float(rows[0]["clean_l2"]) == pytest.approx(df["clean_l2"][0], abs=1e-5)
    assert neutralise(-2.0) == -2.0 and neutralise("\rx") == "'\rx" and neutralise("a=b") == "a=b"


# --- M13, M14 and the digits: the gate -----------------------------------------------------------------------

def _pdms(path: Path) -> dict:
    cert = cf.verify(path)
    cert["verdict"]["metric"] = cert["settings"]["verdict_metric"] = "pdms"
    return cert


def test_m13_a_pdms_regression_fails_a_pdms_metric_gate(tmp_path: Path) -> None:
    """M13: under --drivedegrade-metric pdms the gate compares PDMS retention (cells) and ``axes_pdms``: a PDMS
    drop with unchanged L2 retention is a regression; under l2 the same change is not."""
    from pytest_drivedegrade.plugin.controller import gate

    base = _pdms(make_cert(tmp_path))
    now = copy.deepcopy(base)
    _cell(now, "fog-s3")["pdms_retention"] -= 0.1
    now["axes_pdms"]["quality"] -= 0.05
    got = bl.compare_to_baseline(now, base, 0.02)
    assert [(r.name, r.metric, round(r.drop, 6)) for r in got["cells"]] == [("fog-s3", "pdms", 0.1)]
    assert [(r.name, round(r.drop, 6)) for r in got["axes"]] == [("axis:quality", 0.05)]
    assert got["cells"][0].message().startswith("fog-s3: PDMS retention ")
    lines, failed = gate(now, base, 0.02)
    assert failed and any(line.startswith("REGRESSION axis:quality: PDMS retention") for line in lines)
    l2_now, l2_base = copy.deepcopy(now), copy.deepcopy(base)
    for c in (l2_now, l2_base):
        c["verdict"]["metric"] = c["settings"]["verdict_metric"] = "l2"
    assert bl.compare_to_baseline(l2_now, l2_base, 0.02) == {"cells": [], "axes": []}
    assert bl.cell_regression("fog-s3", _cell(now, "fog-s3")["pdms_retention"], base, 0.02, "pdms") is not None


def test_m13_the_cell_item_gates_the_pdms_retention_of_the_record() -> None:
    """M13, the per-cell item: the retention it compares is the record's PDMS retention (reward: cell over
    clean, over frames scored in both), not its L2 retention."""
    from pytest_drivedegrade.plugin.checks import gated_retention
    from pytest_drivedegrade.scoring.retention import record_retention

    recs, _ = synthetic_run(12)
    clean, fog = next(r for r in recs if r.cell == "clean"), next(r for r in recs if r.cell == "fog-s5")
    clean.pdms, fog.pdms = np.full(12, 0.8), np.full(12, 0.6)
    fog.pdms[3] = np.nan  # not scored: left out of both means
    assert gated_retention(clean, fog, "pdms") == pytest.approx(0.75)
    assert gated_retention(clean, fog, "l2") == record_retention(clean, fog) != pytest.approx(0.75)


def _options(tmp_path: Path, baseline: Path, public_key: Path | None = None):
    from pytest_drivedegrade.plugin.options import RunOptions
    from pytest_drivedegrade.settings import RunSettings

    return RunOptions(None, RunSettings(), (), (), tmp_path / "reports", baseline, 0.02,
                      baseline_public_key=public_key)


def test_m14_the_gate_can_require_a_signed_baseline(tmp_path: Path) -> None:
    """M14: with --drivedegrade-baseline-public-key the baseline must be signed by that key: an unsigned one,
    one signed by another key, or one edited after signing is refused, saying why; the right key passes."""
    from pytest_drivedegrade.plugin.preflight import load_baseline

    for name in ("issuer", "other"):
        assert main(["keygen", str(tmp_path / name)]) == 0
    unsigned = make_cert(tmp_path, "unsigned.json")
    body = cf.verify(unsigned)
    signed = cf.write_certificate(tmp_path / "signed.json", sg.sign(body, sg.load_private_key(
        (tmp_path / "issuer.key").read_bytes(), "k")))
    pub, other = tmp_path / "issuer.pub", tmp_path / "other.pub"
    assert load_baseline(_options(tmp_path, signed, pub))["signature"]
    assert load_baseline(_options(tmp_path, unsigned)) is not None  # no key asked for: the digest only
    with pytest.raises(pytest.UsageError, match=r"--drivedegrade-baseline \(--drivedegrade-baseline-public-key\): "
                                                r".*unsigned\.json: the certificate is unsigned"):
        load_baseline(_options(tmp_path, unsigned, pub))
    with pytest.raises(pytest.UsageError, match="not by the given public key .*: wrong key"):
        load_baseline(_options(tmp_path, signed, other))
    reseal(signed, lambda d: d["planner"].update(name="someone-else"))
    with pytest.raises(pytest.UsageError, match="the signature does not verify with the given public key"):
        load_baseline(_options(tmp_path, signed, pub))


def test_m14_the_gate_refuses_a_baseline_verify_rejects(tmp_path: Path) -> None:
    """M14: a resealed baseline whose arithmetic does not add up (a retention lifted, so nothing regresses
    against it) is refused at start-up, naming the field."""
    from pytest_drivedegrade.plugin.preflight import load_baseline

    path = make_cert(tmp_path)
    reseal(path, lambda d: _cell(d, "blind").update(retention=1.5))
    with pytest.raises(pytest.UsageError, match=r"refused: the digest verifies but the arithmetic does not add up "
                                                r"\(cells\.blind\.retention: certificate says 1\.500000"):
        load_baseline(_options(tmp_path, path))


@pytest.mark.parametrize("base, current, tolerance, shown", [
    (1.0, 0.9996, 0.0002, "retention 0.9996 vs baseline 1.0000 (drop 0.0004)"),
    (1.0, 0.99975, 0.0002, "retention 0.99975 vs baseline 1.00000 (drop 0.00025)"),
    (0.9, 0.85, 0.02, "retention 0.850 vs baseline 0.900 (drop 0.050)"),
    (0.5, 0.47, 0.02, "retention 0.470 vs baseline 0.500 (drop 0.030)"),
])
def test_new_user_the_gate_prints_enough_digits_to_show_the_drop(base, current, tolerance, shown) -> None:
    """The new user's item: a drop of 0.0002-0.0005 printed with 3 decimals read "1.000 vs 1.000 (drop 0.000)";
    the drop is printed with the fewest decimals (3 at least) at which it exceeds the printed tolerance."""
    reg = bl.cell_regression("jpeg-s3", current, {"cells": [{"cell": "jpeg-s3", "retention": base}]}, tolerance)
    assert reg is not None and reg.message() == f"jpeg-s3: {shown}"


# --- L7, L8: wording --------------------------------------------------------------------------------------------

def test_l7_merge_names_the_shard_that_lacks_cells_and_what_to_do(tmp_path: Path) -> None:
    """L7: the merge's missing-cell advice names each shard and the cells it lacks, and says to rerun that
    shard, then the merge (not "rerun the same command", which would rerun the merge)."""
    from pytest_drivedegrade.certificate.merge import ShardResult, missing_advice
    from pytest_drivedegrade.report.terminal import summary_lines
    from pytest_drivedegrade.settings import RunSettings

    def shard(i: int, cells: list[str]) -> ShardResult:
        return ShardResult(tmp_path / f"shard-{i}-of-3", {"index": i, "count": 3}, RunSettings(),
                           dict.fromkeys(cells))  # type: ignore[arg-type]

    cells = ["clean", "null", "jpeg-s1", "jpeg-s5"]
    advice = missing_advice([shard(1, cells), shard(2, cells[:2]), shard(3, cells[:3])], cells)
    assert advice == (f"shard 2/3 ({tmp_path}/shard-2-of-3) lacks jpeg-s1, jpeg-s5; shard 3/3 ({tmp_path}/"
                      "shard-3-of-3) lacks jpeg-s5: rerun each such shard with its own command "
                      "(--drivedegrade-shard I/N; its finished cells are reused), then run this merge again")
    assert missing_advice([shard(1, cells)], cells) == ""
    run = analyse_run(synthetic_run(12)[0], groups=GROUPS, n_resamples=50)
    line = next(x for x in summary_lines(run, ["jpeg-s1", "jpeg-s5"], advice) if x.startswith("missing"))
    assert line == f"missing cells (2): jpeg-s1, jpeg-s5; {advice}"


def test_l8_verify_without_public_key_says_the_signature_was_not_checked(tmp_path: Path, capsys) -> None:
    """L8: a signed certificate verified without --public-key says plainly that its signature was NOT checked,
    that the fingerprint it names is only a claim, and the command that checks it."""
    assert main(["keygen", str(tmp_path / "issuer")]) == 0
    key = sg.load_private_key((tmp_path / "issuer.key").read_bytes(), "k")
    path = cf.write_certificate(tmp_path / "c.json", sg.sign(cf.verify(make_cert(tmp_path)), key))
    assert main(["verify", str(path)]) == 0
    out = capsys.readouterr().out
    fp = sg.fingerprint(key.public_key())
    assert f"the signature was NOT checked: the certificate says it was signed by the key with fingerprint {fp}, " \
           "but anyone can write that" in out
    assert f"drivedegrade verify {path} --public-key NAME.pub" in out


# --- tests that would not notice: verify and the seal ----------------------------------------------------------

def test_mutation_the_axes_pdms_consistency_check_runs(tmp_path: Path) -> None:
    """Kills "the `axes_pdms` consistency check skipped": a resealed PDMS axis is named with both values."""
    path = make_cert(tmp_path)
    cert = cf.verify(path)
    quality = cert["axes_pdms"]["quality"]
    assert quality is not None and check_consistency(cert) == []
    reseal(path, lambda d: d["axes_pdms"].update(quality=round(quality - 0.2, 6)))
    problems = check_consistency(cf.verify(path))
    assert problems == [f"axes_pdms.quality: certificate says {quality - 0.2:.6f}, its cells give {quality:.6f}"]


def test_mutation_ego_label_is_recomputed_from_ego_removal(tmp_path: Path) -> None:
    """Kills "`ego_label` recomputed from `axes.ego` instead of `axes.ego_removal`": here ego_noise S5 barely
    hurts (ego axis ~0.99: ego-insensitive on its own) while ego_blind hurts (ego_removal ~0.2: ego-reliant),
    so the honest certificate verifies only when the label comes from ego_removal, and a forger who writes the
    label the ego axis gives is caught."""
    path = make_cert(tmp_path, ego=True)
    cert = cf.verify(path)
    ax = cert["axes"]
    assert ax["ego"] > 0.95 > ax["ego_removal"]
    assert cert["verdict"]["ego_label"] == ego_label(ax["ego_removal"]) == "ego-reliant" != ego_label(ax["ego"])
    assert check_consistency(cert) == []
    reseal(path, lambda d: d["verdict"].update(ego_label="ego-insensitive"))
    assert check_consistency(cf.verify(path)) == ["verdict.ego_label: certificate says 'ego-insensitive', its ego "
                                                  "axis gives 'ego-reliant'"]


SIGNED_SECTIONS = ("axes", "axes_epdms", "axes_pdms", "cells", "completeness", "cost", "created", "dataset",
                   "epdms_unscored", "floor", "null_control", "planner", "record_digests", "reliance", "schema",
                   "settings", "spec_version", "thresholds", "tool", "verdict")


def _forge(value: object) -> tuple[object, bool]:
    """`value` with its first leaf (depth first, keys sorted) changed as a forger would: a number nudged by 1, a
    flag flipped, a string changed (a digest to another valid one); (new value, whether anything changed)."""
    if isinstance(value, bool):
        return not value, True
    if value is None:
        return value, False
    if isinstance(value, (int, float)):
        return value + 1, True
    if isinstance(value, str):
        return ("0" * 64 if len(value) == 64 else value + "-forged"), True
    items = sorted(value.items()) if isinstance(value, dict) else list(enumerate(value))  # type: ignore[union-attr]
    for key, v in items:
        new, changed = _forge(v)
        if changed:
            value[key] = new  # type: ignore[index]
            return value, True
    return value, False


@pytest.mark.parametrize("section", SIGNED_SECTIONS)
def test_mutation_the_signature_covers_every_section(tmp_path: Path, section: str) -> None:
    """Kills "the signature no longer covering the `floor` section" (and any other section): a resealed edit of
    any one section fails `verify --public-key`; the old forgery test edited only ``planner.name``."""
    assert main(["keygen", str(tmp_path / "issuer")]) == 0
    key = sg.load_private_key((tmp_path / "issuer.key").read_bytes(), "k")
    body = cf.verify(make_cert(tmp_path))
    body.setdefault("completeness", {"complete": True})
    body.setdefault("cost", {"wall_s": 1.0})
    path = cf.write_certificate(tmp_path / "signed.json", sg.sign(body, key))
    assert set(SIGNED_SECTIONS) == set(json.loads(path.read_text())) - {"digest", "section_digests", "signature"}
    public = sg.load_public_key(tmp_path / "issuer.pub")
    sg.verify_signature(cf.verify(path), public)

    def forge(d: dict) -> None:  # a section of only nulls (axes_epdms of a run without lanes) gains a key instead
        value, changed = _forge(d[section])
        d[section] = value if changed or not isinstance(value, dict) else {**value, "forged": 1}

    reseal(path, forge)
    forged = cf.verify(path)  # the digest, recomputed by the forger, verifies
    with pytest.raises(sg.SignatureFailure, match="the signature does not verify"):
        sg.verify_signature(forged, public)
