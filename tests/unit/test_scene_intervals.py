"""Scene-clustered intervals for the full run (issue 36, SPEC section 17): frames of one scene are not independent
draws, so every interval resamples scenes (their frames whole), reads its bounds at the expanded levels for the
scene count, names its basis in the certificate, and states no verdict confidence on too few scenes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_analysis import synthetic_run

from pytest_drivedegrade.certificate.compare import certificate_row
from pytest_drivedegrade.errors import InvalidInput
from pytest_drivedegrade.report.terminal import interval_lines
from pytest_drivedegrade.scoring import intervals as iv
from pytest_drivedegrade.scoring import retention as rt
from pytest_drivedegrade.scoring.analyse import analyse_run


def scenes_of(n_frames: int, n_scenes: int) -> dict[str, str]:
    """tok000.. split into `n_scenes` consecutive scenes of (nearly) equal length."""
    return {f"tok{i:03d}": f"scene-{i * n_scenes // n_frames}" for i in range(n_frames)}


def test_the_expanded_levels_match_a_t_interval_for_the_scene_count() -> None:
    # Phi(-sqrt(G / (G - 1)) t_{G-1, 0.975}): known values
    assert iv.expanded_tail(6) == pytest.approx(0.5 * math.erfc(math.sqrt(6 / 5) * 2.571 / math.sqrt(2)))
    assert iv.expanded_tail(6) == pytest.approx(0.00243, abs=5e-5)
    assert iv.expanded_tail(10) == pytest.approx(0.00855, abs=5e-5)
    assert iv.expanded_tail(1000) == pytest.approx(0.025, abs=2e-4)
    assert iv.expanded_tail(None) == (1 - 0.95) / 2  # the frame bootstrap keeps the plain level
    tails = [iv.expanded_tail(g) for g in range(2, 60)]
    assert tails == sorted(tails)  # more scenes, nearer the plain 2.5 %


def test_a_cluster_draw_takes_whole_scenes_and_as_many_as_there_are() -> None:
    labels, basis = iv.scene_clusters([f"s{i // 5}" for i in range(35)], 35)
    assert basis.units == "scenes" and basis.n_units == 7 and labels is not None
    counts = iv.cluster_counts(np.random.default_rng(1), 300, labels)
    for g in range(7):  # every frame of a scene is drawn as often as its scene
        block = counts[:, labels == g]
        assert (block == block[:, :1]).all()
    assert np.allclose(counts.sum(axis=1), 35 * 0 + 5 * 7)  # G scenes of 5 frames per resample


def test_one_scene_or_unknown_scenes_fall_back_to_frames_and_say_so() -> None:
    assert iv.scene_clusters(None, 10)[1].text == "frame bootstrap, 10 frames (scenes unknown: frames treated as " \
                                                  "independent)"
    one = iv.scene_clusters(["a"] * 10, 10)[1]
    assert one.units == "frames" and "one scene" in one.text and one.confidence_reason is not None
    with pytest.raises(InvalidInput, match="3 scene labels for 4 frames"):
        iv.scene_clusters(["a", "b", "c"], 4)


def _scene_effect(rng: np.random.Generator, n_scenes: int, per_scene: int) -> tuple[np.ndarray, np.ndarray,
                                                                                       list[str]]:
    """Clean and cell per-frame errors where the damage varies by scene (a scene-level effect shared by its
    frames): the population retention is 1 / 1.3 in expectation, but one sample of scenes moves it."""
    scene_damage = rng.normal(0.3, 0.25, size=n_scenes)
    clean = rng.uniform(0.8, 1.2, size=n_scenes * per_scene)
    cell = clean * (1 + np.repeat(scene_damage, per_scene)) + rng.normal(0, 0.01, size=clean.size)
    return clean, cell, [f"s{i // per_scene}" for i in range(clean.size)]


def test_scene_intervals_cover_a_scene_level_effect_where_frame_intervals_do_not() -> None:
    """Coverage of the population retention 1 / 1.3 over 120 draws of 12 scenes x 20 frames: the frame bootstrap
    (frames as independent) is far too narrow; the scene-cluster one covers about as often as it claims."""
    rng = np.random.default_rng(36)
    truth = 1 / 1.3
    covered = {"frames": 0, "scenes": 0}
    widths = {"frames": 0.0, "scenes": 0.0}
    trials = 120
    for k in range(trials):
        clean, cell, scenes = _scene_effect(rng, 12, 20)
        for name, sc in (("frames", None), ("scenes", scenes)):
            lo, hi = rt.bootstrap_retention_ci(clean, cell, n_resamples=400, seed=k, scenes=sc)
            covered[name] += lo <= truth <= hi
            widths[name] += (hi - lo) / trials
    assert covered["frames"] / trials < 0.5  # the old basis: independent frames
    assert covered["scenes"] / trials >= 0.88
    assert widths["scenes"] > 3 * widths["frames"]


def test_the_certificate_names_the_basis_and_withholds_confidence_on_six_scenes() -> None:
    recs, _ = synthetic_run(n_frames=36)
    six = analyse_run(recs, n_resamples=300, scenes=scenes_of(36, 6))
    got = six.settings["intervals"]
    assert got["basis"] == "scene-cluster bootstrap, 6 scenes" and got["units"] == "scenes" and got["n_units"] == 6
    assert got["scheme"] == "scenes (frames whole)" and got["confidence_stated"] is False
    assert "6 scenes, too few" in got["confidence_reason"]
    assert six.verdict.confidence is None and not six.verdict.borderline  # old: 1.000 from frame resamples
    assert "No confidence is stated" in six.verdict.text
    assert six.axes.intervals is not None and six.axes.intervals.quality is not None
    lines = interval_lines(six)
    assert "interval basis: scene-cluster bootstrap, 6 scenes" in lines
    assert any(line.startswith("verdict confidence: not stated (the intervals rest on 6 scenes") for line in lines)
    twelve = analyse_run(recs, n_resamples=300, scenes=scenes_of(36, 12))
    assert twelve.settings["intervals"]["confidence_stated"] is True and twelve.verdict.confidence is not None


def test_scene_intervals_are_wider_than_frame_intervals_on_scene_correlated_cells() -> None:
    """A damage that differs between scenes: every cell CI, axis interval and threshold interval over scenes
    contains (and is wider than) the one over frames, the point figures are unchanged."""
    n = 60
    recs, _ = synthetic_run(n_frames=n)
    scene = np.array([i * 6 // n for i in range(n)])
    for r in recs:  # scenes 0 and 3 hit far harder by every corruption
        if r.cell not in ("clean", "null"):
            r.l2 = r.l2 * (1 + np.where(np.isin(scene, (0, 3)), 0.8, 0.0)[:, None] * (r.severity / 5))
    frames = analyse_run(recs, n_resamples=400)
    scenes = analyse_run(recs, n_resamples=400, scenes=scenes_of(n, 6))
    assert frames.settings["intervals"]["basis"].startswith("frame bootstrap, 60 frames (scenes unknown")
    for a, b in zip(frames.summaries, scenes.summaries):
        assert a.retention == b.retention  # point values do not move
        if a.cell not in ("clean", "null") and math.isfinite(a.retention_ci_low):
            assert b.retention_ci_high - b.retention_ci_low > a.retention_ci_high - a.retention_ci_low
    fq, sq = frames.axes.intervals.quality, scenes.axes.intervals.quality
    assert sq[0] < fq[0] and sq[1] > fq[1]


def test_scene_intervals_are_deterministic_and_need_every_frames_scene() -> None:
    recs, _ = synthetic_run(n_frames=24)
    scenes = scenes_of(24, 4)
    a = analyse_run(recs, n_resamples=200, scenes=scenes).to_builtins()
    b = analyse_run(list(reversed(recs)), n_resamples=200, scenes=dict(reversed(list(scenes.items())))).to_builtins()
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)  # NaN-aware equality
    with pytest.raises(InvalidInput, match="no scene for 1 scored frame"):
        analyse_run(recs, n_resamples=50, scenes={k: v for k, v in scenes.items() if k != "tok005"})


def test_compare_shows_the_basis_and_reads_a_spec4_certificate() -> None:
    from pytest_drivedegrade.certificate.compare import interval_basis

    recs, _ = synthetic_run(n_frames=24)
    cert = analyse_run(recs, n_resamples=100, scenes=scenes_of(24, 6)).to_builtins()
    assert interval_basis(cert) == "scene-cluster bootstrap, 6 scenes"
    row = certificate_row(cert)
    assert row["interval_basis"] == "scene-cluster bootstrap, 6 scenes" and row["verdict_confidence"] is None
    spec4 = {"settings": {"intervals": {"computed": True, "scheme": "paired frames", "percentile": "linear"}}}
    assert interval_basis(spec4) == "frame bootstrap (paired frames; frames treated as independent)"


def test_a_merge_joins_the_shards_scenes_and_an_older_manifest_says_scenes_unknown() -> None:
    from pathlib import Path

    from pytest_drivedegrade.certificate.merge import ShardResult, _scenes
    from pytest_drivedegrade.settings import RunSettings

    def shard(scenes: dict[str, str] | None) -> ShardResult:
        return ShardResult(Path("."), {"scenes": scenes} if scenes is not None else {}, RunSettings(), {})

    got = _scenes([shard({"t0": "a", "t1": "a"}), shard({"t2": "b"})])
    assert got == {"t0": "a", "t1": "a", "t2": "b"}
    assert _scenes([shard({"t0": "a"}), shard(None)]) is None  # a manifest from before scenes were written
