"""cells.csv, report.html and JUnit properties rendered from a synthetic run."""

from __future__ import annotations

import csv
import html
import math
import re
from pathlib import Path

import numpy as np
import pytest
from test_analysis import GROUPS, synthetic_run

from pytest_drivedegrade import cells as cl
from pytest_drivedegrade.certificate.seal import Provenance
from pytest_drivedegrade.report import cells_csv as cells
from pytest_drivedegrade.report import junit
from pytest_drivedegrade.scoring import records as rc
from pytest_drivedegrade.scoring import verdict as vd
from pytest_drivedegrade.scoring.analyse import analyse_run

EVIL = '<script>alert(1)</script>'
PROV = Provenance(EVIL, "sha256:p", "sha256:d", "val", "1.0.0", seed=3, frames=12, command="pytest --drivedegrade x")


@pytest.fixture(scope="module")
def run_and_records():
    recs, gt = synthetic_run(12)
    return analyse_run(recs, groups=GROUPS, n_resamples=100, floor_l2=5.0), recs, gt


@pytest.fixture(scope="module")
def page(run_and_records, tmp_path_factory) -> str:
    from pytest_drivedegrade.report import html as report_html

    res, recs, gt = run_and_records
    by_cell = {r.cell: r for r in recs}
    examples = report_html.trajectory_examples(by_cell, gt, res.summaries)
    montage = np.zeros((60, 120, 3), np.uint8)
    path = tmp_path_factory.mktemp("report") / "report.html"
    report_html.write_report(path, res, PROV, montage=montage, trajectories=examples, created="2025-01-01")
    return path.read_text()


def test_csv_has_the_stable_columns_and_values(run_and_records, tmp_path: Path) -> None:
    res, _, _ = run_and_records
    path = cells.write_cells_csv(tmp_path / "cells.csv", res, PROV)
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    header = list(rows[0])
    assert header[:8] == ["cell", "family", "severity", "frames", "l2_avg", "retention", "retention_ci_low",
                          "retention_ci_high"]
    for col in ("l2_1s_stp3", "l2_3s_uniad", "collision_2s_stp3", "vru_3s_uniad", "jerk", "endpoint_shift",
                "energy", "separable_from_null", "planner_fingerprint", "dataset_fingerprint", "split",
                "spec_version", "seed"):
        assert col in header
    assert len(rows) == len(res.summaries) == 83
    assert rows[0]["cell"] == "clean" and rows[0]["retention"] == "1.0" and rows[0]["separable_from_null"] == ""
    fog = next(r for r in rows if r["cell"] == "fog-s5")
    s = next(s for s in res.summaries if s.cell == "fog-s5")
    assert float(fog["retention"]) == pytest.approx(s.retention, abs=1e-6)
    assert (fog["family"], fog["severity"], fog["frames"], fog["seed"]) == ("fog", "5", "12", "3")
    assert fog["separable_from_null"] == "true" and fog["planner"] == EVIL  # CSV is data, not markup


def test_csv_is_deterministic(run_and_records) -> None:
    """The same records in another order, through JSON, give the same bytes; and the bytes are the stable
    columns with six-decimal floats, clean first at retention 1.0."""
    import json
    import random

    res, recs, _ = run_and_records
    shuffled = [cl.CellRecord.from_builtins(json.loads(json.dumps(r.to_builtins()))) for r in recs]
    random.Random(5).shuffle(shuffled)
    again = analyse_run(shuffled, groups=GROUPS, n_resamples=100, floor_l2=5.0)
    text = cells.cells_csv_text(res, PROV)
    assert cells.cells_csv_text(again, PROV) == text
    lines = text.splitlines()
    assert lines[0] == ",".join(cells.CSV_COLUMNS) and len(lines) == 1 + 83
    clean = res.summaries[0]
    assert lines[1].startswith(f"clean,clean,0,12,{round(clean.l2_avg, 6)!r},1.0,1.0,1.0,")
    fog = next(s for s in res.summaries if s.cell == "fog-s5")
    row = next(line for line in lines if line.startswith("fog-s5,"))
    assert row.split(",")[5] == repr(round(fog.retention, 6))


def test_html_shows_verdict_and_axes(run_and_records, page: str) -> None:
    res, _, _ = run_and_records
    assert html.escape(res.verdict.text, quote=True) in page
    assert res.verdict.label in page
    assert f"{res.axes.quality:.3f}" in page and f"{res.axes.removal:.3f}" in page
    # axes, curves, heatmap, trajectories, montage, and the reliance profile (issue 40)
    assert page.count('src="data:image/png;base64,') == 6 and 'alt="reliance profile chart"' in page


def test_html_escapes_planner_strings(page: str) -> None:
    assert EVIL not in page and "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "<script" not in page.lower()


