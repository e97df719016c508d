"""Closed-loop statistics (issue 36, and issue 37's closed-loop items): the null band is the null's own paired
spread per route, separation / "holds" / "robust" need a paired route-level interval that clears, a failed null
makes the closed label undetermined, unscored runs stop a headline label unless the bounds agree, seeds run only
where they change the inputs and `n` counts distinct runs, and the closed flat line is the run's."""

from __future__ import annotations

import numpy as np
import pytest

from pytest_drivedegrade.certificate.closed import check_closed_loop
from pytest_drivedegrade.closedloop.analysis import RunRow
from pytest_drivedegrade.closedloop.cells import SLICE, closed_id, run_list
from pytest_drivedegrade.scoring.closed_loop import analyse_rows, check_section

ROUTES = [f"route-{i}" for i in range(6)]
QUALITY_CELLS = ("closed-gaussian_blur-s3", "closed-gaussian_blur-s5", "closed-motion_blur-s3",
                 "closed-motion_blur-s5", "closed-blackout-s5")


def rows(values: list[float | None], seeds: int = 1, trace: str = "") -> list[RunRow]:
    """One run per route (or `seeds` per route, all equal when `trace` is given: replays of one another)."""
    out = []
    for route, v in zip(ROUTES, values):
        for s in range(seeds):
            out.append(RunRow(route, s, v, None if v is None else v / 100, "complete" if v is not None else
                              "unscored", trace or f"{route}-{s}-{v}"))
    return out


def noisy(rng: np.random.Generator, base: list[float], sd: float) -> list[float | None]:
    return [float(np.clip(b + rng.normal(0, sd), 0, 100)) for b in base]


def test_a_planner_with_unseeded_noise_has_no_cell_separable_from_its_null() -> None:
    """A planner that ignores the cameras and draws its own noise: every cell differs from clean by noise alone
    (0.2 to 3 DS), as does its clean rerun. The old point rule certified such cells "separable" whenever their
    mean left the null's two means; the paired band of the rerun's own spread does not."""
    base = [82.0, 64.0, 91.0, 55.0, 73.0, 88.0]
    for trial in range(40):
        rng = np.random.default_rng(trial)
        cells = {closed_id("clean", 0): rows(noisy(rng, base, 2.0))}
        cells.update({c: rows(noisy(rng, base, 2.0)) for c in (*QUALITY_CELLS, "closed-blackout-s3")})
        got = analyse_rows(cells, reads_rear=True, null_rows=rows(noisy(rng, base, 2.0)))
        separable = {c.cell: c.separable_from_null for c in got.cells if c.cell != "closed-clean"}
        assert set(separable.values()) == {False}, (trial, separable)
        assert got.null is not None and got.null.band is not None and got.null.band[0] < 0 < got.null.band[1]


def test_a_cell_that_does_move_is_separable_and_its_paired_interval_says_by_how_much() -> None:
    rng = np.random.default_rng(3)
    base = [82.0, 64.0, 91.0, 55.0, 73.0, 88.0]
    cells = {"closed-clean": rows(noisy(rng, base, 1.0)), "closed-blackout-s5": rows(noisy(rng, [20.0] * 6, 1.0)),
             "closed-gaussian_blur-s5": rows(noisy(rng, base, 1.0))}
    got = analyse_rows(cells, reads_rear=True, null_rows=rows(noisy(rng, base, 1.0)))
    blackout = next(c for c in got.cells if c.cell == "closed-blackout-s5")
    assert blackout.separable_from_null is True
    assert blackout.difference_ci is not None and blackout.difference_ci[1] < -30
    assert blackout.retention_ci is not None and blackout.retention_ci[0] < blackout.retention < \
        blackout.retention_ci[1] < 0.4
    figures = blackout.figures()
    assert figures["retention_ci_high"] == blackout.retention_ci[1] and figures["routes"] == 6


def test_a_liar_whose_null_wanders_far_keeps_no_robust_label_on_a_small_gap() -> None:
    """The rerun moves 15 DS per route; quality S5 and removal differ by 1.4 DS: the point corners agree (the
    old "robust"), the route-level intervals do not clear, so it is neither robust nor a separation that holds."""
    clean = [80.0, 60.0, 90.0, 50.0, 70.0, 85.0]
    rerun = [95.0, 45.0, 75.0, 65.0, 55.0, 99.0]
    quality = [c - 0.7 + d for c, d in zip(clean, (9, -9, 8, -8, 7, -7))]
    removal = [c - 2.1 + d for c, d in zip(clean, (-9, 9, -8, 8, -7, 7))]
    cells = {"closed-clean": rows(clean), "closed-gaussian_blur-s5": rows(quality),
             "closed-motion_blur-s5": rows(quality), "closed-blackout-s5": rows(removal)}
    got = analyse_rows(cells, reads_rear=True, null_rows=rows(rerun), flat=0.9)
    assert got.label == "not-shown-to-use-cameras"
    assert not got.robust and len(set(got.labels)) > 1
    assert got.separation["holds"] is False and got.separation["holds_under_every_assignment"] is False
    assert got.separation["gap_ds_ci_low"] < 0 < got.separation["gap_ds_ci_high"]
    assert got.figures()["verdict"]["robust"] is False


