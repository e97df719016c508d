"""Adaptive certification from records (`scoring.sequential`) and its verify (`certificate.adaptive_check`):
the unit plan, where the stopping rule stops, threshold intervals under skipped severities, the section, and
verify catching a tampered stop. Known answers on synthetic records; no planner runs here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.cells import FRAME_ARRAYS, CellRecord
from pytest_drivedegrade.certificate.adaptive_check import check_adaptive
from pytest_drivedegrade.certificate.seal import seal
from pytest_drivedegrade.data.frame import Command, EgoStatus, Frame
from pytest_drivedegrade.payload import CellPayload, record_digest
from pytest_drivedegrade.scoring import sequential as sq
from pytest_drivedegrade.scoring.verdict import FamilyGroups


def frames(scenes: list[int]) -> list[Frame]:
    ego = EgoStatus((0.0, 0.0), (0.0, 0.0), 0.0)
    return [Frame(f"f{i}-{j}", f"s{i}", j, {}, ego, Command.STRAIGHT, np.zeros((6, 2)), np.ones(6, bool))
            for i, n in enumerate(scenes) for j in range(n)]


def test_the_unit_plan_round_trips_and_its_draw_order_is_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sq, "SCENE_UNITS_BELOW", 3)  # three scenes: windows
    plan = sq.UnitPlan.of(frames([20, 9, 3]), seed=4)
    assert plan.kind == "windows"
    assert plan.population == 3 + 2 + 1  # 20 -> 8, 8, 4; 9 -> 8, 1; 3 -> 3
    back = sq.UnitPlan.from_builtins(plan.to_builtins())
    assert [u.scored for u in back.units] == [u.scored for u in plan.units]
    assert [u.warmup for u in back.units] == [u.warmup for u in plan.units]
    assert back.draw_order_problem() is None
    swapped = sq.UnitPlan((plan.units[1], plan.units[0], *plan.units[2:]), plan.seed)
    assert "not drawn in the order seed 4 gives" in (swapped.draw_order_problem() or "")
    assert plan.passes(plan.population, warm=False) == 32
    assert plan.passes(plan.population, warm=True) == 32 + 2 * 3  # three windows start after a warm-up
    single = sq.UnitPlan.of(frames([20, 9, 3]), seed=4, temporal=False)
    assert single.population == 32 and single.window == 1
    assert [len(u.warmup) for u in sorted(single.units, key=lambda u: u.scored)][:3] == [0, 1, 2]  # for history
    assert sq.UnitPlan.matching(frames([20, 9, 3]), 4, 32).window == 1
    assert sq.UnitPlan.matching(frames([20, 9, 3]), 4, 6).window == 8
    assert sq.UnitPlan.from_builtins(single.to_builtins()).window == 1


def test_a_planner_with_reset_gets_whole_scenes_when_the_run_has_few() -> None:
    """Few scenes: each unit is a scene from its start (exact for any memory), no warm-up, scenes weighed by
    their frames (the figure divides by the longest scene)."""
    plan = sq.UnitPlan.of(frames([20, 9, 3]), seed=4)
    assert (plan.kind, plan.population, plan.window) == ("scenes", 3, 20)
    assert sorted(len(u.scored) for u in plan.units) == [3, 9, 20] and not any(u.warmup for u in plan.units)
    back = sq.UnitPlan.from_builtins(plan.to_builtins())
    assert back.kind == "scenes" and [u.scored for u in back.units] == [u.scored for u in plan.units]
    assert sq.UnitPlan.matching(frames([20, 9, 3]), 4, 3).kind == "scenes"
    assert sq.UnitPlan.of(frames([20, 9, 3]), seed=4, temporal=False).kind == "frames"


def test_a_cell_equal_to_clean_settles_above_both_thresholds_on_the_betting_bound() -> None:
    """Betting, nonasymptotic: a cell equal to clean (paired differences 0.1 a_u, in a range of about 9.5 m)
    settles 0.75 after 118 units and 0.9 after 256 of 400 at alpha 0.01; the asymptotic sequence settled both at
    unit 10 (issue 36: valid only as the units grow)."""
    rng = np.random.default_rng(0)
    rng.uniform(0.5, 1.5, 40)
    a = rng.uniform(0.5, 1.5, 400)
    got = sq.stop_at(a[:256], a[:256], (0.9, 0.75), population=400, alpha=0.01)
    assert got is not None and got.reason == "settled" and got.units == 256
    assert [(d.side, d.units, d.how) for d in got.decisions] == [("above", 256, "evidence"), ("above", 118, "evidence")]
    assert sq.stop_at(a[:255], a[:255], (0.9, 0.75), population=400, alpha=0.01) is None
    assert sq.METHOD == "betting"


def test_a_cell_that_ran_every_unit_reports_the_population_value_exactly() -> None:
    """Issue 36: a cell whose units all ran reports the full run's retention (the interval holds it, to 1e-4
    rounded outwards) and decides from it; nothing is clipped, even with units beyond the stated bound."""
    rng = np.random.default_rng(5)
    fr = frames([30, 30])
    plan = sq.UnitPlan.of(fr, seed=1, temporal=False)
    clean = rng.uniform(0.3, 1.0, len(fr))
    cell = clean / 0.7536
    cell[:3] = [9.0, 12.0, 7.5]  # three frames beyond the 5 m bound (the old clip moved the answer)
    truth = float(np.sum(clean) / np.sum(cell))
    got = sq.cell_outcome(plan, clean, record("fog-s4", "fog", 4, cell, plan.population), (0.9, 0.75), alpha=1e-3)
    assert got.interval is not None and got.interval[0] <= truth <= got.interval[1]
    assert got.interval[1] - got.interval[0] <= 2.01e-4 and got.beyond == 3
    assert [d.side for d in got.decisions] == ["below", "below" if truth < 0.75 else "above"]
    assert all(d.how == "exhausted" and d.units == plan.population for d in got.decisions)


def test_a_unit_beyond_the_bound_makes_its_cell_run_every_unit() -> None:
    """The bound is checked, never clipped: once a unit beyond it is seen, no evidence settles the cell."""
    rng = np.random.default_rng(2)
    a = rng.uniform(0.5, 1.5, 200)
    b = a / 0.5
    assert sq.stop_at(a[:100], b[:100], (0.9, 0.75), population=200, alpha=0.01) is not None  # fine without
    b[0] = 6.0
    for k in (50, 100, 199):
        assert sq.stop_at(a[:k], b[:k], (0.9, 0.75), population=200, alpha=0.01) is None
    assert sq.stop_at(a, b, (0.9, 0.75), population=200, alpha=0.01).reason == "data"  # type: ignore[union-attr]


def test_a_cell_on_the_line_runs_out_of_data_and_the_answer_is_exact() -> None:
    rng = np.random.default_rng(3)
    a = rng.uniform(0.5, 1.5, 12)
    b = a / 0.9 * rng.lognormal(0, 0.3, 12)
    b *= a.sum() / 0.9 / b.sum()  # retention exactly 0.90: "not below", known only when every unit is in
    assert sq.stop_at(a[:11], b[:11], (0.9,), population=12, alpha=0.01) is None
    got = sq.stop_at(a, b, (0.9,), population=12, alpha=0.01)
    assert got is not None and got.reason == "data" and got.units == 12 and got.decisions[0].side == "above"


def record(cell: str, family: str, severity: int, l2: np.ndarray, units: int | None) -> CellRecord:
    """A record whose per-frame L2 (every horizon step) is `l2` (NaN: not run)."""
    n = len(l2)
    arrays = {a.name: a.empty(n) for a in FRAME_ARRAYS}
    arrays["l2"] = np.repeat(l2[:, None], arrays["l2"].shape[1], axis=1)
    return CellRecord.of_arrays(cell, family, severity, [f"t{i}" for i in range(n)], arrays, units=units,
                                passes=units)


def run_rule(plan: sq.UnitPlan, clean: np.ndarray, cell: np.ndarray, levels: tuple[float, ...],
             alpha: float) -> int:
    """The plugin's loop: units one at a time until `stop_at` says stop."""
    for k in range(1, plan.population + 1):
        a, b = sq.unit_sums(plan, clean, cell, k)
        if sq.stop_at(a, b, levels, population=plan.population, alpha=alpha) is not None:
            return k
    raise AssertionError("the rule never stopped")


