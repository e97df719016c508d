"""Issue 37 H1, "The planner can read the signing key" (and issue 20 item 1 before it), end to end. A run never
holds a key: a run given one (in its environment, on its command line or in its ini file) is refused before any
conftest.py or planner file is imported, with a message that says how to sign instead and never quotes the key;
a planner that scans every /proc/*/environ it can read, and every file named on its command line, finds no key
material under -n 0 and -n 2; the certificate signed afterwards with `drivedegrade sign` verifies with
--public-key and its report says it is signed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, no_traceback  # noqa: E402

from pytest_drivedegrade.certificate.signing import keygen  # noqa: E402

pytest_plugins = ["plugin_support"]

#: A planner that hunts for key material everywhere a same-user process can look: the initial environment of
#: every process (/proc/*/environ: its own under -n 0, the controller's under -n 2), and every file named on its
#: own and its parent's command line. What it finds, it writes to `found`.
SCANNER = '''
import json
import os

import numpy as np
import pytest

with open({material!r}) as f:  # kept out of this file, which is on the command line the scanner reads
    MATERIAL = json.load(f)


def scan(where):
    hits = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        for name in ("environ", "cmdline"):
            try:
                with open(f"/proc/{{pid}}/{{name}}", "rb") as f:
                    data = f.read()
            except OSError:
                continue
            hits += [f"{{where}} /proc/{{pid}}/{{name}}" for m in MATERIAL if m.encode() in data]
            if name == "cmdline" and pid in (str(os.getpid()), str(os.getppid())):
                for arg in data.split(b"\\0"):
                    try:
                        text = open(arg.decode(), "rb").read()
                    except (OSError, UnicodeDecodeError, ValueError):
                        continue
                    hits += [f"{{where}} file {{arg!r}}" for m in MATERIAL if m.encode() in text]
    with open({found!r}, "a") as f:
        f.write(f"{{where}} {{os.getpid()}} {{len(hits)}} {{hits!r}}\\n")


scan("import")


class Scanner:
    cameras = ("CAM_FRONT",)
    name = "scanner"

    def __init__(self):
        scan("build")
        self.scanned = False

    def predict(self, images, ego, cmd):
        if not self.scanned:
            scan("predict")
            self.scanned = True
        plan = np.zeros((6, 2))
        plan[:, 0] = 2.0 * np.arange(1, 7)
        plan[:, 1] = float(images["CAM_FRONT"][::16, ::16].mean()) / 255.0
        return plan


@pytest.fixture(scope="session")
def planner():
    return Scanner()
'''

CONFTEST = '''
with open({found!r}, "a") as f:
    f.write("conftest imported\\n")
'''


def cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pytest_drivedegrade.cli", *args], capture_output=True, text=True,
                          check=False, env=env)


def leaks(root: Path, material: list[str], skip: Path, *texts: str) -> list[str]:
    """Every file under `root` (but `skip`, the key itself) and every text holding any of `material`."""
    found = [f"output {i}" for i, text in enumerate(texts) if any(m in text for m in material)]
    for path in root.rglob("*"):
        if path.is_file() and path != skip and path.name != "material.json":
            data = path.read_bytes()
            if any(m.encode() in data for m in material):
                found.append(str(path.relative_to(root)))
    return found


def write_scanner(dd, material: list[str]) -> Path:
    found, keep = dd.pytester.path / "found.txt", dd.pytester.path / "material.json"
    keep.write_text(json.dumps(material))
    dd.pytester.makepyfile(scanner=SCANNER.format(material=str(keep), found=str(found)),
                           conftest=CONFTEST.format(found=str(found)))
    return found


@pytest.mark.parametrize(("via", "workers"), [("env", "0"), ("env-path", "2"), ("option", "0"), ("ini", "2")])
def test_the_planner_can_read_the_signing_key_a_run_given_a_key_is_refused_before_any_planner_code(
        dd, monkeypatch, key_material, via, workers):
    """A key in the run's environment (the PEM text, or a key file's path), or given to the option or the ini
    value: the run (a subprocess, so the key is in its /proc/<pid>/environ as in a real shell) is a usage error
    before conftest.py or the planner file is imported (nothing the scanner could run), the message says how to
    sign instead and quotes no key; nothing is written. On the old code the run signed, and the scanner found
    the key in /proc/<pid>/environ."""
    key, _ = keygen(dd.pytester.path / "issuer")
    material = key_material(key)
    found = write_scanner(dd, material)
    extra: tuple[str, ...] = ()
    if via == "env":
        monkeypatch.setenv("DRIVEDEGRADE_SIGNING_KEY", key.read_text())
    elif via == "env-path":
        monkeypatch.setenv("DRIVEDEGRADE_SIGNING_KEY", str(key))
    elif via == "option":
        extra = ("--drivedegrade-sign-key", "issuer.key")
    else:
        extra = ("-o", "drivedegrade_sign_key=issuer.key")
    result = dd.run("-n", workers, *extra, planner="scanner.py", families="jpeg", severities="1", report="rep",
                    subprocess=True)
    text = result.stdout.str() + result.stderr.str()
    assert result.ret == pytest.ExitCode.USAGE_ERROR, text
    no_traceback(result)
    assert "drivedegrade sign REPORT/PLANNER/certificate.json --key PATH" in text, text
    assert ("DRIVEDEGRADE_SIGNING_KEY is set in the environment of this run" if via.startswith("env")
            else "--drivedegrade-sign-key is refused") in text, text
    assert not found.exists(), found.read_text()  # neither conftest.py nor the planner file was imported
    assert leaks(dd.pytester.path, material, key, text) == []
    assert not (dd.pytester.path / "rep").exists()


@pytest.mark.parametrize("workers", ["0", "2"])
def test_the_planner_can_read_the_signing_key_a_scanning_planner_finds_none_and_the_run_signed_after_verifies(
        dd, key_material, workers):
    """The scanner runs (conftest, import, build, predict: in the controller under -n 0, in both workers under
    -n 2) and finds no key material in any /proc/*/environ or file on its command lines; `drivedegrade sign`
    (the key given as a path, then a second run's certificate through the variable) signs the finished
    certificate, which verifies with --public-key, fails with another key, and whose report.html now says it is
    signed by that key's fingerprint; signing again is refused; no output holds key material."""
    key, pub = keygen(dd.pytester.path / "issuer")
    _, other = keygen(dd.pytester.path / "other")
    material = key_material(key)
    found = write_scanner(dd, material)
    result = dd.run("-n", workers, planner="scanner.py", families="jpeg", severities="1", report="rep",
                    subprocess=True)
    no_traceback(result)
    assert result.ret == 0, result.stdout.str()
    lines = found.read_text().splitlines()
    scans = [line for line in lines if not line.startswith("conftest")]
    assert {line.split()[0] for line in scans} == {"import", "build", "predict"}, lines
    assert all(line.split()[2] == "0" for line in scans), lines  # no hit anywhere
    if workers == "2":
        # both workers and the pre-flight's own process (`plugin.isolated`); the controller runs no planner code
        assert len({line.split()[1] for line in scans if line.startswith("predict")}) == 3
    cert_path = dd.pytester.path / "rep" / "scanner" / "certificate.json"
    assert "signature" not in load_json(cert_path)
    assert "integrity only, unsigned" in (cert_path.parent / "report.html").read_text()

    signed = cli("sign", str(cert_path), "--key", str(key))
    assert signed.returncode == 0, signed.stderr
    cert = load_json(cert_path)
    fp = cert["signature"]["public_key_fingerprint"]
    assert f"key of fingerprint {fp}" in signed.stdout
    page = (cert_path.parent / "report.html").read_text()
    assert f"signed (Ed25519, key fingerprint <code>{fp}</code>" in page and cert["digest"] in page
    assert "integrity only" not in page
    ok = cli("verify", str(cert_path), "--public-key", str(pub))
    assert ok.returncode == 0 and "signature verifies" in ok.stdout, ok.stderr
    wrong = cli("verify", str(cert_path), "--public-key", str(other))
    assert wrong.returncode == 1 and "wrong key" in wrong.stderr
    again = cli("sign", str(cert_path), "--key", str(key))
    assert again.returncode == 2 and "already signed" in again.stderr
    assert leaks(dd.pytester.path, material, key, signed.stdout, signed.stderr, ok.stdout) == []


def test_sign_refuses_an_edited_certificate_and_takes_the_key_from_the_variable(dd, tmp_path, key_material):
    """`drivedegrade sign` signs only what verifies: an edited (resealed-by-hand is not needed: plainly edited)
    certificate is refused with exit 1 and left unsigned; no key at all is a usage error naming both ways; the
    PEM text in DRIVEDEGRADE_SIGNING_KEY signs (the sign step is where the variable belongs), and an error
    never quotes the key."""
    import os

    key, pub = keygen(tmp_path / "issuer")
    dd.write_planner()
    dd.run(families="jpeg", severities="1").assert_outcomes(passed=4)
    path = dd.folder() / "certificate.json"
    env = {k: v for k, v in os.environ.items() if k != "DRIVEDEGRADE_SIGNING_KEY"}
    none = cli("sign", str(path), env=env)
    assert none.returncode == 2 and "give --key PATH" in none.stderr and "DRIVEDEGRADE_SIGNING_KEY" in none.stderr
    original = path.read_text()
    data = json.loads(original)
    data["verdict"]["label"] = "not-shown-to-use-cameras"
    path.write_text(json.dumps(data))
    edited = cli("sign", str(path), "--key", str(key), env=env)
    assert edited.returncode == 1 and "not signed" in edited.stderr, edited.stderr
    assert "signature" not in load_json(path)
    path.write_text(original)
    signed = cli("sign", str(path), env={**env, "DRIVEDEGRADE_SIGNING_KEY": key.read_text()})
    assert signed.returncode == 0, signed.stderr
    assert cli("verify", str(path), "--public-key", str(pub)).returncode == 0
    assert leaks(tmp_path, key_material(key), key, signed.stdout, signed.stderr, none.stderr) == []


#: The closed loop's quickest run (as tests/e2e/test_closed_loop.py runs it): two closed cells, four steps each.
CLOSED = ("--drivedegrade-loop", "closed", "--drivedegrade-closed-cells", "clean,blackout-s5",
          "--drivedegrade-closed-steps", "4", "--drivedegrade-split", "all", "--drivedegrade-closed-scenarios", "0")


@pytest.mark.parametrize("layout", ["closed", "isolate", "closed-isolate"])
def test_the_planner_can_read_the_signing_key_the_scanner_finds_none_in_the_closed_loop_or_isolated(
        dd, key_material, layout):
    """The scanner driving the closed loop (it plans every step of every route there), and the scanner under
    --drivedegrade-isolate (built and called in its own child process, whose parent is the run): no
    /proc/*/environ and no file on its or its parent's command line holds key material; the certificate signed
    afterwards verifies with --public-key; no output holds key material."""
    key, pub = keygen(dd.pytester.path / "issuer")
    material = key_material(key)
    found = write_scanner(dd, material)
    extra = (*(CLOSED if "closed" in layout else ()), *(("--drivedegrade-isolate",) if "isolate" in layout else ()))
    result = dd.run("-n", "0", *extra, planner="scanner.py", families="jpeg", severities="1", report="rep",
                    subprocess=True)
    no_traceback(result)
    assert result.ret == 0, result.stdout.str()
    scans = [line for line in found.read_text().splitlines() if not line.startswith("conftest")]
    assert {line.split()[0] for line in scans} == {"import", "build", "predict"}, scans
    assert all(line.split()[2] == "0" for line in scans), scans
    cert_path = dd.pytester.path / "rep" / "scanner" / "certificate.json"
    signed = cli("sign", str(cert_path), "--key", str(key))
    assert signed.returncode == 0, signed.stderr
    assert ("warning" in signed.stderr) == ("isolate" not in layout), signed.stderr  # sign says: not isolated
    ok = cli("verify", str(cert_path), "--public-key", str(pub))
    assert ok.returncode == 0 and "signature verifies" in ok.stdout, ok.stderr
    said = "planner isolated: yes" if "isolate" in layout else "planner isolated: no"
    assert said in ok.stdout, ok.stdout
    assert leaks(dd.pytester.path, material, key, result.stdout.str(), signed.stdout, ok.stdout) == []
