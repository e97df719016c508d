"""CARLA leaderboard results files read into the closed loop's typed runs (SPEC section 13, "CARLA").

A results file is the leaderboard's checkpoint JSON (`--checkpoint`, written by its statistics manager, 1.0 and
2.x alike): `_checkpoint.records` holds one record per route run with `route_id` ("RouteScenario_3", in 2.x
"RouteScenario_3_rep0"), `status`, `scores` (`score_composed` = the Driving Score 0..100, `score_route` = the
route completion 0..100, `score_penalty` 0..1) and `infractions` (kind -> list of messages); `_checkpoint.progress`
is [routes done, routes planned]. One file is one cell: named `CELL=FILE` on the command line, else by the file's
own `"drivedegrade": {"cell": ..., "seed": ...}` object, else by its file name (`blackout-s5.json`).

The suite's rules carry over: a route whose agent or simulator failed (status "Failed - Agent crashed",
"... Simulation crashed", "... Agent couldn't be set up", "... Agent's sensors were invalid", or a record left
"Started") is **unscored**, whatever the leaderboard wrote into its scores; a planned route with no record (the
evaluation stopped early) is an unscored run too, never dropped. Blocked, deviated and timed-out routes are
scored driving outcomes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..corruptions.ladder import FAMILIES
from ..errors import DataError
from .results import END_BLOCKED, END_COMPLETE, END_OFF_ROAD, END_SCENE, END_UNSCORED, Infraction, RunResult

#: The leaderboard's infraction keys that are the suite's kinds; every other key keeps the leaderboard's name.
KINDS = {"collisions_pedestrian": "collision_pedestrian", "collisions_vehicle": "collision_vehicle",
         "collisions_layout": "collision_static", "outside_route_lanes": "off_road"}
#: Failure messages (after "Failed - ") that leave a route unscored: the agent or the simulator failed.
UNSCORED_FAILURES = ("Agent crashed", "Simulation crashed", "Agent couldn't be set up", "Agent's sensors were invalid")
#: Failure messages that end a scored run, and the suite's end reason for each.
ENDS = {"Agent got blocked": END_BLOCKED, "Agent deviated from the route": END_OFF_ROAD,
        "Agent timed out": END_SCENE}
#: Statuses of a scored run without a failure message (the leaderboard's 1.0 and 2.x).
SCORED_STATUSES = ("Completed", "Perfect", "Failed")
#: The most routes a file's progress may plan (the leaderboards' route files hold hundreds): a larger count is a
#: malformed file, refused before any placeholder run is made for it (issue 37, low: memory blow-up).
MAX_PLANNED = 100_000


@dataclass(frozen=True)
class LeaderboardRun:
    """One route run of a results file: the leaderboard's route id, its route and repetition, the cell's seed,
    DS 0..100 and completion 0..1 (None when unscored), the infraction penalty, the status as written, the
    suite's end reason, infraction counts by kind, the route length (m) and the score the file reported."""

    route_id: str
    route: str
    repetition: int
    seed: int
    ds: float | None
    completion: float | None
    penalty: float | None
    status: str
    end: str
    infractions: tuple[tuple[str, int], ...]
    length_m: float
    reported_ds: float | None

    @property
    def scored(self) -> bool:
        return self.ds is not None

    def run_result(self) -> RunResult:
        """The suite's run record (route = the leaderboard's route id; no trace: the simulator keeps it)."""
        found = tuple(Infraction(kind, -1, -1, "carla") for kind, n in self.infractions for _ in range(n))
        error = self.status if not self.scored else ""
        return RunResult(self.route_id, self.seed, self.ds, self.completion, self.end, found, np.zeros((0, 3)),
                         error)


@dataclass(frozen=True)
class ResultsFile:
    """One leaderboard results file as one cell's runs (`cell` without the "closed-" prefix)."""

    path: str
    cell: str
    seed: int
    entry_status: str
    runs: tuple[LeaderboardRun, ...]


#: The name of a second clean run's file: the null control of an agent that reads its rear cameras (`--null`).
CLEAN_RERUN = "clean-rerun"


def cell_name(name: str, where: str) -> str:
    """A cell name ("clean" or "<family>-s<1..5>", "closed-" prefix allowed: the plugin's closed cells), or
    `CLEAN_RERUN`; DataError naming it otherwise."""
    bare = name[len("closed-"):] if name.startswith("closed-") else name
    family, _, severity = bare.rpartition("-s")
    if bare in ("clean", CLEAN_RERUN) or (family in FAMILIES and severity in ("1", "2", "3", "4", "5")):
        return bare
    raise DataError(f"{where}: {name!r} is not a cell name (clean, FAMILY-sN such as blackout-s5, or {CLEAN_RERUN} "
                    "for a second clean run): name the cell as CELL=FILE on the command line or in the file's "
                    "\"drivedegrade\": {\"cell\": ...}")


