"""Reproduction of closed-loop cells (SPEC sections 11 and 13): which closed cells a rerun drives, its command
line, and the comparison of a rerun cell with the certificate's ``closed_loop`` section (record digest, then run
by run, naming route, seed and the step where the paths part)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.certificate import reproduce as rp
from pytest_drivedegrade.certificate import reproduce_closed as rc
from pytest_drivedegrade.closedloop.analysis import RunRow
from pytest_drivedegrade.closedloop.cells import ClosedPayload, ClosedRecord
from pytest_drivedegrade.closedloop.results import Infraction, RunResult
from pytest_drivedegrade.errors import DriveDegradeError

CLOSED = ["closed-clean", "closed-gaussian_blur-s3", "closed-gaussian_blur-s5", "closed-motion_blur-s3",
          "closed-motion_blur-s5", "closed-blackout-s5", "closed-blackout-s3"]
DIGEST = "ab" * 32


def a_run(route: str = "scene-0001", seed: int = 0, ds: float = 60.0, bend: float = 0.0) -> RunResult:
    """A run of 21 poses at 10 Hz along x; `bend` moves the poses from index 11 on (driven by planner step 2
    at 2 Hz: poses 11..15 follow the plan of step 2)."""
    trace = np.stack([np.arange(21.0), np.zeros(21), np.zeros(21)], axis=1)
    trace[11:, 1] += bend
    return RunResult(route, seed, ds, ds / 100.0, "scene_end", (Infraction("collision_vehicle", 1, 7, "car"),),
                     trace, steps=4)


def certificate(record: ClosedRecord, hz: int = 2) -> dict[str, object]:
    rows = [RunRow.of(r).to_list() for r in record.runs]
    return {"cells": [], "closed_loop": {"loop": "closed", "closed_hz": hz, "record_digests": {
        record.cell: record.digest()}, "cells": [{"cell": record.cell, "run_rows": rows}]}}


def test_closed_cells_are_sampled_like_open_ones_with_closed_clean_always() -> None:
    got = rp.sample_cells(CLOSED, DIGEST, 1, "0", rc.CLOSED_ALWAYS)
    assert got[0] == "closed-clean" and len(got) == 2
    assert got == rp.sample_cells(CLOSED[::-1], DIGEST, 1, "0", rc.CLOSED_ALWAYS)[::-1]
    assert rp.sample_cells(CLOSED, DIGEST, 0, "0", rc.CLOSED_ALWAYS) == ["closed-clean"]
    assert rp.sample_cells(CLOSED, DIGEST, 9, "0", rc.CLOSED_ALWAYS) == CLOSED
    assert len({tuple(rp.sample_cells(CLOSED, DIGEST, 1, str(s), rc.CLOSED_ALWAYS)) for s in range(30)}) > 3


def test_the_rerun_collects_exactly_the_sampled_closed_cells() -> None:
    record = ClosedRecord("closed-clean", "clean", 0, (a_run(),))
    cert = {**certificate(record), "dataset": {}, "settings": {}}
    argv = rp.rerun_argv(cert, Path("p.py"), [], Path("out"), None, ["closed-clean", "closed-blackout-s5"])
    text = " ".join(argv)
    assert "--drivedegrade-loop closed --drivedegrade-closed-cells clean,blackout-s5" in text
    assert argv[-2:] == ["-k", "closed-clean or closed-blackout-s5"]
    cert["cells"] = [{"cell": "clean", "family": "clean", "severity": 0},
                     {"cell": "null", "family": "null", "severity": 3}]
    both = rp.rerun_argv(cert, Path("p.py"), ["clean", "null"], Path("out"), None, ["closed-clean"])
    assert "--drivedegrade-loop both --drivedegrade-closed-cells clean" in " ".join(both)
    assert both[-1] == "clean or null or closed-clean"
    only_open = " ".join(rp.rerun_argv(cert, Path("p.py"), ["clean"], Path("out"), None))
    assert only_open.endswith("--drivedegrade-loop open -k clean")  # the last --drivedegrade-loop wins


def test_loops_default_to_the_certificates_and_refuse_one_it_lacks() -> None:
    closed_only = certificate(ClosedRecord("closed-clean", "clean", 0, (a_run(),)))
    assert rc.loops(closed_only, None) == (False, True) and rc.loops(closed_only, "closed") == (False, True)
    with pytest.raises(DriveDegradeError, match=r"--loop both: the certificate has no open-loop cell to rerun "
                                                r"\(it was made with --drivedegrade-loop closed\)"):
        rc.loops(closed_only, "both")
    open_only = {"cells": [{"cell": "clean"}], "settings": {}}
    assert rc.loops(open_only, None) == (True, False)
    with pytest.raises(DriveDegradeError, match="no closed-loop cell"):
        rc.loops(open_only, "closed")


def test_compare_closed_names_route_seed_field_and_step(tmp_path: Path) -> None:
    record = ClosedRecord("closed-blackout-s5", "blackout", 5, (a_run(), a_run("scene-0002", 1, 80.0)))
    cert = certificate(record)
    path = tmp_path / "certificate.json"
    assert rc.compare_closed(cert, path, record) == "identical"
    # another DS on the second run, same path
    other = replace(record, runs=(record.runs[0], a_run("scene-0002", 1, 79.5)))
    assert rc.compare_closed(cert, path, other) == \
        "DIFFERENT (route scene-0002 seed 1: DS 79.5 (certified 80.0), completion 0.795 (certified 0.8))"
    # a path that parts at pose 11: planner step (11 - 1) // 5 = 2, found from the certified cell file
    bent = replace(record, runs=(a_run(bend=1e-12), record.runs[1]))
    assert rc.compare_closed(cert, path, bent).startswith("DIFFERENT (route scene-0001 seed 0: the path differs "
                                                          "(trace digest ")
    (tmp_path / "cells").mkdir()
    payload = ClosedPayload({}, "driver", record)
    (tmp_path / "cells" / "closed-blackout-s5.json").write_text(json.dumps(payload.to_builtins()))
    assert rc.compare_closed(cert, path, bent) == "DIFFERENT (route scene-0001 seed 0: the path parts at step 2)"
    assert rc.compare_closed(certificate(record, hz=10), path, bent) == \
        "DIFFERENT (route scene-0001 seed 0: the path parts at step 10)"
    # one run fewer; an infraction at another step (the rows agree, the record does not)
    assert rc.compare_closed(cert, path, replace(record, runs=record.runs[:1])) == \
        "DIFFERENT (the rerun drove 1 run(s), the certificate has 2)"
    later = replace(record.runs[0], infractions=(Infraction("collision_vehicle", 2, 12, "car"),))
    got = rc.compare_closed(cert, path, replace(record, runs=(later, record.runs[1])))
    assert got.startswith("DIFFERENT (every run's DS, completion, end, trace and infraction counts are as "
                          "certified, but the record is not")
