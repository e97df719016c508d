"""The reliance certificate: seal / verify round trip, tamper detection, the CLI's exit codes, the baseline gate."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from test_analysis import GROUPS, synthetic_run

from pytest_drivedegrade.certificate import seal as cf
from pytest_drivedegrade.cli import main
from pytest_drivedegrade.scoring import baseline as bl
from pytest_drivedegrade.scoring import records as rc
from pytest_drivedegrade.scoring.analyse import analyse_run

PROV = cf.Provenance("demo", "sha256:planner", "sha256:data", "val", "1.0.0", seed=0, frames=12)


@pytest.fixture(scope="module")
def run() -> rc.RunAnalysis:
    return analyse_run(synthetic_run(12)[0], groups=GROUPS, n_resamples=100, floor_l2=5.0)


@pytest.fixture()
def cert_file(tmp_path: Path, run: rc.RunAnalysis) -> Path:
    return cf.write_certificate(tmp_path / "certificate.json",
                                cf.build_certificate(run, PROV, created="2025-01-01T00:00:00+00:00"))


def edit(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data, indent=2))


def test_certificate_has_the_stable_keys(cert_file: Path) -> None:
    cert = cf.verify(cert_file)
    for key in ("spec_version", "planner", "dataset", "cells", "thresholds", "axes", "floor", "null_control",
                "verdict", "digest"):
        assert key in cert
    assert cert["planner"] == {"name": "demo", "fingerprint": "sha256:planner"}
    assert cert["dataset"]["fingerprint"] == "sha256:data" and cert["dataset"]["split"] == "val"
    cell = cert["cells"][3]
    assert {"cell", "family", "severity", "l2_avg", "retention", "retention_ci_low", "retention_ci_high"} <= set(cell)
    assert set(cert["thresholds"]["fog"]) == {"s10", "s25", "s10_ci", "s25_ci", "s10_never", "s25_never",
                                              "partial"}
    assert {"quality", "removal", "gap", "mean"} <= set(cert["axes"]) and "l2_avg" in cert["floor"]
    assert {"passed", "max_abs_diff"} <= set(cert["null_control"])
    # the synthetic planner degrades on both axes (S5 retention ~0.77 on quality, ~0.62 on removal)
    assert (cert["verdict"]["label"], cert["verdict"]["case"]) == ("camera-reliant", "both-below")
    assert cert["settings"]["flat"] == 0.95
    assert cf.check_schema(cert) == []


def test_digest_is_sha256_over_canonical_json_with_rounded_floats(cert_file: Path) -> None:
    import hashlib

    cert = json.loads(cert_file.read_text())
    body = {k: v for k, v in cert.items() if k != "digest"}
    canon = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode()
    assert cert["digest"] == hashlib.sha256(canon).hexdigest()
    assert all(len(repr(c["retention"]).split(".")[-1]) <= 6 for c in cert["cells"])


def test_digest_known_answer() -> None:
    """A two-key body sealed by hand: floats rounded to six decimals, NaN as null, keys sorted, no spaces;
    each section hashed on its own, then everything but the digest. The hex strings are fixed."""
    import hashlib

    sealed = cf.seal({"b": [0.1234567, float("nan"), True], "a": "x"})
    sections = {"a": "ba2df4903a2c14e86dc3bcca58911b44ac1d2514b7227bf6eb08cfb978f55a1b",  # sha256 of '"x"'
                "b": "85c0c85d04e978eb4d547c17df51d402c2818aff876204ea628eaba988444778"}  # '[0.123457,null,true]'
    assert sealed["section_digests"] == sections
    body = ('{"a":"x","b":[0.123457,null,true],"section_digests":{"a":"' + sections["a"] + '","b":"'
            + sections["b"] + '"}}')
    assert sealed["digest"] == hashlib.sha256(body.encode()).hexdigest() == (
        "e584f5b0d7948a47e158446c6f62fed38a64021d73f0f9f7944a506e2434f36d")
    assert hashlib.sha256(b'"x"').hexdigest() == sections["a"]


def test_seal_is_idempotent_and_layout_free(run: rc.RunAnalysis) -> None:
    sealed = cf.seal(cf.build_certificate(run, PROV, created="x"))
    assert cf.seal(sealed) == sealed
    assert cf.verify_data(json.loads(json.dumps(sealed))) == sealed  # compact JSON verifies as well


def test_canonicalize_numpy_and_non_finite() -> None:
    import numpy as np

    got = cf.canonicalize({"a": np.float32(0.1), "b": np.int64(3), "c": [np.nan, np.inf, 1 / 3], "d": np.bool_(1)})
    assert got == {"a": 0.1, "b": 3, "c": [None, None, 0.333333], "d": True}
    assert type(got["b"]) is int


def test_editing_one_number_breaks_verification_and_names_the_section(cert_file: Path) -> None:
    edit(cert_file, lambda d: d["cells"][5].__setitem__("retention", 0.999))
    with pytest.raises(cf.CertificateMismatch) as exc:
        cf.verify(cert_file)
    assert exc.value.sections == ["cells"] and exc.value.recorded != exc.value.computed
    assert "edited section(s): cells" in str(exc.value)


def test_malformed_field_is_named(cert_file: Path) -> None:
    edit(cert_file, lambda d: d["axes"].__setitem__("quality", "high"))
    with pytest.raises(cf.CertificateMismatch, match=r"axes\.quality: expected a number or null, found str"):
        cf.verify(cert_file)


def test_cli_verify_exit_codes(cert_file: Path, tmp_path: Path, capsys) -> None:
    assert main(["verify", str(cert_file)]) == 0
    assert "OK" in capsys.readouterr().out
    edit(cert_file, lambda d: d["verdict"].__setitem__("label", "not-shown-to-use-cameras"))
    assert main(["verify", str(cert_file)]) == 1
    err = capsys.readouterr().err
    assert "digest mismatch" in err and "verdict" in err
    broken = tmp_path / "broken.json"
    broken.write_text('{"spec_version": "1.0.0", ')
    assert main(["verify", str(broken)]) == 2
    assert "not valid JSON" in capsys.readouterr().err
    assert main(["verify", str(tmp_path / "absent.json")]) == 2
    assert "no such file" in capsys.readouterr().err
    (tmp_path / "list.json").write_text("[1, 2]")
    assert main(["verify", str(tmp_path / "list.json")]) == 2
    (tmp_path / "unsealed.json").write_text("{}")
    assert main(["verify", str(tmp_path / "unsealed.json")]) == 2
    assert "no digest" in capsys.readouterr().err


def test_baseline_passes_on_itself_and_catches_a_regression(cert_file: Path, run: rc.RunAnalysis) -> None:
    base = cf.verify(cert_file)
    now = cf.seal(cf.build_certificate(run, PROV))
    assert bl.compare_to_baseline(now, base) == {"cells": [], "axes": []}
    worse = json.loads(json.dumps(now))
    worse["cells"][10]["retention"] -= 0.05
    worse["axes"]["removal"] -= 0.03
    out = bl.compare_to_baseline(worse, base, 0.02)
    assert [r.name for r in out["cells"]] == [worse["cells"][10]["cell"]]
    assert [r.name for r in out["axes"]] == ["axis:removal"]


def test_edited_baseline_is_refused_naming_the_section(cert_file: Path) -> None:
    edit(cert_file, lambda d: d["axes"].__setitem__("quality", 1.0))
    with pytest.raises(cf.CertificateMismatch, match="digest mismatch.*edited section.*axes"):
        cf.verify(cert_file)


def reseal(path: Path, change) -> None:
    """Edit and reseal as a forger would: section digests and digest recomputed with hashlib."""
    import hashlib

    data = json.loads(path.read_text())
    change(data)

    def sha(obj) -> str:
        return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()

    data["section_digests"] = {k: sha(v) for k, v in data.items() if k not in ("digest", "section_digests")}
    data["digest"] = sha({k: v for k, v in data.items() if k != "digest"})
    path.write_text(json.dumps(data, indent=2))


def test_verify_recomputes_axes_thresholds_and_verdict_from_the_cells(cert_file: Path, capsys) -> None:
    from pytest_drivedegrade.certificate.consistency import check_consistency

    assert check_consistency(cf.verify(cert_file)) == []
    s5 = next(i for i, c in enumerate(json.loads(cert_file.read_text())["cells"]) if c["cell"] == "fog-s5")

    def lift_fog(d) -> None:
        d["cells"][s5]["retention"] = 0.999  # the cell says fog barely hurts, the axes and thresholds say not
    reseal(cert_file, lift_fog)
    assert main(["verify", str(cert_file)]) == 1
    err = capsys.readouterr().err
    assert "arithmetic does not add up" in err
    assert re.search(r"axes\.quality: certificate says \d\.\d{6}, its cells give \d\.\d{6}", err)
    assert "axes.mean:" in err and "axes.gap:" in err


def test_a_forged_verdict_or_threshold_is_named(cert_file: Path, capsys) -> None:
    reseal(cert_file, lambda d: (d["verdict"].__setitem__("label", "not-shown-to-use-cameras"),
                                 d["thresholds"]["fog"].__setitem__("s10", 4.5)))
    assert main(["verify", str(cert_file)]) == 1
    err = capsys.readouterr().err
    assert "verdict.label: certificate says 'not-shown-to-use-cameras'" in err
    assert "thresholds.fog.s10: certificate says 4.500000, its cells give" in err


def test_a_consistent_resealed_certificate_passes_and_incomplete_exits_3(cert_file: Path, capsys) -> None:
    reseal(cert_file, lambda d: d["planner"].__setitem__("name", "renamed"))
    assert main(["verify", str(cert_file)]) == 0
    assert "integrity only, unsigned" in capsys.readouterr().out
    reseal(cert_file, lambda d: d.__setitem__("completeness", {"complete": False, "missing_cells": ["jpeg-s3"]}))
    assert main(["verify", str(cert_file)]) == 3
    err = capsys.readouterr().err
    assert "INCOMPLETE" in err and "missing cell(s): jpeg-s3" in err


def _sealed_text(cert_file: Path) -> str:
    return cert_file.read_text()


@pytest.mark.parametrize("edit_text, expected", [
    (lambda t: t.replace('"quality": ', '"quality": NaN, "was": ', 1), r"a NaN literal at axes\.quality"),
    (lambda t: t.replace('"removal": ', '"removal": -Infinity, "was": ', 1), r"a -Infinity literal at axes\.removal"),
    (lambda t: t.replace('"axes": {', '"axes": {"quality": 1.0, ', 1), r"duplicate key 'quality' in axes"),
    (lambda t: t.replace('{', '{"digest": "' + "0" * 64 + '", ', 1), r"duplicate key 'digest' in the top-level"),
    (lambda t: t.replace('"cells": [', '"cells": [' + "[" * 100_000 + "]" * 100_000 + ", ", 1),
     r"nested deeper than 64 levels at line \d+, column \d+"),
], ids=["nan", "infinity", "duplicate-key", "duplicate-top-level", "deep"])
def test_strict_json_is_required_with_what_and_where(cert_file: Path, capsys, edit_text, expected) -> None:
    """Trust case 11: a NaN / Infinity literal, a duplicate key or 100000 nested lists is a CertificateError
    (not "edited", not a traceback) naming the problem and where; `verify` exits 2, the malformed-file code."""
    cert_file.write_text(edit_text(_sealed_text(cert_file)))
    with pytest.raises(cf.CertificateError, match=expected) as caught:
        cf.load_certificate(cert_file)
    assert not isinstance(caught.value, cf.CertificateMismatch)
    assert main(["verify", str(cert_file)]) == 2
    err = capsys.readouterr().err
    assert re.search(expected, err) and str(cert_file) in err and "Traceback" not in err


def test_strict_parsing_keeps_a_sealed_certificate_and_strings_that_look_nested(cert_file: Path) -> None:
    """Brackets inside strings do not count as nesting; a sealed certificate loads unchanged, as plain dicts."""
    assert cf.load_certificate(cert_file) == json.loads(cert_file.read_text())
    assert type(cf.load_certificate(cert_file)["axes"]) is dict
    text = '{"command": "' + "[{" * 200 + '", "n": NaNa}'
    with pytest.raises(cf.CertificateError, match="not valid JSON"):
        cf.parse_certificate_text(text, "x.json")
    assert cf.parse_certificate_text('{"command": "' + "[{" * 200 + '"}', "x.json") == {"command": "[{" * 200}


def test_verify_requires_undetermined_when_a_cell_has_failed_frames(tmp_path: Path, capsys) -> None:
    """Trust case 9: `drivedegrade verify` recomputes the verdict under the failed-frames rule: a sealed
    certificate whose cells count failed frames passes only as `undetermined` naming exactly those cells, and
    a forger who puts the axes' label back is caught."""
    from test_analysis import fail_frames

    from pytest_drivedegrade.certificate.consistency import check_consistency

    recs, _ = synthetic_run(12)
    fail_frames(next(r for r in recs if r.cell == "snow-s5"), [4], data=True)
    path = cf.write_certificate(tmp_path / "certificate.json",
                                cf.build_certificate(analyse_run(recs, groups=GROUPS, n_resamples=50), PROV))
    cert = cf.verify(path)
    assert cert["verdict"]["label"] == "undetermined" and "snow-s5 (1 of 12 frames: 1 data error)" in \
        cert["verdict"]["reason"]
    snow = next(c for c in cert["cells"] if c["cell"] == "snow-s5")
    assert (snow["data_errors"], snow["conformance_errors"]) == (1, 0)
    assert check_consistency(cert, GROUPS) == []
    reseal(path, lambda d: d["verdict"].update(label=d["verdict"]["computed_label"], failed_cells={}))
    problems = check_consistency(cf.verify(path), GROUPS)
    assert problems[0].startswith("verdict.label: certificate says 'camera-reliant', but 1 of its cells have "
                                  "failed frames (snow-s5)")
    assert "verdict.failed_cells: certificate names [], its cells with failed frames are ['snow-s5']" in problems[1]
    reseal(path, lambda d: d["verdict"].update(label="undetermined", failed_cells={"snow-s5": {}}, reason="x"))
    assert check_consistency(cf.verify(path), GROUPS) == []
    reseal(path, lambda d: next(c for c in d["cells"] if c["cell"] == "snow-s5").update(data_errors="1"))
    with pytest.raises(cf.CertificateError, match=r"cells\[\d+\]\.data_errors: expected a count"):
        cf.verify(path)
