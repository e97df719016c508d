"""`--drivedegrade-ray`: the planner built outside pytest, in each Ray actor, and the pool's start for the session.

An actor has no pytest session, so it builds the `planner` fixture from the planner file alone (`PlannerFile`):
the fixture and the fixtures of the same file it requests, each once, with `drivedegrade_context` as the actor's
own RunContext; generator fixtures run to their ``yield`` and are torn down when the pool closes. A fixture that
asks for anything else (``request``, ``tmp_path``, a conftest fixture) is a usage error naming it. The controller
never builds the planner: its name, cameras, fingerprint and call style come from the actors.
"""

from __future__ import annotations

import inspect
import sys
import traceback
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import pytest

from ..errors import DriveDegradeError
from ..planning import FIXTURE_NAME, Planner
from ..run import RunContext
from .compat import fixture_function, is_fixture
from .context import cache_root
from .options import RunOptions

if TYPE_CHECKING:
    from ..raypool import RayPlanner

#: The one fixture of the suite a planner file may request in an actor.
CONTEXT_FIXTURE = "drivedegrade_context"


class FixtureUnavailable(DriveDegradeError):
    """A fixture of the planner file requests one that only pytest's test run provides (``request``, a conftest
    fixture): the planner cannot be built outside pytest."""


@dataclass(frozen=True)
class PlannerFile:
    """Builds the `planner` fixture of `path` (imported as module `module`: a conftest's own name, or by default
    the name the controller imports a planner file under, so the planner's fingerprint is the same). `loaded`:
    the module already imported in this process (the controller's pre-flight), used as it is."""

    path: Path
    module: str | None = None
    loaded: ModuleType | None = field(default=None, compare=False)
    option: str = "--drivedegrade-ray"  #: the option that builds it outside pytest, as its errors name it

    def __call__(self, context: RunContext) -> tuple[Planner, Callable[[], list[str]]]:
        from .items import import_planner_file

        if self.module is not None and self.loaded is None:  # a conftest imports its siblings (pytest's prepend mode)
            sys.path.insert(0, str(self.path.parent))
        try:
            module = self.loaded or import_planner_file(self.path, self.module)
        except pytest.UsageError as exc:
            raise DriveDegradeError(str(exc)) from None
        table = dict(fixture_function(obj) for obj in vars(module).values() if is_fixture(obj))
        built: dict[str, Any] = {CONTEXT_FIXTURE: context}
        open_generators: list[tuple[str, Generator[Any, Any, Any]]] = []

        def value(name: str, chain: tuple[str, ...]) -> Any:
            if name in built:
                return built[name]
            if name not in table:
                via = " -> ".join((*chain, name))
                who, where = _OUTSIDE[self.option]
                raise FixtureUnavailable(
                    f"{self.path}: fixture {chain[-1]!r} requests {name!r} ({via}), which {who} cannot provide: "
                    f"with {self.option} the planner is built {where} from {self.path.name} alone, so its "
                    f"fixtures may request only fixtures of that file and {CONTEXT_FIXTURE}; build it without "
                    f"{name!r}, or run without {self.option}")
            if name in chain:
                cycle = " -> ".join((*chain, name))
                raise DriveDegradeError(f"{self.path}: fixture {name!r} requests itself ({cycle})")
            function = table[name]
            kwargs = {arg: value(arg, (*chain, name)) for arg in _arguments(function)}
            try:
                result = function(**kwargs)
                if inspect.isgenerator(result):
                    generator, result = result, next(result)
                    open_generators.append((name, generator))
            except Exception as exc:  # noqa: BLE001 - the user's fixture failed: say where, no traceback
                raise DriveDegradeError(f"{self.path}{_line(exc, self.path)}: fixture {name!r} raised "
                                        f"{type(exc).__name__}: {exc}") from None
            built[name] = result
            return result

        planner: Planner = value(FIXTURE_NAME, ())

        def close() -> list[str]:
            problems = []
            for name, generator in reversed(open_generators):
                try:
                    next(generator)
                except StopIteration:
                    continue
                except Exception as exc:  # noqa: BLE001 - a teardown failure is reported, the others still run
                    problems.append(f"fixture {name!r} raised {type(exc).__name__} in its teardown: {exc}")
                    continue
                problems.append(f"fixture {name!r} yielded more than once")
            return problems

        return planner, close


#: What builds the planner outside pytest under each option, and where (`PlannerFile`'s errors say it).
_OUTSIDE = {"--drivedegrade-ray": ("a Ray actor", "in each actor"),
            "--drivedegrade-isolate": ("a child process", "in a child process of each worker")}


def _arguments(function: Callable[..., object]) -> list[str]:
    """The fixtures a fixture function requests: its parameters without a default, as pytest reads them."""
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [p.name for p in inspect.signature(function).parameters.values()
            if p.kind in kinds and p.default is inspect.Parameter.empty]


def _line(exc: BaseException, path: Path) -> str:
    where = [f for f in traceback.extract_tb(exc.__traceback__) if Path(f.filename) == path]
    return f":{where[-1].lineno}" if where else ""


def start_planner_actors(config: pytest.Config, options: RunOptions, context: RunContext,
                         collect_path: Path) -> RayPlanner:
    """Start the pool of `options.ray` on the run's data and options; DriveDegradeError saying what went wrong."""
    from ..raypool import ActorRun, RayPlanner, RayPool

    assert options.ray is not None
    module = None
    if options.planner_path is None:  # conftest mode: the conftest's module name, as pytest imported it
        module = next((getattr(p, "__name__", None) for p in config.pluginmanager.get_plugins()
                       if Path(getattr(p, "__file__", "") or ".") == collect_path), None) or "conftest"
    run = ActorRun(options.settings.to_builtins(), str(context.reader.root),
                   None if options.planner_path is None else str(options.planner_path),
                   str(cache_root(config) / "digests"))
    default = options.planner_path.stem if options.planner_path else "planner"
    pool = RayPool.start(options.ray, run=run, build=PlannerFile(collect_path, module),
                         default_name=default, context=context)
    return RayPlanner(pool)
