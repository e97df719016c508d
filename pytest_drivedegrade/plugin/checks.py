"""What one cell item asserts: conformance on every frame, the null control, and the baseline gate.

Runs in every process that runs cells (each xdist worker, or the only process). `certify` returns the
`CellPayload` that travels to the controller and the failure messages; a stored result with the same run key is
reused instead of recomputed (resume).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from ..cells import (
    CellRecord,
    Property,
    cell_id,
    differing_frames,
    identical_plans,
    planned_in_both,
    rear_cameras,
)
from ..payload import CellPayload
from ..planning import planner_name
from ..report.columns import TESTCASE
from ..report.junit import plain
from ..run import MAX_MESSAGES, AnyPlanner, PlannerElsewhere, RunContext, Span, style_of, unread_cameras
from ..scoring.baseline import cell_regression
from ..scoring.records import finite_mean, horizon_metrics
from ..scoring.retention import paired_retention, record_retention
from ..store import ResultStore

if TYPE_CHECKING:
    from .adaptive import AdaptiveRunner


def properties(record: CellRecord, resumed: bool) -> tuple[Property, ...]:
    """The cell's own figures as JUnit testcase properties (`report.columns.TESTCASE`), plain builtins."""
    row: dict[str, Any] = {**horizon_metrics(record), "cell": record.cell, "family": record.family,
                           "severity": int(record.severity), "frames": len(record.frames),
                           "failed_frames": int(np.isnan(record.l2).any(axis=1).sum()),
                           "data_errors": len(record.data_errors), "resumed": int(resumed)}
    row["l2_avg"] = row["l2_avg_stp3"]
    row["pdms"] = finite_mean(record.pdms)
    two_stage = (("epdms2", plain(finite_mean(record.epdms2))),) if np.isfinite(record.epdms2).any() else ()
    return (*((name, plain(row[name])) for name in TESTCASE), *two_stage)


def _conformance(record: CellRecord, seed: int | None = None) -> list[str]:
    """The cell's failed frames, the data's apart from the planner's: a header each, the first few named."""
    if seed is None and record.seed_runs:  # one block per seed run that failed
        return [line for run, s in zip(record.runs(), record.seeds) for line in _conformance(run, s)]
    under = "" if seed is None else f" (corruption seed {seed})"
    out: list[str] = []
    for errors, what in ((record.data_errors, "had data errors (the data set's fault, not the planner's)"),
                         (record.errors, "failed the planner contract")):
        if errors:
            shown, more = errors[:MAX_MESSAGES], len(errors) - MAX_MESSAGES
            out += [f"cell {record.cell}{under}: {len(errors)} of {len(record.frames)} frames {what}",
                    *(f"  {e}" for e in shown), *([f"  ... and {more} more"] if more > 0 else [])]
    return out


#: What the null control says when a replay does not reproduce a recorded plan: the planner's plans depend on
#: what it was called with before, so no camera can be proved to move the plan.
HISTORY = "plans depend on call history: give the planner a reset(), or declare deterministic = False"


def _replay_span(context: RunContext, planner: Any, index: int) -> Span:
    """The frames a replay of frame `index` runs so that the planner is where it was when it planned it: for a
    planner with ``reset``, its scene from the first scored frame (reset first); for a batched one, the batch it
    shared (a batch of one may round differently); else the frame alone."""
    first = index
    style = style_of(planner)
    if style.resets:
        frame = context.frames[index]
        while first > 0 and context.frames[first - 1].scene_token == frame.scene_token:
            first -= 1
        return first, index + 1
    if context.settings.batch > 1 and not isinstance(planner, PlannerElsewhere) and \
            callable(getattr(planner, "predict_batch", None)):
        first = index - index % context.settings.batch
        return first, min(first + context.settings.batch, len(context.frames))
    return first, index + 1


