"""The certification session: the hooks that collect cell items, run each one, receive results as each cell
finishes, and hand the end of the run to the controller.

Computes nothing itself: `checks` does a cell's work, `controller` the end of the run. Results cross the xdist
boundary as plain builtins on the test report (pytest's report serialisation carries extra attributes); the
controller is the only writer.
"""

from __future__ import annotations

from collections.abc import Generator, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from ..cells import CellPayload, run_order
from ..errors import DriveDegradeError
from ..run import RunContext
from ..store import ResultStore
from . import SESSION_KEY
from .context import build_run_context
from .controller import Outcome
from .items import CellCollector, CellItem, NothingCollector, conftest_with_planner, import_planner_file
from .options import RunOptions, parse

__all__ = ["PAYLOAD_ATTR", "SESSION_KEY", "DriveDegradeSession"]

#: The report attribute that carries a finished cell's payload (as builtins) to the controller.
PAYLOAD_ATTR = "drivedegrade_payload"


def _is_worker(config: pytest.Config) -> bool:
    return hasattr(config, "workerinput")


def _certify_cell(planner: Any, request: pytest.FixtureRequest) -> None:
    """One certification cell (the item's name says which); the function every cell item runs."""
    session = request.config.stash[SESSION_KEY]
    item = request.node
    assert isinstance(item, CellItem)
    session.run_item(item, planner)