@settings(max_examples=25, deadline=None)
@given(st.floats(0.5, 1.2), st.integers(0, 10**6))
def test_the_recomputed_stop_is_the_loops_stop(r: float, seed: int) -> None:
    """`cell_outcome` (one call on the stored prefix, what verify runs) stops where the unit-by-unit loop did."""
    rng = np.random.default_rng(seed)
    fr = frames([40, 40, 24])
    plan = sq.UnitPlan.of(fr, seed=seed % 7)
    clean = rng.uniform(0.2, 1.5, len(fr))
    cell = clean / r * rng.lognormal(0, 0.1, len(fr))
    k = run_rule(plan, clean, cell, (0.9, 0.75), 0.01)
    ran = {i for u in plan.units[:k] for i in u.scored}
    stored = np.where([i in ran for i in range(len(fr))], cell, np.nan)
    got = sq.cell_outcome(plan, clean, record("x-s1", "x", 1, stored, k), (0.9, 0.75), alpha=0.01)
    assert got.units == k and got.reason in ("settled", "data")
    assert got.interval is not None and got.interval[0] <= got.interval[1]


def test_threshold_intervals_bound_skipped_severities_by_monotone_retention() -> None:
    d = sq.Outcome(1, "settled", (), None)
    out = {5: sq.Outcome(5, "settled", (), (0.70, 0.80)), 3: sq.Outcome(5, "settled", (), (0.92, 0.96)),
           4: sq.Outcome(5, "settled", (), (0.85, 0.88)), 1: d}
    spans = sq.threshold_spans({s: o for s, o in out.items() if o.interval is not None})
    # low curve: S1, S2 (skipped) 0.92, S3 0.92, S4 0.85, S5 0.70 -> crosses 0.90 between S3 and S4
    assert spans["s10"][0] == pytest.approx(3 + 0.02 / 0.07)
    # high curve: S1..S3 unbounded above (4.0), S3 0.96, S4 0.88 -> 3 + 0.06 / 0.08
    assert spans["s10"][1] == pytest.approx(3 + 0.06 / 0.08)
    assert spans["s25"][0] == pytest.approx(4 + 0.10 / 0.15) and spans["s25"][1] is None


