"""The few pytest internals the plugin needs, in one place, each with a fallback.

pytest has no public API for these four: telling a fixture function from a plain one, reaching the function a
fixture decorator wraps (a Ray actor builds the planner fixture outside pytest), registering the fixtures of a
module imported by hand (the planner file) with the visibility of a collector's items, and reaching the JUnit XML
writer to add suite properties from the controller.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest


def is_fixture(obj: object) -> bool:
    """Whether `obj` is a function decorated with ``@pytest.fixture``."""
    try:
        from _pytest.fixtures import getfixturemarker
    except ImportError:  # pragma: no cover - a pytest without it: the decorator leaves this attribute
        return hasattr(obj, "_fixture_function_marker") or hasattr(obj, "_pytestfixturefunction")
    return getfixturemarker(obj) is not None


def fixture_function(obj: Any) -> tuple[str, Any]:
    """The name a fixture is requested by and the user's function behind the decorator (`obj` is a fixture)."""
    from _pytest.fixtures import getfixturemarker

    marker = getfixturemarker(obj)
    get = getattr(obj, "_get_wrapped_function", None)  # pytest >= 8.4: a FixtureFunctionDefinition
    if callable(get):
        function = get()
    else:  # pragma: no cover - older pytest: the function itself, wrapped to fail when called directly
        wrapped = getattr(obj, "__pytest_wrapped__", None)
        function = wrapped.obj if wrapped is not None else obj
    name = getattr(marker, "name", None) or function.__name__
    return str(name), function


def register_module_fixtures(collector: pytest.Collector, module: ModuleType) -> None:
    """Register `module`'s fixtures for the items under `collector`, as a test module's own fixtures are (so its
    `planner` wins over one a conftest.py above it provides).

    pytest parses a node's fixtures from ``node.obj``; the collector is given the module as its ``obj`` and
    passed as a node, the form pytest 9 keeps (passing a node id string is deprecated).
    """
    collector.obj = module  # type: ignore[attr-defined]
    collector.session._fixturemanager.parsefactories(collector)


def junit_xml(config: pytest.Config) -> Any:
    """The LogXML of ``--junitxml``, or None (not configured, or a pytest that moved it)."""
    try:
        from _pytest.junitxml import xml_key
    except ImportError:  # pragma: no cover
        return None
    return config.stash.get(xml_key, None)
