"""Issue 37's low findings that are checked at the unit level (each fails on the code before the issue)."""

from __future__ import annotations

from pytest_drivedegrade.certificate.consistency import check_null_control


def _cells(**digests: object) -> list[dict]:
    return [{"cell": name, "plans_digest": d, "frames": 4, "conformance_errors": 0, "data_errors": 0}
            for name, d in digests.items()]


def test_deleting_a_plans_digest_no_longer_skips_the_null_control_check() -> None:
    """A failed null control (null's plans differ from clean's) recorded as passed is caught by the digests; with
    null's digest deleted the check was skipped and the forged `passed` stood. Older certificates, which record no
    digest at all, are read as before."""
    cert = {"null_control": {"passed": True, "frames_changed": 0}}
    differ = _cells(clean="ab" * 32, null="cd" * 32, **{"jpeg-s1": "ef" * 32})
    assert any("the control failed" in p for p in check_null_control(cert, differ))
    deleted = [dict(c) for c in differ]
    del deleted[1]["plans_digest"]
    problems = check_null_control(cert, deleted)
    assert problems == ["cells.null.plans_digest: missing (or not a string) in a certificate that records plans "
                        "digests, so the null control cannot be checked"]
    nulled = [dict(c, plans_digest=None) if c["cell"] == "clean" else c for c in differ]
    assert [p.split(":")[0] for p in check_null_control(cert, nulled)] == ["cells.clean.plans_digest"]
    sealed = [{k: v for k, v in c.items() if k != "plans_digest"} for c in differ]
    assert check_null_control(dict(cert, record_digests={}), sealed)  # the seal says digests were recorded
    assert check_null_control(cert, sealed) == []  # an older certificate: nothing recorded, nothing to check