def test_every_severity_is_visited_so_a_planner_bad_only_at_s4_is_seen() -> None:
    """Issue 36: skipping severities assumed monotone retention, and a planner bad only at S4 was certified "never
    crosses". Now no severity is skipped (S5 first, then downwards), and the violation is reported."""
    def outcome(side: str, span: tuple[float, float]) -> sq.Outcome:
        return sq.Outcome(10, "settled", tuple(sq.Settlement(c, side, 10, "evidence") for c in (0.9, 0.75)), span)

    above, below = outcome("above", (0.97, 0.99)), outcome("below", (0.3, 0.4))
    seen: dict[int, sq.Outcome] = {}
    truth = {5: above, 4: below, 3: above, 2: above, 1: above}
    while (nxt := sq.family_plan(seen)[0]) is not None:
        seen[nxt] = truth[nxt]
    assert sorted(seen) == [1, 2, 3, 4, 5]
    _, skipped, assumption, violated = sq.family_plan(seen)
    assert skipped == () and assumption == "" and any("S4" in v and "S5" in v for v in violated)
    assert sq.threshold_spans(seen)["s10"][0] is not None  # crosses: at S4, not "never"


def synthetic_run(tmp_path: Path) -> tuple[dict[str, object], Path]:
    """A sealed adaptive certificate of one family (jpeg) plus clean, with its cells/ folder."""
    rng = np.random.default_rng(1)
    fr = frames([100, 100, 100])
    plan = sq.UnitPlan.drawn(fr, 0, "fp", None, temporal=False, scenes=False)  # single frames
    clean_m = rng.uniform(0.3, 1.0, len(fr))
    recs = {"clean": record("clean", "clean", 0, clean_m, plan.population)}
    for s in range(1, 6):  # every severity visited (none skipped), each stopping on its own decisions
        cell = clean_m / (0.99 - 0.12 * s) * rng.lognormal(0, 0.02, len(fr))
        k = run_rule(plan, clean_m, cell, sq.levels_of("jpeg", s, ("jpeg",), 0.95), sq.alpha_side(0.05, CELLS))
        ran = {i for u in plan.units[:k] for i in u.scored}
        recs[f"jpeg-s{s}"] = record(f"jpeg-s{s}", "jpeg", s,
                                    np.where([i in ran for i in range(len(fr))], cell, np.nan), k)
    section = sq.adaptive_section(recs, plan, CELLS, alpha=0.05, flat=0.95, quality=("jpeg",), removal="blackout")
    folder = tmp_path / "cells"
    folder.mkdir()
    for c, r in recs.items():
        (folder / f"{c}.json").write_text(json.dumps(CellPayload({}, "p", r, ()).to_builtins()))
    cert = {"cells": [{"cell": c, "family": r.family, "severity": r.severity} for c, r in recs.items()],
            "settings": {"flat": 0.95}, "adaptive": section, "planner": {"fingerprint": "fp"},
            "record_digests": {c: record_digest(r.to_builtins()) for c, r in recs.items()}}
    return seal(cert), folder