def _culprits(context: RunContext, planner: Any, index: int, unread: tuple[str, ...], record: CellRecord,
              clean: CellRecord) -> tuple[list[str], str]:
    """Which declared-unread cameras, blacked out alone, change the plan of frame `index`, proved by replays:
    (cameras, "") or ([], why no camera can be blamed).

    A replay is a cell on `_replay_span` (`RunContext.run_cell`, so planner actors replay there). The frame is
    first replayed as it was in clean and in the record's cell: only when both reproduce their recorded plans bit
    for bit does a replay speak for the planner rather than for its call history, and each camera's replay is
    followed by clean's again, which must reproduce too. A camera is blamed when its replay moves the plan off
    clean's (a failed frame, a NaN plan, counts as moved); a replay that does not reproduce names no camera.
    """
    span = _replay_span(context, planner, index)
    own = context.planner_info(planner).unread
    at = index - span[0]

    def reproduces(family: str, severity: int, want: np.ndarray) -> bool:
        got = context.run_cell(planner, family, severity, unread=own, span=span).plans[at]
        return identical_plans(got, want)

    def history(where: str) -> tuple[list[str], str]:
        return [], f"  {HISTORY} (frame {record.frames[index]!r} replayed as in {where} did not reproduce its plan)"

    want = clean.plans[index]
    if not reproduces("clean", 0, want):
        return history("clean")
    if not reproduces(record.family, record.severity, record.plans[index]):
        return history(record.cell)
    found = []
    for cam in unread:
        plan = context.run_cell(planner, "null", 0, unread=(cam,), span=span).plans[at]
        if not reproduces("clean", 0, want):
            return history("clean, after another replay,")
        if np.isnan(plan).any() or not identical_plans(plan, want):
            found.append(cam)
    return found, ""


def _identity(context: RunContext, planner: Any, record: CellRecord, clean: CellRecord,
              unread: tuple[str, ...]) -> list[str]:
    """The null control: plans bit-identical to clean (`cells.identical_plans`) on every frame with a plan in
    both (`cells.planned_in_both`: a frame that failed in either is that cell's conformance failure), else how
    far they wandered and who moved them, as far as a replay proves it (`_culprits`)."""
    both = planned_in_both(record.plans, clean.plans)
    if identical_plans(record.plans[both], clean.plans[both]):
        return []
    a, b = record.plans[both], clean.plans[both]
    diff = np.abs(a - b)
    l2 = np.linalg.norm(a - b, axis=-1)
    first = int(np.flatnonzero(both)[differing_frames(a, b)[0]])
    head = (f"null control failed in cell {record.cell}: plans are not bit-identical to clean "
            f"(max abs difference {np.nanmax(diff):.6g} m, max L2 change {np.nanmax(l2):.6g} m; first at frame "
            f"{record.frames[first]!r})")
    if not unread:
        return [head, "  the planner reads all six cameras, so this was an untouched rerun: predict() is not "
                      "deterministic (seed it, or disable nondeterministic kernels)"]
    culprits, why = _culprits(context, planner, first, unread, record, clean)
    if culprits:
        why = f"  declared-unread camera(s) that change the plan: {', '.join(culprits)}; add them to planner.cameras"
    return [head, why or "  no single unread camera changes it: predict() may not be deterministic"]


def _reusable(stored: CellPayload | None) -> CellRecord | None:
    """A stored record a rerun may reuse: one without per-frame failures. A failed frame may have been a fixed
    data file (a re-extracted JPEG keeps the data set's fingerprint) or a transient hang, so it is run again."""
    if stored is None or any(stored.record.failed_frames()):
        return None
    return stored.record