def test_html_is_self_contained(page: str) -> None:
    assert not re.search(r"https?://", page)
    assert not re.search(r"""(src|href)=["'](?!data:|#)""", page)


def test_html_without_optional_parts(run_and_records) -> None:
    from pytest_drivedegrade.report.html import render_report

    res, _, _ = run_and_records
    axes = vd.compute_axes({}, GROUPS)
    partial = rc.RunAnalysis(res.summaries[:3], {}, axes, vd.verdict(axes), None, res.floor, res.settings, axes)
    page = render_report(partial, PROV)
    assert "undetermined" in page and "Null control:" in page and "not run" in page


def test_most_damaging_and_trajectory_examples(run_and_records) -> None:
    from pytest_drivedegrade.report.html import most_damaging, trajectory_examples

    res, recs, gt = run_and_records
    worst = most_damaging(res.summaries, 3)
    ladder = sorted(s.retention for s in res.summaries if s.family not in cl.DIAGNOSTIC)
    assert [s.retention for s in worst] == ladder[:3]
    ex = trajectory_examples({r.cell: r for r in recs}, gt, res.summaries, n_frames=2)
    assert len(ex) == 2 and list(ex[0].plans) == ["clean"] + [s.cell for s in worst]
    np.testing.assert_array_equal(ex[0].gt, gt[ex[0].frame])


def test_junit_properties_are_plain_builtins(run_and_records) -> None:
    res, _, _ = run_and_records
    props = junit.cell_properties(res.summaries[5])
    assert props[0] == ("cell", res.summaries[5].cell)
    assert dict(props)["retention"] == pytest.approx(res.summaries[5].retention, abs=1e-6)
    suite = junit.suite_properties(res)
    names = dict(suite)
    assert names["drivedegrade_verdict"] == res.verdict.label
    assert names["drivedegrade_axis_quality"] == pytest.approx(res.axes.quality, abs=1e-6)
    assert "drivedegrade_threshold_fog_s10" in names
    for _, value in props + suite:
        assert type(value) in (str, float, int)
        assert not (isinstance(value, float) and not math.isfinite(value))


def test_junit_plain_converts_numpy_and_none() -> None:
    assert junit.plain(np.float32(0.5)) == 0.5 and type(junit.plain(np.float32(0.5))) is float
    assert type(junit.plain(np.int64(3))) is int
    assert junit.plain(np.bool_(True)) == "true" and junit.plain(None) == "none"
    assert junit.plain(float("nan")) == "none" and junit.plain(Path("a")) == "a"


def test_user_text_with_dollar_signs_does_not_break_charts(monkeypatch) -> None:
    """Dollar signs in user text are escaped, so matplotlib prints them instead of parsing mathtext: the
    labels carry the literal text, and the charts are real PNGs of the expected size with the planner's
    point, the plans and the labels drawn."""
    import base64

    import cv2

    from pytest_drivedegrade.report import plots

    figures = []
    render = plots.to_data_uri
    monkeypatch.setattr(plots, "to_data_uri", lambda fig: figures.append(fig) or render(fig))

    def png(uri: str) -> np.ndarray:
        assert uri.startswith("data:image/png;base64,")
        data = np.frombuffer(base64.b64decode(uri.split(",", 1)[1]), np.uint8)
        return cv2.imdecode(data, cv2.IMREAD_COLOR)

    chart = png(plots.axes_chart(rc.Axes(0.9, 0.8, 0.1, None), 0.95, planner="costs $5 and $\\frac{", blind=0.4))
    legend = [t.get_text() for t in figures[0].axes[0].get_legend().get_texts()]
    assert legend == ["ego-only floor", "blind (all cameras off)", r"costs \$5 and \$\frac{"]
    assert 400 < chart.shape[1] < 700 and 350 < chart.shape[0] < 650  # 5.2 x 4.6 in at 110 dpi, trimmed
    accent = np.array([0xEB, 0x63, 0x24])  # ACCENT #2463eb in BGR: the planner's point is drawn
    assert (np.abs(chart.astype(int) - accent).max(axis=2) < 8).sum() > 30
    ex = [{"frame": "tok$_{", "gt": np.zeros((6, 2)), "plans": {"clean": np.ones((6, 2)), "fog-s5$": np.ones((6, 2))}}]
    panels = png(plots.trajectory_panels(ex))
    fig = figures[1]
    assert fig.axes[0].get_title(loc="left") == r"frame tok\$_{"
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["ground truth", "clean", r"fog-s5\$"]
    assert panels.shape[0] > 300 and len(np.unique(panels.reshape(-1, 3), axis=0)) > 20


