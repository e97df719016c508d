"""Issue 42: the paper's tables as data (tests/data/paper/), analysed by `drivedegrade analyse`, and every label,
gap and retention they print compared with the suite's arithmetic. Where the two differ, the test pins which
and why: a printed gap computed from unrounded axes (off by 0.001), DrivoR's blackout S3 at 1.001 (within the
rounding of the printed PDMS, but a null control the table's own EP fails), and the threshold table's ordering
claim (contradicted by ten pairs of its own entries).
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from pytest_drivedegrade.foreign.table import read_table
from pytest_drivedegrade.report.table_import import analyse_model

PAPER = Path(__file__).resolve().parents[1] / "data" / "paper"
#: tab:visrel as printed: clean L2, mean, quality, blackout, dropout, gap; and the label the text gives.
VISREL = {
    "UniAD": (0.942, 0.75, 0.739, 0.680, 0.801, 0.059, "camera-reliant"),
    "DiffusionDrive": (1.065, 0.78, 0.777, 0.505, 0.933, 0.271, "camera-reliant"),
    "SparseDrive": (0.608, 0.84, 0.831, 0.645, 0.955, 0.186, "camera-reliant"),
    "GenAD": (0.908, 0.91, 0.915, 0.752, 0.948, 0.163, "camera-reliant"),
    "VAD": (0.969, 0.97, 0.969, 0.923, 0.999, 0.047, "quality-insensitive"),
    "LAW": (0.524, 0.99, 1.003, 0.903, 0.940, 0.099, "quality-insensitive"),
    "OpenDriveVLA": (0.677, 0.95, 0.943, 0.964, 0.953, -0.021, "camera-reliant"),
    "ego-only MLP": (0.731, 1.00, 1.000, 1.000, 1.000, 0.000, "not-shown-to-use-cameras"),
}
FLOOR = "ego-only MLP"


@pytest.fixture(scope="module")
def visrel():
    table = read_table(PAPER / "visrel.csv")
    return {m: analyse_model(table, m, floor_l2=None if m == FLOOR else VISREL[FLOOR][0]) for m in VISREL}


@pytest.fixture(scope="module")
def pdms():
    table = read_table(PAPER / "pdms.csv")
    return {m: analyse_model(table, m, null_identical=True) for m in table.models()}


def test_every_label_the_paper_gives(visrel):
    for model, (*_, label) in VISREL.items():
        assert visrel[model].analysis.verdict.label == label, model
    # OpenDriveVLA: below the flat line on quality, flat on removal: the one negative gap, flagged
    vla = visrel["OpenDriveVLA"].analysis.verdict
    assert vla.case == "quality-only" and vla.negative_gap and "Negative gap (-0.021)" in vla.text
    assert [m for m in VISREL if visrel[m].analysis.verdict.negative_gap] == ["OpenDriveVLA"]


def test_axes_and_gaps_against_the_printed_columns(visrel):
    """Quality, blackout and dropout are entered, so they come back exactly; the gap is the suite's own
    arithmetic. It equals the printed gap at three decimals for five models and is 0.001 off for three: the paper
    subtracted unrounded axes (each printed axis carries +-0.0005, so their difference +-0.001)."""
    off = {}
    for model, (_, _, q, b, d, gap, _) in VISREL.items():
        axes = visrel[model].analysis.axes
        assert (axes.quality, axes.removal, axes.dropout) == pytest.approx((q, b, d), abs=1e-12)
        assert axes.gap == pytest.approx(q - b, abs=1e-12)
        assert abs(axes.gap - gap) <= 0.001 + 1e-9, model
        if round(axes.gap, 3) != gap:
            off[model] = round(axes.gap, 3)
        # the mean axis needs bit_error S5, which the paper does not print: left missing, never guessed
        assert axes.mean is None and "bit_error" in axes.missing
    assert off == {"DiffusionDrive": 0.272, "VAD": 0.046, "LAW": 0.1}
    # the bold (largest) gap stays DiffusionDrive's; VAD and LAW lose 7.7 % and 9.7 % under front blackout
    assert max(VISREL, key=lambda m: visrel[m].analysis.axes.gap) == "DiffusionDrive"
    assert [round(1 - visrel[m].analysis.axes.removal, 3) for m in ("VAD", "LAW")] == [0.077, 0.097]


def test_floor_comparison_with_the_ego_only_mlp(visrel):
    """With the ego-only MLP's clean L2 as the floor, only LAW and OpenDriveVLA stay below it with the front
    camera removed (their clean L2 over their blackout retention); the others' L2 rises above the MLP's. The
    paper warns the clean L2s follow different protocols, so this is the suite's reading, not the paper's."""
    below = {m: visrel[m].analysis.floor.blackout_s5_below_floor for m in VISREL if m != FLOOR}
    assert [m for m, b in below.items() if b] == ["LAW", "OpenDriveVLA"]
    assert visrel["LAW"].analysis.floor.blackout_s5_l2_avg == pytest.approx(0.524 / 0.903)


def test_every_pdms_retention_the_paper_prints(pdms):
    """Each printed 'ret.' is the suite's PDMS retention (cell / clean, a reward) within the printed rounding,
    but one: DrivoR's blackout S3 at 1.001, whose printed PDMS equals clean's (0.937) and gives 1.000. 1.001 is
    within the rounding of the two printed scores (0.9365/0.9375 .. 0.9375/0.9365), so the note says it cannot be
    checked further; but the row's EP (0.900 against clean's 0.899) and its retention say blackout S3 moved
    DrivoR, which the text denies ('S3 blackout removes only rear cameras and moves neither agent') and which a
    null control, as the suite runs it on a planner that reads no rear camera, fails."""
    table = read_table(PAPER / "pdms.csv")
    for model, run in pdms.items():
        by_cell = {s.cell: s for s in run.analysis.summaries}
        for row in table.of(model):
            got = by_cell[row.cell].metrics["pdms_retention"]
            assert got == pytest.approx(row.get("pdms") / table.of(model)[0].get("pdms"), abs=1e-12)
            if (model, row.cell) != ("DrivoR", "blackout-s3"):
                assert abs(got - row.get("pdms_retention")) <= 0.0005 + 1e-9, (model, row.cell)
    assert pdms["TransFuser"].notes == []
    (note,) = pdms["DrivoR"].notes
    assert note.startswith("blackout-s3: pdms_retention given 1.001, the suite computes 1.000000") and \
        "within the rounding of the figures it is computed from" in note
    assert 0.9365 / 0.9375 < 1.001 < 0.9375 / 0.9365


def test_the_null_control_on_the_pdms_table(pdms):
    fuser, drivor = pdms["TransFuser"].analysis, pdms["DrivoR"].analysis
    assert fuser.null_control is not None and fuser.null_control.passed is True
    assert drivor.null_control is not None and drivor.null_control.passed is False
    assert drivor.verdict.label == "undetermined" and drivor.verdict.case == "null-control-failed"
    assert "ep 0.900 against clean's 0.899" in str(drivor.verdict.reason)
    assert "pdms_retention 1.001 against clean's 1.000" in str(drivor.verdict.reason)
    # front blackout: the collapse the text reports, 0.937 -> 0.531
    s5 = {s.cell: s for s in pdms["DrivoR"].analysis.summaries}["blackout-s5"]
    assert s5.metrics["pdms_retention"] == pytest.approx(0.531 / 0.937)


def _thresholds() -> dict[str, dict[str, float | None]]:
    lines = [line for line in (PAPER / "thresholds.csv").read_text().splitlines() if not line.startswith("#")]
    rows = list(csv.DictReader(lines))
    return {r["family"]: {k: float(v) if v else None for k, v in r.items() if k != "family"} for r in rows}


def test_threshold_table_against_the_s5_retentions(visrel):
    """The paper prints no per-severity retention, so no threshold can be recomputed; what the suite's
    definition does fix: a threshold never reached ('--') means S5 stays at or above 0.90, and a planner that
    crosses none (VAD, LAW) has both axes at or above 0.90. Every blackout and frame-dropout entry agrees with
    tab:visrel's S5 retention that way."""
    thresholds = _thresholds()
    for model in ("UniAD", "DiffusionDrive", "SparseDrive", "GenAD", "VAD", "LAW"):
        axes = visrel[model].analysis.axes
        for family, s5 in (("blackout", axes.removal), ("frame_dropout", axes.dropout)):
            assert s5 is not None
            assert (thresholds[family][model] is None) == (s5 >= 0.90), (model, family)
        for s10 in (thresholds[f][model] for f in thresholds):
            assert s10 is None or 1.0 <= s10 <= 5.0
    for model in ("VAD", "LAW"):
        assert all(thresholds[f][model] is None for f in thresholds)
        axes = visrel[model].analysis.axes
        assert axes.quality is not None and axes.removal is not None
        assert min(axes.quality, axes.removal) >= 0.90