CELLS = [("clean", 0), *(("jpeg", s) for s in range(1, 6))]
GROUPS = FamilyGroups(quality=("jpeg",), core=("jpeg",))


def test_verify_recomputes_the_section_and_catches_a_tampered_stop(tmp_path: Path) -> None:
    cert, folder = synthetic_run(tmp_path)
    section = cert["adaptive"]
    assert isinstance(section, dict)
    assert section["cells"]["jpeg-s5"]["stop"] == "settled" and section["families"]["jpeg"]["skipped"] == []
    assert section["families"]["jpeg"]["visited"] == [1, 2, 3, 4, 5]
    assert "label is wrong with probability at most 0.05" in str(section["guarantee"])
    assert check_adaptive(cert, folder, GROUPS) == []
    tampered = json.loads(json.dumps(cert))
    tampered["adaptive"]["cells"]["jpeg-s5"]["units"] = 3
    problems = check_adaptive(seal(tampered), folder, GROUPS)
    assert any("jpeg-s5.units: certificate says 3" in p for p in problems)
    assert check_adaptive(cert, tmp_path / "nowhere")[0].startswith("adaptive: no cells/ folder")


def test_verify_catches_a_cell_stopped_before_its_rule_settled(tmp_path: Path) -> None:
    cert, folder = synthetic_run(tmp_path)
    path = folder / "jpeg-s5.json"
    payload = CellPayload.from_builtins(json.loads(path.read_text()))
    units = int(payload.record.units or 0)
    short = payload.record
    short.units = units - 1  # the cell claims to have stopped a unit earlier
    path.write_text(json.dumps(CellPayload({}, "p", short, ()).to_builtins()))
    forged = json.loads(json.dumps(cert))
    forged["record_digests"]["jpeg-s5"] = record_digest(short.to_builtins())
    problems = check_adaptive(seal(forged), folder, GROUPS)
    assert any("jpeg-s5: stopped after" in p and "open" in p for p in problems)
    assert any("outside" in p for p in problems)


def test_the_draw_order_follows_the_planners_fingerprint_and_the_baseline_and_verify_checks_it(
        tmp_path: Path) -> None:
    """Issue 36: the order followed the corruption seed alone (0 by default), so whoever wrote the planner knew
    which units a gate reads first. Now the seed hashes the planner's fingerprint and the baseline's digest, the
    plan records both, and verify recomputes it."""
    fr = frames([40, 40, 40])
    one = sq.UnitPlan.drawn(fr, 0, "fp-a", None, temporal=False, scenes=False)
    assert one.seed == sq.draw_seed(0, "fp-a") and one.seed != 0
    others = [sq.UnitPlan.drawn(fr, 0, fp, base, temporal=False, scenes=False)
              for fp, base in (("fp-b", None), ("fp-a", "digest-1"), ("fp-a", "digest-2"))]
    firsts = {tuple(u.scored for u in p.units[:10]) for p in (one, *others)}
    assert len(firsts) == 4  # each candidate / baseline draws its own order
    assert sq.UnitPlan.from_builtins(one.to_builtins()).seed_problem("fp-a", None) is None
    assert "planner fingerprint fp-a" in (one.seed_problem("fp-b", None) or "")
    cert, folder = synthetic_run(tmp_path)
    forged = json.loads(json.dumps(cert))
    forged["adaptive"]["plan"]["draw"]["planner_fingerprint"] = "someone-else"
    assert any("draw seed came from planner fingerprint someone-else" in p
               for p in check_adaptive(seal(forged), folder, GROUPS))


