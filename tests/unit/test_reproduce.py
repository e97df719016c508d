"""Reproduction (SPEC section 11): the certificate's per-cell plans digest, the deterministic cell sampler, the
rerun's command line, the comparison's wording and the usage errors of `drivedegrade reproduce`."""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path

import numpy as np
import pytest
from test_analysis import GROUPS, synthetic_run

from pytest_drivedegrade.cells import CellRecord, plans_digest
from pytest_drivedegrade.certificate import reproduce as rp
from pytest_drivedegrade.certificate import seal as cf
from pytest_drivedegrade.cli import main
from pytest_drivedegrade.scoring.analyse import analyse_run

PROV = cf.Provenance("demo", "sha256:planner", "sha256:data", "val", "1.0.0", seed=0, frames=12)

# --- the digest ---------------------------------------------------------------------------------------------


def test_plans_digest_known_answer_is_the_documented_byte_form() -> None:
    plans = np.arange(24, dtype=float).reshape(2, 6, 2) / 4
    by_hand = hashlib.sha256(b"drivedegrade-plans-v1" + b"|2,6,2|" + struct.pack("<24d", *plans.ravel()))
    assert plans_digest([plans]) == by_hand.hexdigest()
    # frozen: a change to the byte form would make every sealed certificate unreproducible
    assert plans_digest([np.zeros((1, 6, 2))]) == "4d87c8a461bdca459850273d39c7025e6d2aed6c09c7dcef2eeee6d55125a8a6"


def test_plans_digest_canonicalises_nan_and_nothing_else() -> None:
    a = np.ones((3, 6, 2))
    a[1, 2, 0] = np.nan
    b = a.copy()
    b.view(np.uint64)[1, 2, 0] = 0xFFF8_0000_0000_0001  # another NaN: negative sign, other payload
    assert plans_digest([a]) == plans_digest([b])
    c = a.copy()
    c[0, 0, 0] = np.nextafter(1.0, 2.0)  # one float step
    d = a.copy()
    d[2, 5, 1] = -0.0
    e = a.copy()
    e[2, 5, 1] = 0.0
    assert len({plans_digest([a]), plans_digest([c]), plans_digest([d]), plans_digest([e])}) == 4
    assert np.isnan(a).sum() == 1  # the input keeps its own NaN: the digest works on a copy
    assert a.view(np.uint64)[1, 2, 0] == np.float64(np.nan).view(np.uint64)


def test_plans_digest_order_and_seed_runs_matter() -> None:
    x, y = np.zeros((2, 6, 2)), np.zeros((2, 6, 2))
    y[0, 0, 0] = 1.0
    swapped = y[::-1]  # the same frames in another order
    assert plans_digest([y]) != plans_digest([swapped])
    assert plans_digest([x, y]) != plans_digest([y, x]) != plans_digest([x])
    assert plans_digest([x.reshape(1, 2, 6, 2)]) != plans_digest([x])  # the shape is hashed too
    rec = record("jpeg-s1", y)
    rec.seed_runs, rec.seeds = [record("jpeg-s1", x)], [0, 1]
    assert rec.plans_digest() == plans_digest([y, x])


def record(cell: str, plans: np.ndarray, frames: list[str] | None = None) -> CellRecord:
    n = len(plans)
    z = np.zeros((n, 6))
    return CellRecord(cell, cell.split("-")[0], int(cell[-1]) if "-s" in cell else 0,
                      frames or [f"tok{i}" for i in range(n)], plans, z, z, z, np.zeros(n), np.zeros(n))


# --- the sampler --------------------------------------------------------------------------------------------

CELLS = ["clean", "null", "blind", *(f"{f}-s{s}" for f in ("jpeg", "fog", "blackout") for s in range(1, 6))]
DIGEST = "ab" * 32


def test_sampler_is_deterministic_keeps_clean_and_null_and_respects_n() -> None:
    got = rp.sample_cells(CELLS, DIGEST, 3)
    assert got == rp.sample_cells(CELLS, DIGEST, 3) == rp.sample_cells(CELLS[::-1], DIGEST, 3)[::-1]
    assert got[:2] == ["clean", "null"] and len(got) == 5 and got == [c for c in CELLS if c in got]
    assert rp.sample_cells(CELLS, DIGEST, 0) == ["clean", "null"]
    assert set(rp.sample_cells(CELLS, DIGEST, 4)) > set(got)  # one more, the same three first
    # another certificate (digest) or --seed draws other cells, spread over the whole ladder
    samples = {tuple(rp.sample_cells(CELLS, f"{k:064x}", 3)) for k in range(40)}
    assert len(samples) > 20 and {c for s in samples for c in s} == set(CELLS)
    assert rp.sample_cells(CELLS, DIGEST, 3, salt="1") != got


