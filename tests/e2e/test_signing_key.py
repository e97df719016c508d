"""Issue 20 item 1, "The signing key published" (with M7, M8, L4), end to end: a signed run, the key given as a
path to the option or as PEM text in the environment, writes no key material to any output; PEM text given where
a path belongs is a usage error that does not echo it; the planner (and its conftest.py), in the controller and
in xdist workers, never sees DRIVEDEGRADE_SIGNING_KEY."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, no_traceback  # noqa: E402

from pytest_drivedegrade.certificate.signing import keygen  # noqa: E402

pytest_plugins = ["plugin_support"]

SNOOP = '''
import os

import numpy as np
import pytest


def note(where):
    """Record what this process sees of the signing key's variable."""
    with open({seen!r}, "a") as f:
        f.write(f"{{where}} {{os.getpid()}} {{os.environ.get('DRIVEDEGRADE_SIGNING_KEY')!r}}\\n")


note("import")


class Snoop:
    cameras = ("CAM_FRONT",)
    name = "snoop"

    def __init__(self):
        note("build")
        self.noted = False

    def predict(self, images, ego, cmd):
        if not self.noted:
            note("predict")
            self.noted = True
        plan = np.zeros((6, 2))
        plan[:, 0] = 2.0 * np.arange(1, 7)
        plan[:, 1] = float(images["CAM_FRONT"][::16, ::16].mean()) / 255.0
        return plan


@pytest.fixture(scope="session")
def planner():
    return Snoop()
'''

CONFTEST = '''
import os

with open({seen!r}, "a") as f:
    f.write(f"conftest {{os.getpid()}} {{os.environ.get('DRIVEDEGRADE_SIGNING_KEY')!r}}\\n")
'''


def leaks(root: Path, material: list[str], skip: Path, *texts: str) -> list[str]:
    """Every file under `root` (but `skip`, the key itself) and every text holding any of `material`."""
    found = [f"output {i}" for i, text in enumerate(texts) if any(m in text for m in material)]
    for path in root.rglob("*"):
        if path.is_file() and path != skip:
            data = path.read_bytes()
            if any(m.encode() in data for m in material):
                found.append(str(path.relative_to(root)))
    return found


def write_snoop(dd) -> Path:
    seen = dd.pytester.path / "seen.txt"
    dd.pytester.makepyfile(snoop=SNOOP.format(seen=str(seen)), conftest=CONFTEST.format(seen=str(seen)))
    return seen


@pytest.mark.parametrize(("via", "workers"), [("env", "0"), ("option", "2")])
def test_the_signing_key_published_no_output_of_a_signed_run_holds_key_material(
        dd, monkeypatch, key_material, via, workers):
    """The key given both ways, under -n 0 and -n 2: the certificate (tool.command included), report.html,
    cells.csv, cells/*.json, the JUnit XML and the terminal hold no part of the key; the run is signed; the
    planner file, its conftest.py and the planner in every process see no DRIVEDEGRADE_SIGNING_KEY; a key file
    readable by others is warned about (L4)."""
    key, _ = keygen(dd.pytester.path / "issuer")
    material = key_material(key)
    seen = write_snoop(dd)
    if via == "env":
        monkeypatch.setenv("DRIVEDEGRADE_SIGNING_KEY", key.read_text())
        extra: tuple[str, ...] = ()
    else:
        key.chmod(0o644)
        extra = ("--drivedegrade-sign-key", "issuer.key")
    result = dd.run("-n", workers, *extra, "--junitxml", "junit.xml", planner="snoop.py", families="jpeg",
                    severities="1", report="rep")
    no_traceback(result)
    assert result.ret == 0, result.stdout.str()
    folder = dd.pytester.path / "rep" / "snoop"
    cert = load_json(folder / "certificate.json")
    assert cert["signature"]["algorithm"] == "ed25519"
    assert (dd.pytester.path / "junit.xml").exists() and list((folder / "cells").glob("*.json"))
    assert leaks(dd.pytester.path, material, key, result.stdout.str(), result.stderr.str()) == []
    lines = seen.read_text().splitlines()
    assert {line.split()[0] for line in lines} == {"conftest", "import", "build", "predict"}
    assert all(line.endswith(" None") for line in lines), lines
    if workers == "2":
        # both workers saw None, and so did the controller's pre-flight, which predicts one frame before the cells
        assert len({line.split()[1] for line in lines if line.startswith("predict")}) == 3
    if via == "option":
        assert "--drivedegrade-sign-key issuer.key" in cert["tool"]["command"]
        result.stdout.fnmatch_lines(["*--drivedegrade-sign-key: the signing key file*issuer.key is accessible to "
                                     "its group or others (mode 0644)*chmod 600*"], consecutive=False)
    else:
        assert "accessible to its group" not in result.stdout.str()
    assert "DRIVEDEGRADE_SIGNING_KEY" not in __import__("os").environ  # taken from this process's environment too


@pytest.mark.parametrize("how", ["option", "option=", "ini", "env-broken", "env-body"])
def test_the_signing_key_published_key_text_where_a_path_belongs_is_a_usage_error_not_echoed(
        dd, monkeypatch, key_material, how):
    """PEM text given to the option (as its own argument, after `=`, or through -o as the ini value) is refused
    (the message points at the environment variable); a key in the variable that does not parse (M8), or its
    base64 body alone, is refused; no message quotes any of the key, and nothing is written."""
    key, _ = keygen(dd.pytester.path / "issuer")
    pem, material = key.read_text(), key_material(key)
    write_snoop(dd)
    args = {"option": ("--drivedegrade-sign-key", pem), "option=": (f"--drivedegrade-sign-key={pem}",),
            "ini": ("-o", f"drivedegrade_sign_key={pem}")}.get(how, ())
    if how == "env-broken":
        monkeypatch.setenv("DRIVEDEGRADE_SIGNING_KEY", pem[: len(pem) // 2])
    if how == "env-body":
        monkeypatch.setenv("DRIVEDEGRADE_SIGNING_KEY", pem.splitlines()[1])
    result = dd.run(*args, planner="snoop.py", families="jpeg", severities="1", report="rep")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    no_traceback(result)
    text = result.stdout.str() + result.stderr.str()
    if how.startswith("env"):
        assert "DRIVEDEGRADE_SIGNING_KEY: " in text
    else:
        assert "--drivedegrade-sign-key: expected the path of a key file, got what looks like key text (not " \
               "shown); a key's text goes in the DRIVEDEGRADE_SIGNING_KEY environment variable" in text
    assert leaks(dd.pytester.path, material, key, text) == []
    assert not (dd.pytester.path / "rep").exists()
