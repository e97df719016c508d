"""Reference planner: the ego-only floor (AD-MLP style). Ego status and command in, six waypoints out; no image.

The same code (``pytest_drivedegrade.floor``) gives the floor the suite reports beside every planner, so running
this file shows the floor's own ladder: retention 1.000 everywhere, by construction.

It trains on the train split of the data set under test (the embedded world, or ``--drivedegrade-data``) on first
use, deterministically, and shares the suite's cache of floor weights (keyed by the data set's fingerprint).

    pytest --drivedegrade planners/ego_mlp.py
"""

from __future__ import annotations

import pytest

from pytest_drivedegrade.data.nuscenes import NuScenesReader
from pytest_drivedegrade.floor import EgoMLP, load_or_train_floor, train_split_for
from pytest_drivedegrade.plugin.context import cache_root


@pytest.fixture(scope="session")
def planner(request: pytest.FixtureRequest, drivedegrade_context) -> EgoMLP:
    """The floor for the data set under test, trained on its train split (cached after the first run)."""
    split = request.config.getoption("drivedegrade_split", default=None) or "val"
    reader = NuScenesReader(drivedegrade_context.reader.root, split=train_split_for(str(split)))
    return load_or_train_floor(reader, cache_root(request.config) / "floor")
