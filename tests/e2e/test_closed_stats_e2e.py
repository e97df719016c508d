"""Closed-loop statistics end to end (issue 36): a planner with its own unseeded noise, which ignores what it sees,
gets every closed cell "not separable from the null" and no robust closed label; the section verifies.

The planner's noise comes from a generator the suite does not seed (here a fixed one, so the test is repeatable
serially: the point is that the suite's corruption seeds do not control it). A 34-scene world (4 val scenes: 4
routes; the scenario routes are switched off), four planner calls a run.
"""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json  # noqa: E402

from pytest_drivedegrade.certificate.consistency import check_consistency  # noqa: E402

pytest_plugins = ["plugin_support"]

NOISY = '''
import numpy as np
import pytest


class Noisy:
    """Reads every camera (so its null is a clean rerun), looks at none of them, and drives at a speed drawn from
    its own generator: two runs of one route differ by noise alone."""

    name = "noisy"

    def __init__(self):
        self.rng = np.random.default_rng(20261129)

    def reset(self, route):
        pass

    def predict(self, images, ego, cmd):
        speed = max(float(ego.velocity[0]), 2.0) * float(np.clip(1.0 + 0.4 * self.rng.normal(), 0.2, 2.0))
        return np.arange(1, 7)[:, None] * 0.5 * np.array([speed, 0.0])


@pytest.fixture(scope="session")
def planner():
    return Noisy()
'''


@pytest.fixture(scope="module")
def six_route_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from pytest_drivedegrade.closedloop.routes import load_routes
    from pytest_drivedegrade.data.world import write_world

    root = write_world(tmp_path_factory.mktemp("w36"), scenes=34, seed=5)
    assert len(load_routes(root, scenarios=0, lights=0)) == 4  # 4 val scenes: 4 routes (no scenario routes)
    return root


def test_a_planner_with_unseeded_noise_has_every_closed_cell_not_separable(dd, six_route_world: Path) -> None:
    dd.pytester.makepyfile(noisy=NOISY)
    result = dd.run("--drivedegrade-loop", "closed", "--drivedegrade-closed-steps", "4", "-p", "no:randomly",
                    "-p", "no:xdist", "--drivedegrade-closed-scenarios", "0", "--drivedegrade-closed-lights", "0",
                    planner="noisy.py",
                    data=six_route_world)
    assert result.ret == 0, result.stdout.str()
    cert = load_json(dd.folder("noisy") / "certificate.json")
    section = cert["closed_loop"]
    assert section["null_control"]["mode"] == "wander" and section["null_control"]["wander"] > 0
    separable = {c["cell"]: c["separable_from_null"] for c in section["cells"] if c["cell"] != "closed-clean"}
    assert len(separable) == 6 and set(separable.values()) == {False}, separable
    assert section["verdict"]["robust"] is False
    assert section["separation"]["holds"] is not True
    assert all(c["n"] == c["runs"] for c in section["cells"])  # every run is its own (the noise makes it so)
    assert check_consistency(cert) == []