class DriveDegradeSession:
    """Registered as a plugin when --drivedegrade is given; one per process, reached through
    ``config.stash[SESSION_KEY]``."""

    NAME = "drivedegrade-session"

    def __init__(self, config: pytest.Config, options: RunOptions, collect_path: Path,
                 planner_module: ModuleType | None, baseline: Mapping[str, Any] | None) -> None:
        self.config, self.options, self.collect_path = config, options, collect_path
        self.planner_module = planner_module  # the imported planner file; None in conftest mode
        self.baseline = baseline
        self.cells = run_order(options.families, options.severities, ego=options.ego)
        self.store = ResultStore(options.report_dir, options.shard.label if options.shard else None)
        self.context: RunContext | None = None  # opened lazily, once per process
        self.received: dict[str, CellPayload] = {}  # controller: cell -> payload, as each cell finishes
        self.outcome: Outcome | None = None  # controller: the end of the run
        self.name_error: str | None = None  # the planner name's check, done once at the first cell ("": fine)
        self._device_env: str | None = None  # $DRIVEDEGRADE_DEVICE before this run set it

    @classmethod
    def start(cls, config: pytest.Config) -> DriveDegradeSession:
        options = parse(config)
        module = None
        if options.planner_path is not None:
            module = import_planner_file(options.planner_path)  # its fixtures are registered by CellCollector
            collect_path = options.planner_path
        else:
            collect_path = conftest_with_planner(config)
        baseline = None
        if options.baseline_path is not None:
            from ..report.certificate import CertificateError, verify

            if not options.baseline_path.is_file():
                raise pytest.UsageError(f"--drivedegrade-baseline: {options.baseline_path} does not exist")
            try:
                baseline = verify(options.baseline_path)
            except CertificateError as exc:
                raise pytest.UsageError(f"--drivedegrade-baseline: {exc}") from None
        config.args = [str(collect_path)]  # collect the cells, not the rest of the test tree
        session = cls(config, options, collect_path, module, baseline)
        session.use_device()
        return session

    def use_device(self) -> None:
        """--drivedegrade-device for every planner of the run: ``$DRIVEDEGRADE_DEVICE`` set for this process and
        the workers and actors it starts (restored at the end, `pytest_unconfigure`); on CUDA, cuDNN made
        deterministic (no autotuned kernel choice, no TF32 convolutions) so a GPU run is bit-reproducible."""
        import os

        from ..planning import DEVICE_ENV

        self._device_env = os.environ.get(DEVICE_ENV)
        os.environ[DEVICE_ENV] = self.options.device
        if self.options.device != "cpu":
            import torch

            torch.backends.cudnn.deterministic = True
            torch.backends.cudnn.benchmark = False
            torch.backends.cudnn.allow_tf32 = False

    def pytest_unconfigure(self, config: pytest.Config) -> None:
        import os

        from ..planning import DEVICE_ENV

        if self._device_env is None:
            os.environ.pop(DEVICE_ENV, None)
        else:
            os.environ[DEVICE_ENV] = self._device_env

    # --- collection ------------------------------------------------------------------------------------------

    def pytest_collect_file(self, file_path: Path, parent: pytest.Collector) -> pytest.Collector | None:
        if file_path != self.collect_path:
            return None
        collector = CellCollector.from_parent(parent, path=file_path)
        collector.module, collector.cells, collector.call = self.planner_module, self.cells, _certify_cell
        return collector

    @pytest.hookimpl(tryfirst=True)
    def pytest_pycollect_makemodule(self, module_path: Path, parent: pytest.Collector) -> pytest.Collector | None:
        """A planner file named like a test module is collected once, as cells, not also as a module."""
        if module_path == self.collect_path:
            return NothingCollector.from_parent(parent, path=module_path)
        return None

    # --- the run ---------------------------------------------------------------------------------------------

    def run_context(self) -> RunContext:
        """The run's data and scored frames, opened once per process (DriveDegradeError on bad data)."""
        if self.context is None:
            self.context = build_run_context(self.config, self.options)
        return self.context

    def pytest_sessionstart(self, session: pytest.Session) -> None:
        """Render or index the data once on the controller, before workers start, and fail fast on bad data."""
        if _is_worker(self.config):
            return
        try:
            context = self.run_context()
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

    def _check_baseline(self, context: RunContext) -> None:
        """A baseline from another ladder or data set is a usage error now, not a failure after the whole run."""
        if self.baseline is None:
            return
        from ..corruptions.ladder import SPEC_VERSION
        from ..scoring.baseline import BaselineError, check_baseline_compatible

        try:
            check_baseline_compatible(self.baseline, spec_version=SPEC_VERSION,
                                      dataset_fingerprint=context.dataset_fingerprint, seeds=self.options.seeds)
        except BaselineError as exc:
            raise pytest.UsageError(f"--drivedegrade-baseline: {self.options.baseline_path}: {exc}") from None

    def run_item(self, item: CellItem, planner: Any) -> None:
        from .checks import certify

        family, severity = item.drivedegrade_cell
        self._check_name(item, planner)
        try:
            context = self.run_context()
            payload, failures = certify(context, planner, family, severity,
                                        store=self.store, baseline=self.baseline,
                                        tolerance=self.options.tolerance)
        except DriveDegradeError as exc:  # bad data, or planner.cameras / planner.name malformed: no traceback
            pytest.fail(f"cell {item.name}: {exc}", pytrace=False)
        item.stash[PAYLOAD_KEY] = payload
        item.user_properties.extend(payload.properties)
        if failures:
            pytest.fail("\n".join(failures), pytrace=False)

    def _check_name(self, item: CellItem, planner: Any) -> None:
        """The planner's name, checked once when the planner first exists (the first cell): a bad one fails that
        cell with the rule it breaks and stops the session, rather than failing every cell the same way."""
        if self.name_error is None:
            from ..errors import InvalidInput
            from ..planning import planner_name

            default = self.options.planner_path.stem if self.options.planner_path else "planner"
            try:
                planner_name(planner, default)
                self.name_error = ""
            except InvalidInput as exc:
                self.name_error = str(exc)
        if self.name_error:
            message = f"--drivedegrade: unusable planner name: {self.name_error}"
            item.session.shouldstop = message
            pytest.fail(message, pytrace=False)

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_makereport(self, item: pytest.Item,
                                  call: pytest.CallInfo[None]) -> Generator[None, pytest.TestReport, pytest.TestReport]:
        report = yield
        payload = item.stash.get(PAYLOAD_KEY, None)
        if report.when == "call" and payload is not None:
            setattr(report, PAYLOAD_ATTR, payload.to_builtins())
        return report

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        """Controller: write each finished cell to disk at once, so a crash or Ctrl-C loses nothing."""
        data = getattr(report, PAYLOAD_ATTR, None)
        if data is None or _is_worker(self.config):
            return
        payload = CellPayload.from_builtins(data)
        self.received[payload.cell] = payload
        self.store.write(payload)

    @pytest.hookimpl(tryfirst=True)
    def pytest_sessionfinish(self, session: pytest.Session, exitstatus: int) -> None:
        if _is_worker(self.config):
            return
        from .controller import finish_run

        self.outcome = finish_run(self.config, self.options, self.context, self.received, self.cells, self.baseline,
                                  self.store)
        if self.outcome is not None and self.outcome.failed and session.exitstatus == 0:
            session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        if self.outcome is not None:
            terminalreporter.section("drivedegrade")
            for line in self.outcome.lines:
                terminalreporter.write_line(line)


PAYLOAD_KEY = pytest.StashKey[CellPayload]()
