"""Issue 40, closed loop end to end: ``--drivedegrade-closed-cells clean,command_swap`` drives the junction routes
with their command swapped (the route goes straight on where the log turned) as the cell ``closed-command_swap``;
its mean route completion is the "command followed in closed loop" figure, in closed_loop.csv, the certificate's
closed section (recomputed by verify), the terminal and report.html. The privileged expert told the swapped route
follows it; the same expert over the logged routes (it ignores the command and turns where the log turned) does
not. Bit-identical under -n 0 and -n 2; reproduce reruns the cell bit for bit.

Small: the small world's val route and its first 15 scenario routes, no light route; two of them are junction
routes whose logged lane parts from the swapped one by more than the leaderboard's deviation distance
(scenario-0013-braking turns right, scenario-0014-blocked left); scenario-0000-crossing turns too, but its logged
drive ends 2 m from the swapped lane, which could not tell a planner that ignores the command, and is left out.
The expert reads no camera: every run is fast.
"""

from __future__ import annotations

import pytest

pytest.register_assert_rewrite("plugin_support")
from plugin_support import load_json, read_csv  # noqa: E402

from pytest_drivedegrade.certificate.consistency import check_consistency  # noqa: E402
from pytest_drivedegrade.cli import main  # noqa: E402

pytest_plugins = ["plugin_support"]

PLANNER = '''
from dataclasses import replace

import numpy as np
import pytest

from pytest_drivedegrade.closedloop.expert import WorldExpert


class Expert(WorldExpert):
    """The pre-flight's open-loop frames are no route of its: there it plans straight ahead."""

    def reset(self, route):
        self._route = self._routes.get(route)

    def predict(self, images, ego, cmd, context=None):
        if self._route is None or context is None:
            return np.arange(1, 7)[:, None] * np.array([1.0, 0.0])
        return super().predict(images, ego, cmd, context)
from pytest_drivedegrade.closedloop.routes import load_routes
from pytest_drivedegrade.closedloop.swap import junction_routes


@pytest.fixture(scope="session")
def planner():
    """The world's expert over every route; told=False: over the swapped routes it drives the logged route
    (it turns where the log turned, whatever the command says)."""
    routes = load_routes({root!r}, scenarios=15, lights=0)
    swapped = junction_routes(routes)
    if not {told!r}:
        by = {{r.name: r for r in routes}}
        swapped = [replace(by[s.name[:-len("-swap")]], name=s.name) for s in swapped]
    expert = Expert([*routes, *swapped])
    expert.name = {name!r}
    return expert
'''

CLOSED = ("--drivedegrade-loop", "closed", "--drivedegrade-closed-cells", "clean,command_swap",
          "--drivedegrade-split", "all", "-p", "no:randomly", "--drivedegrade-closed-scenarios", "15",
          "--drivedegrade-closed-lights", "0")
SWAPPED = ["scenario-0013-braking-swap", "scenario-0014-blocked-swap"]


def drive(dd, told: bool, *extra: str, report: str = "rep"):
    name = "told" if told else "ignoring"
    dd.pytester.makepyfile(**{name: PLANNER.format(root=str(dd.world), told=told, name=name)})
    result = dd.run(*CLOSED, *extra, planner=f"{name}.py", report=report)
    return result, dd.folder(name, report=report)


