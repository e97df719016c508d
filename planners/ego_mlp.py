"""Reference planner: the ego-only floor (AD-MLP style). Ego status and command in, six waypoints out; no image.

The same code (``pytest_drivedegrade.floor``) gives the floor the suite reports beside every planner, so running
this file shows the floor's own ladder: retention 1.000 everywhere, by construction.

It trains on the train split of the data set under test (the embedded world, or ``--drivedegrade-data``) on first
use, deterministically, and caches the weights by the data set's fingerprint in pytest's cache folder.

    pytest --drivedegrade planners/ego_mlp.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from pytest_drivedegrade.floor import EgoMLP, load_or_train_floor, train_split_for


def _cache_root(config: pytest.Config) -> Path:
    """pytest's cache folder (``.pytest_cache/d/drivedegrade``), or a temporary one without the cache plugin."""
    cache = getattr(config, "cache", None)
    if cache is not None:
        return Path(cache.mkdir("drivedegrade"))
    return Path(tempfile.gettempdir()) / "drivedegrade"


@pytest.fixture(scope="session")
def planner(request: pytest.FixtureRequest) -> EgoMLP:
    """The floor for the data set under test, trained on its train split (cached after the first run)."""
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    config = request.config
    cache_root = _cache_root(config)
    data = config.getoption("drivedegrade_data", default=None)
    split = config.getoption("drivedegrade_split", default=None) or "val"
    if data is None:
        from pytest_drivedegrade.data.world import ensure_default_world

        data = ensure_default_world(cache_root)
    reader = NuScenesReader(Path(data), split=train_split_for(str(split)))
    return load_or_train_floor(reader, cache_root / "floor")
