"""Collection: the planner file imported by hand, and one test item per cell collected from it.

The planner file is imported only when `--drivedegrade` is given; a broken file is a usage error that says what
is wrong and where, never a traceback.
"""

from __future__ import annotations

import importlib.util
import sys
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from ..cells import cell_id
from .compat import is_fixture, register_module_fixtures


def planner_runs_elsewhere(config: pytest.Config, ray: object, isolate: bool = False) -> bool:
    """Whether this process only controls the run (issue 37, "planner code runs in the process that decides the
    exit status"): the xdist controller under ``-n N`` (N >= 1), or any non-worker process under
    ``--drivedegrade-ray``. Such a process never imports the planner file: its code runs in the workers or the
    actors, so no module-level patch, ``atexit`` handler or ``os._exit`` of it can reach the gate's decision or
    the exit status. Under ``--drivedegrade-isolate`` no process of the run imports it: the planner's own
    children do (`childplanner`)."""
    if isolate:
        return True
    if hasattr(config, "workerinput"):
        return False
    workers = getattr(config.option, "numprocesses", None)
    return ray is not None or (bool(workers) and getattr(config.option, "dist", "no") != "no")


def check_planner_file(path: Path) -> None:
    """The checks `import_planner_file` makes, without running any of the file: it exists, is Python, parses,
    and defines a ``planner`` at module level (a usage error otherwise). For a process that must not run it."""
    import ast

    if not path.is_file():
        raise pytest.UsageError(f"--drivedegrade: planner file {path} does not exist; give the path of a .py file "
                                "that defines a `planner` fixture (see planners/template.py)")
    if path.suffix != ".py":
        raise pytest.UsageError(f"--drivedegrade: {path} is not a Python file (.py)")
    try:
        tree = ast.parse(path.read_bytes(), filename=str(path))
    except SyntaxError as exc:
        raise pytest.UsageError(f"--drivedegrade: {path}:{exc.lineno}: syntax error: {exc.msg}") from None
    except (OSError, ValueError) as exc:
        raise pytest.UsageError(f"--drivedegrade: {path} cannot be read: {exc}") from None
    names = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}
    names |= {t.id for n in tree.body if isinstance(n, (ast.Assign, ast.AnnAssign))
              for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
    names |= {a.asname or a.name for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom)) for a in n.names}
    if "planner" not in names and "*" not in names:
        raise pytest.UsageError(f"--drivedegrade: {path} defines no `planner` fixture; add one, e.g.\n"
                                "    @pytest.fixture(scope='session')\n    def planner():\n        return MyPlanner()")


def import_planner_file(path: Path, name: str | None = None) -> ModuleType:
    """Import a planner file as a module (under `name`, by default ``drivedegrade_planner_<stem>``), or raise a
    UsageError that says what is wrong with it."""
    if not path.is_file():
        raise pytest.UsageError(f"--drivedegrade: planner file {path} does not exist; give the path of a .py file "
                                "that defines a `planner` fixture (see planners/template.py)")
    if path.suffix != ".py":
        raise pytest.UsageError(f"--drivedegrade: {path} is not a Python file (.py)")
    name = name or f"drivedegrade_planner_{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:  # pragma: no cover - a .py file always has a loader
        raise pytest.UsageError(f"--drivedegrade: {path} cannot be imported")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except SyntaxError as exc:
        raise pytest.UsageError(f"--drivedegrade: {path}:{exc.lineno}: syntax error: {exc.msg}") from None
    except Exception as exc:  # noqa: BLE001 - any import-time failure of the user's file
        where = [f for f in traceback.extract_tb(exc.__traceback__) if Path(f.filename) == path]
        line = f":{where[-1].lineno}" if where else ""
        raise pytest.UsageError(f"--drivedegrade: importing {path}{line} failed: {type(exc).__name__}: {exc}") from None
    planner = getattr(module, "planner", None)
    if planner is None:
        raise pytest.UsageError(f"--drivedegrade: {path} defines no `planner` fixture; add one, e.g.\n"
                                "    @pytest.fixture(scope='session')\n    def planner():\n        return MyPlanner()")
    if not is_fixture(planner):
        raise pytest.UsageError(f"--drivedegrade: `planner` in {path} is not a pytest fixture; decorate it with "
                                "@pytest.fixture(scope='session')")
    return module


def conftest_with_planner(config: pytest.Config) -> Path:
    """The conftest.py whose `planner` fixture is certified when --drivedegrade has no PATH."""
    found = sorted({Path(p.__file__) for p in config.pluginmanager.get_plugins()
                    if getattr(p, "__file__", "") and Path(p.__file__).name == "conftest.py"
                    and is_fixture(getattr(p, "planner", None))})
    if not found:
        raise pytest.UsageError("--drivedegrade: no PATH given and no conftest.py defines a `planner` fixture; "
                                "pass a planner file (pytest --drivedegrade planners/myplanner.py) or run from the "
                                "test folder whose conftest.py provides `planner`")
    if len(found) > 1:
        raise pytest.UsageError("--drivedegrade: several conftest.py files define `planner` "
                                f"({', '.join(map(str, found))}); pass the one to certify as PATH")
    return found[0]


class CellItem(pytest.Function):
    """One cell's test item. Reported by its cell id and the planner file, not by the plugin's own source."""

    drivedegrade_cell: tuple[str, int]

    def reportinfo(self) -> tuple[Path, None, str]:
        return self.path, None, self.name


class ClosedItem(CellItem):
    """One closed-loop cell's test item (`closed-clean`, `closed-blackout-s5`, ...; SPEC section 13)."""

    drivedegrade_closed: tuple[str, int]


class CellCollector(pytest.File):
    """Collects one item per cell, in run order, from the planner file (or the conftest that provides it).

    `module` is the imported planner file (None in conftest mode); `cells` the (family, severity) run order;
    `call` the function every item runs (it takes the fixtures `planner` and `request`).
    """

    module: ModuleType | None
    cells: list[tuple[str, int]]
    call: Any
    closed: list[tuple[str, int]] = []  #: the closed-loop cells, after the open ones
    closed_call: Callable[..., None] | None = None

    def collect(self) -> Iterator[CellItem]:
        if self.module is not None:
            register_module_fixtures(self, self.module)
        for family, severity in self.cells:
            item = CellItem.from_parent(self, name=cell_id(family, severity), callobj=self.call)
            item.drivedegrade_cell = (family, severity)
            yield item
        for family, severity in self.closed:
            from ..closedloop.cells import closed_id

            closed = ClosedItem.from_parent(self, name=closed_id(family, severity), callobj=self.closed_call)
            closed.drivedegrade_cell = closed.drivedegrade_closed = (family, severity)
            yield closed


class NothingCollector(pytest.File):
    """Stands in for the planner file as a test module: it is collected once, as cells, not also as tests."""

    def collect(self) -> list[pytest.Item]:
        return []
