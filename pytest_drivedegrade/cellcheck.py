"""What one cell item asserts: conformance on every frame, the null control, and the baseline gate.

`certify` returns the payload that travels to the controller (plain builtins) and the failure messages;
a stored result with the same run key is reused instead of recomputed (resume).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .analysis import CellRecord, cell_regression, paired_retention
from .loader import cell_id, samples
from .planning import planner_name
from .run import MAX_MESSAGES, RunContext
from .store import ResultStore

REAR = ("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")


def properties(record: CellRecord, resumed: bool) -> list[tuple[str, Any]]:
    """The cell's own figures as JUnit testcase properties, named like the cells.csv columns.

    Values go through ``report.junit.plain``: builtins only (xdist serialises them), six decimals, "none" for a
    metric no frame produced.
    """
    from .analysis import horizon_metrics
    from .report.junit import plain

    metrics = horizon_metrics(record)
    props: list[tuple[str, Any]] = [
        ("cell", record.cell), ("family", record.family), ("severity", int(record.severity)),
        ("frames", len(record.frames)), ("failed_frames", int(np.isnan(record.l2).any(axis=1).sum())),
        ("l2_avg", metrics["l2_avg_stp3"])]
    props += [(k, metrics[k]) for k in ("l2_1s_stp3", "l2_2s_stp3", "l2_3s_stp3", "l2_1s_uniad", "l2_2s_uniad",
                                        "l2_3s_uniad", "collision_3s_stp3", "vru_3s_stp3", "jerk")]
    props.append(("resumed", int(resumed)))
    return [(name, plain(value)) for name, value in props]


def _conformance(record: CellRecord) -> list[str]:
    if not record.errors:
        return []
    shown = record.errors[:MAX_MESSAGES]
    more = len(record.errors) - len(shown)
    head = f"cell {record.cell}: {len(record.errors)} of {len(record.frames)} frames failed the planner contract"
    return [head, *(f"  {e}" for e in shown), *([f"  ... and {more} more"] if more else [])]


def _culprits(context: RunContext, planner: Any, index: int, unread: tuple[str, ...], clean: np.ndarray) -> list[str]:
    """Which declared-unread cameras, blacked out alone, change the plan of frame `index`."""
    found = []
    for cam in unread:
        sample = next(samples([context.frames[index]], "null", 0, seed=context.seed, decode=context.decode,
                              unread=(cam,)))
        plan = np.asarray(planner.predict(sample, sample.frame.ego, sample.frame.command), dtype=float)
        if not np.array_equal(plan, clean):
            found.append(cam)
    return found


def _identity(context: RunContext, planner: Any, record: CellRecord, clean: CellRecord,
              unread: tuple[str, ...]) -> list[str]:
    """The null control: plans bit-identical to clean, else how far they wandered and who moved them."""
    if np.array_equal(record.plans, clean.plans, equal_nan=True):
        return []
    diff = np.abs(record.plans - clean.plans)
    l2 = np.linalg.norm(record.plans - clean.plans, axis=-1)
    first = int(np.flatnonzero(np.nan_to_num(diff, nan=np.inf).reshape(len(diff), -1).max(axis=1) > 0)[0])
    head = (f"null control failed in cell {record.cell}: plans are not bit-identical to clean "
            f"(max abs difference {np.nanmax(diff):.6g} m, max L2 change {np.nanmax(l2):.6g} m; first at frame "
            f"{record.frames[first]!r})")
    if not unread:
        return [head, "  the planner reads all six cameras, so this was an untouched rerun: predict() is not "
                      "deterministic (seed it, or disable nondeterministic kernels)"]
    culprits = _culprits(context, planner, first, unread, clean.plans[first])
    why = (f"  declared-unread camera(s) that change the plan: {', '.join(culprits)}; add them to planner.cameras"
           if culprits else "  no single unread camera changes it: predict() may not be deterministic")
    return [head, why]


def _reusable(stored: dict[str, Any] | None) -> dict[str, Any] | None:
    """A stored result a rerun may reuse: one without per-frame failures. A failed frame may have been a fixed
    data file (a re-extracted JPEG keeps the data set's fingerprint) or a transient hang, so it is run again."""
    if stored is None or stored["record"].get("errors"):
        return None
    return stored


def certify(context: RunContext, planner: Any, family: str, severity: int, *, store: ResultStore,
            baseline: dict[str, Any] | None, tolerance: float) -> tuple[dict[str, Any], list[str]]:
    """Run (or resume) one cell and check it; returns (payload for the controller, failure messages)."""
    default = context.planner_path.stem if context.planner_path else "planner"
    name = planner_name(planner, default)
    key = context.run_key(planner)
    cell = cell_id(family, severity)
    def stored_record(which: str) -> CellRecord | None:
        found = _reusable(store.read(name, which, key))
        return CellRecord.from_builtins(found["record"]) if found else None

    stored = stored_record(cell)
    if cell == "clean":  # through the per-process clean cell, which the null control and the gate reuse
        record = context.clean_record(planner, lambda: stored)
    else:
        record = stored or context.run_cell(planner, family, severity)
    failures = _conformance(record)
    unread = context.planner_info(planner).unread
    needs_clean = cell == "null" or (cell == "blackout-s3" and set(REAR) <= set(unread)) or baseline is not None
    if needs_clean and cell != "clean":
        clean = context.clean_record(planner, lambda: stored_record("clean"))
        if cell == "null" or cell == "blackout-s3":
            failures += _identity(context, planner, record, clean, unread if cell == "null" else REAR)
        if baseline is not None:
            retention = paired_retention(clean.l2_avg_per_frame(), record.l2_avg_per_frame())
            reg = cell_regression(cell, retention, baseline, tolerance)
            if reg:
                failures.append(f"retention regressed beyond --drivedegrade-tolerance {tolerance:g}: {reg.message()}")
    payload = {"key": key, "planner": name, "record": record.to_builtins(),
               "properties": properties(record, stored is not None)}
    return payload, failures
