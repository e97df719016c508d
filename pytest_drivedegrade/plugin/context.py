"""What a planner file may use from the run: the `drivedegrade_context` fixture and the suite's cache folder.

Registered as a plugin module when `--drivedegrade` is given, so a planner fixture can request
``drivedegrade_context`` (the run's `RunContext`: the reader, the scored frames) and build itself from the data
under test, as `planners/ego_mlp.py` does.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ..errors import DriveDegradeError
from ..run import RunContext
from . import SESSION_KEY
from .options import RunOptions


def cache_root(config: pytest.Config) -> Path:
    """pytest's cache folder for the world and the floor, or a folder under rootdir with -p no:cacheprovider."""
    cache = getattr(config, "cache", None)
    return Path(cache.mkdir("drivedegrade")) if cache is not None else Path(config.rootpath) / ".drivedegrade-cache"


def build_run_context(config: pytest.Config, options: RunOptions) -> RunContext:
    """The data (the embedded world unless --drivedegrade-data) indexed, and the frames to score chosen."""
    root = options.settings.data
    if root is None:
        from ..data.world import ensure_default_world
        from ..progress import Sink

        root = ensure_default_world(cache_root(config), progress=Sink.for_pytest(config))
    context = RunContext.open(options.settings, root=root, planner_path=options.planner_path,
                              digest_cache=cache_root(config) / "digests")
    if options.settings.two_stage:  # its data checked, its step set (the run sits below the closed loop)
        from ..closedloop.twostage import enable

        enable(context)
    return context


@pytest.fixture(scope="session")
def drivedegrade_context(request: pytest.FixtureRequest) -> RunContext:
    """The run's context (data reader, scored frames, ``device``: --drivedegrade-device, where the planner should
    run), built once per process; a data problem fails the cell."""
    try:
        return request.config.stash[SESSION_KEY].run_context()
    except DriveDegradeError as exc:
        pytest.fail(str(exc), pytrace=False)
