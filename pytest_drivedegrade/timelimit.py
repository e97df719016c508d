"""The open-loop timeout (``--drivedegrade-timeout``): ``SIGALRM`` from ``ITIMER_REAL`` around each call.

The planner runs in the same process and could switch the timer off (issue 37: a planner, or a library it
calls, that sets its own ``SIGALRM`` handler or re-arms ``ITIMER_REAL``). So the limit checks its own machinery:

- after the call, a handler that is no longer ours, or a timer disarmed or pushed back by the call, fails the
  frame (`PlannerTimeout`, naming what was changed), as a call past the limit does;
- a watchdog thread, some seconds after the limit, ends the process when the call is still running with the
  timer switched off (a hang the signal can no longer interrupt). Ending it is a failed run (the worker's cells
  fail; under ``-n 0`` the run's status is the kill's), never a pass; the message on stderr says why.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from types import FrameType

#: Seconds after the limit before the watchdog decides that the timer was switched off by the call.
WATCHDOG_GRACE = 10.0
#: Slack for timer reads (the timer's resolution and the time between the call's end and the read).
_SLACK = 0.05


class PlannerTimeout(Exception):
    """predict() ran past --drivedegrade-timeout on one frame (or switched the timer that enforces it off)."""


def _tampered(expire: object, fired: bool, seconds: float, elapsed: float) -> str | None:
    """What the call changed of the timer, or None when it is as the limit set it."""
    if signal.getsignal(signal.SIGALRM) is not expire:
        return "replaced the SIGALRM handler"
    if fired:
        return None
    remaining = signal.getitimer(signal.ITIMER_REAL)[0]
    if remaining == 0 and elapsed < seconds - _SLACK:
        return "disarmed the ITIMER_REAL timer"
    if remaining == 0 and elapsed > seconds + _SLACK:
        return "ran past the limit with the ITIMER_REAL timer disarmed"
    if remaining > max(0.0, seconds - elapsed) + _SLACK:
        return "pushed the ITIMER_REAL timer back"
    return None


class _Call:
    """One limited call, as the watchdog sees it."""

    def __init__(self, expire: object, state: dict[str, bool], seconds: float, start: float) -> None:
        self.expire, self.state, self.seconds, self.start = expire, state, seconds, start
        self.deadline = start + seconds + WATCHDOG_GRACE


class _Watchdog:
    """One daemon thread per process (started at the first limited call; a thread per call cost 170 us a call),
    woken when a call starts or ends: it looks at a call still running `WATCHDOG_GRACE` s after its limit."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.call: _Call | None = None
        self.thread: threading.Thread | None = None

    def watch(self, call: _Call | None) -> None:
        with self.cond:
            self.call = call
            if self.thread is None or not self.thread.is_alive():
                self.thread = threading.Thread(target=self._run, daemon=True, name="drivedegrade-timeout-watchdog")
                self.thread.start()
            self.cond.notify()

    def _run(self) -> None:
        with self.cond:
            while True:
                call = self.call
                if call is None:
                    self.cond.wait()
                    continue
                left = call.deadline - time.monotonic()
                if left > 0:
                    self.cond.wait(left)
                    continue
                if self.call is call:
                    self.call = None  # looked at once
                    _last_resort(call)


def _last_resort(call: _Call) -> None:
    what = _tampered(call.expire, call.state["fired"], call.seconds, time.monotonic() - call.start)
    if what is None:  # the signal is ours and armed: a call stuck in C code that will see it when it returns
        return
    sys.stderr.write(f"\ndrivedegrade: predict() {what} and has now run {call.seconds + WATCHDOG_GRACE:g} s past "
                     f"--drivedegrade-timeout ({call.seconds:g} s): the timeout cannot interrupt it, so this process "
                     "is ended (a failed run)\n")
    sys.stderr.flush()
    os.kill(os.getpid(), signal.SIGKILL)


_WATCHDOG = _Watchdog()


@contextlib.contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Raise PlannerTimeout inside the block after `seconds`, or after it when the block changed the timer (POSIX
    main thread; a no-op elsewhere or at 0)."""
    usable = seconds > 0 and hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()
    if not usable:
        yield
        return
    state = {"fired": False}

    def expire(signum: int, frame: FrameType | None) -> None:
        state["fired"] = True
        raise PlannerTimeout(f"predict() took longer than {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expire)
    start = time.monotonic()
    signal.setitimer(signal.ITIMER_REAL, seconds)
    _WATCHDOG.watch(_Call(expire, state, seconds, start))
    try:
        yield
        what = _tampered(expire, state["fired"], seconds, time.monotonic() - start)
        if what is not None:
            raise PlannerTimeout(f"predict() {what}, which enforces --drivedegrade-timeout ({seconds:g} s): a "
                                 "planner may not change SIGALRM or ITIMER_REAL (a library that does must be kept "
                                 "out of predict)")
    finally:
        _WATCHDOG.watch(None)
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
