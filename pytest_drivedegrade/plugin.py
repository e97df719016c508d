"""The pytest11 entry point: options, and nothing else until `--drivedegrade` is given.

Thin and light: this module imports no OpenCV, torch or pandas, so every pytest run of a user who has the
plugin installed stays fast. With `--drivedegrade` it hands the session to `session.DriveDegradeSession`.
"""

from __future__ import annotations

import pytest

from . import options as opt


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("drivedegrade", "DriveDegrade: certify a planner's reliance on its cameras")
    for spec in opt.OPTIONS:
        group.addoption(spec.flag, dest=spec.dest, default=None, help=spec.help, **spec.argparse)
        parser.addini(spec.dest, help=spec.help, default=None)


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config: pytest.Config) -> None:
    if opt.value(config, opt.ENABLE) is None:
        return
    from .session import DriveDegradeSession

    config.pluginmanager.register(DriveDegradeSession.start(config), DriveDegradeSession.NAME)
