"""The certification session: the hooks that collect cell items, run each one, receive results as each cell
finishes, and hand the end of the run to the controller.

Computes nothing itself: `checks` does a cell's work, `controller` the end of the run. Results cross the xdist
boundary as plain builtins on the test report (pytest's report serialisation carries extra attributes); the
controller is the only writer.
"""

from __future__ import annotations

import time
from collections.abc import Generator, Mapping
from functools import partial
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, cast

import pytest

from ..cells import run_order
from ..closedloop.cells import ClosedPayload, closed_id
from ..closedloop.cells import selection as closed_selection
from ..errors import DriveDegradeError
from ..payload import CellPayload
from ..progress import Progress, Sink
from ..run import AnyPlanner, RunContext
from ..store import ResultStore
from . import SESSION_KEY, exitguard, preflight
from .closed import CLOSED_ATTR, ClosedState, write_stored
from .context import build_run_context
from .controller import Outcome, planner_file
from .egofloor import FloorAhead, start_floor
from .items import (
    CellCollector,
    CellItem,
    ClosedItem,
    NothingCollector,
    check_planner_file,
    conftest_with_planner,
    import_planner_file,
    planner_runs_elsewhere,
)
from .options import RunOptions, parse

if TYPE_CHECKING:
    from ..raypool import RayPlanner
    from ..run import AnyPlanner
    from .adaptive import AdaptiveRunner
    from .childplanner import ChildPlanner

__all__ = ["PAYLOAD_ATTR", "SESSION_KEY", "DriveDegradeSession"]

#: The report attribute that carries a finished cell's payload (as builtins) to the controller.
PAYLOAD_ATTR = "drivedegrade_payload"


def _is_worker(config: pytest.Config) -> bool:
    return hasattr(config, "workerinput")


def _certify_cell(planner: object, request: pytest.FixtureRequest) -> None:
    """One certification cell (the item's name says which); the function every cell item runs."""
    session = request.config.stash[SESSION_KEY]
    item = request.node
    assert isinstance(item, CellItem)
    session.run_item(item, planner)


def _certify_closed(planner: AnyPlanner, request: pytest.FixtureRequest) -> None:
    """One closed-loop cell (SPEC section 13): the planner drives the world's routes through the cell's cameras."""
    session = request.config.stash[SESSION_KEY]
    item = request.node
    assert isinstance(item, ClosedItem)
    session.run_closed_item(item, planner)


