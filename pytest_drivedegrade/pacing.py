"""What runs beside the planner (`--drivedegrade-prefetch`, spec section 16): the scorer thread that scores frame
k-1 while the planner computes frame k, the prefetch depth the machine allows, and the process key under which
the cost ledger records each process's wall and planner seconds. `stream` calls the planner; this module only
keeps the threads and the bookkeeping around it."""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

from .settings import RunSettings


class Scorer:
    """Scores frame k-1 on one thread while the planner computes frame k (`overlap`), in frame order, with at
    most one frame waiting; without `overlap` each frame is scored at once, in the caller's thread (the serial
    path). A scoring failure is raised at the next frame or at the end, as the serial path raises it."""

    def __init__(self, overlap: bool) -> None:
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="drivedegrade-score") if overlap else None
        self.last: Future[None] | None = None

    def __enter__(self) -> Scorer:
        return self

    def submit(self, score: Callable[[], None]) -> None:
        if self.pool is None:
            score()
            return
        self.drain()
        self.last = self.pool.submit(score)

    def drain(self) -> None:
        last, self.last = self.last, None
        if last is not None:
            last.result()

    def __exit__(self, kind: type[BaseException] | None, *rest: object) -> None:
        if self.pool is None:
            return
        try:
            if kind is None:
                self.drain()
        finally:
            self.pool.shutdown(wait=True, cancel_futures=True)


#: The --drivedegrade-prefetch of a machine with a core to spare for the loading and scoring threads.
SPARE_CORE_PREFETCH = 2


def auto_prefetch(processes: int, cpus: int | None = None) -> int:
    """The default --drivedegrade-prefetch: `SPARE_CORE_PREFETCH` where the machine has more cores than the
    `processes` that run cells on it (each process's planner keeps one busy, its loading and scoring threads
    need another), else 0: the threads would only take cores from the other workers."""
    cpus = os.cpu_count() if cpus is None else cpus
    return SPARE_CORE_PREFETCH if (cpus or 1) > processes else 0


def prefetch_depth(settings: RunSettings) -> int:
    """The frames made ahead of the planner (`loader.ahead`): the setting, or where it is None (settings made
    outside the options) `auto_prefetch` for this process among the xdist workers it knows of."""
    if settings.prefetch is not None:
        return settings.prefetch
    return auto_prefetch(max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)))


def closed_threads(settings: RunSettings) -> int:
    """The threads a closed-loop cell drives with beside the planner (`closedloop.simulate.run_route`: a step's
    cameras rendered at once, the last plan's steps judged while the next cameras render): the prefetch depth
    plus one where it is above 0, else none (the serial path)."""
    depth = prefetch_depth(settings)
    return depth + 1 if depth > 0 else 0


_PROCESS: tuple[int, str] = (0, "")


def process_key() -> str:
    """This process's name in the cost ledger (`CellRecord.seconds` ``wall@KEY``): random, never a pid or host,
    and new in a forked child."""
    global _PROCESS
    if _PROCESS[0] != os.getpid():
        _PROCESS = (os.getpid(), secrets.token_hex(4))
    return _PROCESS[1]
