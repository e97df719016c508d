"""pytest-drivedegrade: certify how much an end-to-end driving planner relies on its cameras.

The public API is imported lazily, so that the pytest entry point (``pytest_drivedegrade.plugin``) stays
light: a plain ``pytest`` run of a user who has the plugin installed never imports OpenCV, torch or pandas.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_LAZY = {
    "corrupt": "pytest_drivedegrade.corruptions.api",
    "corrupt_sample": "pytest_drivedegrade.corruptions.api",
    "FAMILIES": "pytest_drivedegrade.corruptions.ladder",
    "SPEC_VERSION": "pytest_drivedegrade.corruptions.ladder",
    "inject_loader": "pytest_drivedegrade.corruptions.hooks",
    "patch_loader": "pytest_drivedegrade.corruptions.hooks",
    "Injection": "pytest_drivedegrade.corruptions.hooks",
    "ladder_cells": "pytest_drivedegrade.foreign.ladder",
}

__all__ = ["__version__", *_LAZY]

if TYPE_CHECKING:  # pragma: no cover
    from .corruptions.api import corrupt, corrupt_sample
    from .corruptions.hooks import Injection, inject_loader, patch_loader
    from .corruptions.ladder import FAMILIES, SPEC_VERSION
    from .foreign.ladder import ladder_cells


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'pytest_drivedegrade' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
