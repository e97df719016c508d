"""The pre-flight's planner check in a process of its own, under -n N (issue 37: the controller decides the gate
and the exit status, so it never runs planner code; issue 41: the check still runs before any cell).

The controller writes a request (the run's settings as builtins, the data root, the planner file), starts
``python -m pytest_drivedegrade.plugin.isolated REQUEST ANSWER`` and reads the answer. A child that ends without
an answer (the planner called ``os._exit``, crashed the interpreter or hung past the limit) is a failed
pre-flight, a usage error naming what happened: never a pass.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, cast

import pytest

from ..errors import DriveDegradeError
from ..run import RunContext
from ..store import ResultStore
from .childplanner import clean_environment
from .options import RunOptions
from .plannercheck import HEAD, Found, Probe, inspect_planner

if TYPE_CHECKING:
    from ..run import AnyPlanner
    from .childplanner import ChildPlanner

#: Seconds the child may take beyond two planner calls' limit: the interpreter, torch, the data index, the build.
START_SECONDS = 600.0


def start_isolated(config: pytest.Config, options: RunOptions, context: RunContext,
                   collect_path: Path) -> ChildPlanner:
    """--drivedegrade-isolate: the planner built in a child process of this worker (`childplanner`), and its
    stand-in here; DriveDegradeError saying why it cannot be built."""
    from functools import partial

    from ..pacing import OPENCV_THREADS_ENV, opencv_threads
    from .childplanner import spawn, start_child_planner
    from .context import cache_root

    assert options.planner_path is not None  # `options.parse` refuses --drivedegrade-isolate without a file
    request = {"run": {"settings": options.settings.to_builtins(), "root": str(context.reader.root),
                       "planner_path": str(options.planner_path),
                       "digest_cache": str(cache_root(config) / "digests")},
               "collect_path": str(collect_path), "module": None, "default_name": options.planner_path.stem,
               "opencv_threads": 0 if os.environ.get(OPENCV_THREADS_ENV) else opencv_threads()}
    return start_child_planner(partial(spawn, request), options.settings.timeout)


def certify_isolated(request: pytest.FixtureRequest) -> None:
    """One cell (open or closed loop) under --drivedegrade-isolate, the function its item runs: the planner is
    this process's stand-in (`childplanner`), its child started at the first cell; a planner that cannot be
    built there fails every cell, saying why. No process of the run builds the planner itself."""
    from . import SESSION_KEY
    from .items import ClosedItem

    session = request.config.stash[SESSION_KEY]
    if session.isolated is None:
        try:
            session.isolated = start_isolated(session.config, session.options, session.run_context(),
                                              session.collect_path)
        except DriveDegradeError as exc:
            session.isolated = f"--drivedegrade-isolate: the planner could not be built in its process: {exc}"
    if isinstance(session.isolated, str):
        pytest.fail(session.isolated, pytrace=False)
    session.isolated.new_cell()
    planner = cast("AnyPlanner", session.isolated)  # called as the planner it stands in for
    item = request.node
    if isinstance(item, ClosedItem):
        session.run_closed_item(item, planner)
    else:
        session.run_item(item, planner)


def _request(options: RunOptions, context: RunContext, collect_path: Path, module: ModuleType | None,
             store: ResultStore | None, cells: Sequence[tuple[str, int]], digests: Path) -> dict[str, object]:
    return {"settings": options.settings.to_builtins(), "root": str(context.reader.root),
            "planner_path": None if options.planner_path is None else str(options.planner_path),
            "digest_cache": str(digests), "collect_path": str(collect_path),
            "module": None if module is None else module.__name__,
            "store": None if store is None else {"report_dir": str(store.report_dir), "shard": store.shard,
                                                 "resume": store.resume, "reuse": store.reuse},
            "cells": [list(c) for c in cells]}


def _tail(text: str, lines: int = 8) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


def check_in_child(options: RunOptions, context: RunContext, collect_path: Path, module: ModuleType | None,
                   store: ResultStore | None, cells: Sequence[tuple[str, int]], digests: Path) -> Found | str:
    """`inspect_planner` run in a child process, or why no frame could be checked (a fixture that cannot be built
    outside pytest); a usage error when the child gives no answer or the planner cannot be built."""
    limit = START_SECONDS + 3 * (options.settings.timeout or 60.0)
    with tempfile.TemporaryDirectory(prefix="drivedegrade-preflight-") as tmp:
        req, ans = Path(tmp) / "request.json", Path(tmp) / "answer.json"
        req.write_text(json.dumps(_request(options, context, collect_path, module, store, cells, digests)))
        try:
            done = subprocess.run([sys.executable, "-m", __name__, str(req), str(ans)], capture_output=True,
                                  text=True, timeout=limit, check=False, env=clean_environment())
        except subprocess.TimeoutExpired:
            raise pytest.UsageError(f"{HEAD}: the planner's check did not finish within {limit:.0f} s (building "
                                    "the planner and two clean predictions), so no cell ran") from None
        if not ans.is_file():
            why = _tail(done.stderr) or _tail(done.stdout) or "no output"
            raise pytest.UsageError(f"{HEAD}: the process that builds and checks the planner ended (exit "
                                    f"{done.returncode}) without an answer, so no cell ran: planner code that ends "
                                    f"its process (os._exit, a crash) fails the run. Its last output:\n{why}")
        answer = json.loads(ans.read_text())
    if "unavailable" in answer:
        return str(answer["unavailable"])
    if "error" in answer:  # an import failure already reads "--drivedegrade: importing FILE failed: ..."
        error = str(answer["error"])
        raise pytest.UsageError(error if error.startswith("--drivedegrade:") else
                                f"{HEAD}: building the planner failed, so no cell ran: {error}")
    probe = answer["probe"]
    return Found(tuple(answer["problems"]), tuple(answer["notes"]),
                 None if probe is None else Probe(probe["token"], float(probe["seconds"]), tuple(probe["read"]),
                                                  probe["name"]),
                 frozenset(answer["stored"]))


def _answer(request: dict[str, object]) -> dict[str, object]:
    from ..planning import DEVICE_ENV
    from ..rayactor import ActorRun
    from .actors import FixtureUnavailable, PlannerFile

    run = ActorRun(request["settings"], str(request["root"]), request["planner_path"],  # type: ignore[arg-type]
                   request["digest_cache"])  # type: ignore[arg-type]
    os.environ[DEVICE_ENV] = run.device
    context = run.open()
    try:
        planner, close = PlannerFile(Path(str(request["collect_path"])), request["module"])(  # type: ignore[arg-type]
            context)
    except FixtureUnavailable as exc:  # as `plannercheck.build_planner` says it in process
        return {"unavailable": str(exc).split(", which a ")[0]}
    except DriveDegradeError as exc:
        return {"error": str(exc)}
    spec = request["store"]
    store = None if not isinstance(spec, dict) else ResultStore(Path(spec["report_dir"]), spec["shard"],
                                                                 resume=spec["resume"], reuse=spec["reuse"])
    cells = [(str(f), int(s)) for f, s in request["cells"]]  # type: ignore[attr-defined]
    try:
        found = inspect_planner(planner, context, store, cells)
    finally:
        close()
    p = found.probe
    return {"problems": list(found.problems), "notes": list(found.notes), "stored": sorted(found.stored),
            "probe": None if p is None else {"token": p.token, "seconds": p.seconds, "read": list(p.read),
                                             "name": p.name}}


def main(argv: Sequence[str]) -> int:
    """Answer one request (REQUEST ANSWER paths); the answer is written last, so its presence means a finished
    check."""
    request = json.loads(Path(argv[0]).read_text())
    answer = _answer(request)
    tmp = Path(argv[1]).with_suffix(".part")
    tmp.write_text(json.dumps(answer))
    tmp.replace(argv[1])
    return 0


if __name__ == "__main__":  # pragma: no cover - run by check_in_child
    raise SystemExit(main(sys.argv[1:]))