def test_sampler_with_n_above_the_cells_takes_them_all_and_rejects_negative_n() -> None:
    assert rp.sample_cells(CELLS, DIGEST, 100) == CELLS
    assert rp.sample_cells(["clean", "jpeg-s1"], DIGEST, 3) == ["clean", "jpeg-s1"]  # no null: not invented
    with pytest.raises(ValueError, match="--cells must be 0 or more"):
        rp.sample_cells(CELLS, DIGEST, -1)


# --- the certificate, the rerun's command, the comparison ---------------------------------------------------


@pytest.fixture(scope="module")
def recs() -> dict[str, CellRecord]:
    return {r.cell: r for r in synthetic_run(12)[0]}


@pytest.fixture()
def cert_file(tmp_path: Path, recs: dict[str, CellRecord]) -> Path:
    run = analyse_run(recs.values(), groups=GROUPS, n_resamples=20)
    return cf.write_certificate(tmp_path / "certificate.json", cf.build_certificate(run, PROV, records=recs))


def test_certificate_cells_carry_the_digest_and_check_schema_validates_it(cert_file, recs) -> None:
    cert = cf.verify(cert_file)
    assert {c["cell"]: c["plans_digest"] for c in cert["cells"]} == {c: r.plans_digest() for c, r in recs.items()}
    cert["cells"][2]["plans_digest"] = "XYZ"
    assert cf.check_schema(cert) == ["cells[2].plans_digest: expected 64 lowercase hex digits, found str 'XYZ'"]


def test_rerun_argv_carries_the_certificate_settings(cert_file) -> None:
    cert = cf.verify(cert_file)
    cert["settings"].update(seed=7, seeds=3, batch=4, timeout=30.0)
    cert["dataset"]["frames_requested"] = 6
    cells = ["clean", "null", "fog-s2", "jpeg-s5"]
    argv = rp.rerun_argv(cert, Path("/p/planner.py"), cells, Path("/tmp/out"), Path("/data"))
    text = " ".join(argv[1:])
    assert text.startswith("-m pytest -p no:cacheprovider --drivedegrade /p/planner.py --drivedegrade-report /tmp/out")
    for flag in ("--drivedegrade-split val", "--drivedegrade-seed 7", "--drivedegrade-frames 6",
                 "--drivedegrade-seeds 3", "--drivedegrade-batch 4", "--drivedegrade-timeout 30",
                 "--drivedegrade-data /data", "--drivedegrade-families fog,jpeg", "--drivedegrade-severities 2,5"):
        assert flag in text, flag
    assert argv[-2:] == ["-k", "clean or null or fog-s2 or jpeg-s5"]
    assert "--drivedegrade-device" not in text and "--drivedegrade-no-reuse" not in text  # cpu, reuse: defaults
    cert["settings"].update(device="cuda:1", reuse=False)  # a GPU run with reuse off reruns as such
    text = " ".join(rp.rerun_argv(cert, Path("/p/planner.py"), cells, Path("/tmp/out"), None))
    assert "--drivedegrade-device cuda:1" in text and "--drivedegrade-no-reuse" in text
    del cert["dataset"]["frames_requested"]  # a certificate from before: it scored dataset.frames frames
    assert "--drivedegrade-frames 12" in " ".join(rp.rerun_argv(cert, Path("p.py"), ["clean"], Path("o"), None))


def test_compare_plans_names_the_first_frame_and_the_largest_difference(recs) -> None:
    clean = recs["clean"]
    moved = record("clean", clean.plans.copy(), clean.frames)
    moved.plans[4, 2, 0] += 1e-9
    moved.plans[7, 0, 1] += 3e-9
    digest = clean.plans_digest()
    assert rp.compare_plans(digest, record("clean", clean.plans.copy(), clean.frames), clean) == "identical"
    assert rp.compare_plans(digest, moved, clean) == \
        f"DIFFERENT (first differing frame {clean.frames[4]}, 2 frame(s) differ, max plan difference 3e-09 m)"
    assert "which frame differs is unknown" in rp.compare_plans(digest, moved, None)


