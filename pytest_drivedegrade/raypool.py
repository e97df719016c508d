"""A pool of Ray planner actors (SPEC section 9, `--drivedegrade-ray`): each cell's frames are split into
scene-contiguous groups that actors run, and the controller joins their records into the cell's.

Each actor (`PlannerActor`) opens its own `RunContext` over the same data and options as the controller and
builds the planner once, with a builder the plugin hands over (the `planner` fixture of the planner file, built
outside pytest); it runs `RunContext.run_cell` on a span of frames and returns the record as builtins. Groups are
whole scenes (`shards.partition`, balanced by frame count, `GROUPS_PER_ACTOR` per actor), and ``reset`` and
frame_dropout's state restart at each scene, so the joined record (`CellRecord.concat`) is exactly the record of
one sequential run. The controller feeds the groups from one queue, `DEPTH` per actor, so no actor idles while
it finishes a cell, and starts the next cell early (`prefetch`). An actor whose process dies is replaced and the
group it was running is rerun (`losses`, reported in the terminal summary). The controller stays the only writer.

``import ray`` happens only here, and only when a pool starts, so the package works without Ray installed. The
actor's side (what it opens, builds and runs) is `rayactor`.
"""

from __future__ import annotations

import importlib
import logging
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

from .cells import CellRecord
from .data.frame import Frame
from .errors import DriveDegradeError, InvalidInput
from .planning import CallStyle
from .rayactor import ActorRun, Builder, PlannerActor
from .run import PlannerElsewhere, PlannerInfo, RunContext, Span
from .settings import Builtin
from .shards import partition, scene_runs

#: How to install Ray: the package's `ray` extra.
INSTALL = 'pip install -e ".[ray]"'
#: Actors of a local cluster (`--drivedegrade-ray local`) when --drivedegrade-ray-actors is not given.
LOCAL_ACTORS = 2
#: A cell is split into up to this many scene groups per actor (fewer when it has fewer scenes), so an actor
#: that finishes early takes the next group instead of idling at the end of the cell. One actor has no other to
#: wait for: it runs each cell whole, since every group pays its own first frame's loading and last frames'
#: scoring beside no planner call (`benchmarks/overlap.py`, 48 frames of two scenes: cells' wall 1.12-1.14 of the
#: planner's time in two groups, 1.07 whole).
GROUPS_PER_ACTOR = 3
#: Groups sent to one actor ahead of time: one running and one waiting, so the actor never waits for the
#: controller (which is writing the last cell) to hand it work.
DEPTH = 2
#: Seconds an actor may take to open the data and build the planner (loading weights, moving them to a GPU).
START_TIMEOUT = 600.0
#: Object store of a local cluster: records are small (tens of kB per group), so Ray's minimum is plenty.
LOCAL_OBJECT_STORE = 128 * 2**20

def import_ray() -> ModuleType:
    """The `ray` module, or DriveDegradeError saying how to install it."""
    try:
        return importlib.import_module("ray")
    except ImportError:
        raise DriveDegradeError(f"Ray is not installed; install the ray extra: {INSTALL}") from None


@dataclass(frozen=True)
class RayOptions:
    """`--drivedegrade-ray ADDRESS` (``local``, ``auto``, ``ray://host:port`` or ``host:port``), the actors
    (None: `LOCAL_ACTORS` on a local cluster, else as many as the cluster's CPUs, or GPUs / `gpus`) and the GPUs
    each actor asks for (fractional allowed)."""

    address: str
    actors: int | None = None
    gpus: float = 0.0

    @property
    def local(self) -> bool:
        return self.address == "local"


@dataclass
class _Job:
    """One cell (under one seed and one set of blacked-out cameras) on one span, as groups of whole scenes."""

    family: str
    severity: int
    unread: tuple[str, ...]
    seed: int
    spans: list[Span]
    parts: list[dict[str, Any] | None]
    error: str | None = None

    @property
    def done(self) -> bool:
        return self.error is not None or all(p is not None for p in self.parts)


@dataclass(frozen=True)
class _Task:
    job: _Job
    index: int

    def describe(self, frames: list[Frame]) -> str:
        a, b = self.job.spans[self.index]
        cell = self.job.family if self.job.severity == 0 else f"{self.job.family}-s{self.job.severity}"
        scenes = len({f.scene_token for f in frames[a:b]})
        return f"cell {cell} (seed {self.job.seed}), frames {a}-{b - 1} ({scenes} scene(s))"


@dataclass
class _Slot:
    """An actor of the pool: its number (1-based), the process it runs in, and its groups in submission order
    (an actor runs its tasks one at a time in that order, so the first one is the one running)."""

    number: int
    actor: Any
    pid: int = 0
    outstanding: list[tuple[Any, _Task]] = field(default_factory=list)