def test_csv_fields_that_would_start_a_formula_are_neutralised() -> None:
    from pytest_drivedegrade.report.cells_csv import _field

    assert [_field(v) for v in ("=HYPERLINK(\"x\")", "+1+1", "-cmd", "@SUM(A1)", "plain")] == \
        ["'=HYPERLINK(\"x\")", "'+1+1", "'-cmd", "'@SUM(A1)", "plain"]
    assert [_field(v) for v in ("-0.5", "+3", "-1e-3", -2, -0.25)] == ["-0.5", "+3", "-1e-3", "-2", "-0.25"]


# --- EPDMS on the page and in JUnit (spec 4.1) ----------------------------------------------------------------

@pytest.fixture(scope="module")
def epdms_run():
    """The synthetic run with PDMS and EPDMS arrays: a cell's EPDMS is 0.9 times its L2 retention on every frame
    (so its EPDMS retention is that retention), ddc 1, lk 0.5, hc 1, ec 0.75, tlc not scored (NaN)."""
    from dataclasses import replace

    recs, _ = synthetic_run(12)
    clean_l2 = float(recs[0].l2.mean())
    out, ratios = [], {}
    for r in recs:
        n, ratio = len(r.frames), clean_l2 / float(r.l2.mean())
        ratios[r.cell] = ratio
        arrays = {k: np.full(n, v, dtype=float) for k, v in (
            ("nc", 1.0), ("dac", 1.0), ("ttc", 1.0), ("ep", 1.0), ("comfort", 1.0), ("pdms", 0.95 * ratio),
            ("map_scored", 1.0), ("ddc", 1.0), ("tlc", math.nan), ("lk", 0.5), ("hc", 1.0), ("ec", 0.75),
            ("epdms", 0.9 * ratio))}
        out.append(replace(r, **arrays))
    return analyse_run(out, groups=GROUPS, n_resamples=50, floor_l2=5.0), ratios


def test_html_shows_epdms_beside_l2_and_pdms_and_says_what_is_not_scored(epdms_run) -> None:
    from pytest_drivedegrade.report.html import render_report

    epdms_run, _ = epdms_run
    page = render_report(epdms_run, PROV)
    text = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", page))
    assert "L2, PDMS and EPDMS retention, side by side" in text
    assert "tlc not scored: the data have no traffic lights." in text
    assert "EPDMS retention heatmap" in page and "PDMS and EPDMS sub-scores of the most damaging cells" in text
    ax = epdms_run.axes_epdms
    for k in ("quality", "removal"):  # each card: L2, PDMS, EPDMS retention in that order
        card = re.search(rf'<div class="k">{k}</div>(.*?)</div>\s*</div>', page, re.S)
        values = re.findall(r'<div class="v"[^>]*>([^<]*)</div>', page[card.start():card.start() + 600])[:3]
        assert values == [f"{epdms_run.axes.value(k):.3f}", f"{epdms_run.axes_pdms.value(k):.3f}",
                          f"{ax.value(k):.3f}"], (k, values)
    clean_row = re.search(r"<tr><td>clean</td>(.*?)</tr>", page, re.S).group(1)
    cells_ = re.findall(r'<td class="n">([^<]*)</td>', clean_row)
    assert cells_[-7:] == ["1.000", "0.900", "1.000", "—", "0.500", "1.000", "0.750"]  # retention, epdms .. ec


def test_html_without_epdms_keeps_the_two_figures(page: str) -> None:
    text = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", page))
    assert "L2 and PDMS retention, side by side" in text and "EPDMS" not in text and "not scored:" not in text


def test_junit_carries_the_epdms_axes_terms_and_what_is_not_scored(epdms_run) -> None:
    epdms_run, ratios = epdms_run
    suite = dict(junit.suite_properties(epdms_run))
    for k in ("quality", "removal", "gap", "mean"):
        want = epdms_run.axes_epdms.value(k)
        assert suite[f"drivedegrade_axis_epdms_{k}"] == (pytest.approx(want, abs=1e-6) if want is not None else "none")
    assert suite["drivedegrade_epdms_unscored_tlc"] == "the data have no traffic lights"
    assert [k for k in suite if k.startswith("drivedegrade_epdms_unscored_")] == ["drivedegrade_epdms_unscored_tlc"]
    fog = next(s for s in epdms_run.summaries if s.cell == "fog-s5")
    props = dict(junit.cell_properties(fog))
    assert props["epdms"] == pytest.approx(0.9 * ratios["fog-s5"], abs=1e-6)  # known answers of the fixture
    assert props["epdms_retention"] == pytest.approx(ratios["fog-s5"], abs=1e-6)
    assert props["lk"] == 0.5 and props["ec"] == 0.75 and props["hc"] == 1.0 and props["tlc"] == "none"
