"""Issue 37, "a planner or library that re-arms SIGALRM / ITIMER_REAL switches the open-loop timeout off": the
limit checks its own timer after the call and fails a call that replaced the handler, disarmed the timer or
pushed it back; a call that hangs with the timer switched off is ended by the watchdog (a failed run, never a
pass). On the old code every one of these calls passed (or hung)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from pytest_drivedegrade.stream import PlannerTimeout, time_limit


def test_an_honest_call_passes_and_a_slow_one_times_out() -> None:
    with time_limit(1.0):
        time.sleep(0.01)
    with pytest.raises(PlannerTimeout, match="took longer than 0.1 s"), time_limit(0.1):
        time.sleep(2.0)
    assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)


@pytest.mark.parametrize(("tamper", "what"), [
    (lambda: signal.signal(signal.SIGALRM, signal.SIG_IGN), "replaced the SIGALRM handler"),
    (lambda: signal.signal(signal.SIGALRM, lambda *a: None), "replaced the SIGALRM handler"),
    (lambda: signal.setitimer(signal.ITIMER_REAL, 0), "disarmed the ITIMER_REAL timer"),
    (lambda: signal.setitimer(signal.ITIMER_REAL, 100.0), "pushed the ITIMER_REAL timer back"),
    (lambda: signal.alarm(100), "pushed the ITIMER_REAL timer back"),
], ids=["sig-ign", "own-handler", "disarmed", "itimer-later", "alarm-later"])
def test_a_call_that_switches_the_timer_off_fails(tamper, what) -> None:
    previous = signal.getsignal(signal.SIGALRM)
    with pytest.raises(PlannerTimeout, match=what), time_limit(1.0):
        tamper()
    assert signal.getsignal(signal.SIGALRM) is previous  # restored whatever the call did
    assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)


def test_a_call_that_disarms_the_timer_and_runs_past_it_fails() -> None:
    with pytest.raises(PlannerTimeout, match="ran past the limit with the ITIMER_REAL timer disarmed"), \
            time_limit(0.1):
        signal.setitimer(signal.ITIMER_REAL, 0)
        time.sleep(0.4)


def test_a_call_that_hangs_with_the_timer_off_is_ended_by_the_watchdog() -> None:
    code = ("import signal, time\n"
            "import pytest_drivedegrade.stream as s, pytest_drivedegrade.timelimit as t\n"
            "t.WATCHDOG_GRACE = 0.5\n"
            "with s.time_limit(0.2):\n"
            "    signal.signal(signal.SIGALRM, signal.SIG_IGN)\n"
            "    time.sleep(60)\n"
            "print('passed')\n")
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50, check=False)
    assert done.returncode == -signal.SIGKILL, (done.returncode, done.stderr)
    assert "replaced the SIGALRM handler and has now run" in done.stderr and "passed" not in done.stdout
    assert time.monotonic() - start < 30
