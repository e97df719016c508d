"""Closed-loop cells (SPEC section 13): which exist (`--drivedegrade-closed-cells slice|all|LIST`), their ids
(`closed-clean`, `closed-blackout-s5`), which (route, seed) runs a cell holds and which of them a shard runs, and
the stored record of a cell (its runs as JSON builtins, exact: a trace read back is the trace written, bit for
bit), with the content digest a resumed or merged cell must still hash to.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TypeAlias

import numpy as np

from ..errors import DriveDegradeError, InvalidInput
from ..settings import Builtin
from .results import Infraction, RunResult

PREFIX = "closed-"
#: The paper's seven cells, in run order: clean, the two quality families at S3 and S5, blackout S5, and blackout
#: S3 last (the null control compares it with clean, which by then is stored: no worker computes clean twice).
SLICE: tuple[tuple[str, int], ...] = (("clean", 0), ("gaussian_blur", 3), ("gaussian_blur", 5), ("motion_blur", 3),
                                      ("motion_blur", 5), ("blackout", 5), ("blackout", 3))
#: The null control's cell: blackout S3 darkens exactly the rear three cameras.
NULL_CELL = ("blackout", 3)
#: The command swap's cell (`closedloop.swap`, issue 40): clean cameras, the junction routes with their command
#: swapped (the route going straight on where the log turned). Not in the slice; in `all`, or named in a list.
SWAP = "command_swap"
#: Version of a stored closed cell (part of its run key). 2 (spec 5): runs scored as the CARLA leaderboard scores
#: them (every collision, percentage infractions with their value, route deviation and blocked ends).
CLOSED_RECORD_VERSION = 2
#: The plan rates the loop supports: 10 Hz sim steps divide evenly into planner calls.
HZ_CHOICES = (1, 2, 5, 10)
#: JSON as builtins: what a stored closed cell, a Ray actor's result and the certificate section hold.
Json: TypeAlias = None | bool | int | float | str | list["Json"] | dict[str, "Json"]


def as_float(value: object, where: str = "value") -> float:
    """A JSON number as float; ValueError naming `where` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: expected a number, got {value!r:.40}")
    return float(value)


def as_opt_float(value: object, where: str = "value") -> float | None:
    return None if value is None else as_float(value, where)


def as_int(value: object, where: str = "value") -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{where}: expected an integer, got {value!r:.40}")
    return value


def as_list(value: object, where: str = "value") -> list[object]:
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{where}: expected a list, got {type(value).__name__}")
    return list(value)


def as_map(value: object, where: str = "value") -> Mapping[str, object]:
    if not isinstance(value, Mapping):
        raise ValueError(f"{where}: expected an object, got {type(value).__name__}")
    return value


def closed_id(family: str, severity: int) -> str:
    """`closed-clean`, `closed-command_swap` or `closed-<family>-s<severity>`."""
    return f"{PREFIX}{family}" if family in ("clean", SWAP) else f"{PREFIX}{family}-s{int(severity)}"


def parse_id(cell: str) -> tuple[str, int]:
    """(family, severity) of a closed cell id (with or without the `closed-` prefix); InvalidInput otherwise."""
    name = cell[len(PREFIX):] if cell.startswith(PREFIX) else cell
    if name in ("clean", SWAP):
        return name, 0
    family, sep, sev = name.rpartition("-s")
    if not sep or not sev.isdigit():
        raise InvalidInput(f"{cell!r} is not a closed-loop cell (clean, {SWAP} or <family>-s<severity>, e.g. "
                           "blackout-s5)")
    return family, int(sev)


