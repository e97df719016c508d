"""The ladder: every family module imported, and the registered families in the order of SPEC section 3.

`FAMILIES` maps a family name to its `Family` record; `spec/ladder.yaml` is emitted from these records, so
specification and code cannot diverge. Importing this module is what fills the registry.
"""

from __future__ import annotations

from . import contamination, memory, sensor, temporal, transmission, weather  # noqa: F401 - fill the registry
from .registry import ORDER, REGISTERED, SEVERITIES, SPEC_VERSION, Family

FAMILIES: dict[str, Family] = {name: REGISTERED[name] for name in ORDER}
QUALITY_FAMILIES: tuple[str, ...] = tuple(n for n in ORDER if FAMILIES[n].axis == "quality")

if set(REGISTERED) != set(ORDER):  # pragma: no cover - a programming error, caught by every test run
    raise AssertionError(f"registry and ORDER differ: {sorted(set(REGISTERED) ^ set(ORDER))}")

__all__ = ["FAMILIES", "ORDER", "QUALITY_FAMILIES", "SEVERITIES", "SPEC_VERSION", "Family"]
