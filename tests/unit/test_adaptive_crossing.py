"""Issue 22's pieces beyond one process, unit by unit: which cells an adaptive shard owns, the sequential gate's
test rebuilt from the parts a certificate records (equal to `gate_cell`, bit for bit), and a full run gated on an
adaptive baseline's intervals (known answers)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.cells import run_order
from pytest_drivedegrade.errors import DriveDegradeError
from pytest_drivedegrade.scoring.adaptive import GateBaseline, gate_cell, gate_range
from pytest_drivedegrade.scoring.seqgate import _pack, gate_settlement, interval_gate, unpack
from pytest_drivedegrade.scoring.sequential import METHOD
from pytest_drivedegrade.settings import Shard
from pytest_drivedegrade.shards import adaptive_groups, adaptive_owned

CELLS = run_order(("jpeg", "fog", "blackout"), (1, 2, 3, 4, 5))


@pytest.mark.parametrize("count", [1, 2, 3, 4])
def test_adaptive_shards_own_disjoint_whole_families_covering_the_run(count):
    owned = [adaptive_owned(CELLS, Shard(i, count)) for i in range(1, count + 1)]
    flat = [c for part in owned for c in part]
    assert sorted(flat) == sorted(CELLS) and len(flat) == len(set(flat))
    assert {("clean", 0), ("blind", 0), ("null", 0)} <= set(owned[0])
    for family in ("jpeg", "fog", "blackout", "ego_noise"):
        holders = [i for i, part in enumerate(owned) if any(f == family for f, _ in part)]
        assert len(holders) == 1, family  # a family's schedule runs in one shard
    # clean+blind+null, 3 ladder, ego_noise, ego_blind, command_blind, command_swap (issue 40)
    assert [len(g) for g in adaptive_groups(CELLS)] == [3, 5, 5, 5, 5, 1, 1, 1]


def test_more_adaptive_shards_than_groups_is_refused():
    with pytest.raises(DriveDegradeError, match="has 8 group.*use at most 8 shards"):
        adaptive_owned(CELLS, Shard(1, 9))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(12, 60), drop=st.floats(0.0, 0.6), units=st.integers(1, 60))
def test_the_gate_rebuilt_from_its_recorded_parts_is_gate_cell(seed, n, drop, units):
    """Every side occurs (about 40 % above, 30 % below, 30 % open over these draws)."""
    rng = np.random.default_rng(seed)
    units = min(units, n)
    base_clean, base_cell = rng.uniform(0.2, 1.0, n), rng.uniform(0.3, 6.0, n)  # some clipped at the 5 m bound
    clean, cell = base_clean + rng.normal(0, 0.02, n), base_cell * (1 + drop) + rng.normal(0, 0.02, n)
    ref = GateBaseline(base_clean, base_cell)
    want = gate_cell(clean, cell, ref, list(range(units)), tolerance=0.02, alpha=0.01, method=METHOD)
    level = ref.retention() - 0.02
    d = base_clean - level * base_cell  # nothing clipped: the baseline's units are known, the range holds them
    span = tuple(float.fromhex(v.hex()) for v in gate_range(level, d))
    parts = float.fromhex(level.hex()), float.fromhex(float(np.mean(d)).hex()), unpack(_pack(d[:units]))
    assert gate_settlement(clean[:units], cell[:units], *parts, n, 0.01, span) == want


def test_a_full_run_is_gated_on_the_adaptive_baseline_s_intervals():
    baseline = {"adaptive": {"alpha": 0.05, "cells": {
        "jpeg-s5": {"interval": [0.80, 0.90]}, "fog-s5": {"interval": [0.50, 0.70]},
        "fog-s3": {"interval": [0.85, 0.95]}, "fog-s1": {"stop": "skipped"}}, "axes": {
        "removal": {"interval": [0.10, 0.20], "side": "below"}}}}
    current = {"cells": [{"cell": "clean", "retention": 1.0}, {"cell": "jpeg-s5", "retention": 0.77},
                         {"cell": "fog-s5", "retention": 0.69}, {"cell": "fog-s3", "retention": 0.88},
                         {"cell": "fog-s1", "retention": 0.99}, {"cell": "snow-s5", "retention": 0.5}],
               "axes": {"removal": 0.30, "quality": None}}
    got = interval_gate(current, baseline, 0.02)
    assert got.regressions == [("jpeg-s5", 0.80, 0.77)]  # 0.77 < 0.80 - 0.02
    assert got.passed == ["fog-s5", "axis removal"]  # 0.69 >= 0.70 - 0.02; 0.30 >= 0.18
    assert got.open == ["fog-s3"]  # 0.83 <= 0.88 < 0.93
    assert got.skipped == ["fog-s1"] and got.ungated == ["snow-s5"] and got.failed
