"""The plugin's wiring without pytester: option parsing, cell ids and bit-identity, the payload and the store,
what one cell asserts (on a fake context), and the controller's gathering of cells."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from pytest_drivedegrade import FAMILIES
from pytest_drivedegrade.cells import (
    CellRecord,
    cell_id,
    differing_frames,
    identical_plans,
    rear_cameras,
    run_order,
)
from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.errors import InvalidInput
from pytest_drivedegrade.payload import CellPayload
from pytest_drivedegrade.plugin import checks
from pytest_drivedegrade.plugin.controller import gate, gather
from pytest_drivedegrade.plugin.options import parse
from pytest_drivedegrade.scoring.records import report_order
from pytest_drivedegrade.scoring.verdict import null_control
from pytest_drivedegrade.settings import RunSettings
from pytest_drivedegrade.store import ResultStore

# --- options -------------------------------------------------------------------------------------------------


class FakeConfig:
    """What `options.parse` reads of a pytest Config: command-line values, ini values, the invocation folder."""

    def __init__(self, tmp: Path, cli: dict[str, Any] | None = None, ini: dict[str, Any] | None = None) -> None:
        self.cli, self.ini = cli or {}, ini or {}
        self.invocation_params = SimpleNamespace(dir=tmp)
        self.stash = pytest.Stash()  # where the signing key taken from the environment is kept

    def getoption(self, dest: str, default: Any = None) -> Any:
        return self.cli.get(dest, default)

    def getini(self, dest: str) -> Any:
        return self.ini.get(dest)


def test_options_defaults(tmp_path):
    opts = parse(FakeConfig(tmp_path, {"drivedegrade": "planners/p.py"}))  # type: ignore[arg-type]
    assert opts.planner_path == tmp_path / "planners" / "p.py"
    assert opts.families == tuple(FAMILIES) and opts.severities == (1, 2, 3, 4, 5)
    got = opts.settings
    assert (got.seed, opts.tolerance, got.flat, got.timeout, got.split) == (0, 0.02, 0.95, 60.0, "val")
    assert opts.report_dir == tmp_path / "reports" and got.data is None and opts.baseline_path is None


def test_options_from_ini_and_in_ladder_order(tmp_path):
    opts = parse(FakeConfig(tmp_path, {"drivedegrade": ""},  # type: ignore[arg-type]
                            {"drivedegrade_families": "jpeg, fog,blackout", "drivedegrade_severities": "5,1,5",
                             "drivedegrade_seed": "7"}))
    assert opts.planner_path is None
    assert opts.families == ("jpeg", "fog", "blackout") and opts.severities == (1, 5) and opts.settings.seed == 7


def test_timeout_zero_and_a_millisecond_are_accepted(tmp_path):
    for raw, want in (("0", 0.0), ("0.001", 0.001)):
        assert parse(FakeConfig(tmp_path, {"drivedegrade": "", "drivedegrade_timeout": raw})).settings.timeout == want  # type: ignore[arg-type]


@pytest.mark.parametrize(("dest", "raw", "message"), [
    ("drivedegrade_tolerance", "nan", "--drivedegrade-tolerance: must be a finite number"),
    ("drivedegrade_flat", "inf", "--drivedegrade-flat: must be a finite number"),
    ("drivedegrade_timeout", "nan", "--drivedegrade-timeout: must be a finite number"),
    ("drivedegrade_timeout", "0.0001", "--drivedegrade-timeout: must be 0 (no limit) or at least 0.001 s"),
    ("drivedegrade_tolerance", "1.5", "--drivedegrade-tolerance: must be between 0.0 and 1.0, got 1.5"),
    ("drivedegrade_frames", "0", "--drivedegrade-frames: must be at least 1, got 0"),
    ("drivedegrade_seed", "x", "--drivedegrade-seed: expected an integer, got 'x'"),
    ("drivedegrade_families", "jpeg,fgo", "unknown family 'fgo'; valid families: gaussian_blur"),
    ("drivedegrade_severities", "6", "severity '6' is not one of 1, 2, 3, 4, 5"),
    ("drivedegrade_split", "nope", "unknown split 'nope'"),
    ("drivedegrade_families", " , ", "--drivedegrade-families: is empty"),
])
def test_bad_option_is_a_usage_error_naming_it(tmp_path, dest, raw, message):
    with pytest.raises(pytest.UsageError) as exc:
        parse(FakeConfig(tmp_path, {"drivedegrade": "", dest: raw}))  # type: ignore[arg-type]
    assert message in str(exc.value)


# --- cells and bit-identity ------------------------------------------------------------------------------------


def test_cell_ids_and_run_order():
    assert [cell_id(f, s) for f, s in run_order(["jpeg", "fog"], [1, 5])] == \
        ["clean", "jpeg-s1", "jpeg-s5", "fog-s1", "fog-s5", "ego_noise-s1", "ego_noise-s5", "ego_blind",
         "command_blind", "command_swap", "blind", "null"]
    assert [cell_id(f, s) for f, s in run_order(["jpeg"], [1], ego=False)] == ["clean", "jpeg-s1", "blind", "null"]
    assert sorted(["ego_blind", "fog-s1", "null", "ego_noise-s2", "jpeg-s5", "clean", "blind", "jpeg-s1"],
                  key=lambda c: report_order(*(c.split("-s")[0], int(c.split("-s")[1])) if "-s" in c else (c, 0),
                                             families=("jpeg", "fog"))) == \
        ["clean", "null", "blind", "jpeg-s1", "jpeg-s5", "fog-s1", "ego_noise-s2", "ego_blind"]
    assert rear_cameras() == ("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT") == FAMILIES["blackout"].value(3)


def _plans(n: int = 3) -> np.ndarray:
    return np.arange(n * 12, dtype=np.float64).reshape(n, 6, 2) / 7.0


NAN_A = np.frombuffer(np.uint64(0x7FF8000000000001).tobytes(), np.float64)[0]  # a NaN with another payload


@pytest.mark.parametrize(("edit", "identical", "compared"), [
    (lambda p: p, True, 3),
    (lambda p: p.__setitem__((1, 2, 0), np.nextafter(p[1, 2, 0], np.inf)), False, 3),  # one float step away
    (lambda p: p.__setitem__((2, 0, 1), -0.0), False, 3),  # a signed zero where clean has 0.0
    (lambda p: p.__setitem__((0, 5, 1), np.nan), False, 2),  # NaN where clean has a number: a failed frame
])
def test_identity_at_the_edge_of_equality(edit, identical, compared):
    clean = _plans()
    clean[2, 0, 1] = 0.0
    other = clean.copy()
    edit(other)
    assert identical_plans(clean, other) is identical
    assert len(differing_frames(clean, other)) == (0 if identical else 1)
    control = null_control(clean, other)  # the certificate's control compares the frames with a plan in both
    assert control.frames_compared == compared
    assert control.passed is (identical or compared < 3)  # a failed frame is its cell's failure, not a wander


def test_identity_of_nans_is_by_bit_pattern():
    a, b = _plans(), _plans()
    a[1] = np.nan
    b[1] = np.nan
    assert identical_plans(a, b) and null_control(a, b).passed  # failed frames are the same canonical NaN
    b[1, 0, 0] = NAN_A
    assert not identical_plans(a, b)
    assert differing_frames(a, b).tolist() == [1]
    assert null_control(a, b).passed and null_control(a, b).frames_compared == 2  # frame 1 failed in both


def test_the_cell_check_and_the_certificate_agree_on_signed_zero(tmp_path):
    """The null item passes iff the certificate's null_control passes (they used to disagree on -0.0)."""
    clean = record("clean", _plans())
    clean.plans[0, 0, 0] = 0.0
    null = record("null", clean.plans.copy())
    null.plans[0, 0, 0] = -0.0
    context = FakeContext({"clean": clean, "null": null})
    _, failures = checks.certify(context, FakePlanner(), "null", 0, store=ResultStore(tmp_path), baseline=None,
                                 tolerance=0.02)
    assert failures and "not bit-identical" in failures[0]
    assert null_control(clean.plans, null.plans).passed is False