def prefetch(context: RunContext, planner: Any, family: str, severity: int, *, store: ResultStore) -> None:
    """Start a coming cell on a planner that runs elsewhere (Ray actors), so they work on it while the controller
    finishes the current one; nothing for a local planner, or for a cell `certify` will reuse from the store.
    Every seed of `seeds_for`, the cameras `certify` blacks out: the arguments its `run_cell` calls use."""
    if not isinstance(planner, PlannerElsewhere):
        return
    cell = cell_id(family, severity)
    default = context.planner_path.stem if context.planner_path else "planner"
    if cell == "clean" or _reusable(store.read(planner_name(planner, default), cell, context.run_key(planner))):
        return  # clean: the first cell, computed once per process; its own call starts it
    unread = unread_cameras(planner.cameras)
    for seed in context.seeds_for(family):
        planner.prefetch(context, family, severity, unread=unread, seed=seed)


def gated_retention(clean: CellRecord, record: CellRecord, metric: str) -> float:
    """The cell's retention on the verdict's metric, as its certificate row holds it: L2 (`record_retention`) or
    PDMS or EPDMS (M(cell) / M(clean) over the frames scored in both, averaged over seed runs), which the gate
    compares."""
    if metric not in ("pdms", "epdms", "epdms2"):
        return record_retention(clean, record)
    values = [paired_retention(getattr(clean, metric), getattr(run, metric), "reward") for run in record.runs()]
    return values[0] if len(values) == 1 else finite_mean(values)


def stored_reader(context: RunContext, planner: AnyPlanner,
                  store: ResultStore) -> Callable[[str], CellRecord | None]:
    """cell id -> this run's stored record of it that a rerun may reuse (`_reusable`), or None."""
    default = context.planner_path.stem if context.planner_path else "planner"
    name = planner_name(planner, default)
    key = context.run_key(planner)
    return lambda which: _reusable(store.read(name, which, key))


def certify(context: RunContext, planner: Any, family: str, severity: int, *, store: ResultStore,
            baseline: Mapping[str, Any] | None, tolerance: float,
            runner: AdaptiveRunner | None = None) -> tuple[CellPayload, list[str]]:
    """Run (or resume) one cell and check it; returns (payload for the controller, failure messages). With
    `runner` (--drivedegrade-adaptive) the cell stops as its rule says, on the runner's units."""
    default = context.planner_path.stem if context.planner_path else "planner"
    name = planner_name(planner, default)
    key = context.run_key(planner)
    cell = cell_id(family, severity)
    stored_record = stored_reader(context, planner, store)

    stored = stored_record(cell)
    unread = context.planner_info(planner).unread
    rear = rear_cameras()
    rear_is_null = cell == cell_id("blackout", 3) and set(rear) <= set(unread)
    if runner is not None:
        record = stored or runner.record(family, severity)
    elif cell == "clean":  # through the per-process clean cell, which the null control and the gate reuse
        record = context.clean_record(planner, lambda: stored)
    elif stored is not None:
        record = stored
    else:  # frames whose inputs equal clean's take its plans: the clean cell of this process, computed or stored
        context.prime_clean(planner)  # clean planned first in every process: a memo holds clean's plans (M12)
        clean = context.clean_record(planner, lambda: stored_record("clean")) \
            if context.reuses_clean(planner, family, severity) else None
        record = context.run_seeded_cell(planner, family, severity, clean=clean)
    failures = _conformance(record)
    if (cell == "null" or rear_is_null or baseline is not None) and cell != "clean":
        clean = runner.clean() if runner is not None else \
            context.clean_record(planner, lambda: stored_record("clean"))
        if cell == "null" or rear_is_null:
            failures += _identity(context, planner, record, clean, unread if cell == "null" else rear)
        if baseline is not None and runner is None and "adaptive" not in baseline:  # those gate at the end
            metric = context.settings.metric
            reg = cell_regression(cell, gated_retention(clean, record, metric), baseline, tolerance, metric)
            if reg:
                failures.append(f"retention regressed beyond --drivedegrade-tolerance {tolerance:g}: {reg.message()}")
    resumed = stored is not None
    why = "" if resumed else store.digest_failures.get(cell, "")
    stale = "" if resumed else store.stale.get(cell, "")
    return CellPayload(key, name, record, properties(record, resumed), resumed, why, stale), failures
