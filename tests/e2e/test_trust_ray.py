"""Issue 20 on Ray planner actors (`--drivedegrade-ray local`): "False accusation" (the culprit search replays on
the actors too, and a planner whose plans depend on its call history is never blamed for a camera there), and
"The signing key published" (M7: a signed run's actors never see DRIVEDEGRADE_SIGNING_KEY)."""

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
    find, a failure says the plans depend on call history and no camera is named. The run is signed through the
    environment, and the planner in each actor notes what it sees of the variable: nothing."""
    from pytest_drivedegrade.certificate.signing import keygen

    key, _ = keygen(dd.pytester.path / "issuer")
    monkeypatch.setenv("DRIVEDEGRADE_SIGNING_KEY", key.read_text())
    seen = dd.pytester.path / "seen.txt"
    note = (f"        with open({str(seen)!r}, 'a') as f:\n"
            "            f.write(f\"{os.getpid()} {os.environ.get('DRIVEDEGRADE_SIGNING_KEY')!r}\\n\")\n")
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
    assert "signature" in (dd.folder("frontchange") / "certificate.json").read_text()