# --- payload and store -----------------------------------------------------------------------------------------


def record(cell: str, plans: np.ndarray, errors: list[str] | None = None) -> CellRecord:
    n = len(plans)
    family, _, sev = cell.partition("-s")
    return CellRecord(cell, family, int(sev or 0), [f"tok{i}" for i in range(n)], plans,
                      np.abs(plans).sum(axis=-1), np.zeros((n, 6)), np.zeros((n, 6)), np.ones(n), np.full(n, 0.4),
                      seconds={"total": 1.5}, errors=errors or [])


KEY = {"spec_version": "x", "planner_fingerprint": "p", "dataset_fingerprint": "d", "frames_key": "f", "seed": 0}


def test_payload_round_trips_through_builtins_and_json():
    rec = record("jpeg-s3", _plans())
    rec.plans[1] = np.nan
    payload = CellPayload(KEY, "demo", rec, (("cell", "jpeg-s3"), ("l2_avg", 1.25)), resumed=True)
    back = CellPayload.from_builtins(json.loads(json.dumps(payload.to_builtins())))
    assert back.key == KEY and back.planner == "demo" and back.resumed and back.properties == payload.properties
    assert back.cell == "jpeg-s3" and identical_plans(back.record.plans, rec.plans)
    assert back.record.seconds == {"total": 1.5}