def test_the_threshold_tables_ordering_claim():
    """The caption: 'whenever a corruption breaks a more camera-reliant planner it breaks it earlier'. With the
    planners in the paper's reliance order (mean S5 retention 0.75 .. 0.99), ten pairs of its own entries break
    it: a less reliant planner crossing earlier, or crossing where the more reliant one never does."""
    order = ["UniAD", "DiffusionDrive", "SparseDrive", "GenAD", "VAD", "LAW"]
    found = []
    for family, row in _thresholds().items():
        for i, a in enumerate(order):
            for b in order[i + 1:]:
                sa, sb = row[a], row[b]
                if sb is not None and (sa is None or sa > sb):
                    found.append((family, a, b))
    assert found == [("gaussian_noise", "DiffusionDrive", "GenAD"), ("gaussian_noise", "SparseDrive", "GenAD"),
                     ("snow", "UniAD", "DiffusionDrive"), ("snow", "UniAD", "SparseDrive"),
                     ("low_light", "SparseDrive", "GenAD"), ("raindrop", "DiffusionDrive", "GenAD"),
                     ("raindrop", "SparseDrive", "GenAD"), ("occlusion", "UniAD", "DiffusionDrive"),
                     ("occlusion", "UniAD", "SparseDrive"), ("blackout", "SparseDrive", "GenAD")]
