"""One scene of a world as one task, run in worker processes (and this one): the build spread over the cores.

A task generates its scene and writes the scene's own files (point clouds, CAN bus, map expansion, images); the
tables it returns as JSON text and its share of the world's fingerprint as bytes, which the builder joins in scene
order. Every byte written is what the serial build writes, in whatever order the tasks finish.
"""

from __future__ import annotations

import functools
import hashlib
import multiprocessing
import os
import sys
from collections import deque
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

from ...errors import DriveDegradeError
from ...settings import cores
from ..maps import expansion_path
from . import export
from .rig import Rig
from .scene import KEYFRAMES, make_scene

#: The tables a scene appends records to, in the order `export.scene_tables` fills them.
SCENE_TABLES = ("log", "scene", "sample", "ego_pose", "sample_data", "sample_annotation", "instance")
MAX_WORKERS = 8  # beyond this a default world (6 val scenes of ~3 s, 94 train of ~0.2 s) gains little
#: Relative cost of a task, to start the slow ones first: rendering 240 images costs ~10 scenes of tables.
RENDER_COST, TABLES_COST = 10, 1


@dataclass(frozen=True)
class SceneTask:
    """What to do for scene `index` (named `name`) of the world with `seed`, under `root`."""

    root: str
    seed: int
    index: int
    name: str
    full_size: bool
    tables: bool = True  # its records, point clouds, CAN bus and map expansion
    render: bool = False  # its six cameras' JPEGs at every keyframe
    fingerprint_images: bool = False  # the JPEGs count in the world's fingerprint (val scenes)
    keyframes: int = KEYFRAMES  # the keyframes exported (`scene.scene_keyframes`: 42 for 4 s of future)

    @property
    def cost(self) -> int:
        return RENDER_COST * self.render + TABLES_COST * self.tables


@dataclass
class SceneOutput:
    """A finished task: its tables' records as JSON text (a list's items without the brackets, "" for none), its
    log token (the map record lists them), what it adds to the fingerprint, and its keyframes' events."""

    tables: dict[str, str]
    log_token: str
    fingerprint: bytes
    events: list[str]


@functools.lru_cache(maxsize=2)
def _rig(full_size: bool) -> Rig:
    return Rig.nuscenes_like(full_size)


def run_task(task: SceneTask) -> SceneOutput:
    """Generate the scene and write its files; what `write_world` once did inline per scene, in the same order."""
    root, rig = Path(task.root), _rig(task.full_size)
    scene = make_scene(task.seed, task.index, task.name, task.keyframes)
    feed: list[bytes] = []
    fragments = dict.fromkeys(SCENE_TABLES, "")
    log_token = ""
    if task.tables:
        records: dict[str, list[dict]] = {name: [] for name in SCENE_TABLES}
        records["map"] = [{"log_tokens": []}]
        for path, data in export.scene_tables(scene, task.seed, records, rig).items():
            (root / path).parent.mkdir(parents=True, exist_ok=True)
            (root / path).write_bytes(data)
            feed.append(hashlib.blake2b(data, digest_size=16).digest())
        log_token = records["map"][0]["log_tokens"][0]
        fragments = {name: export.items_json(records[name]) for name in SCENE_TABLES}
        export.dump(root / "can_bus" / f"{scene.name}_pose.json", export.can_bus(scene))
        feed.append(export.dump(expansion_path(root, export.location(scene, task.seed)),
                                export.map_expansion(scene, task.seed)))
    if task.render:
        digests = export.render_scene(scene, rig, root)
        if task.fingerprint_images:
            feed += digests
    return SceneOutput(fragments, log_token, b"".join(feed), list(scene.events))


def default_workers(tasks: int) -> int:
    """Worker processes for `tasks` tasks: the cores this process may run on (`settings.cores`), at most
    `MAX_WORKERS` and at most the tasks; 1 means in this process, no pool."""
    return max(1, min(cores(), MAX_WORKERS, tasks))


#: Why a build worker that re-ran a script's top level stops, and what a build whose worker stopped says.
UNGUARDED_MAIN = ("the embedded world is built on spawned processes, which import the main script: a script that "
                  "calls pytest.main() at its top level must do it under `if __name__ == \"__main__\":`")


def starting_worker() -> bool:
    """Whether this process is a spawned worker still importing the main script (multiprocessing's own flag for
    it, the one behind its 'bootstrapping phase' error). A script calling ``pytest.main`` without a main guard
    re-runs it there, and the worker would wait forever for the world its parent is building."""
    return bool(getattr(multiprocessing.current_process(), "_inheriting", False))


def stop_starting_worker() -> None:
    """End a spawned worker that is re-running a script's pytest.main (`starting_worker`), saying why: its
    parent's build then fails with `UNGUARDED_MAIN` instead of both waiting on the world's lock for ever."""
    if starting_worker():
        sys.stderr.write(f"drivedegrade: this build worker stopped: {UNGUARDED_MAIN}\n")
        sys.stderr.flush()
        os._exit(1)


def _init_worker() -> None:
    """One OpenCV thread per worker: the workers already fill the cores (results do not depend on it)."""
    import cv2

    cv2.setNumThreads(1)


def run_tasks(tasks: list[SceneTask], workers: int | None = None,
              done: Callable[[SceneTask], None] | None = None) -> list[SceneOutput]:
    """Run `tasks` on `workers` processes (None: `default_workers`), the costliest first; outputs in task order.

    This process is one of them: it runs tasks itself while `workers - 1` spawned processes run theirs, so work
    starts at once, not after a worker has started and imported (and one process fewer is spawned). Workers are
    spawned, not forked: the caller may be a pytest process with torch's or OpenCV's threads running.
    `done` is called in this process as each task finishes (for a progress line).
    """
    n = default_workers(len(tasks)) if workers is None else max(1, min(workers, len(tasks) or 1))
    note = done or (lambda task: None)
    if n == 1:
        outputs = []
        for task in tasks:
            outputs.append(run_task(task))
            note(task)
        return outputs
    results: dict[int, SceneOutput] = {}
    queue = deque(sorted(range(len(tasks)), key=lambda i: (-tasks[i].cost, i)))
    pending: dict[Future[SceneOutput], int] = {}
    pool = ProcessPoolExecutor(n - 1, mp_context=get_context("spawn"), initializer=_init_worker)
    try:
        while queue or pending:
            while queue and len(pending) < 2 * (n - 1):  # the workers' next tasks, queued while this one works
                i = queue.popleft()
                pending[pool.submit(run_task, tasks[i])] = i
            if queue:
                i = queue.popleft()
                results[i] = _here(tasks[i])
                note(tasks[i])
            finished, _ = wait(pending, timeout=0 if queue else None, return_when=FIRST_COMPLETED)
            for future in finished:
                i = pending.pop(future)
                results[i] = future.result()
                note(tasks[i])
    except BrokenProcessPool as exc:
        raise DriveDegradeError(f"a process building the embedded world stopped before its scenes were done ({exc}). "
                                f"If pytest runs from a script: {UNGUARDED_MAIN}. Otherwise the machine may have run "
                                "out of memory: run again, and the build starts over") from None
    finally:  # on an error or an interrupt, the tasks not yet started are dropped, not waited for
        pool.shutdown(wait=True, cancel_futures=True)
    return [results[i] for i in range(len(tasks))]


def _here(task: SceneTask) -> SceneOutput:
    """`run_task` in this process, on one OpenCV thread as in the workers (the caller's setting restored)."""
    import cv2

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return run_task(task)
    finally:
        cv2.setNumThreads(threads)