def test_store_reuses_only_the_same_run(tmp_path):
    store = ResultStore(tmp_path)
    payload = CellPayload(KEY, "demo", record("fog-s2", _plans()))
    path = store.write(payload)
    assert path == tmp_path / "demo" / "cells" / "fog-s2.json"
    got = store.read("demo", "fog-s2", dict(KEY))
    assert got is not None and identical_plans(got.record.plans, payload.record.plans)
    assert store.read("demo", "fog-s2", {**KEY, "seed": 1}) is None  # another run
    assert store.read("demo", "fog-s3", KEY) is None  # absent
    path.write_text(path.read_text()[:50])  # truncated by a crash
    assert store.read("demo", "fog-s2", KEY) is None
    path.write_text(json.dumps({**payload.to_builtins(), "record": 5}))  # wrong shape
    assert store.read("demo", "fog-s2", KEY) is None


def test_the_payload_travels_as_the_stores_text_and_its_checked_digest_is_kept(tmp_path):
    """A worker sends `to_json` (one string); the controller reads it back with its digest checked and kept, writes
    that very text, and the certificate takes the kept digest: each equal to hashing the record again."""
    from pytest_drivedegrade.payload import RecordDigestMismatch, record_digest, record_digests

    sent = CellPayload(KEY, "demo", record("fog-s2", _plans()))
    assert sent.digest == ""  # a computed payload: hashed when asked
    text = sent.to_json()
    assert text == json.dumps(sent.to_builtins(), allow_nan=True)
    got = CellPayload.from_json(text)
    assert got.digest == record_digest(got.record.to_builtins()) == sent.record_digest_of()
    assert got.to_json() == text and (got.key, got.cell) == (sent.key, sent.cell)
    path = ResultStore(tmp_path).write(got, text)
    assert path.read_text() == text == ResultStore(tmp_path / "again").write(got).read_text()
    tampered = json.loads(text)
    tampered["record"]["plans"][0][0][0] += 1.0
    with pytest.raises(RecordDigestMismatch):
        CellPayload.from_json(json.dumps(tampered))
    with pytest.raises(InvalidInput, match="not JSON"):
        CellPayload.from_json(text[:40])
    # the certificate's record_digests: a known digest taken as it is (a wrong one would show), others hashed
    records = {"fog-s2": got.record, "fog-s3": record("fog-s3", _plans())}
    hashed = {c: record_digest(r.to_builtins()) for c, r in records.items()}
    assert record_digests(records, ["fog-s3", "fog-s2", "jpeg-s1"], {"fog-s2": got.digest}) == {
        "fog-s3": hashed["fog-s3"], "fog-s2": hashed["fog-s2"]}
    assert record_digests(records, ["fog-s2"], {"fog-s2": "f" * 64}) == {"fog-s2": "f" * 64}


def test_a_payload_remade_with_another_record_never_carries_the_old_digest():
    """Only `from_builtins` vouches for a digest: a payload made from a read one with ``dataclasses.replace``
    (another record, say) hashes its own record, so its store file and the certificate's record_digests match
    what it holds, not what it was made from; and no caller can pass a digest in."""
    import dataclasses

    from pytest_drivedegrade.payload import record_digest

    got = CellPayload.from_json(CellPayload(KEY, "demo", record("fog-s2", _plans())).to_json())
    other = record("fog-s2", _plans() + 1.0)
    remade = dataclasses.replace(got, record=other)
    assert got.digest and remade.digest == ""
    assert remade.record_digest_of() == record_digest(other.to_builtins()) != got.digest
    assert json.loads(remade.to_json())["record_digest"] == record_digest(other.to_builtins())
    assert CellPayload.from_json(remade.to_json()).digest == remade.record_digest_of()  # reads back, checked
    with pytest.raises(TypeError):
        CellPayload(KEY, "demo", other, digest="f" * 64)  # type: ignore[call-arg]


