"""--drivedegrade-adaptive in a process that runs cells: each cell runs unit by unit in the run's seeded draw order,
paired with clean on the same units, until `scoring.sequential.stop_at` says every decision the certificate
takes from it is settled; a camera family's severities are visited S5 first, then by bisection
(`scoring.sequential.family_plan`), the others recorded as skipped.

Moves data only: what a unit is, where a cell stops and which severity comes next are `scoring.sequential`'s.
The decision reads only the seeded order and the plans, never timing or worker layout, so every process that
runs a cell (an xdist worker, the only process, the Ray controller) gets the same record. A cell another process
already finished is taken from the store (the controller writes each cell as it arrives).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from ..cells import FRAME_ARRAYS, CellRecord, cell_id, is_camera_ladder
from ..errors import DriveDegradeError
from ..run import AnyPlanner, RunContext, style_of
from ..scoring.adaptive import SEVERITIES, GateBaseline, Unit, gate_cell
from ..scoring.sequential import (
    FULL_CELLS,
    METHOD,
    Outcome,
    UnitPlan,
    alpha_side,
    cell_outcome,
    family_plan,
    levels_of,
    stop_at,
    unit_figure,
    unit_sums,
)
from ..scoring.verdict import FamilyGroups


def baseline_digest(path: Path) -> str | None:
    """The baseline certificate's digest (None when it cannot be read: the gate reports that itself)."""
    import json

    try:
        got = json.loads(path.read_text()).get("digest")
    except (OSError, ValueError, AttributeError):
        return None
    return got if isinstance(got, str) else None


#: A finished cell's stored record of this run (None: not stored yet).
Stored = Callable[[str], "CellRecord | None"]


def rows(record: CellRecord, start: int) -> dict[str, np.ndarray]:
    """`record`'s per-frame arrays from row `start` on (a unit's scored frames after its warm-up)."""
    return {a.name: record.array(a.name)[start:] for a in FRAME_ARRAYS}