def test_the_expert_follows_the_swapped_command_a_command_ignoring_planner_does_not_and_shards_merge(dd, capsys):
    result, folder = drive(dd, True, "-p", "no:xdist")
    assert result.ret == 0, result.stdout.str()
    rows = read_csv(folder / "closed_loop.csv")
    swap = [r for r in rows if r["cell"] == "closed-command_swap"]
    # two junction routes, clean cameras: the first seed only (another would replay it)
    assert [(r["route"], r["seed"], r["family"], r["severity"]) for r in swap] == \
        [(name, "0", "command_swap", "0") for name in SWAPPED]
    assert all(r["end"] == "complete" and float(r["completion"]) == 1.0 for r in swap)
    cert = load_json(folder / "certificate.json")
    figure = cert["closed_loop"]["command_swap"]
    assert figure["command_followed"] == 1.0 and figure["routes"] == 2 and figure["complete_runs"] == 2
    assert figure["clean_runs"] == 2 and figure["clean_completion"] == 1.0  # clean over the same routes unswapped
    cell = {c["cell"]: c for c in cert["closed_loop"]["cells"]}["closed-command_swap"]
    assert cell["retention"] is None and cell["separable_from_null"] is None  # never paired with clean's routes
    assert check_consistency(cert) == []
    assert main(["verify", str(folder / "certificate.json")]) == 0
    out = result.stdout.str()
    assert "command followed in closed loop: 1.000 (mean route completion of 2 junction route(s)" in out
    assert "command followed in closed loop: 1.000" in (folder / "report.html").read_text().lower()

    parallel, pfolder = drive(dd, True, "-n", "2", "--drivedegrade-no-resume", report="rep2")
    assert parallel.ret == 0, parallel.stdout.str()
    assert (pfolder / "closed_loop.csv").read_text() == (folder / "closed_loop.csv").read_text()
    assert load_json(pfolder / "certificate.json")["closed_loop"]["cells"] == cert["closed_loop"]["cells"]

    ignoring, ifolder = drive(dd, False, "-p", "no:xdist")
    assert ignoring.ret == 0, ignoring.stdout.str()
    went = [r for r in read_csv(ifolder / "closed_loop.csv") if r["cell"] == "closed-command_swap"]
    assert [r["route"] for r in went] == SWAPPED and all(r["end"] == "route_deviation" for r in went)
    figure = load_json(ifolder / "certificate.json")["closed_loop"]["command_swap"]
    # it drives the unswapped route as well as the expert (clean), and leaves the swapped one at the junction
    assert figure["clean_completion"] == 1.0 and 0.3 < figure["command_followed"] < 0.8
    assert figure["complete_runs"] == 0 and figure["ds_mean"] < 80

    shards_merge_reproduce_and_tamper(dd, folder, capsys)


def shards_merge_reproduce_and_tamper(dd, folder, capsys) -> None:
    """The told run's swap cell in two shards merges to its unsharded CSV and certificate; reproduce reruns the
    cell bit for bit; a tampered command-followed figure fails the consistency check. (Part of the test above, which
    has made the serial run this starts from.)"""
    cert_path = folder / "certificate.json"
    cert = load_json(cert_path)
    for i in (1, 2):  # the swap cell's two runs fall one to each shard
        shard, _ = drive(dd, True, "-p", "no:xdist", "--drivedegrade-shard", f"{i}/2", report="sh")
        assert shard.ret == 0, shard.stdout.str()
    shards, out = dd.pytester.path / "sh" / "told", dd.pytester.path / "merged"
    assert main(["merge", str(shards / "shard-2-of-2"), str(shards / "shard-1-of-2"), "--out", str(out)]) == 0
    assert (out / "told" / "closed_loop.csv").read_text() == (folder / "closed_loop.csv").read_text()
    merged = load_json(out / "told" / "certificate.json")["closed_loop"]
    assert merged["cells"] == cert["closed_loop"]["cells"] and merged["command_swap"] == \
        cert["closed_loop"]["command_swap"]
    capsys.readouterr()
    assert main(["reproduce", str(cert_path), str(dd.pytester.path / "told.py"), "--closed-cells", "1",
                 "--seed", "0"]) == 0
    out, err = capsys.readouterr()
    assert "closed-command_swap" in out and "identical" in out, out + err
    assert "--drivedegrade-closed-cells clean,command_swap" in err

    from pytest_drivedegrade.certificate.seal import seal

    cert["closed_loop"]["command_swap"]["command_followed"] = 0.5
    assert any(p.startswith("closed_loop.command_swap.command_followed") for p in check_consistency(seal(cert)))


def test_a_run_without_a_junction_route_fails_the_swap_cell_saying_why(dd):
    result, _ = drive(dd, True, "-p", "no:xdist", "--drivedegrade-closed-routes", "1")
    assert result.ret != 0
    out = result.stdout.str()
    assert "closed-command_swap: none of the 1 closed-loop route(s) turns at a junction" in out
    assert "Traceback" not in out