def test_a_failed_null_makes_the_closed_label_undetermined() -> None:
    clean = [80.0, 60.0, 90.0, 50.0, 70.0, 85.0]
    cells = {"closed-clean": rows(clean), "closed-gaussian_blur-s5": rows([c * 0.5 for c in clean]),
             "closed-motion_blur-s5": rows([c * 0.5 for c in clean]), "closed-blackout-s5": rows([10.0] * 6),
             "closed-blackout-s3": rows([c - 5 for c in clean])}  # a planner that does read the rear cameras
    got = analyse_rows(cells, reads_rear=False)
    assert got.null is not None and got.null.passed is False
    assert got.label == "undetermined" and "null control failed" in str(got.reason) and not got.robust
    assert got.figures()["verdict"]["label"] == "undetermined"
    # the same cells with a null that reproduces clean keep their label
    ok = analyse_rows({**cells, "closed-blackout-s3": rows(clean, trace="")}, reads_rear=False)
    assert ok.null is not None and ok.null.passed is True and ok.label == "camera-reliant"
    assert ok.null.band == (0.0, 0.0)


def test_unscored_runs_stop_a_headline_label_unless_the_bounds_agree() -> None:
    """A planner that raises on its worst blackout routes: the complete-case mean of the rest flatters it."""
    clean = [80.0, 60.0, 90.0, 50.0, 70.0, 85.0]
    blur = [c * 0.97 for c in clean]
    cells = {"closed-clean": rows(clean), "closed-gaussian_blur-s5": rows(blur), "closed-motion_blur-s5": rows(blur),
             "closed-blackout-s5": rows([c * 0.95 for c in clean[:3]] + [None, None, None])}
    got = analyse_rows(cells)
    assert got.label == "undetermined" and "3 unscored run(s)" in str(got.reason)
    # bounds that agree: one unscored run far from any line keeps the label
    agree = {**cells, "closed-blackout-s5": rows([5.0, 3.0, 8.0, 2.0, 4.0, None])}
    kept = analyse_rows(agree)
    assert kept.label == "quality-insensitive" and kept.reason is None and kept.robust


def test_seeds_run_only_where_they_change_the_inputs() -> None:
    from pytest_drivedegrade.closedloop.cells import cell_seeds

    seeds = [0, 1]
    assert cell_seeds("clean", seeds) == [0] and cell_seeds("gaussian_blur", seeds) == [0]
    assert cell_seeds("blackout", seeds) == [0] and cell_seeds("motion_blur", seeds) == [0, 1]
    slice_runs = sum(len(run_list(ROUTES, seeds, fam)) for fam, _ in SLICE)
    assert slice_runs == 6 * (5 + 2 * 2)  # motion_blur S3/S5 under both seeds, the rest once: 54, not 84
    assert run_list(ROUTES, seeds) == [(r, s) for r in ROUTES for s in seeds]  # no family: every seed


def test_n_counts_distinct_runs() -> None:
    from pytest_drivedegrade.closedloop.analysis import distinct_runs

    replayed = rows([80.0, 60.0, 90.0, 50.0, 70.0, 85.0], seeds=2, trace="same")
    assert distinct_runs(replayed) == 6 and len(replayed) == 12
    got = analyse_rows({"closed-clean": replayed}).figures()
    cell = got["cells"][0]
    assert (cell["runs"], cell["n"], cell["routes"]) == (12, 6, 6)


def test_the_closed_flat_line_is_the_runs() -> None:
    """A certificate resealed with another closed flat line changes the closed label; its own rows recompute it,
    so only the tie to settings.flat catches it."""
    clean = [80.0, 60.0, 90.0, 50.0, 70.0, 85.0]
    cells = {"closed-clean": rows(clean), "closed-gaussian_blur-s5": rows([c * 0.85 for c in clean]),
             "closed-motion_blur-s5": rows([c * 0.85 for c in clean]), "closed-blackout-s5": rows([10.0] * 6)}
    honest = analyse_rows(cells, flat=0.9).figures()
    forged = analyse_rows(cells, flat=0.8).figures()
    assert honest["verdict"]["label"] != forged["verdict"]["label"]
    for section in (honest, forged):
        assert check_section(section, None) == []  # each adds up on its own rows
    cert = {"settings": {"flat": 0.9}, "verdict": {"label": "undetermined"}, "cells": [], "closed_loop": forged}
    problems = check_closed_loop(cert)
    assert any("closed_loop.verdict.flat" in p and "settings.flat is 0.9" in p for p in problems)
    assert check_closed_loop({**cert, "closed_loop": honest}) == []


def test_a_spec4_closed_section_is_still_read() -> None:
    """A section written before the route statistics (no verdict.basis) is checked on the figures both rules
    share; its older separability and label are not recomputed under the new rule."""
    clean = [80.0, 60.0, 90.0, 50.0, 70.0, 85.0]
    cells = {"closed-clean": rows(clean), "closed-blackout-s5": rows([c - 1 for c in clean])}
    section = analyse_rows(cells).figures()
    old = {**section, "verdict": {k: v for k, v in section["verdict"].items() if k not in ("basis", "reason")}}
    old["separation"] = {"holds": True}
    old["cells"] = [{k: v for k, v in c.items() if not k.endswith(("_ci_low", "_ci_high")) and k not in ("n", "routes")}
                    | {"separable_from_null": True} for c in section["cells"]]
    assert check_section(old, None) == []
    old["cells"][1]["ds_mean"] = 99.0
    assert any("ds_mean" in p for p in check_section(old, None))


@pytest.mark.parametrize("values", [[80.0] * 6, [0.0, 100.0, 50.0, 20.0, 70.0, 90.0]])
def test_the_band_of_a_null_that_equals_clean_is_zero(values: list[float]) -> None:
    from pytest_drivedegrade.scoring import routestats as rs

    draws = rs.RouteDraws.of(ROUTES)
    v = np.asarray(values)
    assert rs.band(draws, v, v) == (0.0, 0.0)
    assert rs.separable((0.5, 2.0), (0.0, 0.0)) is True and rs.separable((-0.5, 2.0), (0.0, 0.0)) is False
