"""Ed25519 signatures of certificates: keygen, sign before sealing, verify --public-key, forgeries, wrong keys."""

from __future__ import annotations

import hashlib
import json
import stat
from pathlib import Path

import pytest
from test_analysis import GROUPS, synthetic_run

from pytest_drivedegrade.certificate import seal as cf
from pytest_drivedegrade.certificate import signing as sg
from pytest_drivedegrade.cli import main
from pytest_drivedegrade.errors import DriveDegradeError
from pytest_drivedegrade.scoring.analyse import analyse_run

PROV = cf.Provenance("demo", "sha256:planner", "sha256:data", "val", "1.0.0", seed=0, frames=12)


@pytest.fixture(scope="module")
def cert() -> dict:
    run = analyse_run(synthetic_run(12)[0], groups=GROUPS, n_resamples=50, floor_l2=5.0)
    return cf.build_certificate(run, PROV, created="2025-01-01T00:00:00+00:00")


@pytest.fixture()
def keys(tmp_path: Path) -> tuple[Path, Path]:
    assert main(["keygen", str(tmp_path / "issuer")]) == 0
    return tmp_path / "issuer.key", tmp_path / "issuer.pub"


def forge(path: Path, change) -> None:
    """Edit and reseal the way a forger would: recompute the section digests and the digest with hashlib."""
    data = json.loads(path.read_text())
    change(data)

    def sha(obj) -> str:
        return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode()) \
            .hexdigest()

    body = {k: v for k, v in data.items() if k not in ("digest", "section_digests")}
    data["section_digests"] = {k: sha(v) for k, v in body.items()}
    data["digest"] = sha({k: v for k, v in data.items() if k != "digest"})
    path.write_text(json.dumps(data, indent=2))


def test_keygen_writes_a_private_pem_0600_and_a_public_pem(keys, tmp_path: Path) -> None:
    key, pub = keys
    assert key.read_text().startswith("-----BEGIN PRIVATE KEY-----")
    assert pub.read_text().startswith("-----BEGIN PUBLIC KEY-----")
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    with pytest.raises(DriveDegradeError, match="already exists"):
        sg.keygen(tmp_path / "issuer")


def test_signed_certificate_verifies_and_a_resealed_forgery_does_not(cert, keys, tmp_path: Path, capsys) -> None:
    key, pub = keys
    signed = sg.sign(cert, sg.load_private_key(key.read_bytes(), "k"))
    path = cf.write_certificate(tmp_path / "c.json", signed)
    stored = json.loads(path.read_text())
    section = stored["signature"]
    assert section["algorithm"] == "ed25519" and len(section["public_key_fingerprint"]) == 64
    assert stored["section_digests"]["signature"]  # the digest covers the signature
    assert main(["verify", str(path), "--public-key", str(pub)]) == 0
    assert "signature verifies" in capsys.readouterr().out
    assert main(["verify", str(path)]) == 0
    assert "NOT checked" in capsys.readouterr().out

    forge(path, lambda d: d["planner"].__setitem__("name", "someone-else"))
    assert main(["verify", str(path)]) == 0  # the digest alone cannot catch a deliberate edit
    capsys.readouterr()
    assert main(["verify", str(path), "--public-key", str(pub)]) == 1
    assert "signature does not verify" in capsys.readouterr().err


def test_wrong_key_and_unsigned_fail_with_a_public_key(cert, keys, tmp_path: Path, capsys) -> None:
    key, _ = keys
    path = cf.write_certificate(tmp_path / "c.json", sg.sign(cert, sg.load_private_key(key.read_bytes(), "k")))
    _, other = sg.keygen(tmp_path / "other")
    assert main(["verify", str(path), "--public-key", str(other)]) == 1
    assert "wrong key" in capsys.readouterr().err

    unsigned = cf.write_certificate(tmp_path / "u.json", cert)
    assert main(["verify", str(unsigned)]) == 0
    assert "integrity only, unsigned" in capsys.readouterr().out
    assert main(["verify", str(unsigned), "--public-key", str(other)]) == 1
    assert "unsigned" in capsys.readouterr().err


def test_key_sources_and_bad_keys(keys, tmp_path: Path, capsys) -> None:
    key, pub = keys
    assert sg.read_key_source(key.read_text(), "env", pem_allowed=True) == sg.read_key_source(str(key), "env")
    with pytest.raises(DriveDegradeError, match="no such key file"):
        sg.read_key_source(str(tmp_path / "absent.key"), "--drivedegrade-sign-key")
    with pytest.raises(DriveDegradeError, match="not an unencrypted PEM private key"):
        sg.load_private_key(pub.read_bytes(), "--drivedegrade-sign-key")
    assert main(["verify", str(tmp_path / "x.json"), "--public-key", str(key)]) == 2
    assert "not a PEM public key" in capsys.readouterr().err


