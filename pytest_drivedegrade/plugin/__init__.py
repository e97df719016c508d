"""The pytest11 entry point: options, and nothing else until `--drivedegrade` is given.

Thin and light: this module imports no OpenCV, torch or pandas, so every pytest run of a user who has the
plugin installed stays fast. With `--drivedegrade` it registers the run's `DriveDegradeSession` (reached through
``config.stash[SESSION_KEY]``) and the fixtures planner files may request (`plugin.context`).

The package is the wiring of the pipeline to pytest and computes nothing itself: `options` (the flags),
`session` (the hooks), `preflight` (the start-up policies), `items` (the planner file and the cell items),
`checks` (what one cell asserts; runs in every worker), `controller` (the end of the run; the controller process
only), `context` (the run's data and the fixtures a planner may use), `compat` (the few pytest internals, with
fallbacks).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import pytest

from . import options as opt

if TYPE_CHECKING:
    from .session import DriveDegradeSession

#: Where the run's `DriveDegradeSession` lives: ``config.stash[SESSION_KEY]``. Defined in this entry module,
#: which pytest loads once per process, so every module that reaches the session shares the one key (pytester's
#: in-process runs drop and re-import the plugin's other modules).
SESSION_KEY: pytest.StashKey[DriveDegradeSession] = pytest.StashKey["DriveDegradeSession"]()
#: `exitguard`'s state, here for the same reason: the real ``os._exit`` and the status of the last session to
#: finish in this process.
EXIT_STATE: list[object] = [os._exit, 0]  # [the real os._exit, the last session's status]


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("drivedegrade", "DriveDegrade: certify a planner's reliance on its cameras")
    for spec in opt.OPTIONS:
        group.addoption(spec.flag, dest=spec.dest, default=None, help=spec.help, **spec.argparse)
        parser.addini(spec.dest, help=spec.help, default=None)


@pytest.hookimpl(tryfirst=True)
def pytest_load_initial_conftests(early_config: pytest.Config, parser: pytest.Parser, args: list[str]) -> None:
    """Before any conftest.py is imported: a run given `--drivedegrade` refuses a signing key in its environment
    or options (`keys.refuse_run_key`): the planner it runs could read it; the certificate is signed afterwards."""
    enabled = getattr(early_config.known_args_namespace, opt.ENABLE, None) is not None
    if not enabled:
        try:
            enabled = bool(early_config.getini(opt.ENABLE))  # as `options.value` reads it
        except (ValueError, KeyError):  # pragma: no cover - the ini value is not known yet
            enabled = False
    if enabled:
        from .keys import refuse_run_key

        refuse_run_key(early_config)


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config: pytest.Config) -> None:
    if opt.value(config, opt.ENABLE) is None:
        return
    import importlib

    from .session import DriveDegradeSession

    # Through sys.modules, not `from . import context`: that returns the package's `context` attribute when it
    # is set, which after pytester's in-process runs restore sys.modules can be an older copy of the module than
    # the one `session` imported; the fixture registered must be the current one.
    context = importlib.import_module(f"{__name__}.context")
    session = DriveDegradeSession.start(config)
    config.stash[SESSION_KEY] = session
    config.pluginmanager.register(session, DriveDegradeSession.NAME)
    config.pluginmanager.register(context, "drivedegrade-context")


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session: pytest.Session) -> None:
    """Every session's final status, for the status guard of a run whose planner shared its process
    (`exitguard`): the last session to finish in a process decides what it ends with."""
    from .exitguard import record

    record(int(session.exitstatus))
