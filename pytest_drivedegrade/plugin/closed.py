"""What one closed-loop cell item does (SPEC section 13): drive its (route, seed) runs, or resume them from the
store, and check the null control; and, on the controller, gather the run's closed cells. Runs in every process
that runs cells; computes nothing itself (`closedloop` drives, `scoring.closed_loop` analyses).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field

from ..cells import Property, rear_cameras
from ..certificate.closed import ClosedRun
from ..closedloop.analysis import RunRow, first_difference, parting_step
from ..closedloop.cells import (
    CLOSED_RECORD_VERSION,
    NULL_CELL,
    SWAP,
    ClosedPayload,
    ClosedRecord,
    as_float,
    as_map,
    closed_id,
    run_from_builtins,
    run_list,
    shard_runs,
)
from ..closedloop.results import RunResult
from ..closedloop.routes import Route, load_routes
from ..closedloop.simulate import Corruption, Rules, Timings, run_route
from ..closedloop.swap import junction_routes
from ..errors import DriveDegradeError, InvalidInput
from ..pacing import closed_threads, opencv_share
from ..planning import planner_name
from ..report.junit import plain
from ..run import AnyPlanner, PlannerElsewhere, RunContext
from ..scoring.closed_loop import analyse_rows
from ..settings import Builtin, RunSettings
from ..store import ResultStore

#: The report attribute that carries a finished closed cell's payload (as builtins) to the controller.
CLOSED_ATTR = "drivedegrade_closed"
#: 10 Hz simulation steps.
SIM_HZ = 10
#: What the controller hands `closed_run`: the closed payloads received this session, and the expected cell ids.
ClosedInput = tuple[Mapping[str, ClosedPayload], Sequence[str]]


@dataclass
class ClosedState:
    """Per process: the routes (built once) and the clean cell (the null control's reference, computed or
    stored once)."""

    routes: list[Route] | None = None
    swapped: list[Route] | None = None
    clean: dict[int, ClosedRecord] = field(default_factory=dict)

    def route_list(self, context: RunContext) -> list[Route]:
        if self.routes is None:
            limit = context.settings.closed_routes
            self.routes = load_routes(context.reader.root, context.settings.closed_scenarios, limit=limit,
                                      lights=context.settings.closed_lights)
        return self.routes

    def cell_routes(self, context: RunContext, family: str) -> list[Route]:
        """The routes a cell drives: every route, or for the command swap the junction routes swapped."""
        if family != SWAP:
            return self.route_list(context)
        if self.swapped is None:
            self.swapped = junction_routes(self.route_list(context))
        return self.swapped


def closed_key(context: RunContext, planner: AnyPlanner) -> dict[str, Builtin]:
    """A closed cell's run key: the run's (tool, planner and data fingerprints, seed) and the closed settings."""
    s = context.settings
    return {**context.run_key(planner), "closed_record_version": CLOSED_RECORD_VERSION,
            "closed_seeds": s.closed_seeds, "closed_hz": s.closed_hz, "closed_routes": s.closed_routes,
            "closed_steps": s.closed_steps, "closed_scenarios": s.closed_scenarios,
            **({"closed_lights": s.closed_lights} if s.closed_lights else {}),
            **({"closed_agents": s.closed_agents} if s.closed_agents != "log" else {}),
            **({"closed_collisions": s.closed_collisions} if s.closed_collisions != "all" else {})}


def drive(context: RunContext, state: ClosedState, planner: AnyPlanner, family: str, severity: int) -> ClosedRecord:
    """Every run of the cell this process drives (a shard's share of them), in run order."""
    s = context.settings
    routes = {r.name: r for r in state.cell_routes(context, family)}  # the names; actors build their own routes
    runs = run_list(list(routes), [s.seed + k for k in range(s.closed_seeds)], family)
    if s.shard is not None:
        runs = shard_runs(runs, s.shard.index, s.shard.count)
    if isinstance(planner, PlannerElsewhere):  # Ray planner actors: each run is a job of its own
        return _drive_elsewhere(planner, runs, family, severity, SIM_HZ // s.closed_hz, s.closed_steps,
                                s.closed_agents, Rules(s.closed_collisions, s.timeout), s.closed_scenarios,
                                s.closed_lights)
    timings, out, threads = Timings(), [], closed_threads(s)
    corruption = Corruption() if family == SWAP else Corruption(family, severity)  # the swap: clean cameras
    with opencv_share(), ThreadPoolExecutor(threads, "drivedegrade-closed") if threads else nullcontext() as pool:
        for route, seed in runs:
            out.append(run_route(planner, routes[route], corruption, seed, timings,
                                 plan_every=SIM_HZ // s.closed_hz, max_steps=s.closed_steps, agents=s.closed_agents,
                                 pool=pool, rules=Rules(s.closed_collisions, s.timeout)))
    seconds = {"render": timings.render, "plan": timings.plan, "track": timings.track, "score": timings.score}
    return ClosedRecord(closed_id(family, severity), family, severity, tuple(out), seconds=seconds)


def _drive_elsewhere(planner: PlannerElsewhere, runs: Sequence[tuple[str, int]], family: str, severity: int,
                     plan_every: int, max_steps: int | None, agents: str = "log",
                     rules: Rules | None = None, scenarios: int = 0, lights: int = 0) -> ClosedRecord:
    """The cell's runs on Ray planner actors (`closedloop.remote.drive_one`), collected in run order."""
    from ..raypool import RayPlanner

    rules = rules or Rules()
    if not isinstance(planner, RayPlanner):
        raise DriveDegradeError("closed-loop cells run on Ray planner actors or in this process only")
    got = planner.jobs("pytest_drivedegrade.closedloop.remote:drive_one",
                       [{"family": family, "severity": severity, "route": route, "seed": seed,
                         "plan_every": plan_every, "max_steps": max_steps, "agents": agents,
                         "collisions": rules.collisions, "timeout": rules.timeout, "scenarios": scenarios,
                         "lights": lights}
                        for route, seed in runs])
    seconds: dict[str, float] = {}
    out: list[RunResult] = []
    for item in got:
        g = as_map(item, "a closed-loop run's result")
        for k, v in as_map(g["seconds"]).items():
            seconds[k] = seconds.get(k, 0.0) + as_float(v)
        out.append(run_from_builtins(as_map(g["run"])))
    return ClosedRecord(closed_id(family, severity), family, severity, tuple(out), seconds=seconds)


def read_stored(store: ResultStore, planner: str, cell: str, key: Mapping[str, Builtin]) -> ClosedPayload | None:
    """The stored closed cell with this run key (None when absent, stale, edited, or without resume)."""
    if not store.resume:
        return None
    try:
        payload = ClosedPayload.from_builtins(json.loads(store.path(planner, cell).read_text()))
    except (OSError, ValueError, InvalidInput):
        return None
    return payload if dict(payload.key) == dict(key) and payload.cell == cell else None


def write_stored(store: ResultStore, payload: ClosedPayload) -> None:
    from ..atomic import atomic_write_text

    atomic_write_text(store.path(payload.planner, payload.cell), json.dumps(payload.to_builtins()))


def reads_rear(context: RunContext, planner: AnyPlanner) -> bool:
    return bool(set(rear_cameras()) & set(context.planner_info(planner).cameras))


def null_failure(clean: ClosedRecord, record: ClosedRecord, plan_every: int) -> str | None:
    """Where `record` (blackout S3 of a planner that declares no rear camera) first parts from clean, or None."""
    rows = [RunRow.of(r) for r in record.runs]
    first = first_difference([RunRow.of(r) for r in clean.runs], rows)
    if first is None:
        return None
    at = next(i for i, r in enumerate(rows) if r is first)
    mine, theirs = record.runs[at], clean.runs[at] if at < len(clean.runs) else None
    step = 0 if theirs is None else parting_step(theirs, mine, plan_every)
    ds = "unscored" if mine.ds is None else f"{mine.ds:.3f}"
    was = "none" if theirs is None else "unscored" if theirs.ds is None else f"{theirs.ds:.3f}"
    return (f"closed null control failed in cell {record.cell}: route {mine.route} (seed {mine.seed}) parts from "
            f"closed-clean at step {step} (DS {ds}, clean {was}): blackout S3 darkens only the rear cameras, which "
            "the planner declares it does not read; it reads one of them (add it to planner.cameras) or predict() "
            "is not deterministic")


def properties(record: ClosedRecord, resumed: bool) -> tuple[Property, ...]:
    """The cell's figures as JUnit testcase properties (plain builtins)."""
    cell = analyse_rows({record.cell: [RunRow.of(r) for r in record.runs]}).cells[0]
    low, high = cell.bounds
    values = {"closed_cell": record.cell, "closed_runs": len(record.runs), "closed_unscored": cell.unscored,
              "closed_ds_mean": cell.mean, "closed_ds_std": cell.std, "closed_ds_low": low, "closed_ds_high": high,
              "closed_completion": cell.completion, "resumed": int(resumed)}
    return tuple((k, plain(v)) for k, v in values.items())


def certify_closed(context: RunContext, state: ClosedState, planner: AnyPlanner, family: str, severity: int, *,
                   store: ResultStore) -> tuple[ClosedPayload, list[str]]:
    """Run (or resume) one closed cell and check it: (payload for the controller, failure messages)."""
    default = context.planner_path.stem if context.planner_path else "planner"
    name, key, cell = planner_name(planner, default), closed_key(context, planner), closed_id(family, severity)
    stored = read_stored(store, name, cell, key)
    if cell == closed_id("clean", 0):
        record = state.clean.get(id(planner)) or (stored.record if stored else drive(context, state, planner,
                                                                                       "clean", 0))
        state.clean[id(planner)] = record
    else:
        record = stored.record if stored else drive(context, state, planner, family, severity)
    failures = [f"run {r.route} (seed {r.seed}) unscored: {r.error}" for r in record.runs if r.ds is None]
    if family == SWAP and not record.runs:
        failures.append(f"{cell}: none of the {len(state.route_list(context))} closed-loop route(s) turns at a "
                        "junction its logged ego enters, so no command can be swapped; drive more routes "
                        "(--drivedegrade-closed-routes, --drivedegrade-closed-scenarios) or leave command_swap out of "
                        "--drivedegrade-closed-cells")
    if (family, severity) == NULL_CELL:
        rear = reads_rear(context, planner)
        if rear and not record.null_runs:  # the null is an untouched rerun of clean: how far does it wander?
            start = time.perf_counter()
            rerun = drive(context, state, planner, "clean", 0)
            record = ClosedRecord(record.cell, family, severity, record.runs, rerun.runs,
                                  {**record.seconds, "null_rerun": time.perf_counter() - start})
        elif not rear:
            clean = state.clean.get(id(planner))
            if clean is None:
                got = read_stored(store, name, closed_id("clean", 0), key)
                clean = got.record if got else drive(context, state, planner, "clean", 0)
                state.clean[id(planner)] = clean
            problem = null_failure(clean, record, SIM_HZ // context.settings.closed_hz)
            failures += [problem] if problem else []
    return ClosedPayload(key, name, record, stored is not None), failures


def gather_closed(received: Mapping[str, ClosedPayload], expected: Sequence[str], store: ResultStore,
                  planner: str | None, key: Mapping[str, Builtin] | None) -> tuple[dict[str, ClosedPayload], list[str]]:
    """The run's closed cells: this session's plus stored ones of the same run, in `expected` order; and the
    expected cells neither has."""
    first = next(iter(received.values()), None)
    planner = planner or (first.planner if first else None)
    key = key if key is not None else (dict(first.key) if first else None)
    out: dict[str, ClosedPayload] = {}
    for cell in expected:
        got = received.get(cell)
        if got is None and planner is not None and key is not None:
            got = read_stored(store, planner, cell, key)
        if got is not None:
            out[cell] = got
    return out, [c for c in expected if c not in out]


def closed_run(settings: RunSettings, store: ResultStore, closed: ClosedInput | None) -> ClosedRun | None:
    """The run's closed cells (this session's and stored ones of the same run key) as the certificate takes
    them; None when the run has no closed cell."""
    if closed is None or not closed[1]:
        return None
    payloads, missing = gather_closed(closed[0], closed[1], store, None, None)
    if not payloads:
        return None
    return ClosedRun(payloads, settings, tuple(missing))