class AdaptiveRunner:
    """One process's adaptive cells for one planner: clean's units (computed once, or read from the stored clean
    cell), each visited cell's record, and each family's schedule."""

    def __init__(self, context: RunContext, planner: AnyPlanner, cells: list[tuple[str, int]],
                 severities: tuple[int, ...], stored: Stored) -> None:
        self.context, self.planner, self.stored = context, planner, stored
        style = style_of(planner)
        self.warm = style.resets  # a planner with neither reset nor context keeps no scene state: single frames
        self.scenes = style.takes_context and not style.resets  # its memory is not cut mid-scene: whole scenes
        self.plan = self.draw(context, planner, None)
        self.alpha = alpha_side(context.settings.alpha, cells)
        groups = FamilyGroups.from_registry()
        self.axis_families = (*groups.quality, groups.removal)
        self.scheduled = tuple(severities) == SEVERITIES  # a run of some severities visits each of them
        self.severities = severities
        self._clean_units: dict[int, CellRecord] = {}
        self._clean_m = np.full(len(context.frames), np.nan)  #: clean's per-frame L2 on the units computed
        self._clean: CellRecord | None = None
        self._done: dict[str, CellRecord] = {}
        #: --drivedegrade-baseline: the baseline's cells/ folder (its per-frame results) and its tolerance
        self.baseline_cells: Path | None = None
        #: the baseline certificate's sealed record_digests: a baseline cell file is read only when it hashes to
        #: its entry (issue 37 H2; `preflight.check_baseline_cells` checked them all before any cell ran)
        self.baseline_digests: Mapping[str, object] = {}
        self.tolerance = 0.0
        self._baseline: dict[str, GateBaseline | None] = {}

    def draw(self, context: RunContext, planner: AnyPlanner, baseline: str | None) -> UnitPlan:
        """The run's unit plan under its draw seed (`sequential.draw_seed`: the corruption seed, the planner's
        fingerprint, the baseline's digest in a gate run)."""
        return UnitPlan.drawn(context.frames, context.seed, context.planner_info(planner).fingerprint, baseline,
                              temporal=self.warm, scenes=self.scenes)

    def gate_against(self, baseline_path: Path, tolerance: float) -> None:
        """A gate run: cells also stop on the sequential gate's test against the baseline's per-frame results
        (its cells/ beside it), and the draw order depends on the baseline's digest too."""
        self.baseline_cells, self.tolerance = baseline_path.parent / "cells", tolerance
        self.plan = self.draw(self.context, self.planner, baseline_digest(baseline_path))

    # --- units ---------------------------------------------------------------------------------------------------

    def _frames(self, unit: Unit) -> tuple[int, ...]:
        """The frames a unit runs: its warm-up too for a planner with `reset`. A temporal corruption needs none:
        a span replays frame_dropout's loss draws from the scene's start (`RunContext.run_cell`), so a unit's
        frames get the full run's images bit for bit."""
        return (*unit.warmup, *unit.scored) if self.warm else unit.scored

    def _run_unit(self, family: str, severity: int, unit: Unit, clean: CellRecord | None = None) -> CellRecord:
        """The cell on the unit's frames (warm-up first, `reset` at its start), as a run of them alone."""
        idx = self._frames(unit)
        return self.context.run_cell(self.planner, family, severity, span=(idx[0], idx[-1] + 1), clean=clean)

    def clean_unit(self, k: int) -> CellRecord:
        """Clean on unit `k` of the draw order, once per process: the clean record's rows of its scored frames
        when there is one (this process's, or one another process stored), else computed (warm-up rows first)."""
        if k not in self._clean_units:
            unit = self.plan.units[k]
            if self._clean is not None:
                idx = list(unit.scored)
                got = CellRecord.of_arrays("clean", "clean", 0, [self._clean.frames[i] for i in idx],
                                           {a.name: self._clean.array(a.name)[idx] for a in FRAME_ARRAYS})
            else:
                got = self._run_unit("clean", 0, unit)
            self._clean_units[k] = got
            self._clean_m[list(unit.scored)] = got.l2_avg_per_frame()[len(got.frames) - len(unit.scored):]
        return self._clean_units[k]

    def _stored_clean(self) -> CellRecord | None:
        got = self.stored("clean")
        return got if got is not None and got.units is not None else None

    def _assemble(self, family: str, severity: int, parts: list[CellRecord]) -> CellRecord:
        """The cell's record over every scored frame of the run, NaN where no unit it ran scored a frame."""
        n = len(self.context.frames)
        arrays = {a.name: a.empty(n) for a in FRAME_ARRAYS}
        seconds: dict[str, float] = {}
        for unit, part in zip(self.plan.units, parts):
            skip = len(part.frames) - len(unit.scored)
            for name, values in rows(part, skip).items():
                arrays[name][list(unit.scored)] = values
            for key, v in part.seconds.items():
                seconds[key] = seconds.get(key, 0.0) + float(v)
        return CellRecord.of_arrays(cell_id(family, severity), family, severity,
                                    [f.token for f in self.context.frames], arrays, seconds=seconds,
                                    errors=[e for p in parts for e in p.errors],
                                    data_errors=[e for p in parts for e in p.data_errors],
                                    reused=sum(p.reused for p in parts), units=len(parts),
                                    passes=sum(len(p.frames) for p in parts))

    # --- cells ---------------------------------------------------------------------------------------------------

    def full(self, family: str) -> CellRecord:
        """Clean or the null control: every unit, no stopping (clean is what every cell pairs with)."""
        if family == "clean" and self._clean is not None:
            return self._clean
        parts = [self.clean_unit(k) if family == "clean" else self._run_unit(family, 0, u)
                 for k, u in enumerate(self.plan.units)]
        record = self._assemble(family, 0, parts)
        if family == "clean":
            self._clean = record
        return record

    def clean(self) -> CellRecord:
        """The run's clean record: a stored one (another process computed it) or this process's."""
        if self._clean is None:
            self._clean = self._stored_clean()
        return self._clean if self._clean is not None else self.full("clean")

    def stopping(self, family: str, severity: int) -> CellRecord:
        """A stopping cell: units in draw order until `stop_at` settles its levels, or the data run out."""
        levels = levels_of(family, severity, self.axis_families, self.context.settings.flat)
        reuse = self.context.reuses_clean(self.planner, family, severity)
        if self._clean is None:  # another process may have stored clean since: its rows are free
            self._clean = self._stored_clean()
        parts: list[CellRecord] = []
        a: list[float] = []
        b: list[float] = []
        for k, unit in enumerate(self.plan.units):
            clean = self.clean_unit(k)
            part = self._run_unit(family, severity, unit, clean if reuse else None)
            parts.append(part)
            n = len(unit.scored)
            x, y = unit_figure(clean.l2_avg_per_frame()[-n:], part.l2_avg_per_frame()[-n:], self.plan.window)
            a.append(x)
            b.append(y)
            gate = self.gate_settled(cell_id(family, severity), a, b)
            if gate or (gate is None and stop_at(np.asarray(a), np.asarray(b), levels,
                                                 population=self.plan.population, alpha=self.alpha) is not None):
                break
        return self._assemble(family, severity, parts)

    def gate_settled(self, cell: str, a: list[float], b: list[float]) -> bool | None:
        """A gate run (with a baseline): whether the sequential gate's test of the cell (`scoring.adaptive.
        gate_cell`, at alpha / C) is settled on the units so far, which is then the cell's whole stopping rule;
        None without a baseline, or one lacking the cell's units (the cell stops on its own decisions)."""
        ref = self.baseline(cell)
        if ref is None:
            return None
        n, k = self.plan.population, len(a)
        now = np.concatenate([a, np.zeros(n - k)]), np.concatenate([b, np.zeros(n - k)])
        return gate_cell(*now, ref, list(range(k)), tolerance=self.tolerance, alpha=2 * self.alpha,
                         method=METHOD).side != "open"

    def baseline(self, cell: str) -> GateBaseline | None:
        """The baseline's per-unit figures of `cell` (from the cells/ folder beside it), when it has them all."""
        if self.baseline_cells is None:
            return None
        if cell not in self._baseline:
            from ..certificate.adaptive_check import load_records

            got, problems = load_records(self.baseline_cells, ["clean", cell], self.baseline_digests)
            if problems:  # changed since the run started: never gate on a record the baseline did not seal
                raise DriveDegradeError(f"--drivedegrade-baseline: {problems[0]}")
            clean, base = got.get("clean"), got.get(cell)
            ok = clean is not None and base is not None and np.isfinite(base.l2_avg_per_frame()).all()
            self._baseline[cell] = GateBaseline(*unit_sums(
                self.plan, clean.l2_avg_per_frame(), base.l2_avg_per_frame(), self.plan.population)) \
                if ok and clean is not None and base is not None else None
        return self._baseline[cell]

    def skipped(self, family: str, severity: int) -> CellRecord:
        """A severity the schedule skipped: no unit run, every row NaN, ``units`` 0."""
        return self._assemble(family, severity, [])

    def outcome(self, record: CellRecord) -> Outcome:
        """Where the rule stopped `record` and its interval (`cell_outcome`), clean taken on its units."""
        for k in range(int(record.units or 0)):
            self.clean_unit(k)
        levels = levels_of(record.family, record.severity, self.axis_families, self.context.settings.flat)
        return cell_outcome(self.plan, self._clean_m, record, levels, alpha=self.alpha)

    def _visit(self, family: str, severity: int) -> CellRecord:
        cell = cell_id(family, severity)
        if cell not in self._done:
            self._done[cell] = self.stored(cell) or self.stopping(family, severity)
        return self._done[cell]

    def family(self, family: str) -> dict[int, CellRecord]:
        """Every severity of a camera family: visited as the schedule says, the others skipped."""
        if not self.scheduled or self.baseline_cells is not None:  # a gate run gates every severity
            return {s: self._visit(family, s) for s in self.severities}
        outcomes: dict[int, Outcome] = {}
        while (nxt := family_plan(outcomes)[0]) is not None:  # every severity, S5 first (none skipped)
            outcomes[nxt] = self.outcome(self._visit(family, nxt))
        return {s: self._done[cell_id(family, s)] if s in outcomes else self.skipped(family, s)
                for s in self.severities}

    def record(self, family: str, severity: int) -> CellRecord:
        """The cell's adaptive record (clean and null: every unit)."""
        if family == "clean":
            return self.clean()
        if family in FULL_CELLS:
            return self.full(family)
        if is_camera_ladder(family):
            return self.family(family)[severity]
        undecided = not levels_of(family, severity, self.axis_families, self.context.settings.flat)
        if undecided and self.baseline(cell_id(family, severity)) is None:  # nothing to settle: no unit run
            return self.skipped(family, severity)
        return self._visit(family, severity)
