"""`drivedegrade compare` (SPEC section 10): one row per certificate, ranks, rank reversals, refusals."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import pytest
from test_analysis import GROUPS, synthetic_run

from pytest_drivedegrade.certificate import seal as cf
from pytest_drivedegrade.certificate.compare import CompareError, write_compare
from pytest_drivedegrade.cli import main
from pytest_drivedegrade.scoring.analyse import analyse_run

PROV = cf.Provenance("a", "sha256:planner", "sha256:data", "val", "1.0.0", seed=0, frames=12)


def certify(tmp_path: Path, name: str, damage, *, offset: float = 0.0, **prov) -> Path:
    """A sealed certificate of a synthetic planner: `damage` shapes its retention, `offset` its clean L2."""
    recs, _ = synthetic_run(16, damage=damage)
    for r in recs:
        r.l2 = r.l2 + offset
    analysis = analyse_run(recs, groups=GROUPS, n_resamples=50)
    path = tmp_path / f"{name}.json"
    cf.write_certificate(path, cf.build_certificate(analysis, dataclasses.replace(PROV, planner_name=name, **prov)))
    return path


def test_compare_ranks_and_flags_a_reversal(tmp_path):
    # "sharp" plans best on clean images but degrades most; "dull" plans worse and does not degrade at all
    sharp = certify(tmp_path, "sharp", lambda f, s: 0.3 * s, offset=0.0)
    dull = certify(tmp_path, "dull", lambda f, s: 0.0, offset=2.0)
    mid = certify(tmp_path, "mid", lambda f, s: 0.1 * s, offset=1.0)
    csv_path, html_path, df = write_compare([sharp, dull, mid], tmp_path / "cmp")
    rows = {r["planner"]: r for r in csv.DictReader(csv_path.open())}
    assert list(rows) == ["sharp", "dull", "mid"]
    assert (rows["sharp"]["rank_clean_l2"], rows["mid"]["rank_clean_l2"], rows["dull"]["rank_clean_l2"]) == \
        ("1", "2", "3")
    assert (rows["dull"]["rank_mean_retention"], rows["mid"]["rank_mean_retention"],
            rows["sharp"]["rank_mean_retention"]) == ("1", "2", "3")
    assert all(r["rank_reversal"] == "True" for r in rows.values())
    assert "dull" in rows["sharp"]["reversed_with"]
    for col in ("clean_l2", "clean_pdms", "axis_quality", "axis_removal", "axis_mean", "pdms_axis_quality",
                "verdict", "ego_label", "floor_l2", "jpeg_s10"):
        assert col in rows["sharp"]
    page = html_path.read_text()
    assert "Rank reversals" in page and "sharp" in page and "<script" not in page


def test_certificates_of_another_data_set_or_spec_are_refused_unless_forced(tmp_path, capsys):
    a = certify(tmp_path, "a", lambda f, s: 0.1 * s)
    other_data = certify(tmp_path, "b", lambda f, s: 0.1 * s, dataset_fingerprint="sha256:other")
    other_spec = certify(tmp_path, "c", lambda f, s: 0.1 * s, spec_version="0.9.0")
    with pytest.raises(CompareError, match="data set"):
        write_compare([a, other_data], tmp_path / "x")
    assert main(["compare", str(a), str(other_spec), "--out", str(tmp_path / "y")]) == 2
    assert "spec version" in capsys.readouterr().err
    assert main(["compare", str(a), str(other_spec), "--out", str(tmp_path / "y"), "--force"]) == 0
    assert (tmp_path / "y" / "compare.csv").is_file() and (tmp_path / "y" / "compare.html").is_file()


def test_an_edited_certificate_is_refused(tmp_path, capsys):
    a = certify(tmp_path, "a", lambda f, s: 0.1 * s)
    data = json.loads(a.read_text())
    data["axes"]["quality"] = 1.0
    a.write_text(json.dumps(data))
    assert main(["compare", str(a), "--out", str(tmp_path / "z")]) == 2
    assert "digest mismatch" in capsys.readouterr().err


def test_the_verdicts_come_first_in_one_screen_wide_table_and_a_planner_far_worse_than_its_floor_is_flagged(
        tmp_path):
    """compare.html was one 60-column table with the verdict columns off-screen and no floor warning (issue 41)."""
    import pandas as pd

    from pytest_drivedegrade.certificate.compare import SUMMARY, floor_warnings

    a = certify(tmp_path, "a", lambda f, s: 0.1 * s)
    b = certify(tmp_path, "b", lambda f, s: 0.0, offset=1.0)
    _, html_path, df = write_compare([a, b], tmp_path / "cmp")
    page = html_path.read_text()
    first = page.index("<h2>Verdicts</h2>")
    summary = page[first:page.index("<h2>Every column</h2>")]
    assert [f"<th>{c}</th>" in summary for c in SUMMARY] == [True] * len(SUMMARY)
    assert "jpeg_s10" not in summary and "jpeg_s10" in page[page.index("<h2>Every column</h2>"):]
    rows = pd.DataFrame([{"planner": "wired", "clean_l2": 0.30, "floor_l2": 0.34},
                         {"planner": "miswired", "clean_l2": 3.30, "floor_l2": 0.34},
                         {"planner": "close", "clean_l2": 0.15, "floor_l2": 0.06},  # 2.5x, but only 0.09 m worse
                         {"planner": "unknown", "clean_l2": 3.30, "floor_l2": None}])
    assert floor_warnings(rows) == ["miswired: clean L2 3.300 m against the ego-only floor's 0.340 m: a planner "
                                    "that reads no camera plans far better (a miswired adapter, other data, too "
                                    "little training or a perception-free design); read its retention with that in "
                                    "mind"]