def _number(value: object, where: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not lo - 1e-6 <= value <= hi + 1e-6:
        raise DataError(f"{where}: expected a number in [{lo:g}, {hi:g}], got {value!r}")
    return float(min(max(value, lo), hi))


def _split_id(route_id: str) -> tuple[str, int]:
    route, sep, rep = route_id.rpartition("_rep")
    return (route, int(rep)) if sep and rep.isdigit() else (route_id, 0)


def _infractions(raw: object, where: str) -> tuple[tuple[str, int], ...]:
    if not isinstance(raw, dict):
        raise DataError(f"{where}: \"infractions\" must be an object (kind -> list of messages), got {raw!r}")
    out = []
    for key, value in sorted(raw.items()):
        count = len(value) if isinstance(value, list) else value if isinstance(value, int) else None
        if count is None or count < 0:
            raise DataError(f"{where}: infractions[{key!r}] must be a list of messages, got {value!r}")
        if count:
            out.append((KINDS.get(str(key), str(key)), int(count)))
    return tuple(out)


def read_record(record: object, seed: int, where: str) -> LeaderboardRun:
    """One `_checkpoint.records` entry as a run; DataError naming `where` (file and record) when malformed."""
    if not isinstance(record, dict) or "route_id" not in record or "status" not in record:
        raise DataError(f"{where}: expected a route record with route_id, status, scores and infractions")
    route_id, status = str(record["route_id"]), str(record["status"])
    route, rep = _split_id(route_id)
    infractions = _infractions(record.get("infractions", {}), where)
    meta = record.get("meta")
    length = meta.get("route_length") if isinstance(meta, dict) else None
    length = float(length) if isinstance(length, (int, float)) and not isinstance(length, bool) else 0.0
    failure = status.partition(" - ")[2]
    known = status in (*SCORED_STATUSES, "Started") or (status.startswith("Failed - ") and failure in
                                                              (*UNSCORED_FAILURES, *ENDS))
    if not known:  # issue 37: an unknown status is neither scored as a driving outcome nor dropped
        raise DataError(f"{where}: unknown route status {status!r}; known: Completed, Perfect, Failed, Started, "
                        f"and 'Failed - ' with one of: {', '.join((*UNSCORED_FAILURES, *ENDS))}. A status this "
                        "import does not know cannot be scored as a driving outcome: fix the file, or report "
                        "the leaderboard version that writes it")
    if status == "Started" or failure in UNSCORED_FAILURES:
        given = record.get("scores")
        reported = given.get("score_composed") if isinstance(given, dict) else None
        reported = reported if isinstance(reported, (int, float)) and not isinstance(reported, bool) else None
        return LeaderboardRun(route_id, route, rep, seed, None, None, None, status, END_UNSCORED, infractions, length,
                              None if reported is None else float(reported))
    scores = record.get("scores")
    if not isinstance(scores, dict):
        raise DataError(f"{where}: \"scores\" must be an object with score_composed, score_route, score_penalty")
    ds = _number(scores.get("score_composed"), f"{where}: scores.score_composed", 0.0, 100.0)
    completion = _number(scores.get("score_route"), f"{where}: scores.score_route", 0.0, 100.0) / 100.0
    penalty = _number(scores.get("score_penalty", ds / max(100.0 * completion, 1e-9)),
                      f"{where}: scores.score_penalty", 0.0, 1.0)
    end = END_COMPLETE if status in ("Completed", "Perfect") else ENDS.get(failure, END_SCENE)
    return LeaderboardRun(route_id, route, rep, seed, ds, completion, penalty, status, end, infractions, length, ds)


def _load(path: Path) -> dict[str, object]:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DataError(f"{path}: no such results file (the leaderboard writes it where --checkpoint says)") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read the results file ({exc})") from None
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise DataError(f"{path}: not JSON ({exc}); a results file is the leaderboard's --checkpoint output") from None
    if not isinstance(data, dict) or not isinstance(data.get("_checkpoint"), dict) \
            or not isinstance(data["_checkpoint"].get("records"), list):
        raise DataError(f"{path}: not a leaderboard results file (no \"_checkpoint\": {{\"records\": [...]}})")
    return data


def read_results(path: Path, cell: str | None = None, seed: int = 0) -> ResultsFile:
    """A results file as one cell's runs: the cell from `cell`, else the file's "drivedegrade" object, else the
    file name; the seed from that object, else `seed`. Planned routes without a record are unscored runs."""
    data = _load(path)
    meta = data.get("drivedegrade") if isinstance(data.get("drivedegrade"), dict) else {}
    assert isinstance(meta, dict)
    name = cell_name(cell or str(meta.get("cell") or path.name.removesuffix(".json")), str(path))
    seed = meta.get("seed", seed)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise DataError(f"{path}: \"drivedegrade\".seed must be an integer, got {seed!r}")
    checkpoint = data["_checkpoint"]
    assert isinstance(checkpoint, dict)
    records = checkpoint["records"]
    runs = [read_record(r, seed, f"{path}: _checkpoint.records[{i}]") for i, r in enumerate(records)]
    progress = checkpoint.get("progress")
    planned = int(progress[1]) if isinstance(progress, list) and len(progress) == 2 \
        and isinstance(progress[1], int) and not isinstance(progress[1], bool) else len(runs)
    if not 0 <= planned <= MAX_PLANNED:
        raise DataError(f"{path}: _checkpoint.progress plans {planned} routes: not a route count (0 to "
                        f"{MAX_PLANNED}); fix the file")
    for i in range(len(runs), planned):  # the evaluation stopped before these routes: unscored, not dropped
        runs.append(LeaderboardRun(f"unrun_{i}", f"unrun_{i}", 0, seed, None, None, None,
                                   f"not run: progress says {planned} routes, the file has {len(records)} records",
                                   END_UNSCORED, (), 0.0, None))
    return ResultsFile(str(path), name, seed, str(data.get("entry_status", "")), tuple(runs))


def parse_source(arg: str) -> tuple[str | None, Path]:
    """A command-line source: `CELL=FILE` or `FILE`."""
    name, sep, path = arg.partition("=")
    return (name, Path(path)) if sep and not Path(arg).exists() else (None, Path(arg))
