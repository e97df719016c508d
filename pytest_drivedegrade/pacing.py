"""What runs beside the planner (`--drivedegrade-prefetch`, spec section 16): the scorer thread that scores frame
k-1 while the planner computes frame k, a cell's PDMS scored in spans there (`CellPdms`), the prefetch depth the
machine allows, OpenCV's share of its cores while cells run (`opencv_share`), and the process key under which the
cost ledger records each process's wall and planner seconds.
`stream` calls the planner; this module only keeps the threads and the bookkeeping around it."""

from __future__ import annotations

import os
import secrets
import threading
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Protocol

import cv2
import numpy as np

from .cells import PDMS_FIELDS, RecordBuilder
from .data.frame import Frame
from .metrics.pdms import EgoStates, PreparedFrame, tracked_states
from .metrics.pdms.extended import EC_MAX_INTERVAL_S, epdms_score, extended_comfort
from .settings import RunSettings, cores

#: Frames whose PDMS the scoring thread scores together beside the planner (`CellPdms`): one tracker batch
#: costs about as much for 1 plan as for 200, so a span trades CPU for not scoring the whole cell at its end.
PDMS_SPAN = 32


class PdmsSource(Protocol):
    """Where a cell's PDMS preparation comes from (`run.RunContext.pdms_frame`, once per frame and process)."""

    def pdms_frame(self, frame: Frame, poses: int = ...) -> PreparedFrame: ...


class CellPdms:
    """The PDMS and EPDMS of a cell's frames with a plan, scored span by span as their rows are filled: every
    `span` frames (on the scoring thread, beside the planner) or, with `span` None, all at the cell's end in one
    tracker batch (the serial path: the cheapest). The figures are the same either way: a plan's tracked states
    do not depend on its batch, and a frame's EC reads the previous frame's states, which are kept across spans.
    Not `enabled`: nothing is scored (the columns stay NaN)."""

    def __init__(self, source: PdmsSource, rows: RecordBuilder, frames: list[Frame], span: int | None,
                 enabled: bool = True) -> None:
        self.source, self.rows, self.frames, self.span, self.enabled = source, rows, frames, span, enabled
        self.done = 0
        self.states: dict[int, EgoStates] = {}

    def ready(self, i: int) -> bool:
        """Frame `i`'s row is filled (rows fill in frame order): prepare its frame (`PdmsSource.pdms_frame`, once
        per process: the first cell's, frame by frame beside the planner rather than a span's worth at once,
        which held the planner's next frame back) and score the span it ends, if it ends one."""
        if not self.enabled or self.span is None:
            return False
        self.source.pdms_frame(self.frames[i], self.rows.arrays["plans"].shape[1])
        if i + 1 - self.done < self.span:
            return False
        self._score(i + 1)
        return True

    def finish(self) -> None:
        """Score the frames left (all of them on the serial path)."""
        if self.enabled:
            self._score(len(self.frames))

    def _score(self, stop: int) -> None:
        score_cell_pdms(self.source, self.rows, self.frames, range(self.done, stop), self.states)
        self.done = stop
        self.states = {i: s for i, s in self.states.items() if i == stop - 1}  # what the next span's EC reads


def score_cell_pdms(source: PdmsSource, rows: RecordBuilder, frames: list[Frame], span: range,
                    states: dict[int, EgoStates]) -> None:
    """The PDMS and EPDMS of the frames in `span` with a plan (its own or clean's), their plans tracked in one
    batch (added to `states`) and each frame's EC against the previous keyframe's plan of its scene in this cell
    (`previous_frame`, its states in `states`): deterministic for any batches, spans, workers or reuse."""
    plans = rows.arrays["plans"]
    have = [i for i in span if np.isfinite(plans[i]).all()]
    prepared = {i: source.pdms_frame(frames[i], plans.shape[1]) for i in have}
    states.update(zip(have, tracked_states(plans[have], [prepared[i].initial for i in have])))
    for i in have:
        result, terms = prepared[i].judged(plans[i], states[i])
        human = prepared[i].human
        prev = previous_frame(frames, i)
        ec = extended_comfort(states[i], states.get(prev) if prev is not None else None,
                              (frames[i].timestamp - frames[prev].timestamp) * 1e-6 if prev is not None else 0.5)
        rows.put(i, map_scored=float(result.map_scored), **{k: getattr(result, k) for k in PDMS_FIELDS},
                 ddc=terms.ddc, tlc=terms.tlc, lk=terms.lk, hc=terms.hc, ec=ec,
                 epdms=epdms_score(terms.filtered(human) if human is not None else terms, ec))


