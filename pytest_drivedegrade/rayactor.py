"""One Ray planner actor's side of the pool (`raypool`): what it opens (`ActorRun`, the run's settings as
builtins), how it builds the planner (`Builder`) and the state `ray.remote` wraps (`PlannerActor`): its own
RunContext, the planner built once, cells run on spans of frames and returned as builtins."""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import DriveDegradeError, InvalidInput
from .planning import DEVICE_ENV, Planner, call_style, planner_name
from .run import RunContext
from .settings import DEFAULTS, Builtin, RunSettings

#: What builds the planner in an actor: called with the actor's RunContext, returns the planner and a function
#: that tears its fixtures down (returning a line per teardown problem); raises DriveDegradeError saying why the
#: planner cannot be built there.
Builder = Callable[[RunContext], tuple[Planner, Callable[[], list[str]]]]


@dataclass(frozen=True)
class ActorRun:
    """What each actor opens, as builtins: the run's settings (`RunSettings.to_builtins`), the data root the
    controller resolved (the embedded world's folder too), the planner file and the digest cache folder."""

    settings: dict[str, Builtin]
    root: str
    planner_path: str | None = None
    digest_cache: str | None = None

    @property
    def device(self) -> str:
        return str(self.settings.get("device", DEFAULTS.device))

    def open(self) -> RunContext:
        """The actor's own RunContext over the run's data and settings."""
        return RunContext.open(RunSettings.from_builtins(self.settings), root=Path(self.root),
                               planner_path=None if self.planner_path is None else Path(self.planner_path),
                               digest_cache=None if self.digest_cache is None else Path(self.digest_cache))


class PlannerActor:
    """One actor's state (the class `ray.remote` wraps): its own RunContext over the run's data and options, the
    planner built once, and cells run on spans of frames."""

    def __init__(self, run: ActorRun, build: Builder, default_name: str) -> None:
        self.run_spec, self.build, self.default_name = run, build, default_name
        self.context: RunContext | None = None
        self.planner: Planner | None = None
        self.close: Callable[[], list[str]] | None = None

    def start(self) -> dict[str, Any]:
        """Open the data and build the planner; what the controller needs to know of them, or ``{"error": why}``.
        A bad ``cameras`` or ``name`` is reported as such and fails the cells, as in a local run."""
        os.environ[DEVICE_ENV] = self.run_spec.device  # the run's device, on any cluster
        try:
            self.context = context = self.run_spec.open()
            self.planner, self.close = self.build(context)
            style = call_style(self.planner)
        except DriveDegradeError as exc:
            return {"error": str(exc)}
        out: dict[str, Any] = {"pid": os.getpid(), "frames_key": context.frames_key,
                               "dataset_fingerprint": context.dataset_fingerprint,
                               "takes_context": style.takes_context, "resets": style.resets}
        try:
            info = context.planner_info(self.planner)
            out.update(cameras=list(info.cameras), fingerprint=info.fingerprint)
        except InvalidInput as exc:
            out["cameras_error"] = str(exc)
        try:
            out["name"] = planner_name(self.planner, self.default_name)
        except InvalidInput as exc:
            out["name_error"] = str(exc)
        return out

    def run(self, family: str, severity: int, unread: list[str], seed: int, start: int, stop: int) -> dict[str, Any]:
        """The cell on frames ``[start, stop)`` of the run, as `CellRecord.to_builtins`."""
        if self.context is None or self.planner is None:
            raise DriveDegradeError("the planner actor was not started")
        self.context.prime_clean(self.planner)  # clean planned first in this actor too (M12)
        record = self.context.run_cell(self.planner, family, severity, unread=tuple(unread), seed=seed,
                                       span=(start, stop))
        return record.to_builtins()

    def job(self, target: str, kwargs: dict[str, Builtin]) -> object:
        """``module:function`` called with this actor's RunContext, its planner and `kwargs`: work of a later
        stage (the closed loop's runs, `closedloop.remote`) that this module does not import."""
        if self.context is None or self.planner is None:
            raise DriveDegradeError("the planner actor was not started")
        module, _, name = target.partition(":")
        function: Callable[..., object] = getattr(importlib.import_module(module), name)
        return function(self.context, self.planner, **kwargs)

    def stop(self) -> list[str]:
        """Tear the planner's fixtures down (generator fixtures past their ``yield``); one line per problem."""
        close, self.close = self.close, None
        return close() if close is not None else []