def test_the_signing_key_published_pem_text_is_taken_from_the_environment_only(keys, key_material) -> None:
    """Issue 20 item 1: PEM text where a path belongs (the option, the ini value, merge --sign-key) is refused, and
    the refusal does not echo it; the environment variable may hold it."""
    key, _ = keys
    pem = key.read_text()
    with pytest.raises(DriveDegradeError) as exc:
        sg.read_key_source(pem, "--drivedegrade-sign-key")
    assert "DRIVEDEGRADE_SIGNING_KEY" in str(exc.value)
    assert not any(m in str(exc.value) for m in key_material(key))
    assert sg.read_key_source(pem, "DRIVEDEGRADE_SIGNING_KEY", pem_allowed=True) == pem.strip().encode() + b"\n"
    assert sg.read_key_source(key.name, "k", base=key.parent) == key.read_bytes()  # a path, relative to base


def test_the_signing_key_published_no_error_echoes_a_key(keys, key_material, tmp_path: Path) -> None:
    """Issue 20 M8: a key that does not parse (truncated, a line missing, the base64 body without its armour given
    as a "path") is an error that quotes none of it."""
    key, _ = keys
    pem = key.read_text()
    lines = pem.splitlines()
    body = lines[1]
    broken = [
        ("DRIVEDEGRADE_SIGNING_KEY", pem[: len(pem) // 2]),  # truncated: no END line
        ("DRIVEDEGRADE_SIGNING_KEY", "\n".join([lines[0], body[:-4] + "!!!!", lines[-1]])),  # a bad body
        ("--drivedegrade-sign-key", body),  # the body alone: not key text by its looks, and no such file
        ("DRIVEDEGRADE_SIGNING_KEY", body),
    ]
    for where, value in broken:
        with pytest.raises(DriveDegradeError) as exc:
            sg.load_private_key(sg.read_key_source(value, where, pem_allowed=where.isupper()), where)
        text = str(exc.value)
        assert where in text and body[:16] not in text and body[-16:] not in text, text
        assert not any(m in text for m in key_material(key)), text
    with pytest.raises(DriveDegradeError, match="no such key file") as missing:
        sg.read_key_source(str(tmp_path / "absent.key"), "--drivedegrade-sign-key")
    assert "absent.key" not in str(missing.value)  # a path that names no file may be key text: not echoed


def test_the_signing_key_published_a_key_file_readable_by_others_is_warned_about(keys, capsys) -> None:
    """Issue 20 L4: a key file with group or other bits set gets a warning naming the file and the fix; keygen's
    0600 gets none; `drivedegrade merge --sign-key` warns too."""
    key, _ = keys
    assert sg.loose_permissions(key) is None
    key.chmod(0o644)
    warning = sg.loose_permissions(key)
    assert warning is not None and "mode 0644" in warning and f"chmod 600 {key}" in warning
    key.chmod(0o640)
    assert "mode 0640" in (sg.loose_permissions(key) or "")
    assert main(["merge", str(key.parent / "no-such-shard"), "--out", str(key.parent / "m"),
                 "--sign-key", str(key)]) == 2
    assert "accessible to its group or others (mode 0640)" in capsys.readouterr().err


def test_the_signing_key_published_the_recorded_command_never_holds_key_text(keys) -> None:
    """Issue 20 item 1: the command line the certificate and report record keeps a key file's path and replaces
    any other value of the option (however given) and any argument that looks like key text."""
    from pytest_drivedegrade.plugin.keys import REDACTED, recorded_args

    key, _ = keys
    here, pem = key.parent, key.read_text()
    body = pem.splitlines()[1]
    args = ["--drivedegrade", "p.py", "--drivedegrade-sign-key", key.name, "--drivedegrade-sign-key", body,
            f"--drivedegrade-sign-key={body}", "-o", f"drivedegrade_sign_key={body}",
            f"-odrivedegrade_sign_key={body}", f"--override-ini=drivedegrade_sign_key={body}",
            "--override-ini", f"drivedegrade_sign_key={key.name}", "-k", pem, "-o", "cache_dir=x"]
    assert recorded_args(args, here) == [
        "--drivedegrade", "p.py", "--drivedegrade-sign-key", key.name, "--drivedegrade-sign-key", REDACTED,
        f"--drivedegrade-sign-key={REDACTED}", "-o", f"drivedegrade_sign_key={REDACTED}",
        f"-odrivedegrade_sign_key={REDACTED}", f"--override-ini=drivedegrade_sign_key={REDACTED}",
        "--override-ini", f"drivedegrade_sign_key={key.name}", "-k", REDACTED, "-o", "cache_dir=x"]
