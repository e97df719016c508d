"""Issue 40 (the command_swap cell): the record keeps the expert's change of path at junction frames only, the
analysis reads the following figure from clean and command_swap, and the certificate, verify, cells.csv, the JUnit
suite properties, the verdict and the reliance profile carry it. Hidden-behaviour planners as synthetic records
(ignores the command, follows it, follows it only where its cameras show the junction) with known answers."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest
from test_analysis import GROUPS, record
from test_command_following import frames

from pytest_drivedegrade.cells import FRAME_ARRAYS, RECORD_VERSION, CellRecord
from pytest_drivedegrade.certificate.command_check import check_command
from pytest_drivedegrade.certificate.seal import Provenance, canonicalize
from pytest_drivedegrade.scoring.analyse import analyse_run
from pytest_drivedegrade.scoring.command import swap_probe

#: Frames away from any junction appended to the junction frames: their command_target is NaN.
AWAY = 6


def swap_run(plan_of, n: int = 24, seed: int = 0) -> list[CellRecord]:
    """Records for clean, null and command_swap over `n` junction frames plus `AWAY` frames away from junctions,
    the planner's plans ``plan_of(own, logged, target, shows, told_other)``; away from junctions command_swap's
    plans are moved by 5 m (a planner that does something else there: never scored)."""
    logged, target, shows, own = frames(n, seed)
    far = np.stack([np.arange(1, 7) * 2.0, np.zeros(6)], axis=-1)[None].repeat(AWAY, 0)
    gt = np.concatenate([logged, far])
    p0 = np.concatenate([plan_of(own, logged, target, shows, False), far + 0.2])
    p1 = np.concatenate([plan_of(own, logged, target, shows, True), far + 5.2])
    swap = record("command_swap", "command_swap", 0, p1, gt)
    swap.command_target = np.concatenate([target - logged, np.full((AWAY, 6, 2), np.nan)])
    return [record("clean", "clean", 0, p0, gt), record("null", "null", 0, p0.copy(), gt), swap]


def ignores(own, logged, target, shows, told_other):
    return own.copy()


def follows(own, logged, target, shows, told_other):
    return own + (0.9 * (target - logged) if told_other else 0.0)


def follows_when_shown(own, logged, target, shows, told_other):
    """Follows where its cameras show the junction (two frames in three), else keeps its plan."""
    return own + (0.9 * (target - logged) * shows[:, None, None] if told_other else 0.0)


def certificate(res) -> dict:
    """The sections `check_command` reads, as the sealed certificate stores them (six decimals)."""
    return canonicalize({"command": res.command.to_builtins(), "settings": res.settings,
                         "cells": [{"cell": s.cell} for s in res.summaries]})


@pytest.mark.parametrize("plan_of, label, low, high", [
    (ignores, "command-insensitive", 0.0, 0.0),
    (follows, "command-following", 0.9, 0.9),
    (follows_when_shown, "command-partial", None, None),
])
def test_each_hidden_behaviour_gets_its_label_and_verify_recomputes_it(plan_of, label, low, high) -> None:
    res = analyse_run(swap_run(plan_of), groups=GROUPS, n_resamples=500)
    got = res.command
    assert got is not None and got.junction_frames == 24 and got.following.frames == 24  # AWAY frames not scored
    f = got.following
    assert f.label == label
    if low is not None:  # an interval that excludes the other label
        assert f.low == pytest.approx(low, abs=1e-6) and f.high == pytest.approx(high, abs=1e-6)
    else:  # partial following: 0.9 x the share of the expert's change on the frames it sees, neither label
        assert 0.1 <= f.high and f.low < 0.5 and 0.3 < f.value < 0.8
    assert f.text() in res.verdict.text and f"{label}" in res.verdict.text
    cert = certificate(res)
    assert check_command(cert) == []
    forged = {**cert, "command": {**cert["command"], "label": "command-following", "following": 0.95}}
    if label != "command-following":
        assert any(p.startswith("command.label: certificate says 'command-following'") for p in
                   check_command(forged))
    assert any(p.startswith("command.following: certificate says 0.95") for p in check_command(forged))


def test_frames_away_from_junctions_are_not_scored_and_a_run_without_them_is_not_measured() -> None:
    recs = swap_run(follows)
    recs[2].command_target[:] = np.nan  # no junction in the run
    res = analyse_run(recs, groups=GROUPS, n_resamples=100)
    assert res.command is not None and res.command.junction_frames == 0 and res.command.following.value is None
    assert "Command: not measured" in res.verdict.text
    assert check_command(certificate(res)) == []
    no_cell = analyse_run(recs[:2], groups=GROUPS, n_resamples=100)
    assert no_cell.command is None and "Command" not in no_cell.verdict.text
    assert "command" not in no_cell.to_builtins()


def test_a_spec_4_certificate_without_the_section_has_nothing_to_check() -> None:
    assert check_command({"spec_version": "4.1.0", "cells": [{"cell": "clean"}]}) == []
    assert check_command({"command": {"sums": "x"}})[0].startswith("command.sums: not a list")
    res = analyse_run(swap_run(follows), groups=GROUPS, n_resamples=100)
    cert = certificate(res)
    lost = {**cert, "cells": [c for c in cert["cells"] if c["cell"] != "command_swap"]}
    assert any("no 'command_swap' cell" in p for p in check_command(lost))


def test_the_record_keeps_the_target_at_junction_frames_only_and_old_records_keep_their_form() -> None:
    assert RECORD_VERSION == 7
    recs = swap_run(follows)
    swap, clean = recs[2], recs[0]
    back = CellRecord.from_builtins(swap.to_builtins())
    assert np.array_equal(back.command_target, swap.command_target, equal_nan=True)
    assert "command_target" not in clean.to_builtins()  # every other cell: its record's form unchanged
    assert np.isnan(CellRecord.from_builtins(clean.to_builtins()).command_target).all()
    halves = [CellRecord.of_arrays(swap.cell, swap.family, 0, swap.frames[part],
                                   {a.name: swap.array(a.name)[part] for a in FRAME_ARRAYS})
              for part in (slice(0, 10), slice(10, None))]
    joined = CellRecord.concat(halves)
    assert np.array_equal(joined.command_target, swap.command_target, equal_nan=True)  # shards merge whole


def test_the_probe_is_computed_from_the_sums_the_certificate_stores() -> None:
    logged, target, _, own = frames(12)
    got = swap_probe(own, own + 0.5 * (target - logged), target - logged, n_resamples=200, seed=3)
    assert got.following.value == pytest.approx(0.5, abs=1e-6)
    assert all(round(v, 6) == v for v in got.num + got.den)  # what the certificate stores, exactly
    again = swap_probe(own, own + 0.5 * (target - logged), target - logged, n_resamples=200, seed=3)
    assert again == got  # seeded: bit-identical


def test_cells_csv_junit_and_the_profile_carry_the_figure() -> None:
    from pytest_drivedegrade.report.cells_csv import cells_csv_text
    from pytest_drivedegrade.report.junit import suite_properties
    from pytest_drivedegrade.report.profile import profile_lines

    res = analyse_run(swap_run(follows), groups=GROUPS, n_resamples=200)
    prov = Provenance("p", "sha256:p", "sha256:d", "val", "5.0.0", seed=0, frames=30, command="pytest")
    rows = {r["cell"]: r for r in csv.DictReader(io.StringIO(cells_csv_text(res, prov)))}
    assert rows["command_swap"]["command_following"] == "0.9" and rows["command_swap"]["command_label"] == \
        "command-following"
    assert rows["command_swap"]["junction_frames"] == "24" and rows["command_swap"]["command_frames"] == "24"
    assert rows["clean"]["command_following"] == "" and rows["clean"]["junction_frames"] == ""
    props = dict(suite_properties(res))
    assert props["drivedegrade_command_label"] == "command-following"
    assert props["drivedegrade_command_following"] == pytest.approx(0.9, abs=1e-6)
    assert props["drivedegrade_command_junction_frames"] == 24
    lines = profile_lines(res.reliance, res.axes, 0.95, None, res.command.following)
    assert lines[3] == ("  command: not probed (command_blind did not run); following 0.900 [0.900 .. 0.900] "
                        "over 24 junction frames (command-following)")


class _Recorder:
    """A deterministic planner without reset that plans along the logged command's side and records each
    command it is given."""

    cameras = ("CAM_FRONT",)

    def __init__(self) -> None:
        self.commands: list[int] = []

    def predict(self, images, ego, cmd):
        self.commands.append(int(cmd))
        return np.stack([np.arange(1, 7) * 1.0, np.full(6, float(int(cmd)))], axis=-1)


def test_the_cell_gives_the_alternative_at_junction_frames_and_records_the_target(small_world, monkeypatch) -> None:
    """On a real run: frames the lane map calls junctions (here every other frame, patched in: the small world has
    none) get the alternative command and their record row the expert's change; the others the logged command,
    NaN target. The same frames in two halves give the record of one run (shards, -n 2)."""
    from pytest_drivedegrade.data.frame import Command
    from pytest_drivedegrade.data.junctions import Alternative
    from pytest_drivedegrade.run import RunContext
    from pytest_drivedegrade.settings import RunSettings

    context = RunContext.open(RunSettings(data=small_world, frames=6, timeout=0.0))
    junction = {f.token for f in context.frames[::2]}

    def alternative_of(frame):
        if frame.token not in junction:
            return None
        other = Command.LEFT if frame.command != Command.LEFT else Command.RIGHT
        return Alternative(other, np.asarray(frame.gt_future) + [0.0, 2.0])

    monkeypatch.setattr(context, "alternative_of", alternative_of)
    planner = _Recorder()
    rec = context.run_cell(planner, "command_swap", 0)
    logged = [int(f.command) for f in context.frames]
    assert planner.commands == [(int(Command.LEFT) if c != int(Command.LEFT) else int(Command.RIGHT))
                                if f.token in junction else c for f, c in zip(context.frames, logged)]
    at = np.array([f.token in junction for f in context.frames])
    np.testing.assert_allclose(rec.command_target[at], np.broadcast_to([0.0, 2.0], (at.sum(), 6, 2)))
    assert np.isnan(rec.command_target[~at]).all()
    halves = [context.run_cell(planner, "command_swap", 0, span=span) for span in ((0, 3), (3, 6))]
    joined = CellRecord.concat(halves)
    assert np.array_equal(joined.command_target, rec.command_target, equal_nan=True)
    assert np.array_equal(joined.plans, rec.plans)


def test_compare_shows_the_command_label_and_reads_a_spec_4_certificate_without_it() -> None:
    from pytest_drivedegrade.certificate.compare import certificate_row

    res = analyse_run(swap_run(follows), groups=GROUPS, n_resamples=100)
    new = {"spec_version": "5.0.0", "command": res.command.to_builtins(), "verdict": {"label": "camera-reliant"}}
    old = {"spec_version": "4.1.0", "verdict": {"label": "not-shown-to-use-cameras"}}
    assert certificate_row(new)["command_label"] == "command-following"
    assert certificate_row(new)["command_following"] == pytest.approx(0.9)
    assert certificate_row(old)["command_label"] is None and certificate_row(old)["command_following"] is None


def test_the_interval_resamples_scenes_when_the_frames_scenes_are_known() -> None:
    """Two scenes of six junction frames each: one where the plan follows the told manoeuvre fully, one where it
    ignores it. Frames treated as independent give an interval about 0.5 ([0.17, 0.83]);
    the scene-cluster bootstrap (two scenes: resamples 0, 0.5 or 1, read at the expanded levels for 2 scenes) gives
    [0, 1], the spread two scenes can support. Verify recomputes each from the section, scenes included."""
    logged, target, _, own = frames(12)
    target = logged + np.stack([np.zeros(6), np.linspace(0.5, 3.0, 6)], axis=-1)  # the same |change| everywhere
    told = own + (target - logged) * (np.arange(12) < 6)[:, None, None]
    scenes = ["a"] * 6 + ["b"] * 6
    by_frames = swap_probe(own, told, target - logged, n_resamples=400, seed=1)
    by_scenes = swap_probe(own, told, target - logged, n_resamples=400, seed=1, scenes=scenes)
    assert by_frames.following.value == by_scenes.following.value == pytest.approx(0.5)
    assert by_frames.following.scenes is None and 0.1 < by_frames.following.low < 0.5 < by_frames.following.high < 0.9
    f = by_scenes.following
    assert (f.low, f.high, f.scenes, f.label) == (0.0, 1.0, 2, "undetermined")
    assert "scene-cluster bootstrap, 2 scenes" in f.text()
    section = by_scenes.to_builtins()
    assert section["scenes"] == [0] * 6 + [1] * 6 and section["basis"] == "scene-cluster bootstrap, 2 scenes"
    settings = {"seed": 1, "n_resamples": 400}
    cert = canonicalize({"command": section, "settings": settings, "cells": [{"cell": "command_swap"}]})
    assert check_command(cert) == []
    moved = {**cert, "command": {**cert["command"], "scenes": [0] * 12}}  # one scene: a frame bootstrap's interval
    assert any(p.startswith("command.low: certificate says 0.0") for p in check_command(moved))
    bad = {**cert, "command": {**cert["command"], "scenes": [0] * 5}}
    assert check_command(bad)[0].startswith("command.scenes: not a list of 12 scene indices")
    old = {**cert, "command": {k: v for k, v in by_frames.to_builtins().items()}}  # as spec 5.0.0 wrote it
    assert "scenes" not in old["command"] and check_command(old) == []


def test_a_spec_5_0_certificate_between_the_lines_still_verifies_as_undetermined() -> None:
    """Spec 5.0.0 had no `command-partial`: a frame-bootstrap figure of 0.5 [0.17, 0.83] was `undetermined` there
    and verifies so; the same section under a later spec must say `command-partial`."""
    logged, target, _, own = frames(12)
    target = logged + np.stack([np.zeros(6), np.linspace(0.5, 3.0, 6)], axis=-1)
    told = own + (target - logged) * (np.arange(12) < 6)[:, None, None]
    section = swap_probe(own, told, target - logged, n_resamples=400, seed=1).to_builtins()
    assert section["label"] == "command-partial"
    settings = {"seed": 1, "n_resamples": 400}
    old = canonicalize({"spec_version": "5.0.0", "settings": settings, "cells": [{"cell": "command_swap"}],
                        "command": {**section, "label": "undetermined"}})
    assert check_command(old) == []
    new = {**old, "spec_version": "5.1.0"}
    assert check_command(new) == ["command.label: certificate says 'undetermined', its sums give 'command-partial'"]


def test_the_run_analysis_gives_the_probe_the_frames_scenes() -> None:
    recs = swap_run(follows)
    scenes = {t: f"s{i % 3}" for i, t in enumerate(recs[0].frames)}
    res = analyse_run(recs, groups=GROUPS, n_resamples=300, scenes=scenes)
    assert res.command is not None and res.command.following.scenes == 3
    assert res.command.scenes == tuple(i % 3 for i in range(24))  # junction frames only, in order
    assert check_command(certificate(res)) == []


def test_the_section_names_its_basis_only_where_a_frame_was_scored() -> None:
    logged, target, _, own = frames(3)
    one = swap_probe(own[:1], own[:1] + (target - logged)[:1], (target - logged)[:1], n_resamples=100, seed=0,
                     scenes=["a"])
    assert one.following.low is None and one.to_builtins()["basis"] == "no interval"
    none = swap_probe(own, own, np.full_like(target, np.nan), n_resamples=100, seed=0, scenes=["a", "b", "c"])
    assert "scenes" not in none.to_builtins() and "basis" not in none.to_builtins()  # the 5.0.0 section's form
