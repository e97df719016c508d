"""The certification session: collection of cell items, the xdist hand-off, results as each cell finishes.

Computes nothing itself: `run` does a cell's work, `finish` the controller's end-of-run analysis and
outputs. Results cross the xdist boundary as plain builtins attached to the test report.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from typing import Any

import pytest

from .loader import cell_id
from .options import RunOptions, parse
from .store import ResultStore

RECORD_ATTR = "drivedegrade_record"


def _is_worker(config: pytest.Config) -> bool:
    return hasattr(config, "workerinput")


def _fixture_marker(obj: Any) -> bool:
    from _pytest.fixtures import getfixturemarker

    return getfixturemarker(obj) is not None


def _import_planner_file(path: Path) -> Any:
    """Import a planner file as a module, or raise a UsageError that says what is wrong with it."""
    if not path.is_file():
        raise pytest.UsageError(f"--drivedegrade: planner file {path} does not exist; give the path of a .py file "
                                "that defines a `planner` fixture (see planners/template.py)")
    if path.suffix != ".py":
        raise pytest.UsageError(f"--drivedegrade: {path} is not a Python file (.py)")
    name = f"drivedegrade_planner_{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)  # type: ignore[union-attr]
    except SyntaxError as exc:
        raise pytest.UsageError(f"--drivedegrade: {path}:{exc.lineno}: syntax error: {exc.msg}") from None
    except Exception as exc:  # noqa: BLE001 - any import-time failure of the user's file
        import traceback

        where = [f for f in traceback.extract_tb(exc.__traceback__) if Path(f.filename) == path]
        line = f":{where[-1].lineno}" if where else ""
        raise pytest.UsageError(f"--drivedegrade: importing {path}{line} failed: {type(exc).__name__}: {exc}") from None
    planner = getattr(module, "planner", None)
    if planner is None:
        raise pytest.UsageError(f"--drivedegrade: {path} defines no `planner` fixture; add one, e.g.\n"
                                "    @pytest.fixture(scope='session')\n    def planner():\n        return MyPlanner()")
    if not _fixture_marker(planner):
        raise pytest.UsageError(f"--drivedegrade: `planner` in {path} is not a pytest fixture; decorate it with "
                                "@pytest.fixture(scope='session')")
    return module


def _conftest_with_planner(config: pytest.Config) -> Path:
    """The conftest.py whose `planner` fixture is certified when --drivedegrade has no PATH."""
    found = sorted({Path(p.__file__) for p in config.pluginmanager.get_plugins()
                    if getattr(p, "__file__", "") and Path(p.__file__).name == "conftest.py"
                    and _fixture_marker(getattr(p, "planner", None))})
    if not found:
        raise pytest.UsageError("--drivedegrade: no PATH given and no conftest.py defines a `planner` fixture; "
                                "pass a planner file (pytest --drivedegrade planners/myplanner.py) or run from the "
                                "test folder whose conftest.py provides `planner`")
    if len(found) > 1:
        raise pytest.UsageError("--drivedegrade: several conftest.py files define `planner` "
                                f"({', '.join(map(str, found))}); pass the one to certify as PATH")
    return found[0]


def _certify_cell(planner: Any, drivedegrade_context: Any, request: pytest.FixtureRequest) -> None:
    """One certification cell (the item's name says which)."""
    session = request.config.pluginmanager.get_plugin(DriveDegradeSession.NAME)
    session.run_item(request.node, planner, drivedegrade_context)


class CellItem(pytest.Function):
    """One cell's test item. Reported by its cell id and the planner file, not by the plugin's own source."""

    def reportinfo(self):
        return self.path, None, self.name


class CellCollector(pytest.File):
    """Collects one item per cell from the planner file (or the conftest that provides `planner`)."""

    def collect(self):
        session = self.config.pluginmanager.get_plugin(DriveDegradeSession.NAME)
        if session.planner_module is not None:
            # The file's fixtures, scoped to its items as a test module's are: its `planner` wins over a
            # `planner` fixture some conftest.py above it provides (registered as a plugin, it would lose).
            self.session._fixturemanager.parsefactories(session.planner_module, self.nodeid)
        for family, severity in session.cells():
            item = CellItem.from_parent(self, name=cell_id(family, severity), callobj=_certify_cell)
            item.drivedegrade_cell = (family, severity)
            yield item


class DriveDegradeSession:
    """Registered as a plugin when --drivedegrade is given; one per process."""

    NAME = "drivedegrade-session"

    def __init__(self, config: pytest.Config, options: RunOptions, collect_path: Path,
                 baseline: dict[str, Any] | None) -> None:
        self.config, self.options, self.collect_path, self.baseline = config, options, collect_path, baseline
        self.planner_module: Any = None  # the imported planner file; None in conftest mode
        self.context = None  # RunContext, opened lazily per process
        self.records: dict[str, dict[str, Any]] = {}  # controller: cell -> {"key", "planner", "record"}
        self.outcome: Any = None  # finish.Outcome on the controller

    @classmethod
    def start(cls, config: pytest.Config) -> "DriveDegradeSession":
        options = parse(config)
        if options.planner_path is not None:
            module = _import_planner_file(options.planner_path)  # its fixtures are parsed by CellCollector
            collect_path = options.planner_path
        else:
            collect_path = _conftest_with_planner(config)
        baseline = None
        if options.baseline_path is not None:
            from .report.certificate import CertificateError, verify

            if not options.baseline_path.is_file():
                raise pytest.UsageError(f"--drivedegrade-baseline: {options.baseline_path} does not exist")
            try:
                baseline = verify(options.baseline_path)
            except CertificateError as exc:
                raise pytest.UsageError(f"--drivedegrade-baseline: {exc}") from None
        config.args = [str(collect_path)]  # collect the cells, not the rest of the test tree
        session = cls(config, options, collect_path, baseline)
        session.planner_module = module if options.planner_path is not None else None
        return session

    # --- collection ------------------------------------------------------------------------------------------

    def cells(self) -> list[tuple[str, int]]:
        """Cells in run order: clean first and the null control last, so that under xdist the clean result
        is already stored when the null control (and the baseline gate) compare against it, and no worker
        computes clean twice."""
        ladder = [(f, s) for f in self.options.families for s in self.options.severities]
        return [("clean", 0), *ladder, ("blind", 0), ("null", 0)]

    def pytest_collect_file(self, file_path: Path, parent: pytest.Collector):
        if file_path == self.collect_path:
            return CellCollector.from_parent(parent, path=file_path)
        return None

    @pytest.hookimpl(tryfirst=True)
    def pytest_pycollect_makemodule(self, module_path: Path, parent: pytest.Collector):
        """A planner file named like a test module is collected once, as cells, not also as a module."""
        if module_path == self.collect_path:
            return _Nothing.from_parent(parent, path=module_path)
        return None

    # --- the run ---------------------------------------------------------------------------------------------

    def open_context(self):
        if self.context is None:
            from .finish import open_run_context

            self.context = open_run_context(self.config, self.options)
        return self.context

    @pytest.fixture(scope="session")
    def drivedegrade_context(self):
        from .errors import DriveDegradeError

        try:
            return self.open_context()
        except DriveDegradeError as exc:
            pytest.fail(str(exc), pytrace=False)

    def pytest_sessionstart(self, session: pytest.Session) -> None:
        """Render or index the data once on the controller, before workers start, and fail fast on bad data."""
        if _is_worker(self.config):
            return
        from .errors import DriveDegradeError

        try:
            context = self.open_context()
        except DriveDegradeError as exc:
            raise pytest.UsageError(f"--drivedegrade: {exc}") from None
        self._check_baseline(context)
        self._check_report_dir()

    def _check_report_dir(self) -> None:
        """Results are written as each cell finishes: a report folder that cannot be created fails now."""
        folder = self.options.report_dir
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise pytest.UsageError(f"--drivedegrade-report: cannot create the report folder {folder}: "
                                    f"{exc.strerror or exc}") from None

    def _check_baseline(self, context: Any) -> None:
        """A baseline from another ladder or data set is a usage error now, not a failure after the whole run."""
        if self.baseline is None:
            return
        from .analysis import BaselineError, check_baseline_compatible
        from .corruptions.registry import SPEC_VERSION

        try:
            check_baseline_compatible(self.baseline, spec_version=SPEC_VERSION,
                                      dataset_fingerprint=context.dataset_fingerprint)
        except BaselineError as exc:
            raise pytest.UsageError(f"--drivedegrade-baseline: {self.options.baseline_path}: {exc}") from None

    def run_item(self, item: pytest.Item, planner: Any, context: Any) -> None:
        from .cellcheck import certify
        from .errors import DriveDegradeError

        family, severity = item.drivedegrade_cell
        store = ResultStore(self.options.report_dir)
        try:
            payload, failures = certify(context, planner, family, severity, store=store, baseline=self.baseline,
                                        tolerance=self.options.tolerance)
        except DriveDegradeError as exc:  # e.g. planner.cameras or planner.name is malformed: say so, no traceback
            payload, failures = None, [f"cell {item.name}: {exc}"]
        if payload is None:
            pytest.fail(failures[0], pytrace=False)
        setattr(item, RECORD_ATTR, payload)
        item.user_properties.extend(payload["properties"])
        if failures:
            pytest.fail("\n".join(failures), pytrace=False)

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_makereport(self, item: pytest.Item, call: pytest.CallInfo):
        report = yield
        payload = getattr(item, RECORD_ATTR, None)
        if report.when == "call" and payload is not None:
            setattr(report, RECORD_ATTR, payload)
        return report

    @pytest.hookimpl(wrapper=True)
    def pytest_report_to_serializable(self, config: pytest.Config, report: Any):
        data = yield
        payload = getattr(report, RECORD_ATTR, None)
        if data is not None and payload is not None:
            data[RECORD_ATTR] = payload
        return data

    @pytest.hookimpl(wrapper=True)
    def pytest_report_from_serializable(self, config: pytest.Config, data: dict[str, Any]):
        report = yield
        if report is not None and RECORD_ATTR in data:
            setattr(report, RECORD_ATTR, data[RECORD_ATTR])
        return report

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        """Controller: write each finished cell to disk at once, so a crash or Ctrl-C loses nothing."""
        payload = getattr(report, RECORD_ATTR, None)
        if payload is None or _is_worker(self.config):
            return
        self.records[payload["record"]["cell"]] = payload
        ResultStore(self.options.report_dir).write(payload)

    @pytest.hookimpl(tryfirst=True)
    def pytest_sessionfinish(self, session: pytest.Session, exitstatus: int) -> None:
        if _is_worker(self.config):
            return
        from .finish import finish_run

        self.outcome = finish_run(self, session)
        if self.outcome is not None and self.outcome.failed and session.exitstatus == 0:
            session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        if self.outcome is not None:
            terminalreporter.section("drivedegrade")
            for line in self.outcome.lines:
                terminalreporter.write_line(line)


class _Nothing(pytest.File):
    def collect(self):
        return []
