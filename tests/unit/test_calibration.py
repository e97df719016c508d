"""benchmarks/calibration.py (issue 36): its populations have the retentions they claim, its Monte Carlo interval
is the Wilson one, and its quick mode replays the plugin's rule and gate and keeps the family-wise error under
alpha on a skewed population."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import calibration as cal  # noqa: E402


@pytest.mark.parametrize("kind", ["iid heavy-tailed", "scene AR 0.9", "5% failure frames"])
def test_synthetic_populations_hold_their_retentions(kind: str) -> None:
    pop = cal.synthetic(kind, 12, 3)
    assert pop.cells.shape == (12, cal.FRAMES) and (pop.clean > 0).all()
    np.testing.assert_allclose(pop.retention(), cal._retentions(12), rtol=1e-12)
    worse = cal.regressed(pop, 0.05, np.random.default_rng(0))
    np.testing.assert_allclose(pop.clean.sum() / worse.sum(axis=1), pop.retention() - 0.05, rtol=1e-9)
    assert int(((worse - pop.cells) > 0).sum(axis=1)[0]) == cal.FRAMES // 20  # on 5 % of the frames only


def test_the_monte_carlo_interval_is_wilsons() -> None:
    lo, hi = cal.wilson(0, 1000)
    assert lo == 0.0 and hi == pytest.approx(0.00383, abs=1e-5)
    lo, hi = cal.wilson(129, 1000)  # issue 36's 12.9 %: 10.9-15.2 %
    assert lo == pytest.approx(0.109, abs=1e-3) and hi == pytest.approx(0.152, abs=1e-3)


def test_the_quick_replay_keeps_the_family_wise_error_under_alpha(capsys: pytest.CaptureFixture[str]) -> None:
    assert cal.main(["--quick", "--alpha", "0.1", "--populations", "5% failure frames", "--orders", "40"]) == 0
    out = capsys.readouterr().out
    assert "method betting" in out and "FWE 0.0000" in out and "false 'no regression' 0.0000" in out
