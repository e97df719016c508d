"""The certification session: the hooks that collect cell items, run each one, receive results as each cell
finishes, and hand the end of the run to the controller.

Computes nothing itself: `checks` does a cell's work, `controller` the end of the run. Results cross the xdist
boundary as plain builtins on the test report (pytest's report serialisation carries extra attributes); the
controller is the only writer.
"""

from __future__ import annotations

import json
import time
from collections.abc import Generator, Mapping
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import pytest

from ..cells import CellPayload, cell_id, run_order
from ..errors import DriveDegradeError
from ..run import RunContext
from ..store import ResultStore
from . import SESSION_KEY
from .context import build_run_context
from .controller import Outcome, planner_file
from .items import CellCollector, CellItem, NothingCollector, conftest_with_planner, import_planner_file
from .options import RunOptions, parse

if TYPE_CHECKING:
    from ..raypool import RayPlanner

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


#: The files the controller writes in a planner's (or a shard's) folder; cells/ holds one <cell>.json each.
OUTPUT_FILES = ("certificate.json", "cells.csv", "report.html", "shard.json")


def sweep_temporaries(report_dir: Path, started: float) -> list[Path]:
    """Remove the temporary files of our atomic writes that an interrupted run left (named exactly as the atomic
    writer names them, older than this run's start) in each planner folder, its shard folders and their cells/;
    return what was removed."""
    from ..atomic import stray_temporaries

    removed = []
    for planner in sorted(p for p in report_dir.iterdir() if p.is_dir() and not p.is_symlink()):
        for folder in (planner, *sorted(p for p in planner.iterdir() if p.is_dir() and p.name != "cells")):
            for path in [*stray_temporaries(folder, OUTPUT_FILES, started),
                         *stray_temporaries(folder / "cells", None, started)]:
                try:
                    path.unlink()
                    removed.append(path)
                except OSError:
                    pass
    return removed


def _refuse_own_output(options: RunOptions) -> None:
    """A baseline that is (or resolves to, through symlinks) a certificate this run writes, some
    `<report>/<planner>/certificate.json`, would be replaced by the run it gates, so the next run compares the
    planner with itself and passes: a usage error before anything runs."""
    assert options.baseline_path is not None
    real = options.baseline_path.resolve()
    if real.name == "certificate.json" and real.parent.parent == options.report_dir.resolve():
        shown = "" if real == options.baseline_path else f" (it resolves to {real})"
        raise pytest.UsageError(
            f"--drivedegrade-baseline: {options.baseline_path}{shown} lies in this run's report folder "
            f"{options.report_dir}, where the run writes its own certificate: a failing run would replace the "
            "baseline and the next run would pass against itself; copy it elsewhere first (e.g. cp "
            f"{real} baseline.json) and pass the copy, or pass another --drivedegrade-report")


