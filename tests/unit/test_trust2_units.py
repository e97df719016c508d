"""Trust issue 20, medium item M4 (unit level): a failed null control makes the verdict undetermined, and
verify's arithmetic (`consistency.check_verdict`) recomputes the same."""

from __future__ import annotations

from test_analysis import GROUPS, synthetic_run

from pytest_drivedegrade.certificate.consistency import check_verdict
from pytest_drivedegrade.scoring.analyse import analyse_run
from pytest_drivedegrade.scoring.records import RunAnalysis


def _cert(res: RunAnalysis, **verdict: object) -> dict:
    """The certificate sections `check_verdict` reads, from an analysis (the verdict's fields overridden)."""
    cells = [{"cell": s.cell, "conformance_errors": 0, "data_errors": 0} for s in res.summaries]
    assert res.null_control is not None
    return {"verdict": {**res.verdict.to_builtins(), **verdict}, "settings": res.settings,
            "axes": res.axes.to_builtins(), "null_control": res.null_control.to_builtins(), "cells": cells}


def res_passed(res: RunAnalysis) -> bool:
    return res.null_control is not None and res.null_control.passed is True


def test_m4_a_failed_null_control_makes_the_verdict_undetermined_and_verify_agrees() -> None:
    clean_run = analyse_run(synthetic_run(8)[0], groups=GROUPS, n_resamples=50)
    assert clean_run.null_control is not None and res_passed(clean_run) and clean_run.verdict.label == "camera-reliant"
    res = analyse_run(synthetic_run(8, null_wander=0.5)[0], groups=GROUPS, n_resamples=50)
    v = res.verdict.to_builtins()
    assert res.null_control is not None and res.null_control.passed is False
    assert v["label"] == "undetermined" and v["case"] == "null-control-failed"
    assert v["computed_label"] == "camera-reliant" and v["ego_label"] == "undetermined"
    assert v["reason"].startswith("the null control failed (plans moved by up to 0.707107 m")
    assert v["text"].startswith("Undetermined: the null control failed")
    cert = _cert(res)
    assert check_verdict(cert, cert["cells"]) == []
    # the verdict a run before M4 sealed: the axes' label over a failed null control, which verify now rejects
    old = _cert(res, label="camera-reliant", case="both-below")
    problems = check_verdict(old, old["cells"])
    assert problems == ["verdict.label: certificate says 'camera-reliant', but its null control failed, which "
                        "makes it 'undetermined'"]
    # a passed null control leaves the verdict to the axes, and check_verdict still recomputes it
    fine = _cert(clean_run)
    assert check_verdict(fine, fine["cells"]) == []
