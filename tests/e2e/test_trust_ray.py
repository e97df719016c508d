"""Issue 20 on Ray planner actors (`--drivedegrade-ray local`): "False accusation" (the culprit search replays on
the actors too, and a planner whose plans depend on its call history is never blamed for a camera there), and
"The signing key published" (issue 37 H1: a run never holds the key, so the actors scanning every
/proc/*/environ find none; the certificate is signed afterwards)."""

from __future__ import annotations

import pytest

pytest.importorskip("ray")
pytest.register_assert_rewrite("plugin_support")
import test_ray  # noqa: E402
from plugin_support import no_traceback  # noqa: E402
from test_trust import FRONT_CHANGE, no_camera_named  # noqa: E402

pytest_plugins = ["plugin_support"]
#: Every test that starts Ray runs on one xdist worker (`--dist loadgroup`, pyproject addopts): the no_stray_ray
#: check counts the Ray daemons that appeared during a test, and another worker's Ray run would be counted.
pytestmark = pytest.mark.xdist_group("ray")

no_stray_ray = test_ray.no_stray_ray  # the fixture: no Ray daemon outlives the run


def test_false_accusation_a_stateful_planner_without_reset_is_never_blamed_for_a_camera_on_ray(dd, no_stray_ray,
                                                                                               monkeypatch):
    """The front-only planner with state and no reset(), its cells run by two actors: whatever its null controls
    find, a failure says the plans depend on call history and no camera is named. The planner in each actor
    scans every /proc/*/environ it can read for the signing key's variable: none holds it; the certificate
    signed after the run (`drivedegrade sign`) verifies with the public key."""
    import subprocess
    import sys

    from pytest_drivedegrade.certificate.signing import keygen

    key, pub = keygen(dd.pytester.path / "issuer")
    seen = dd.pytester.path / "seen.txt"
    note = (f"        with open({str(seen)!r}, 'a') as f:\n"
            "            hits = []\n"
            "            for pid in filter(str.isdigit, os.listdir('/proc')):\n"
            "                try:\n"
            "                    data = open(f'/proc/{pid}/environ', 'rb').read()\n"
            "                except OSError:\n"
            "                    continue\n"
            f"                hits += [pid] if {key.read_text().splitlines()[1]!r}.encode() in data else []\n"
            "            f.write(f\"{os.getpid()} {hits or None!r}\\n\")\n")
    source = FRONT_CHANGE.replace("import numpy", "import os\n\nimport numpy").replace(
        "    def predict(self, images, ego, cmd):\n", "    def predict(self, images, ego, cmd):\n" + note)
    dd.pytester.makepyfile(frontchange=source)
    result = dd.run(*test_ray.RAY, planner="frontchange.py", families="jpeg,blackout", severities="3", subprocess=True)
    no_traceback(result)
    text = result.stdout.str()
    no_camera_named(text)
    result.stdout.fnmatch_lines(["*ray: 2 planner actor(s) on a local cluster*"], consecutive=False)
    lines = text.splitlines()
    failed = [i for i, line in enumerate(lines) if line.startswith("null control failed in cell")]
    # each actor's state crosses cells; since every actor plans clean first (the memo check, M12) the null control
    # may pass bit for bit; where it fails, the failure names call history, never a camera
    assert failed or "null control: passed" in text, text
    assert all(lines[i + 1].startswith("  plans depend on call history: give the planner a reset()")
               for i in failed), text
    calls = seen.read_text().splitlines()
    assert len({c.split()[0] for c in calls}) == 2 and all(c.endswith(" None") for c in calls)  # both actors
    cert = dd.folder("frontchange") / "certificate.json"
    assert "signature" not in cert.read_text()
    cli = [sys.executable, "-m", "pytest_drivedegrade.cli"]
    assert subprocess.run([*cli, "sign", str(cert), "--key", str(key)], check=False).returncode == 0
    assert subprocess.run([*cli, "verify", str(cert), "--public-key", str(pub)], check=False).returncode == 0


def test_the_signing_key_a_scanning_planner_on_one_ray_actor_finds_none(dd, no_stray_ray, key_material):
    """Issue 37's done-when, Ray local with one actor: the scanner of tests/e2e/test_signing_key.py (every
    /proc/*/environ, every file on its and its parent's command line) runs in the actor and finds no key
    material; the certificate signed afterwards verifies with --public-key."""
    import subprocess
    import sys

    from test_signing_key import leaks, write_scanner

    from pytest_drivedegrade.certificate.signing import keygen

    key, pub = keygen(dd.pytester.path / "issuer")
    material = key_material(key)
    found = write_scanner(dd, material)
    result = dd.run(*test_ray.RAY, "--drivedegrade-ray-actors", "1", planner="scanner.py", families="jpeg",
                    severities="1", subprocess=True)
    no_traceback(result)
    assert result.ret == 0, result.stdout.str()
    result.stdout.fnmatch_lines(["*ray: 1 planner actor(s) on a local cluster*"], consecutive=False)
    scans = [line for line in found.read_text().splitlines() if not line.startswith("conftest")]
    assert {line.split()[0] for line in scans} >= {"build", "predict"}, scans
    assert all(line.split()[2] == "0" for line in scans), scans
    cert = dd.folder("scanner") / "certificate.json"
    cli = [sys.executable, "-m", "pytest_drivedegrade.cli"]
    assert subprocess.run([*cli, "sign", str(cert), "--key", str(key)], check=False).returncode == 0
    ok = subprocess.run([*cli, "verify", str(cert), "--public-key", str(pub)], capture_output=True, text=True,
                        check=False)
    assert ok.returncode == 0 and "signature verifies" in ok.stdout, ok.stderr
    assert leaks(dd.pytester.path, material, key, result.stdout.str(), ok.stdout) == []