def _certify_cell_in_actors(request: pytest.FixtureRequest) -> None:
    """One cell under --drivedegrade-ray: the planner is the actors' (the controller never builds it)."""
    session = request.config.stash[SESSION_KEY]
    item = request.node
    assert isinstance(item, CellItem) and session.remote is not None
    session.run_item(item, session.remote)


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
        shard = options.settings.shard
        self.store = ResultStore(options.report_dir, shard.label if shard else None)
        self.context: RunContext | None = None  # opened lazily, once per process
        self.received: dict[str, CellPayload] = {}  # controller: cell -> payload, as each cell finishes
        self.outcome: Outcome | None = None  # controller: the end of the run
        self.name_error: str | None = None  # the planner name's check, done once at the first cell ("": fine)
        self.started = time.time()  # temporary files older than this are left by an earlier, interrupted run
        self.remote: RayPlanner | None = None  # --drivedegrade-ray: the planner actors (controller only)
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
            from ..certificate.seal import CertificateError, verify

            if not options.baseline_path.is_file():
                raise pytest.UsageError(f"--drivedegrade-baseline: {options.baseline_path} does not exist")
            _refuse_own_output(options)
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

        from ..planning import DEVICE_ENV, deterministic_cuda

        self._device_env = os.environ.get(DEVICE_ENV)
        os.environ[DEVICE_ENV] = self.options.settings.device
        if self.options.settings.device != "cpu":
            deterministic_cuda()

    def pytest_unconfigure(self, config: pytest.Config) -> None:
        """Never leave actors or a local cluster behind, whatever ended the session; restore the device variable."""
        import os

        self._close_actors()

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
        call = _certify_cell_in_actors if self.options.ray else _certify_cell
        collector.module, collector.cells, collector.call = self.planner_module, self.cells, call
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
        if self.options.ray is not None:
            from .actors import start_planner_actors

            try:
                self.remote = start_planner_actors(self.config, self.options, context, self.collect_path)
            except DriveDegradeError as exc:
                raise pytest.UsageError(f"--drivedegrade-ray: {exc}") from None

    def _check_report_dir(self) -> None:
        """Results are written as each cell finishes: a report folder that cannot be created fails now. The
        temporary files of writes a kill -9 interrupted are swept, and the terminal says so."""
        folder = self.options.report_dir
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise pytest.UsageError(f"--drivedegrade-report: cannot create the report folder {folder}: "
                                    f"{exc.strerror or exc}") from None
        removed = sweep_temporaries(folder, self.started)
        reporter = self.config.pluginmanager.get_plugin("terminalreporter")
        if removed and reporter is not None:
            shown = ", ".join(str(p.relative_to(folder)) for p in removed[:5])
            more = f" and {len(removed) - 5} more" if len(removed) > 5 else ""
            reporter.write_line(f"drivedegrade: removed {len(removed)} temporary file(s) left in {folder} by an "
                                f"interrupted write: {shown}{more}")

    def _check_baseline(self, context: RunContext) -> None:
        """A baseline from another ladder, data set or settings, or one that does not cover this run's cells
        (unless --drivedegrade-baseline-partial), is a usage error now, not a failure after the whole run."""
        if self.baseline is None:
            return
        from ..corruptions.ladder import SPEC_VERSION
        from ..scoring.baseline import BaselineError, check_baseline_compatible, not_compared

        opts = self.options
        where = f"--drivedegrade-baseline: {opts.baseline_path}"
        try:
            check_baseline_compatible(self.baseline, spec_version=SPEC_VERSION,
                                      dataset_fingerprint=context.dataset_fingerprint,
                                      frames_scored=context.frames_total, settings=opts.settings)
        except BaselineError as exc:
            raise pytest.UsageError(f"{where}: {exc}") from None
        gaps = not_compared(self.baseline, [cell_id(f, s) for f, s in self.cells])
        if gaps and not opts.baseline_partial:
            raise pytest.UsageError(f"{where}: the baseline does not cover this run, so part of it would not be "
                                    f"compared: {'; '.join(gaps)}; certify a complete baseline with this run's "
                                    "families and severities, or pass --drivedegrade-baseline-partial to gate on "
                                    "what both have")

    def run_item(self, item: CellItem, planner: Any) -> None:
        from .checks import certify, prefetch

        family, severity = item.drivedegrade_cell
        self._check_name(item, planner)
        try:
            context = self.run_context()
            coming = self._next_cell(item)
            if coming is not None:  # planner actors: start the next cell now, so they never wait for this one's end
                prefetch(context, planner, *coming, store=self.store)
            payload, failures = certify(context, planner, family, severity,
                                        store=self.store, baseline=self.baseline,
                                        tolerance=self.options.tolerance)
        except DriveDegradeError as exc:  # bad data, or planner.cameras / planner.name malformed: no traceback
            pytest.fail(f"cell {item.name}: {exc}", pytrace=False)
        item.stash[PAYLOAD_KEY] = payload
        item.user_properties.extend(payload.properties)
        if failures:
            pytest.fail("\n".join(failures), pytrace=False)

    def _next_cell(self, item: CellItem) -> tuple[str, int] | None:
        """The cell of the item that runs after `item` (None for the last one, or without planner actors)."""
        if self.remote is None:
            return None
        items = item.session.items
        at = next((i for i, it in enumerate(items) if it is item), len(items))
        return next((it.drivedegrade_cell for it in items[at + 1:] if isinstance(it, CellItem)), None)

    def _check_name(self, item: CellItem, planner: Any) -> None:
        """The planner's name, checked once when the planner first exists (the first cell): a bad one, or one
        that is not the baseline's planner (unless --drivedegrade-baseline-any-planner), fails that cell with
        the reason and stops the session, rather than failing every cell the same way."""
        if self.name_error is None:
            self.name_error = self._name_problem(planner)
        if self.name_error:
            item.session.shouldstop = self.name_error
            pytest.fail(self.name_error, pytrace=False)

    def _name_problem(self, planner: Any) -> str:
        """Why this planner cannot be certified under its name ("" when it can)."""
        from ..errors import InvalidInput
        from ..planning import planner_name

        default = self.options.planner_path.stem if self.options.planner_path else "planner"
        try:
            name = planner_name(planner, default)
        except InvalidInput as exc:
            return f"--drivedegrade: unusable planner name: {exc}"
        if self.baseline is not None and not self.options.baseline_any_planner:
            from ..scoring.baseline import planner_mismatch

            foreign = planner_mismatch(self.baseline, name)
            if foreign:
                return f"--drivedegrade-baseline: {self.options.baseline_path}: {foreign}"
        if not self.options.report_overwrite:
            return self._folder_owner_problem(name)
        return ""

    def _folder_owner_problem(self, name: str) -> str:
        """A report folder whose certificate records another planner file (a planner of the same name) is not
        overwritten silently; checked when the name is first known, before any cell computes."""
        folder = self.options.report_dir / name
        try:
            planner = json.loads((folder / "certificate.json").read_text()).get("planner", {})
            theirs = planner.get("file") if isinstance(planner, dict) else None
        except (OSError, ValueError, AttributeError):
            return ""  # none, or unreadable: nothing recorded to protect
        mine = planner_file(self.config, self.collect_path)
        if not isinstance(theirs, str) or theirs == mine:
            return ""
        return (f"--drivedegrade-report: {folder} holds the certificate of another planner named {name!r} "
                f"(planner file {theirs}; this run's is {mine}); pass another --drivedegrade-report, or "
                "--drivedegrade-report-overwrite to replace its outputs")

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

        actors = self._close_actors()
        self.outcome = finish_run(self.config, self.options, self.context, self.received, self.cells, self.baseline,
                                  self.store, planner_file=planner_file(self.config, self.collect_path))
        if self.outcome is not None:
            self.outcome.lines += actors
        if self.outcome is not None and self.outcome.failed and session.exitstatus == 0:
            session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def _close_actors(self) -> list[str]:
        """Tear the planner actors down (their fixtures' teardown) and disconnect from Ray; the pool's lines."""
        remote, self.remote = self.remote, None
        if remote is None:
            return []
        return remote.pool.summary() + remote.pool.close()

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        if self.outcome is not None:
            terminalreporter.section("drivedegrade")
            for line in self.outcome.lines:
                terminalreporter.write_line(line)


PAYLOAD_KEY = pytest.StashKey[CellPayload]()