def test_a_context_planner_without_reset_gets_whole_scenes() -> None:
    """Issue 36: it got single frames, which cut its memory (frame_dropout S5 1.031 against the full run's 0.439)."""
    fr = frames([40, 35, 30])
    plan = sq.UnitPlan.drawn(fr, 0, "fp", None, temporal=False, scenes=True)
    assert plan.kind == "scenes" and sorted(len(u.scored) for u in plan.units) == [30, 35, 40]
    assert sq.UnitPlan.matching(fr, 0, 3, "fp").kind == "scenes"
    assert sq.UnitPlan.matching(fr, 0, 105, "fp").kind == "frames"


def test_a_gate_runs_certificate_marks_its_partial_cells_and_its_point_figures(tmp_path: Path) -> None:
    """Issue 36: a gate run's axes and "stable" verdict were computed from the few units the gate needed (removal
    0.709 against the full run's 0.919) without saying so. Now the section lists the partial cells, its guarantee
    says the point figures are not certified, and the terminal's line says it too."""
    rng = np.random.default_rng(3)
    fr = frames([100, 100])
    plan = sq.UnitPlan.drawn(fr, 0, "fp", "base", temporal=False, scenes=False)
    clean = rng.uniform(0.3, 1.0, len(fr))
    ran = {i for u in plan.units[:12] for i in u.scored}
    cut = np.where([i in ran for i in range(len(fr))], clean / 0.93, np.nan)  # 12 units: nothing settled yet
    recs = {"clean": record("clean", "clean", 0, clean, plan.population),
            **{f"jpeg-s{s}": record(f"jpeg-s{s}", "jpeg", s, cut, 12) for s in range(1, 6)}}
    section = sq.adaptive_section(recs, plan, CELLS, alpha=0.05, flat=0.95, quality=("jpeg",), removal="blackout",
                                  rule="gate")
    assert section["partial_cells"] == [f"jpeg-s{s}" for s in range(1, 6)]
    assert "NOT certified" in str(section["guarantee"]) and "5 cell(s) are partial" in str(section["guarantee"])
    assert "5 partial cell(s)" in sq.summary_line(section)
    whole = sq.adaptive_section(recs, plan, CELLS, alpha=0.05, flat=0.95, quality=("jpeg",), removal="blackout")
    assert "partial_cells" not in whole  # a certify run's cells stop only when settled: verify checks that


def test_the_union_bound_counts_stopping_cells() -> None:
    cells = [("clean", 0), ("null", 0), ("blind", 0), *(("jpeg", s) for s in range(1, 6))]
    assert sq.stopping_cells(cells) == 6
    assert sq.alpha_side(0.05, cells) == pytest.approx(0.05 / 12)
    assert sq.levels_of("jpeg", 5, ("jpeg",), 0.95) == (0.9, 0.75, 0.95)
    assert sq.levels_of("jpeg", 4, ("jpeg",), 0.95) == (0.9, 0.75)
    assert sq.levels_of("ego_noise", 5, ("jpeg",), 0.95) == (0.95,) and sq.levels_of("ego_blind", 0, (), 0.9) == (0.9,)
    assert sq.levels_of("ego_noise", 3, ("jpeg",), 0.95) == () and sq.levels_of("blind", 0, ("jpeg",), 0.95) == ()
    assert FamilyGroups.from_registry().removal == "blackout"
