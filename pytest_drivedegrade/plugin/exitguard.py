"""The exit status under ``-n 0``, where the planner shares the run's process (issue 37, "planner code runs in the
process that decides the exit status").

Under ``-n N`` and ``--drivedegrade-ray`` the controller never imports the planner (`items.planner_runs_elsewhere`),
so nothing of it can reach the status; a worker or actor that ends itself fails its cell. Under ``-n 0`` two
guards keep the status the run's:

- while the run is live (`arm` .. `disarm`), ``os._exit`` called by planner code raises `PlannerExitRefused`
  instead of ending the process with the planner's status and no outputs: the cell fails, naming it;
- after the run (`hold_final_status`), a handler registered after every ``atexit`` handler the planner could
  have registered (atexit runs them last in, first out) ends a failed process with its own status before a
  planner's ``atexit`` ``os._exit(0)`` runs. The status is that of the last pytest session to finish in the
  process (`record`), so an outer session (pytester's in-process runs) decides its own.

Planner code in the run's own process can still reach anything (ctypes, signals, the plugin's modules): a run
whose exit status must be trusted runs its planner in workers (``-n 1`` or more) or actors
(``--drivedegrade-ray``); see docs/explanation/trust-model.md.
"""

from __future__ import annotations

import atexit
import os
import sys
from collections.abc import Callable
from typing import NoReturn, cast


def _state() -> list[object]:
    from . import EXIT_STATE  # the entry module's: one per process, whichever copy of this module runs

    return EXIT_STATE


def _real_exit() -> Callable[[int], NoReturn]:
    return cast("Callable[[int], NoReturn]", _state()[0])


class PlannerExitRefused(RuntimeError):
    """Planner code called ``os._exit`` while the run was live (under ``-n 0``)."""


def _refuse(status: int) -> NoReturn:
    raise PlannerExitRefused(f"planner code called os._exit({status}) during the run: refused, since in the run's "
                             f"own process (-n 0) it would end the run with status {status} and no outputs; raise "
                             "an exception instead (or run with -n 1 or more, where a planner's process is its own)")


def arm() -> None:
    """``os._exit`` (and ``posix._exit``, the same function) refused until `disarm`."""
    import posix

    os._exit = _refuse
    posix._exit = _refuse


def disarm() -> None:
    import posix

    os._exit = posix._exit = _real_exit()  # type: ignore[assignment]  # the function saved at import


def record(status: int) -> None:
    """The exit status of the pytest session that just finished in this process (every session records it)."""
    _state()[1] = int(status)


def _final_status() -> None:
    status = _state()[1]
    if isinstance(status, int) and status != 0:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        _real_exit()(status)


def hold_final_status() -> None:
    """Register (again, so that it is the last registered and runs first) the handler that ends a failed process
    with its recorded status before any planner ``atexit`` handler can end it with another."""
    atexit.unregister(_final_status)
    atexit.register(_final_status)