def test_metric_differences_name_the_field_and_both_values() -> None:
    assert rp.metric_differences({"l2_avg": 0.5, "retention": None, "plans_digest": "a"},
                                 {"l2_avg": 0.5, "retention": None, "plans_digest": "b"}) == []
    assert rp.metric_differences({"l2_avg": 0.5, "frames": 6}, {"l2_avg": 0.500001, "frames": 6}) == \
        ["l2_avg 0.500001 (certified 0.5)"]


def test_version_notes_say_what_differs() -> None:
    here = {"python": "3.11.0", "numpy": "2.0.0", "opencv": "4.10.0", "torch": None}
    cert = {"spec_version": "3.0.0", "tool": {"version": "0.1.0", "versions": dict(here)}}
    assert rp.version_notes(cert, here, "0.1.0", "3.0.0") == []
    cert["tool"]["versions"]["opencv"] = "4.8.1"
    notes = rp.version_notes(cert, here, "0.2.0", "3.0.0")
    assert notes[0].startswith("library versions differ (OpenCV 4.10.0 here, 4.8.1 in the certificate)")
    assert notes[1] == "pytest-drivedegrade 0.2.0 here, 0.1.0 in the certificate"
    assert "does not record" in rp.version_notes({"spec_version": "3.0.0", "tool": {}}, here, "0.1.0", "3.0.0")[0]


# --- usage errors: exit 2 with one clear line, nothing run ----------------------------------------------------


def test_usage_errors_exit_2(cert_file: Path, tmp_path: Path, capsys) -> None:
    planner = tmp_path / "planner.py"
    planner.write_text("")
    assert main(["reproduce", str(cert_file), str(tmp_path / "missing.py")]) == 2
    assert "planner file" in capsys.readouterr().err
    assert main(["reproduce", str(tmp_path / "nope.json"), str(planner)]) == 2
    assert "nope.json: no such file" in capsys.readouterr().err
    cert = json.loads(cert_file.read_text())
    cert["cells"][0]["l2_avg"] = 9.0
    edited = tmp_path / "edited.json"
    edited.write_text(json.dumps(cert))
    assert main(["reproduce", str(edited), str(planner)]) == 2
    assert "digest mismatch" in capsys.readouterr().err
    old = cf.verify(cert_file)
    for c in old["cells"]:
        del c["plans_digest"]
    cf.write_certificate(tmp_path / "old.json", old)
    assert main(["reproduce", str(tmp_path / "old.json"), str(planner)]) == 2
    # since issue 37 a certificate without its plans digests fails verify's null-control check first: refused,
    # naming why, and nothing is rerun
    err = capsys.readouterr().err
    assert "records plans digests, so the null control cannot be checked" in err and "nothing was rerun" in err
    assert main(["reproduce", str(cert_file), str(planner), "--cells", "-1"]) == 2
    assert "--cells must be 0 or more" in capsys.readouterr().err


def test_signature_and_data_checks_come_before_any_rerun(cert_file: Path, tmp_path: Path, capsys) -> None:
    from pytest_drivedegrade.certificate import signing

    planner = tmp_path / "planner.py"
    planner.write_text("")
    key_path, pub = signing.keygen(tmp_path / "issuer")
    _, other = signing.keygen(tmp_path / "other")
    signed = tmp_path / "signed.json"
    key = signing.load_private_key(key_path.read_bytes(), str(key_path))
    cf.write_certificate(signed, signing.sign(cf.verify(cert_file), key))
    assert main(["reproduce", str(cert_file), str(planner), "--public-key", str(pub)]) == 2
    assert "the certificate is unsigned" in capsys.readouterr().err
    assert main(["reproduce", str(signed), str(planner), "--public-key", str(other)]) == 2
    assert "wrong key" in capsys.readouterr().err
    # the right key passes the signature: the run then stops at the next usage error, before pytest starts
    assert main(["reproduce", str(signed), str(planner), "--public-key", str(pub), "--data", str(tmp_path / "x")]) == 2
    assert f"--data {tmp_path / 'x'}: no such folder" in capsys.readouterr().err
    cert = cf.verify(cert_file)
    cert["dataset"]["source"] = str(tmp_path / "nuscenes")
    cf.write_certificate(tmp_path / "elsewhere.json", cert)
    assert main(["reproduce", str(tmp_path / "elsewhere.json"), str(planner)]) == 2
    assert "not on this machine: pass its root with --data PATH" in capsys.readouterr().err