def _certify_closed_in_actors(request: pytest.FixtureRequest) -> None:
    """One closed-loop cell under --drivedegrade-ray: its runs are jobs of the planner actors."""
    session = request.config.stash[SESSION_KEY]
    item = request.node
    assert isinstance(item, ClosedItem) and session.remote is not None
    session.run_closed_item(item, session.remote)


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
                 planner_module: ModuleType | None, baseline: Mapping[str, object] | None) -> None:
        self.config, self.options, self.collect_path = config, options, collect_path
        self.planner_module = planner_module  # the imported planner file; None in conftest mode
        self.baseline = baseline
        loop = options.settings.loop
        self.cells = run_order(options.families, options.severities, ego=options.ego) if loop != "closed" else []
        self.closed = closed_selection(options.settings.closed_cells) if loop != "open" else []
        self.closed_state = ClosedState()  # the closed loop's routes and clean cell, once per process
        self.closed_received: dict[str, ClosedPayload] = {}  # controller: closed cell -> payload
        shard = options.settings.shard
        self.store = ResultStore(options.report_dir, shard.label if shard else None, resume=options.resume,
                                 reuse=options.settings.reuse)
        self.context: RunContext | None = None  # opened lazily, once per process
        self.received: dict[str, CellPayload] = {}  # controller: cell -> payload, as each cell finishes
        self.outcome: Outcome | None = None  # controller: the end of the run
        self.name_error: str | None = None  # the planner name's check, done once at the first cell ("": fine)
        self.horizon_error: str | None = None  # the planner horizon's check against the data's, likewise
        self.started = time.time()  # temporary files older than this are left by an earlier, interrupted run
        self.remote: RayPlanner | None = None  # --drivedegrade-ray: the planner actors (controller only)
        self.isolated: ChildPlanner | str | None = None  # --drivedegrade-isolate: the stand-in, or why none
        self._device_env: str | None = None  # $DRIVEDEGRADE_DEVICE before this run set it
        self.runner: AdaptiveRunner | None = None  # --drivedegrade-adaptive: this process's adaptive cells
        self.floor: FloorAhead | None = None  # the xdist controller's floor, worked out beside the cells
        self.guarded = False  # -n 0: os._exit refused while the run is live (`exitguard`)
        self.worker_usage: str | None = None  # -n N: a worker's usage error (the planner file failed to import)
        self.progress: Progress | None = None  # controller: the cells' progress line
        self.running: dict[str, str] = {}  # controller: node id -> cell, of the cells started and not finished

    @classmethod
    def start(cls, config: pytest.Config) -> DriveDegradeSession:
        options = parse(config)
        elsewhere = planner_runs_elsewhere(config, options.ray, options.settings.isolate)
        guarded = not elsewhere and not _is_worker(config)  # -n 0: the planner shares the status's process
        if guarded:
            exitguard.arm()
        try:
            module = None
            if options.planner_path is not None:
                if elsewhere:  # the workers or actors import it, never this process
                    check_planner_file(options.planner_path)
                else:
                    module = import_planner_file(options.planner_path)  # fixtures registered by CellCollector
                collect_path = options.planner_path
            else:
                collect_path = conftest_with_planner(config)
            baseline = preflight.load_baseline(options)
        except BaseException:
            if guarded:
                exitguard.disarm()
            raise
        config.args = [str(collect_path)]  # collect the cells, not the rest of the test tree
        session = cls(config, options, collect_path, module, baseline)
        session.guarded = guarded
        session._device_env = preflight.use_device(options.settings.device)
        return session

    def pytest_unconfigure(self, config: pytest.Config) -> None:
        """Never leave actors or a local cluster behind, whatever ended the session; restore the device variable;
        let go of the run's data (its tables, frames and caches: millions of objects), so that the full garbage
        collections pytest runs after this hook (five, for unraisable exceptions) do not walk them: 2.5 s at the
        end of the main job."""
        self._close_actors()
        if self.isolated is not None and not isinstance(self.isolated, str):
            self.isolated.close()
        preflight.restore_device(self._device_env)
        if self.floor is not None:
            self.floor.close()
        self.context, self.floor, self.runner = None, None, None
        self.received.clear()
        if self.guarded:  # the planner ran here: its os._exit is its own again, the run's status is held
            exitguard.disarm()
            exitguard.hold_final_status()

    # --- collection ------------------------------------------------------------------------------------------

    def pytest_collect_file(self, file_path: Path, parent: pytest.Collector) -> pytest.Collector | None:
        if file_path != self.collect_path:
            return None
        collector = CellCollector.from_parent(parent, path=file_path)
        call = _certify_cell_in_actors if self.options.ray else _certify_cell
        closed_call = _certify_closed_in_actors if self.options.ray else _certify_closed
        if self.options.settings.isolate:
            from .isolated import certify_isolated

            call = closed_call = certify_isolated
        collector.module, collector.cells, collector.call = self.planner_module, self.owned_cells(), call
        collector.closed, collector.closed_call = self.closed, closed_call
        return collector

    def owned_cells(self) -> list[tuple[str, int]]:
        """The cells this process collects: all of the run's, or an adaptive shard's own (`shards.adaptive_owned`;
        `self.cells` stays the run's, which the union bound counts)."""
        shard = self.options.settings.shard
        if shard is None or not self.options.settings.adaptive:
            return self.cells
        from ..shards import adaptive_owned

        return adaptive_owned(self.cells, shard)

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
        preflight.check_baseline(self.baseline, self.options, context, self.cells)
        reporter = self.config.pluginmanager.get_plugin("terminalreporter")
        self._preflight(context, reporter)
        swept = preflight.prepare_report_dir(self.options.report_dir, self.started)
        if swept and reporter is not None:
            reporter.write_line(swept)
        self.progress = Progress("drivedegrade cells", len(self.owned_cells()) + len(self.closed), unit="cells",
                                 sink=Sink.log_for_pytest(self.config), milestones=10, eta=True)
        if self.cells:  # the open cells' floor, beside them on an xdist controller (`controller.start_floor`)
            self.floor = start_floor(self.config, self.options, context)
        if self.options.ray is not None:
            from .actors import start_planner_actors

            try:
                self.remote = start_planner_actors(self.config, self.options, context, self.collect_path)
            except DriveDegradeError as exc:
                raise pytest.UsageError(f"--drivedegrade-ray: {exc}") from None

    def _preflight(self, context: RunContext, reporter: pytest.TerminalReporter | None) -> None:
        """The pre-flight check (`plannercheck`): a usage error before any cell on a mismatch; its estimate
        printed; --drivedegrade-dry-run ends the session here."""
        from .plannercheck import preflight_lines

        child = None
        if self.config.getoption("numprocesses", default=None) or self.options.settings.isolate:  # no planner code
            # runs in the controller (issue 37), nor in any process of an isolated run
            from .context import cache_root
            from .isolated import check_in_child

            child = partial(check_in_child, digests=cache_root(self.config) / "digests")
        lines = preflight_lines(self.config, self.options, context, self.collect_path, self.planner_module,
                                self.owned_cells(), len(self.closed), self.store, child)
        for line in lines:
            if reporter is not None:
                reporter.write_line(line)
        if self.options.dry_run:
            pytest.exit("drivedegrade: --drivedegrade-dry-run: stopped after the pre-flight check; no cell ran",
                        returncode=pytest.ExitCode.OK)

    def run_item(self, item: CellItem, planner: object) -> None:
        from .checks import certify, prefetch

        family, severity = item.drivedegrade_cell
        self._check_name(item, planner)
        try:
            context = self.run_context()
            self._check_horizon(item, planner, context)
            coming = self._next_cell(item)
            if coming is not None:  # planner actors: start the next cell now, so they never wait for this one's end
                prefetch(context, planner, *coming, store=self.store)
            payload, failures = certify(context, planner, family, severity,
                                        store=self.store, baseline=self.baseline,
                                        tolerance=self.options.tolerance, runner=self._runner(context, planner))
        except DriveDegradeError as exc:  # bad data, or planner.cameras / planner.name malformed: no traceback
            pytest.fail(f"cell {item.name}: {exc}", pytrace=False)
        item.stash[PAYLOAD_KEY] = payload
        item.user_properties.extend(payload.properties)
        if failures:
            pytest.fail("\n".join(failures), pytrace=False)

    def run_closed_item(self, item: ClosedItem, planner: AnyPlanner) -> None:
        """One closed-loop cell: drive (or resume) its runs and check the null control (`plugin.closed`)."""
        from .closed import certify_closed

        self._check_name(item, planner)
        try:
            payload, failures = certify_closed(self.run_context(), self.closed_state, planner,
                                               *item.drivedegrade_closed, store=self.store)
        except DriveDegradeError as exc:
            pytest.fail(f"cell {item.name}: {exc}", pytrace=False)
        from .closed import properties

        item.stash[CLOSED_KEY] = payload
        item.user_properties.extend(properties(payload.record, payload.resumed))
        if failures:
            pytest.fail("\n".join(failures), pytrace=False)

    def _runner(self, context: RunContext, planner: object) -> AdaptiveRunner | None:
        """--drivedegrade-adaptive: this process's runner of adaptive cells (built at its first cell)."""
        if not self.options.settings.adaptive:
            return None
        if self.runner is None:
            from .adaptive import AdaptiveRunner
            from .checks import stored_reader

            chosen = cast("AnyPlanner", planner)  # the fixture's object, which `certify` calls the same way
            self.runner = AdaptiveRunner(context, chosen, self.cells, self.options.severities,
                                         stored_reader(context, chosen, self.store))
            if self.options.baseline_path is not None:  # cells also stop on the sequential gate's test
                self.runner.gate_against(self.options.baseline_path, self.options.tolerance)
                self.runner.baseline_digests = preflight.sealed_digests(self.baseline)
        return self.runner

    def _next_cell(self, item: CellItem) -> tuple[str, int] | None:
        """The cell of the item that runs after `item` (None for the last one, or without planner actors)."""
        if self.remote is None or self.options.settings.adaptive:  # an adaptive cell asks for one unit at a time
            return None
        items = item.session.items
        at = next((i for i, it in enumerate(items) if it is item), len(items))
        return next((it.drivedegrade_cell for it in items[at + 1:] if isinstance(it, CellItem)
                     and not isinstance(it, ClosedItem)), None)

    def _check_horizon(self, item: CellItem, planner: object, context: RunContext) -> None:
        """The planner's horizon against the data's, once, before its first cell: an 8-pose planner on data with
        3 s of future fails that cell with the reason and stops the session (`planning.horizon_problem`)."""
        if self.horizon_error is None:
            from ..planning import horizon_problem

            problem = horizon_problem(planner, context.reader.future_poses, f"the data at {context.reader.root}")
            self.horizon_error = f"--drivedegrade: {problem}" if problem else ""
        if self.horizon_error:
            item.session.shouldstop = self.horizon_error
            pytest.fail(self.horizon_error, pytrace=False)

    def _check_name(self, item: CellItem, planner: object) -> None:
        """The planner's name, checked once when the planner first exists (the first cell): a bad one, or one
        that is not the baseline's planner (unless --drivedegrade-baseline-any-planner), fails that cell with
        the reason and stops the session, rather than failing every cell the same way."""
        if self.name_error is None:
            mine = planner_file(self.config, self.collect_path)
            self.name_error = preflight.name_problem(planner, self.options, self.baseline, mine)
        if self.name_error:
            item.session.shouldstop = self.name_error
            pytest.fail(self.name_error, pytrace=False)

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_makereport(self, item: pytest.Item,
                                  call: pytest.CallInfo[None]) -> Generator[None, pytest.TestReport, pytest.TestReport]:
        report = yield
        payload = item.stash.get(PAYLOAD_KEY, None)
        if report.when == "call" and payload is not None:
            setattr(report, PAYLOAD_ATTR, payload.to_json())
        closed = item.stash.get(CLOSED_KEY, None)
        if report.when == "call" and closed is not None:
            setattr(report, CLOSED_ATTR, closed.to_builtins())
        return report

    def pytest_runtest_logstart(self, nodeid: str, location: tuple[str, int | None, str]) -> None:
        """Controller: a cell started (on some worker), for the progress line's list of running cells."""
        if not _is_worker(self.config):
            self.running[nodeid] = nodeid.rpartition("::")[2]

    def _advance(self, report: pytest.TestReport) -> None:
        """The progress line, once per finished cell: done/total, the time left at the pace so far, what runs."""
        if self.progress is None or report.nodeid not in self.running:
            return
        if report.when == "call" or report.outcome != "passed":  # a cell failed in set-up has no call
            cell = self.running.pop(report.nodeid)
            now = ", ".join(sorted(self.running.values())[:4])
            self.progress.advance(note=f"{cell} done" + (f"; running {now}" if now else ""))

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        """Controller: write each finished cell to disk at once, so a crash or Ctrl-C loses nothing."""
        if _is_worker(self.config):
            return
        self._advance(report)
        closed = getattr(report, CLOSED_ATTR, None)
        if closed is not None:
            got = ClosedPayload.from_builtins(closed)
            self.closed_received[got.cell] = got
            write_stored(self.store, got)
        text = getattr(report, PAYLOAD_ATTR, None)
        if text is None:
            return
        payload = CellPayload.from_json(text)
        self.received[payload.cell] = payload
        self.store.write(payload, text)

    @pytest.hookimpl(tryfirst=True)
    def pytest_sessionfinish(self, session: pytest.Session, exitstatus: int) -> None:
        if _is_worker(self.config):
            return
        from .controller import finish_run

        actors = self._close_actors()
        if self.progress is not None:
            self.progress.finish()
        self.outcome = finish_run(self.config, self.options, self.context, self.received, self.cells, self.baseline,
                                  self.store, planner_file=planner_file(self.config, self.collect_path),
                                  closed=(self.closed_received, [closed_id(f, s) for f, s in self.closed]),
                                  floor=self.floor)
        if self.outcome is not None:
            self.outcome.lines += actors
        if self.outcome is not None and self.outcome.failed and session.exitstatus == 0:
            session.exitstatus = pytest.ExitCode.TESTS_FAILED
        if self.worker_usage is not None:  # the planner file, imported by the workers alone, failed there
            self.outcome = self.outcome or Outcome()
            self.outcome.lines.append(f"ERROR: {self.worker_usage}")
            session.exitstatus = pytest.ExitCode.USAGE_ERROR

    @pytest.hookimpl(optionalhook=True)
    def pytest_testnodedown(self, node: object, error: object) -> None:
        """xdist: a worker ended by a usage error (under -n the workers alone import the planner file, so a file
        that fails to import fails there): the run's usage error, said once at the end, and its exit status."""
        import re

        found = re.search(r"UsageError: (--drivedegrade[^\n]*)", str(error or ""))
        if found:
            self.worker_usage = found.group(1)

    def _close_actors(self) -> list[str]:
        """Tear the planner actors down (their fixtures' teardown) and disconnect from Ray; the pool's lines."""
        remote, self.remote = self.remote, None
        if remote is None:
            return []
        return remote.pool.summary() + remote.pool.close()

    def pytest_terminal_summary(self, terminalreporter: pytest.TerminalReporter) -> None:
        if self.outcome is not None:
            terminalreporter.section("drivedegrade")
            for line in self.outcome.lines:
                terminalreporter.write_line(line)


PAYLOAD_KEY = pytest.StashKey[CellPayload]()
CLOSED_KEY = pytest.StashKey[ClosedPayload]()