# --- what a cell asserts, on a fake context ----------------------------------------------------------------


class FakePlanner:
    cameras = CAMERAS
    name = "fake"

    def predict(self, images: Any, ego: Any, cmd: Any) -> np.ndarray:  # never called by these tests
        raise AssertionError("predict() called")


class FakeContext:
    """The part of RunContext a cell check uses; cells come from `records` and count how often they ran."""

    planner_path = None
    seed = 0

    def __init__(self, records: dict[str, CellRecord], unread: tuple[str, ...] = ()) -> None:
        self.records, self.ran = records, []
        self.unread = unread
        self._clean: CellRecord | None = None

    def run_key(self, planner: Any) -> dict[str, Any]:
        return dict(KEY)

    def planner_info(self, planner: Any) -> Any:
        return SimpleNamespace(unread=self.unread)

    settings = RunSettings()

    def run_cell(self, planner: Any, family: str, severity: int, *, unread: Any = None, span: Any = None) -> Any:
        """A cell's record; with `span` (a replay of the null control's culprit search), its plans on those frames,
        a cell without a record planning as clean does (so a replay reproduces and no camera moves a plan)."""
        if span is not None:
            self.ran.append(f"replay {cell_id(family, severity)} {span} {unread}")
            return SimpleNamespace(plans=self.records.get(cell_id(family, severity), self.records["clean"])
                                   .plans[span[0]:span[1]])
        self.ran.append(cell_id(family, severity))
        return self.records[cell_id(family, severity)]

    def run_seeded_cell(self, planner: Any, family: str, severity: int, clean: Any = None) -> CellRecord:
        return self.run_cell(planner, family, severity)  # one seed: the cell's only run

    def reuses_clean(self, planner: Any, family: str, severity: int) -> bool:
        return False  # these checks are about the cells' records, not about reuse

    def clean_record(self, planner: Any, stored: Any = lambda: None) -> CellRecord:
        if self._clean is None:
            self._clean = stored() or self.run_cell(planner, "clean", 0)
        return self._clean

    def prime_clean(self, planner: Any) -> None:
        """Nothing: the fake's cells are records, not calls, so there is no planner memo to prime (M12)."""


def test_certify_runs_a_cell_once_and_reports_its_properties(tmp_path):
    context = FakeContext({"clean": record("clean", _plans()), "jpeg-s1": record("jpeg-s1", _plans() + 1)})
    payload, failures = checks.certify(context, FakePlanner(), "jpeg", 1, store=ResultStore(tmp_path),
                                       baseline=None, tolerance=0.02)
    assert failures == [] and context.ran == ["jpeg-s1"] and not payload.resumed
    props = dict(payload.properties)
    assert props["cell"] == "jpeg-s1" and props["frames"] == 3 and props["failed_frames"] == 0
    assert props["resumed"] == 0 and props["l2_avg"] == props["l2_avg"]  # a finite number, not "none"


def test_certify_reuses_a_stored_cell_but_not_one_with_failed_frames(tmp_path):
    store = ResultStore(tmp_path)
    stored = record("jpeg-s1", _plans() + 2)
    store.write(CellPayload(KEY, "fake", stored))
    context = FakeContext({"jpeg-s1": record("jpeg-s1", _plans() + 1)})
    payload, _ = checks.certify(context, FakePlanner(), "jpeg", 1, store=store, baseline=None, tolerance=0.02)
    assert payload.resumed and context.ran == [] and identical_plans(payload.record.plans, stored.plans)
    store.write(CellPayload(KEY, "fake", record("jpeg-s1", _plans(), errors=["frame 'tok0': boom"])))
    payload, _ = checks.certify(context, FakePlanner(), "jpeg", 1, store=store, baseline=None, tolerance=0.02)
    assert not payload.resumed and context.ran == ["jpeg-s1"]


