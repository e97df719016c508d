"""Typed results of the closed loop: one run (route, seed) and one cell (its runs), as the CARLA leaderboard
scores them (`leaderboard`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .leaderboard import PENALTIES, PERCENT_PENALTIES

__all__ = ["PENALTIES", "PERCENT_PENALTIES", "Infraction", "RunResult", "CellResult"]
#: Why a run ended (END_DEVIATED: farther from the route than the leaderboard allows; END_OFF_ROAD is read in
#: records of spec 4, whose runs ended 2 m off the carriageway).
END_COMPLETE, END_BLOCKED, END_OFF_ROAD, END_SCENE, END_UNSCORED = "complete", "blocked", "off_road", "scene_end", \
    "unscored"
END_DEVIATED = "route_deviation"


@dataclass(frozen=True)
class Infraction:
    """An infraction: its kind (a PENALTIES or PERCENT_PENALTIES key; "off_road" in records of spec 4), the
    route step (planner call) it happened in, the 10 Hz sim step, what it involved (agent role or prop), and for
    a percentage infraction its percentage (outside route lanes: share of the route driven outside them; min
    speed: the ego's mean speed as a share of the traffic's)."""

    kind: str
    step: int
    sim_step: int
    what: str = ""
    value: float | None = None


@dataclass(frozen=True)
class RunResult:
    """One run: `ds` 0..100 and `completion` 0..1 (None when unscored: the planner raised, timed out or returned
    a bad plan, `error` says which), why it ended, its infractions and its trace of world poses (N, 3) at 10 Hz."""

    route: str
    seed: int
    ds: float | None
    completion: float | None
    end: str
    infractions: tuple[Infraction, ...]
    trace: np.ndarray
    error: str = ""
    steps: int = 0

    @property
    def scored(self) -> bool:
        return self.ds is not None

    def count(self, kind: str) -> int:
        return sum(1 for i in self.infractions if i.kind == kind)


@dataclass(frozen=True)
class CellResult:
    """A cell's runs and what they say together: mean and standard deviation of DS over the scored runs (the
    complete-case mean), the identification bounds (unscored runs assigned 0 and 100), mean completion."""

    cell: str
    runs: tuple[RunResult, ...]
    infractions: dict[str, int] = field(default_factory=dict)

    @property
    def scored(self) -> list[RunResult]:
        return [r for r in self.runs if r.scored]

    @property
    def unscored(self) -> int:
        return len(self.runs) - len(self.scored)

    @property
    def mean(self) -> float | None:
        """The complete-case mean DS (None when no run is scored)."""
        ds = [r.ds for r in self.scored if r.ds is not None]
        return float(np.mean(ds)) if ds else None

    @property
    def std(self) -> float | None:
        ds = [r.ds for r in self.scored if r.ds is not None]
        return float(np.std(ds)) if ds else None

    @property
    def bounds(self) -> tuple[float, float]:
        """Mean DS with every unscored run at 0 and at 100: every assignment of them lies in between."""
        if not self.runs:
            return (0.0, 100.0)
        total = sum(r.ds for r in self.scored if r.ds is not None)
        n = len(self.runs)
        return (total / n, (total + 100.0 * self.unscored) / n)

    @property
    def completion(self) -> float | None:
        c = [r.completion for r in self.scored if r.completion is not None]
        return float(np.mean(c)) if c else None

    @staticmethod
    def of(cell: str, runs: list[RunResult]) -> CellResult:
        counts: dict[str, int] = {}
        for run in runs:
            for inf in run.infractions:
                counts[inf.kind] = counts.get(inf.kind, 0) + 1
        return CellResult(cell, tuple(runs), dict(sorted(counts.items())))