def selection(text: str) -> list[tuple[str, int]]:
    """The cells of `--drivedegrade-closed-cells`: `slice`, `all` (the slice, every other family at S3 and S5,
    and the command swap), or a comma-separated list of cells (clean, blackout-s5, closed-motion_blur-s3,
    command_swap, ...), always with clean first and blackout S3 (when present) last. DriveDegradeError naming
    what is wrong."""
    from ..corruptions.ladder import FAMILIES, SEVERITIES

    text = text.strip()
    if text == "slice":
        cells = list(SLICE)
    elif text == "all":
        cells = [*SLICE[:-1], *((f, s) for f in FAMILIES if f not in ("gaussian_blur", "motion_blur", "blackout")
                                for s in (3, 5)), (SWAP, 0), NULL_CELL]
    else:
        cells = []
        for part in (p.strip() for p in text.split(",") if p.strip()):
            family, severity = parse_id(part)
            if family not in ("clean", SWAP) and (family not in FAMILIES or severity not in SEVERITIES):
                raise DriveDegradeError(f"unknown closed-loop cell {part!r}: give slice, all, or cells such as "
                                        f"clean,blackout-s5 (families: {', '.join(FAMILIES)}; severities 1..5) "
                                        f"or {SWAP}")
            if (family, severity) not in cells:
                cells.append((family, severity))
        if not cells:
            raise DriveDegradeError("no closed-loop cell named: give slice, all, or a list such as clean,blackout-s5")
    rest = [c for c in cells if c not in (("clean", 0), NULL_CELL)]
    return [("clean", 0), *rest, *([NULL_CELL] if NULL_CELL in cells else [])]


def run_list(routes: Sequence[str], seeds: Sequence[int], family: str | None = None) -> list[tuple[str, int]]:
    """A cell's runs, route-major: (route, seed) for every route under every seed of `cell_seeds` (every seed
    given when `family` is None)."""
    chosen = list(seeds) if family is None else cell_seeds(family, seeds)
    return [(r, s) for r in routes for s in chosen]


def cell_seeds(family: str, seeds: Sequence[int]) -> list[int]:
    """The corruption seeds a closed cell runs under: every one for a random family (the seed draws its noise,
    drops or occluders, so each seed gives other images), the first alone for clean and every deterministic
    family (another seed gives the same inputs: its runs would replay the first's and count as evidence they are
    not; issue 36)."""
    from ..corruptions.registry import REGISTERED

    got = REGISTERED.get(family)
    return list(seeds) if got is not None and got.random else list(seeds[:1])