def test_certify_conformance_failures_are_listed_five_at_most(tmp_path):
    errors = [f"frame 'tok{i}': predict() raised ValueError: bad" for i in range(7)]
    context = FakeContext({"fog-s2": record("fog-s2", _plans(7), errors=errors)})
    _, failures = checks.certify(context, FakePlanner(), "fog", 2, store=ResultStore(tmp_path), baseline=None,
                                 tolerance=0.02)
    assert failures[0] == "cell fog-s2: 7 of 7 frames failed the planner contract"
    assert failures[1:6] == [f"  {e}" for e in errors[:5]] and failures[6] == "  ... and 2 more"


def test_certify_null_control_of_a_six_camera_planner_names_the_frame(tmp_path):
    clean = record("clean", _plans())
    moved = clean.plans.copy()
    moved[2, 5] += 0.25
    context = FakeContext({"clean": clean, "null": record("null", moved)})
    _, failures = checks.certify(context, FakePlanner(), "null", 0, store=ResultStore(tmp_path), baseline=None,
                                 tolerance=0.02)
    assert "max abs difference 0.25 m" in failures[0] and "first at frame 'tok2'" in failures[0]
    assert "untouched rerun: predict() is not deterministic" in failures[1]


def test_rear_blackout_is_a_null_control_only_for_a_planner_that_does_not_read_the_rear(tmp_path):
    clean = record("clean", _plans())
    moved = record("blackout-s3", clean.plans + 0.5)
    front_only = FakeContext({"clean": clean, "blackout-s3": moved}, unread=rear_cameras())
    reads_all = FakeContext({"clean": clean, "blackout-s3": moved})
    base = {"cells": [{"cell": "blackout-s3", "retention": 0.0}]}  # a baseline makes the check load clean
    for context, fails in ((reads_all, False), (front_only, True)):
        _, failures = checks.certify(context, FakePlanner(), "blackout", 3, store=ResultStore(tmp_path),
                                     baseline=base, tolerance=0.02)
        assert any("null control failed in cell blackout-s3" in f for f in failures) is fails
        # the rear cameras' culprit search: each blacked out alone (the fake's replays plan as clean: none moves)
        assert [r for r in context.ran if r.startswith("replay null")] == \
            ([f"replay null (0, 1) ('{c}',)" for c in rear_cameras()] if fails else [])
    assert "no single unread camera changes it" in failures[-1]


def test_certify_gate_fails_a_regressed_cell_with_both_numbers(tmp_path):
    clean = record("clean", _plans())
    worse = record("fog-s5", _plans() * 2)
    context = FakeContext({"clean": clean, "fog-s5": worse})
    base = {"cells": [{"cell": "fog-s5", "retention": 0.9}]}
    _, failures = checks.certify(context, FakePlanner(), "fog", 5, store=ResultStore(tmp_path), baseline=base,
                                 tolerance=0.02)
    assert failures == ["retention regressed beyond --drivedegrade-tolerance 0.02: fog-s5: retention 0.500 vs "
                        "baseline 0.900 (drop 0.400)"]


# --- the controller's gathering and gate ------------------------------------------------------------------------


def test_gather_joins_received_and_stored_cells_of_the_same_run(tmp_path):
    store = ResultStore(tmp_path)
    store.write(CellPayload(KEY, "demo", record("jpeg-s1", _plans())))
    store.write(CellPayload({**KEY, "seed": 9}, "demo", record("jpeg-s5", _plans())))  # another run's
    received = {"clean": CellPayload(KEY, "demo", record("clean", _plans())),
                "fog-s1": CellPayload({**KEY, "seed": 3}, "demo", record("fog-s1", _plans()))}  # stale: dropped
    run = gather(received, [("clean", 0), ("jpeg", 1), ("jpeg", 5), ("fog", 1), ("null", 0)], store)
    assert run is not None and run.planner == "demo" and dict(run.key) == KEY
    assert sorted(run.payloads) == ["clean", "jpeg-s1"] and run.missing == ["jpeg-s5", "fog-s1", "null"]
    assert gather({}, [("clean", 0)], store) is None


def test_gate_fails_only_on_an_axis_regression():
    cert = {"spec_version": "3", "dataset": {"fingerprint": "d"}, "axes": {"quality": 0.80, "removal": 0.5},
            "cells": [{"cell": "fog-s5", "retention": 0.5}]}
    base = {"spec_version": "3", "dataset": {"fingerprint": "d"}, "axes": {"quality": 0.85, "removal": 0.5},
            "cells": [{"cell": "fog-s5", "retention": 0.9}]}
    lines, failed = gate(cert, base, 0.02)
    assert failed and lines == ["REGRESSION axis:quality: retention 0.800 vs baseline 0.850 (drop 0.050)",
                                "baseline: 1 cell and 1 axis regression(s) beyond tolerance 0.02"]
    assert gate(cert, None, 0.02) == ([], False)
    lines, failed = gate(cert, {**base, "spec_version": "2"}, 0.02)
    assert failed and "spec version" in lines[0]