@dataclass(frozen=True)
class Loss:
    """An actor whose process died: which one, what it was running (rerun), and how many groups it had."""

    actor: int
    pid: int
    running: str
    groups: int


class RayPool:
    """The actors and the queue of groups. Built by `start`; `close` tears the fixtures down and disconnects."""

    def __init__(self, ray: Any, options: RayOptions, remote: Any, run: ActorRun, build: Builder,
                 default_name: str, frames: list[Frame]) -> None:
        self.ray, self.options, self.remote = ray, options, remote
        self.run, self.build, self.default_name = run, build, default_name
        self.frames = frames
        self.slots: list[_Slot] = []
        self.queue: deque[_Task] = deque()
        self.refs: dict[Any, _Slot] = {}
        self.jobs: dict[tuple[Any, ...], _Job] = {}
        self.losses: list[Loss] = []
        self.groups_run = 0
        self.described: dict[str, Any] = {}
        self.broken: str | None = None
        self.where = "a local cluster" if options.local else f"the cluster at {options.address}"

    # --- start and end -------------------------------------------------------------------------------------------

    @classmethod
    def start(cls, options: RayOptions, *, run: ActorRun, build: Builder, default_name: str,
              context: RunContext) -> RayPool:
        """Connect (or start a local cluster), start the actors and build the planner in each; DriveDegradeError
        saying what went wrong (Ray disconnected again) when the cluster cannot hold them or the planner cannot
        be built there."""
        ray = import_ray()
        settings: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING}
        actors = options.actors
        try:
            if options.local:
                actors = actors or LOCAL_ACTORS
                ray.init(address="local", num_cpus=actors, object_store_memory=LOCAL_OBJECT_STORE, **settings)
            else:
                ray.init(address=options.address, **settings)
        except Exception as exc:  # noqa: BLE001 - Ray raises ConnectionError, RuntimeError, ValueError ...
            raise DriveDegradeError(f"cannot start or join a Ray cluster at {options.address!r}: "
                                    f"{type(exc).__name__}: {exc}") from None
        remote = ray.remote(PlannerActor)
        pool = cls(ray, options, remote, run, build, default_name, context.frames)
        try:
            pool._start_actors(actors, context)
        except BaseException:
            pool.close()
            raise
        return pool

    def _start_actors(self, actors: int | None, context: RunContext) -> None:
        resources = self.ray.cluster_resources()
        cpus, gpus = float(resources.get("CPU", 0)), float(resources.get("GPU", 0))
        if actors is None:
            actors = int(gpus // self.options.gpus) if self.options.gpus > 0 else int(cpus)
        actors = max(1, actors)
        if cpus < actors or gpus + 1e-9 < actors * self.options.gpus:
            raise DriveDegradeError(
                f"{self.where} has {cpus:g} CPU(s) and {gpus:g} GPU(s); {actors} actor(s) need {actors} CPU(s) and "
                f"{actors * self.options.gpus:g} GPU(s) (--drivedegrade-ray-gpus {self.options.gpus:g} each): ask "
                "for fewer --drivedegrade-ray-actors or --drivedegrade-ray-gpus")
        self.slots = [_Slot(n + 1, self._new_actor()) for n in range(actors)]
        described = self._get([s.actor.start.remote() for s in self.slots], "starting the planner actors")
        for slot, info in zip(self.slots, described):
            self._check_started(slot, info, context)
        self.described = described[0]

    def _new_actor(self) -> Any:
        return self.remote.options(num_cpus=1, num_gpus=self.options.gpus, max_restarts=0,
                                   max_task_retries=0).remote(self.run, self.build, self.default_name)

    def _get(self, refs: list[Any], doing: str) -> list[Any]:
        try:
            return list(self.ray.get(refs, timeout=START_TIMEOUT))
        except self.ray.exceptions.GetTimeoutError:
            raise DriveDegradeError(f"{doing} on {self.where} took longer than {START_TIMEOUT:g} s") from None
        except self.ray.exceptions.RayError as exc:
            raise DriveDegradeError(f"{doing} on {self.where} failed: {exc}") from None

    def _check_started(self, slot: _Slot, info: Mapping[str, Any], context: RunContext) -> None:
        if "error" in info:
            raise DriveDegradeError(f"building the planner in a Ray actor failed: {info['error']}")
        if info["frames_key"] != context.frames_key or info["dataset_fingerprint"] != context.dataset_fingerprint:
            raise DriveDegradeError(f"Ray actor {slot.number} (pid {info['pid']}) reads other frames than the "
                                    f"controller from {self.run.root}: every node must see the "
                                    "same data at the same path")
        if self.described and info.get("fingerprint") != self.described.get("fingerprint"):
            raise DriveDegradeError(f"Ray actor {slot.number} built a planner with another fingerprint than actor 1: "
                                    "the planner (its weights or its `fingerprint`) must be the same in every actor")
        slot.pid = int(info["pid"])

    def close(self) -> list[str]:
        """Tear the planners' fixtures down, end the actors and disconnect (a local cluster stops); the lines
        of teardown problems. Safe to call twice."""
        if not self.ray.is_initialized():
            return []
        lines: list[str] = []
        try:
            for problems in self.ray.get([s.actor.stop.remote() for s in self.slots], timeout=120):
                lines += [f"ray: planner teardown: {p}" for p in problems]
        except self.ray.exceptions.RayError as exc:
            lines.append(f"ray: planner teardown did not finish: {type(exc).__name__}")
        for slot in self.slots:
            self.ray.kill(slot.actor, no_restart=True)
        self.ray.shutdown()
        return lines

    # --- work ----------------------------------------------------------------------------------------------------

    def spans(self, span: Span) -> list[Span]:
        """`span` split into up to GROUPS_PER_ACTOR x actors groups of whole scenes, balanced by frame count; one
        group, the whole span, on one actor."""
        frames = self.frames[span[0]:span[1]]
        count = min(len(scene_runs(frames)), GROUPS_PER_ACTOR * len(self.slots)) if len(self.slots) > 1 else 1
        out, start = [], span[0]
        for group in partition(frames, count):
            out.append((start, start + len(group)))
            start += len(group)
        return out

    def submit(self, family: str, severity: int, unread: tuple[str, ...], seed: int, span: Span) -> _Job:
        """Queue the cell's groups (once: the same arguments find the queued job)."""
        key = (family, severity, tuple(unread), seed, span)
        job = self.jobs.get(key)
        if job is None:
            spans = self.spans(span)
            job = self.jobs[key] = _Job(family, severity, tuple(unread), seed, spans, [None] * len(spans))
            self.queue.extend(_Task(job, i) for i in range(len(spans)))
        return job

    def result(self, family: str, severity: int, unread: tuple[str, ...], seed: int, span: Span) -> CellRecord:
        """The cell's record, its groups joined in frame order; DriveDegradeError when it cannot be computed."""
        if self.broken:
            raise DriveDegradeError(self.broken)
        job = self.submit(family, severity, unread, seed, span)
        mine = [t for t in self.queue if t.job is job]  # the cell asked for now goes first
        self.queue = deque([*mine, *(t for t in self.queue if t.job is not job)])
        while not job.done:
            self._pump()
            ready, _ = self.ray.wait(list(self.refs), num_returns=1)
            for ref in ready:
                self._collect(ref)
            if self.broken:
                raise DriveDegradeError(self.broken)
        del self.jobs[(family, severity, tuple(unread), seed, span)]
        if job.error is not None:
            raise DriveDegradeError(job.error)
        return CellRecord.concat([CellRecord.from_builtins(p) for p in job.parts if p is not None])

    def _pump(self) -> None:
        """Hand queued groups to the actors with fewer than DEPTH, the least busy first."""
        while self.queue:
            slot = min(self.slots, key=lambda s: (len(s.outstanding), s.number))
            if len(slot.outstanding) >= DEPTH:
                return
            task = self.queue.popleft()
            a, b = task.job.spans[task.index]
            ref = slot.actor.run.remote(task.job.family, task.job.severity, list(task.job.unread), task.job.seed, a, b)
            slot.outstanding.append((ref, task))
            self.refs[ref] = slot

    def _collect(self, ref: Any) -> None:
        slot = self.refs.pop(ref, None)
        if slot is None:  # a group of an actor already replaced
            return
        running = slot.outstanding[0][1]
        task = next(t for r, t in slot.outstanding if r == ref)
        try:
            data = self.ray.get(ref)
        except self.ray.exceptions.RayActorError:
            self._replace(slot, running)
            return
        except self.ray.exceptions.RayError as exc:  # the suite's own code failed in the actor: the cell fails
            slot.outstanding = [(r, t) for r, t in slot.outstanding if r != ref]
            task.job.error = f"Ray actor {slot.number} failed on {task.describe(self.frames)}: {exc}"
            return
        slot.outstanding = [(r, t) for r, t in slot.outstanding if r != ref]
        task.job.parts[task.index] = data
        self.groups_run += 1

    def _replace(self, slot: _Slot, running: _Task) -> None:
        """The actor's process died: its groups go back to the front of the queue (the one it was running is
        rerun, the others had not started) and a new actor takes its place."""
        tasks = [t for _, t in slot.outstanding]
        for r, _ in slot.outstanding:
            self.refs.pop(r, None)
        slot.outstanding = []
        self.queue.extendleft(reversed(tasks))
        self.losses.append(Loss(slot.number, slot.pid, running.describe(self.frames), len(tasks)))
        if len(self.losses) > 2 * len(self.slots):
            self.broken = (f"Ray planner actors died {len(self.losses)} times (last: actor {slot.number} while running "
                           f"{self.losses[-1].running}): the planner kills its process (a crash, os._exit, out of "
                           "memory); run that cell without --drivedegrade-ray to see the error")
            return
        try:
            self.ray.kill(slot.actor, no_restart=True)
        except self.ray.exceptions.RayError:
            pass
        slot.actor = self._new_actor()
        try:
            info = self._get([slot.actor.start.remote()], f"replacing Ray actor {slot.number}")[0]
            if "error" in info or info["frames_key"] != self.described["frames_key"]:
                raise DriveDegradeError(f"the replacement of Ray actor {slot.number} could not build the planner: "
                                        f"{info.get('error', 'it reads other frames')}")
            if info.get("fingerprint") != self.described.get("fingerprint") or \
                    info.get("dataset_fingerprint") != self.described.get("dataset_fingerprint"):
                what = "planner" if info.get("fingerprint") != self.described.get("fingerprint") else "data set"
                raise DriveDegradeError(f"the replacement of Ray actor {slot.number} (pid {info.get('pid')}) built a "
                                        f"{what} with another fingerprint than the run's: its cells would mix two "
                                        f"{what}s, so the run stops (was the planner's file, weights or data changed "
                                        "during the run?); rerun once they are settled")
        except DriveDegradeError as exc:
            self.broken = str(exc)
            return
        slot.pid = int(info["pid"])

    def summary(self) -> list[str]:
        """The terminal summary's lines: the pool, and every lost actor with what was rerun."""
        gpus = f", {self.options.gpus:g} GPU(s) each" if self.options.gpus else ""
        lines = [f"ray: {len(self.slots)} planner actor(s) on {self.where}{gpus}; {self.groups_run} scene group(s) run"]
        for loss in self.losses:
            waiting = loss.groups - 1
            lines.append(f"ray: actor {loss.actor} (pid {loss.pid}) died while running {loss.running}; replaced, "
                         f"1 shard rerun" + (f" ({waiting} queued shard(s) resubmitted)" if waiting else "") +
                         ", nothing lost")
        return lines


class RayPlanner(PlannerElsewhere):
    """The controller's handle on the planner the actors built: its name, cameras, fingerprint and call style
    as actor 1 reported them (a bad ``name`` or ``cameras`` raises InvalidInput where a local planner's would),
    and its cells run by the pool."""

    def __init__(self, pool: RayPool) -> None:
        self.pool = pool
        self.described = pool.described
        self._style = CallStyle(bool(self.described["takes_context"]), bool(self.described["resets"]))

    @property
    def name(self) -> str:
        if "name_error" in self.described:
            raise InvalidInput(self.described["name_error"])
        return str(self.described["name"])

    @property
    def cameras(self) -> tuple[str, ...]:
        if "cameras_error" in self.described:
            raise InvalidInput(self.described["cameras_error"])
        return tuple(self.described["cameras"])

    @property
    def info(self) -> PlannerInfo:
        return PlannerInfo(self.cameras, str(self.described["fingerprint"]))

    @property
    def style(self) -> CallStyle:
        return self._style

    def run_cell(self, context: RunContext, family: str, severity: int, *, unread: tuple[str, ...], seed: int,
                 span: Span) -> CellRecord:
        return self.pool.result(family, severity, unread, seed, span)

    def prefetch(self, context: RunContext, family: str, severity: int, *, unread: tuple[str, ...], seed: int) -> None:
        self.pool.submit(family, severity, unread, seed, (0, len(context.frames)))

    def jobs(self, target: str, kwargs: list[dict[str, Builtin]]) -> list[object]:
        """`PlannerActor.job` for each of `kwargs`, spread over the actors in turn; the results in order (the
        closed loop's runs: each is independent, its planner reset per route)."""
        pool = self.pool
        refs = [pool.slots[i % len(pool.slots)].actor.job.remote(target, kw) for i, kw in enumerate(kwargs)]
        try:
            return list(pool.ray.get(refs))
        except pool.ray.exceptions.RayError as exc:
            raise DriveDegradeError(f"closed-loop runs on {pool.where} failed: {exc}") from None