def shard_runs(runs: Sequence[tuple[str, int]], index: int, count: int) -> list[tuple[str, int]]:
    """The runs shard `index` of `count` (1-based) drives: contiguous, balanced to one run, in order, so the
    shards' runs joined in shard order are the unsharded cell's."""
    n = len(runs)
    return list(runs[(index - 1) * n // count: index * n // count])


def run_to_builtins(run: RunResult) -> dict[str, Json]:
    trace: list[Json] = [[float(v) for v in row] for row in np.asarray(run.trace, dtype=np.float64).reshape(-1, 3)]
    return {"route": run.route, "seed": int(run.seed), "ds": run.ds, "completion": run.completion, "end": run.end,
            "infractions": [[i.kind, int(i.step), int(i.sim_step), i.what,
                             *([] if i.value is None else [float(i.value)])] for i in run.infractions],
            "trace": trace, "error": run.error, "steps": int(run.steps)}


def run_from_builtins(data: Mapping[str, object]) -> RunResult:
    infractions = []
    for item in as_list(data["infractions"], "infractions"):
        kind, step, sim_step, what, *value = as_list(item, "infraction")
        infractions.append(Infraction(str(kind), as_int(step), as_int(sim_step), str(what),
                                      as_float(value[0], "infraction value") if value else None))
    return RunResult(str(data["route"]), as_int(data["seed"], "seed"), as_opt_float(data["ds"], "ds"),
                     as_opt_float(data["completion"], "completion"), str(data["end"]), tuple(infractions),
                     np.asarray(data["trace"], dtype=np.float64).reshape(-1, 3), str(data.get("error", "")),
                     as_int(data.get("steps", 0), "steps"))


def trace_digest(run: RunResult) -> str:
    """SHA-256 (16 hex) of a run's trace, float64 little-endian C order: equal digests, bit-identical paths."""
    return hashlib.sha256(np.ascontiguousarray(run.trace, dtype="<f8").tobytes()).hexdigest()[:16]


@dataclass(frozen=True)
class ClosedRecord:
    """One closed-loop cell: its runs in run order; `null_runs`, on the null control's cell of a planner that
    reads a rear camera, a rerun of clean (how far an untouched rerun wanders); `seconds` spent rendering,
    planning, tracking and scoring (outside the content digest: they differ between reruns)."""

    cell: str
    family: str
    severity: int
    runs: tuple[RunResult, ...]
    null_runs: tuple[RunResult, ...] = ()
    seconds: Mapping[str, float] = field(default_factory=dict)

    def content(self) -> dict[str, Json]:
        runs: list[Json] = [run_to_builtins(r) for r in self.runs]
        null_runs: list[Json] = [run_to_builtins(r) for r in self.null_runs]
        return {"cell": self.cell, "family": self.family, "severity": int(self.severity), "runs": runs,
                "null_runs": null_runs}

    def digest(self) -> str:
        """SHA-256 hex of the record's content (runs and traces, not the seconds)."""
        text = json.dumps(self.content(), sort_keys=True, separators=(",", ":"), allow_nan=False)
        return hashlib.sha256(text.encode()).hexdigest()

    def to_builtins(self) -> dict[str, Json]:
        seconds: dict[str, Json] = {k: float(v) for k, v in self.seconds.items()}
        return {**self.content(), "seconds": seconds}

    @classmethod
    def from_builtins(cls, data: Mapping[str, object]) -> ClosedRecord:
        try:
            return cls(str(data["cell"]), str(data["family"]), as_int(data["severity"], "severity"),
                       tuple(run_from_builtins(as_map(r, "run")) for r in as_list(data["runs"], "runs")),
                       tuple(run_from_builtins(as_map(r, "run")) for r in as_list(data.get("null_runs", []))),
                       {str(k): as_float(v, "seconds") for k, v in as_map(data.get("seconds") or {}).items()})
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidInput(f"not a closed-loop cell record ({type(exc).__name__}: {exc})") from None

    @staticmethod
    def concat(parts: Sequence[ClosedRecord]) -> ClosedRecord:
        """Shards' records of one cell joined in shard order (their runs, their null reruns, summed seconds)."""
        first = parts[0]
        seconds: dict[str, float] = {}
        for p in parts:
            for k, v in p.seconds.items():
                seconds[k] = seconds.get(k, 0.0) + v
        return ClosedRecord(first.cell, first.family, first.severity, tuple(r for p in parts for r in p.runs),
                            tuple(r for p in parts for r in p.null_runs), seconds)


@dataclass(frozen=True)
class ClosedPayload:
    """What travels to the controller and is stored as ``cells/closed-<cell>.json``: the record with its run
    key, planner and content digest, and whether it was reused from the store."""

    key: Mapping[str, Builtin]
    planner: str
    record: ClosedRecord
    resumed: bool = False

    @property
    def cell(self) -> str:
        return self.record.cell

    def to_builtins(self) -> dict[str, Json]:
        return {"key": dict(self.key), "planner": self.planner, "record": self.record.to_builtins(),
                "digest": self.record.digest(), "resumed": self.resumed}

    @classmethod
    def from_builtins(cls, data: object) -> ClosedPayload:
        """Inverse of `to_builtins`; InvalidInput when the record no longer hashes to its digest (edited)."""
        if not isinstance(data, Mapping) or not isinstance(data.get("record"), Mapping):
            raise InvalidInput("not a closed-loop cell file")
        record = ClosedRecord.from_builtins(data["record"])
        if data.get("digest") != record.digest():
            raise InvalidInput(f"{record.cell}: the stored runs no longer hash to their digest (edited or corrupted)")
        key = {str(k): v for k, v in as_map(data.get("key") or {}).items()
               if v is None or isinstance(v, (str, int, float))}
        return cls(key, str(data.get("planner", "")), record, bool(data.get("resumed")))