def previous_frame(frames: list[Frame], i: int) -> int | None:
    """The index of frame i's previous keyframe when it is frame i - 1 of the cell: same scene, the keyframe
    before, at most EC_MAX_INTERVAL_S earlier (else None: EC not scored for frame i)."""
    if i == 0:
        return None
    a, b = frames[i - 1], frames[i]
    gap = (b.timestamp - a.timestamp) * 1e-6
    same = a.scene_token == b.scene_token and b.index == a.index + 1
    return i - 1 if same and 0.0 < gap < EC_MAX_INTERVAL_S else None


#: Frames the scoring thread may hold beside the planner (`Scorer`): two, so that a PDMS span scored with one
#: frame (`CellPdms`, about 40 ms for 32 plans) does not hold the planner's next frame back.
SCORER_DEPTH = 2


class Scorer:
    """Scores the planner's last frames on one thread while it computes the next (`overlap`), in frame order,
    with at most `SCORER_DEPTH` frames waiting (their samples and images: the memory bound); without `overlap`
    each frame is scored at once, in the caller's thread (the serial path). A scoring failure is raised at a
    later frame or at the end, as the serial path raises it."""

    def __init__(self, overlap: bool) -> None:
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="drivedegrade-score") if overlap else None
        self.waiting: deque[Future[None]] = deque()

    def __enter__(self) -> Scorer:
        return self

    def submit(self, score: Callable[[], None]) -> None:
        if self.pool is None:
            score()
            return
        while len(self.waiting) >= SCORER_DEPTH:
            self.waiting.popleft().result()
        self.waiting.append(self.pool.submit(score))

    def drain(self) -> None:
        while self.waiting:
            self.waiting.popleft().result()

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
    """The default --drivedegrade-prefetch: `SPARE_CORE_PREFETCH` where this process has more cores (`cores`)
    than the `processes` that run cells on them (each process's planner keeps one busy, its loading and scoring
    threads need another), else 0: the threads would only take cores from the other workers."""
    return SPARE_CORE_PREFETCH if (cores() if cpus is None else cpus) > processes else 0


def prefetch_depth(settings: RunSettings) -> int:
    """The frames made ahead of the planner (`loader.ahead`): the setting, or where it is None (settings made
    outside the options) `auto_prefetch` for this process among the xdist workers it knows of."""
    if settings.prefetch is not None:
        return settings.prefetch
    return auto_prefetch(processes_here())


#: OpenCV's own variable for its thread count: where the user set it, the run leaves OpenCV's threads alone.
OPENCV_THREADS_ENV = "OPENCV_FOR_THREADS_NUM"


def opencv_threads(cpus: int | None = None) -> int:
    """The threads OpenCV may use in a process running cells: its share of the cores (`cores`) among the
    processes that run cells on the machine (`processes_here`), at least one. OpenCV starts a thread per core in
    every process by default, so under ``-n 2`` on two cores each worker's resize, blur or remap was split in two
    and half of it waited for the core the other worker held. One process keeps every core: there a GPU planner's thread
    leaves its core to the loading thread's OpenCV calls. OpenCV's results do not depend on its thread count."""
    return max(1, (cores() if cpus is None else cpus) // processes_here())


#: (cells running now in this process, OpenCV's count before the first of them): the first cell in sets the
#: count, the last one out puts it back, so cells overlapping on threads (the floor's beside a cell) never leave
#: one cell's setting behind.
_OPENCV_SHARED: list[int] = [0, 0]
_OPENCV_LOCK = threading.Lock()


@contextmanager
def opencv_share() -> Iterator[None]:
    """OpenCV's thread count set to `opencv_threads` while cells run, and put back after the last of them; left
    alone where the user set $OPENCV_FOR_THREADS_NUM."""
    if os.environ.get(OPENCV_THREADS_ENV):
        yield
        return
    with _OPENCV_LOCK:
        if _OPENCV_SHARED[0] == 0:
            _OPENCV_SHARED[1] = cv2.getNumThreads()
            cv2.setNumThreads(opencv_threads())
        _OPENCV_SHARED[0] += 1
    try:
        yield
    finally:
        with _OPENCV_LOCK:
            _OPENCV_SHARED[0] -= 1
            if _OPENCV_SHARED[0] == 0:
                cv2.setNumThreads(_OPENCV_SHARED[1])


def processes_here() -> int:
    """The processes running cells on this machine as this one knows them: the xdist workers, else 1."""
    return max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1))


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