def test_gate_fails_on_what_a_weak_baseline_leaves_uncompared():
    """Trust case 8: axes null in the baseline, cells it lacks, an incomplete baseline or another planner's
    fail the gate saying what was not compared; partial / any_planner accept them with the same line."""
    cert = {"spec_version": "3", "dataset": {"fingerprint": "d", "frames": 8}, "planner": {"name": "a"},
            "axes": {"quality": 0.8, "removal": 0.5, "mean": 0.65},
            "cells": [{"cell": "fog-s5", "retention": 0.5}, {"cell": "jpeg-s5", "retention": 0.7}]}
    base = {**cert, "axes": {"quality": None, "removal": 0.5, "mean": None},
            "cells": [{"cell": "fog-s5", "retention": 0.5}],
            "completeness": {"complete": False, "missing_cells": ["jpeg-s5"]}}
    lines, failed = gate(cert, base, 0.02)
    assert failed
    assert lines[0] == ("baseline: FAILED: not compared: the baseline run is incomplete (completeness.complete is "
                        "false; 1 cell(s) missing); 1 cell(s) of this run have no retention in the baseline: "
                        "jpeg-s5; axes quality, mean are null in the baseline; certify a complete baseline with "
                        "this run's families and severities, or pass --drivedegrade-baseline-partial to gate on "
                        "what both have")
    lines, failed = gate(cert, base, 0.02, partial=True)
    assert not failed and lines[0].startswith("baseline (--drivedegrade-baseline-partial): not compared: the ")
    lines, failed = gate(cert, {**cert, "planner": {"name": "b"}}, 0.02)
    assert failed and "is of planner 'b' but this run certifies 'a'" in lines[0]
    assert gate(cert, {**cert, "planner": {"name": "b"}}, 0.02, any_planner=True) == (
        ["baseline: 0 cell and 0 axis regression(s) beyond tolerance 0.02"], False)
    lines, failed = gate(cert, {**cert, "dataset": {"fingerprint": "d", "frames": 6}}, 0.02)
    assert failed and "scored frames: baseline 6, this run 8 (--drivedegrade-frames)" in lines[0]


@pytest.mark.parametrize("forge", ["digest of another record", "digest removed", "digest null", "record not an object",
                                   "record a list", "digest rewritten to match an edit"])
def test_a_forged_payload_text_is_refused_or_carries_the_digest_of_what_it_holds(forge):
    """A hostile store file or worker text: a digest that is not its record's, none, or a record that is not an
    object is refused with the project's own error (never a bare TypeError, never a payload vouching for a digest
    it does not hold); a digest rewritten to match an edited record reads back, and then the digest it carries is
    that record's own, so the certificate's record_digests seal what is there and `reproduce` compares it."""
    from pytest_drivedegrade.payload import RecordDigestMismatch, record_digest

    data = json.loads(CellPayload(KEY, "demo", record("fog-s2", _plans())).to_json())
    other = CellPayload(KEY, "demo", record("fog-s2", _plans() + 1.0)).to_builtins()
    if forge == "digest of another record":
        data["record_digest"] = other["record_digest"]
    elif forge == "digest removed":
        del data["record_digest"]
    elif forge == "digest null":
        data["record_digest"] = None
    elif forge == "record not an object":
        data["record"] = 5
    elif forge == "record a list":
        data["record"] = [data["record"]]
    else:
        data["record"]["plans"][0][0][0] += 1.0
        data["record_digest"] = record_digest(data["record"])
        got = CellPayload.from_json(json.dumps(data))
        assert got.digest == record_digest(got.record.to_builtins()) == got.record_digest_of()
        assert got.record.plans[0][0][0] == data["record"]["plans"][0][0][0]
        return
    with pytest.raises(InvalidInput) as err:
        CellPayload.from_json(json.dumps(data))
    if forge in ("digest of another record", "digest removed", "digest null"):
        assert isinstance(err.value, RecordDigestMismatch) and "fog-s2" in str(err.value)
