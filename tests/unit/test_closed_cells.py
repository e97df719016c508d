"""Closed-loop cells and their analysis (SPEC section 13) on known runs: the selection, shards of runs, exact
stored records, bounds that widen with unscored runs, retention bounds, the verdict under every assignment, the
separation, the null control (identical or a rerun's wander), and the certificate section that verify recomputes.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pytest_drivedegrade.certificate.closed import ClosedRun, check_closed_loop, closed_only_certificate
from pytest_drivedegrade.certificate.consistency import check_consistency
from pytest_drivedegrade.certificate.seal import Provenance, seal, verify_data
from pytest_drivedegrade.closedloop.analysis import RunRow, first_difference, parting_step
from pytest_drivedegrade.closedloop.cells import (
    SLICE,
    ClosedPayload,
    ClosedRecord,
    closed_id,
    parse_id,
    run_list,
    selection,
    shard_runs,
)
from pytest_drivedegrade.closedloop.results import Infraction, RunResult
from pytest_drivedegrade.errors import DriveDegradeError, InvalidInput
from pytest_drivedegrade.report.closed_outputs import closed_csv_text
from pytest_drivedegrade.scoring.closed_loop import analyse_runs, check_section
from pytest_drivedegrade.settings import RunSettings


def run(route: str, ds: float | None, seed: int = 0, shift: float = 0.0, kinds: tuple[str, ...] = ()) -> RunResult:
    trace = np.stack([np.arange(12.0), np.full(12, shift), np.zeros(12)], axis=1)
    return RunResult(route, seed, ds, None if ds is None else ds / 100, "complete" if ds is not None else "unscored",
                     tuple(Infraction(k, 1, 5) for k in kinds), trace, "" if ds is not None else "boom", 2)


def test_the_slice_is_the_papers_seven_with_clean_first_and_the_null_last() -> None:
    assert selection("slice") == list(SLICE) and len(SLICE) == 7
    assert SLICE[0] == ("clean", 0) and SLICE[-1] == ("blackout", 3)
    every = selection("all")
    assert every[0] == ("clean", 0) and every[-1] == ("blackout", 3) and len(every) == 7 + 2 * 13 + 1
    assert every[-2] == ("command_swap", 0) and ("command_swap", 0) not in SLICE  # opt-in: `all` or named
    assert selection("command_swap,clean") == [("clean", 0), ("command_swap", 0)]
    assert closed_id("command_swap", 0) == "closed-command_swap" and parse_id("closed-command_swap") == \
        ("command_swap", 0) and parse_id("command_swap") == ("command_swap", 0)
    assert selection("blackout-s3, closed-motion_blur-s5,clean") == [("clean", 0), ("motion_blur", 5),
                                                                      ("blackout", 3)]
    assert [closed_id(*c) for c in SLICE[:2]] == ["closed-clean", "closed-gaussian_blur-s3"]
    assert parse_id("closed-blackout-s5") == ("blackout", 5)
    with pytest.raises(DriveDegradeError, match="unknown closed-loop cell 'fog-s9'"):
        selection("clean,fog-s9")
    with pytest.raises(InvalidInput):
        parse_id("nonsense")


@given(st.integers(0, 30), st.integers(1, 8))
def test_shards_split_the_runs_into_contiguous_parts_that_join_back_in_order(n: int, count: int) -> None:
    runs = run_list([f"r{i}" for i in range(n)], [0, 1])
    parts = [shard_runs(runs, i, count) for i in range(1, count + 1)]
    assert [r for p in parts for r in p] == runs
    assert max(map(len, parts)) - min(map(len, parts)) <= 1


def test_a_stored_record_reads_back_bit_for_bit_and_an_edit_breaks_its_digest() -> None:
    r = run("a", 71.25, kinds=("collision_vehicle",))
    trace = r.trace.copy()
    trace[3, 0] = 0.1 + 0.2  # a float whose decimal form is long
    record = ClosedRecord("closed-clean", "clean", 0, (RunResult("a", 0, 71.25, 0.7125, "complete", r.infractions,
                                                                 trace), run("b", None)), seconds={"render": 1.5})
    payload = ClosedPayload({"seed": 0}, "p", record)
    back = ClosedPayload.from_builtins(json.loads(json.dumps(payload.to_builtins())))
    assert back.record.runs[0].trace.tobytes() == trace.tobytes()
    assert back.record.digest() == record.digest() and back.record.runs[1].ds is None
    data = payload.to_builtins()
    data["record"]["runs"][0]["ds"] = 90.0
    with pytest.raises(InvalidInput, match="no longer hash"):
        ClosedPayload.from_builtins(data)


def test_bounds_widen_with_unscored_runs_and_retention_carries_them() -> None:
    got = analyse_runs({"closed-clean": [run("a", 80.0), run("b", 60.0)],
                        "closed-blackout-s5": [run("a", 20.0), run("b", None)]}, flat=0.9)
    clean, dark = got.cells
    assert (clean.mean, clean.bounds) == (70.0, (70.0, 70.0))
    assert dark.mean == 20.0 and dark.bounds == (10.0, 60.0) and dark.unscored == 1
    assert dark.retention == pytest.approx(20 / 70)
    assert (dark.retention_low, dark.retention_high) == pytest.approx((10 / 70, 60 / 70))
    assert got.axes["removal"] == pytest.approx(20 / 70) and got.axes["quality"] is None


def test_the_verdict_and_the_separation_under_every_assignment_of_the_unscored_runs() -> None:
    clean = [run("a", 100.0), run("b", 100.0)]
    blur = [run("a", 96.0), run("b", 98.0)]
    sure = analyse_runs({"closed-clean": clean, "closed-gaussian_blur-s5": blur,
                         "closed-blackout-s5": [run("a", 20.0), run("b", 10.0)]}, flat=0.9,
                        open_label="quality-insensitive")
    assert sure.label == "quality-insensitive" and sure.robust and sure.agrees is True
    assert sure.separation["holds"] is True and sure.separation["holds_under_every_assignment"] is True
    unsure = analyse_runs({"closed-clean": clean, "closed-gaussian_blur-s5": blur,
                           "closed-blackout-s5": [run("a", 80.0), run("b", None)]}, flat=0.9,
                          open_label="camera-reliant")  # removal 0.8, bounds [0.4, 0.9]: the flat line is inside
    # issue 36/37: an unscored run whose bounds allow another label stops the headline label
    assert unsure.label == "undetermined" and not unsure.robust and unsure.agrees is None
    assert unsure.reason is not None and "1 unscored run" in unsure.reason
    assert {"quality-insensitive", "not-shown-to-use-cameras"} <= set(unsure.labels)
    # route b's removal run may have scored 100, above the blur's 98 there: the paired gap does not clear 0
    assert unsure.separation["holds_under_every_assignment"] is False
    close = analyse_runs({"closed-clean": clean, "closed-gaussian_blur-s5": blur,
                          "closed-blackout-s5": [run("a", 95.0), run("b", None)]}, flat=0.9)
    assert close.separation["holds"] is True and close.separation["holds_under_every_assignment"] is False


def test_the_null_control_names_the_first_run_that_parts_and_where() -> None:
    clean = [run("a", 80.0), run("b", 60.0)]
    same = analyse_runs({"closed-clean": clean, "closed-blackout-s3": [run("a", 80.0), run("b", 60.0)]})
    assert same.null is not None and same.null.mode == "identical" and same.null.passed is True
    off = run("b", 60.0, shift=0.0)
    off.trace[7, 1] = 1e-9  # the paths part at the 8th 10 Hz pose: driven by the planner call of step 1
    parted = analyse_runs({"closed-clean": clean, "closed-blackout-s3": [run("a", 80.0), off]}, first_step=1)
    assert parted.null is not None and parted.null.passed is False
    assert (parted.null.first_route, parted.null.first_seed, parted.null.first_step) == ("b", 0, 1)
    assert first_difference([RunRow.of(r) for r in clean], [RunRow.of(run("a", 80.0)), RunRow.of(off)]) is not None
    assert parting_step(clean[1], off, 5) == 1


def test_a_rerun_that_wanders_makes_small_effects_inseparable_from_the_null() -> None:
    clean = [run("a", 80.0), run("b", 60.0)]
    rerun = [run("a", 70.0, shift=1.0), run("b", 58.0, shift=1.0)]
    got = analyse_runs({"closed-clean": clean, "closed-gaussian_blur-s5": [run("a", 66.0), run("b", 66.0)],
                        "closed-blackout-s5": [run("a", 10.0), run("b", 20.0)],
                        "closed-blackout-s3": [run("a", 75.0), run("b", 55.0)]}, reads_rear=True, null_runs=rerun)
    assert got.null is not None and got.null.mode == "wander" and got.null.passed is None
    assert got.null.wander == pytest.approx(6.0) and (got.null.low, got.null.high) == (64.0, 70.0)
    by = {c.cell: c for c in got.cells}
    assert by["closed-gaussian_blur-s5"].separable_from_null is False  # 66 lies within the null's [64, 70]
    assert by["closed-blackout-s5"].separable_from_null is True
    assert by["closed-clean"].separable_from_null is None


def closed_run(tmp: Path | None = None) -> ClosedRun:
    cells = {"closed-clean": [run("a", 80.0), run("b", 60.0, kinds=("off_road",))],
             "closed-gaussian_blur-s5": [run("a", 75.0), run("b", 50.0)],
             "closed-blackout-s5": [run("a", 20.0), run("b", None)],
             "closed-blackout-s3": [run("a", 80.0), run("b", 60.0, kinds=("off_road",))]}
    payloads = {c: ClosedPayload({}, "p", ClosedRecord(c, *parse_id(c), tuple(rs))) for c, rs in cells.items()}
    return ClosedRun(payloads, RunSettings(loop="closed", closed_seeds=1))


def test_the_section_verifies_and_a_tampered_figure_is_named() -> None:
    prov = Provenance("p", "sha256:p", "sha256:d", "val", "4.0.0")
    cert = seal(closed_only_certificate(prov, closed_run(), flat=0.9))
    assert verify_data(cert) and check_consistency(cert) == []
    section = cert["closed_loop"]
    assert section["loop"] == "closed" and section["null_control"]["passed"] is True
    assert check_section(section, None) == []
    edited = json.loads(json.dumps(cert))
    edited["closed_loop"]["cells"][2]["run_rows"][0][2] = 99.0  # a run's DS: its cell's figures no longer follow
    problems = check_closed_loop(edited)
    assert any(p.startswith("closed_loop.cells.closed-blackout-s5.ds_mean") for p in problems)
    edited = json.loads(json.dumps(cert))
    edited["closed_loop"]["verdict"]["label"] = "not-shown-to-use-cameras"
    assert any(p.startswith("closed_loop.verdict.label") for p in check_closed_loop(edited))


def test_closed_loop_csv_has_one_row_per_run_in_cell_and_run_order() -> None:
    lines = closed_csv_text("p", closed_run()).splitlines()
    assert len(lines) == 1 + 8
    assert lines[1].startswith("p,closed-clean,clean,0,a,0,80.000000,0.800000,complete,2,0,0,0,0,")
    assert lines[6].startswith("p,closed-blackout-s5,blackout,5,b,0,,,unscored,2,0,0,0,0,") and \
        lines[6].endswith(",boom")
