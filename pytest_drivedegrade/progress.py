"""One progress line for long work (building the world, merging shards, reproducing a certificate).

On a terminal the line is rewritten in place (at most every `Progress.interval_s`); where output is a log (CI, a
pipe, a file) it is a few milestone lines and a closing one, never a line per step. Where the lines go is a
`Sink`: a stream (stderr by default), pytest's terminal reporter, or nowhere.

    with Progress("drivedegrade world", total=100, unit="scenes", sink=Sink.for_pytest(config)) as bar:
        for scene in scenes:
            ...
            bar.advance(note=scene.name)
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from types import TracebackType
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:  # pragma: no cover
    import pytest


class Sink:
    """Where progress lines go: a text stream, rewritten in place with ``\\r`` when `tty` (a terminal)."""

    def __init__(self, stream: TextIO | None = None, *, tty: bool | None = None) -> None:
        self._stream = stream
        self.tty = bool(tty) if tty is not None else _isatty(self.stream)
        self._shown = 0  # length of the line being rewritten (to erase a longer one)

    @property
    def stream(self) -> TextIO:
        return self._stream if self._stream is not None else sys.stderr  # the stderr of now (pytest swaps it)

    def line(self, text: str) -> None:
        """Write a finished line."""
        self.stream.write(text + "\n")
        self.stream.flush()

    def rewrite(self, text: str) -> None:
        """Replace the line being rewritten with `text` (terminals only)."""
        self.stream.write("\r" + text + " " * max(self._shown - len(text), 0))
        self.stream.flush()
        self._shown = len(text)

    def rewrite_start(self) -> None:
        """Back to the start of the (blank) line being rewritten, for other output to take it."""
        self.stream.write("\r")
        self.stream.flush()
        self._shown = 0

    def end_rewrite(self) -> None:
        """Finish the line being rewritten."""
        self.stream.write("\n")
        self.stream.flush()
        self._shown = 0

    @staticmethod
    def for_pytest(config: pytest.Config) -> Sink:
        """pytest's terminal reporter where there is one (in place on a terminal), else stderr."""
        reporter = config.pluginmanager.get_plugin("terminalreporter")
        return Sink() if reporter is None else _ReporterSink(reporter)

    @staticmethod
    def log_for_pytest(config: pytest.Config) -> Sink:
        """pytest's terminal reporter as a log (milestone lines, never rewritten in place): for progress beside
        pytest's own (the cells' dots, which a line rewritten in place would erase)."""
        reporter = config.pluginmanager.get_plugin("terminalreporter")
        sink = Sink() if reporter is None else _ReporterSink(reporter)
        sink.tty = False
        return sink

    @staticmethod
    def silent() -> Sink:
        """Nowhere (for library calls and tests that want no output)."""
        return _SilentSink()


class _ReporterSink(Sink):
    """Lines through pytest's `TerminalReporter` (its public `write_line`, `rewrite` and `write`)."""

    def __init__(self, reporter: object) -> None:
        super().__init__(tty=bool(getattr(reporter, "isatty", False)))
        self._reporter = reporter

    def line(self, text: str) -> None:
        self._reporter.write_line(text)  # type: ignore[attr-defined]

    def rewrite(self, text: str) -> None:
        self._reporter.rewrite(text, erase=True)  # type: ignore[attr-defined]
        self._reporter.write("", flush=True)  # type: ignore[attr-defined]

    def rewrite_start(self) -> None:
        self._reporter.write("\r", flush=True)  # type: ignore[attr-defined]

    def end_rewrite(self) -> None:
        self._reporter.write("\n", flush=True)  # type: ignore[attr-defined]


class _SilentSink(Sink):
    def __init__(self) -> None:
        super().__init__(tty=False)

    def line(self, text: str) -> None:
        pass

    def rewrite(self, text: str) -> None:
        pass

    def rewrite_start(self) -> None:
        pass

    def end_rewrite(self) -> None:
        pass


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # a closed or file-less stream
        return False


class Progress:
    """`done` of `total` steps of one piece of work, shown on `sink` as one line.

    Terminal: the line is rewritten in place, at most every `interval_s` and always at the last step. Log: a line
    at each of the `milestones - 1` quarter-like marks crossed (25 %, 50 %, 75 % for 4), then the closing line.
    """

    def __init__(self, label: str, total: int, *, unit: str = "", sink: Sink | None = None, milestones: int = 4,
                 interval_s: float = 0.1, clock: Callable[[], float] = time.monotonic, eta: bool = False) -> None:
        self.label, self.total, self.unit, self.eta = label, max(int(total), 0), unit, eta
        self.sink = sink if sink is not None else Sink()
        self.milestones, self.interval_s, self._clock = max(int(milestones), 1), interval_s, clock
        self.done = 0
        self._start = clock()
        self._drawn_at: float | None = None
        self._mark = 0  # milestones already written (log mode)
        self._closed = False

    @property
    def elapsed(self) -> float:
        return self._clock() - self._start

    def text(self, note: str = "") -> str:
        """The line as it reads now."""
        unit = f" {self.unit}" if self.unit else ""
        pct = f" ({100 * self.done // self.total} %)" if self.total else ""
        tail = f", {note}" if note else ""
        return f"{self.label}: {self.done}/{self.total}{unit}{pct} {self.elapsed:.1f} s{self._left()}{tail}"

    def _left(self) -> str:
        """With `eta`: ", about N s left" at the pace so far (nothing before the first step or after the last)."""
        if not self.eta or not self.done or not self.total or self.done >= self.total:
            return ""
        left = self.elapsed / self.done * (self.total - self.done)
        return f", about {left:.0f} s left" if left < 90 else f", about {left / 60:.0f} min left"

    def advance(self, n: int = 1, note: str = "") -> None:
        """`n` more steps done; `note` says what the last one was (shown on a terminal only)."""
        self.done = min(self.done + n, self.total) if self.total else self.done + n
        now = self._clock()
        if self.sink.tty:
            last = self.total and self.done >= self.total
            if last or self._drawn_at is None or now - self._drawn_at >= self.interval_s:
                self.sink.rewrite(self.text(note))
                self._drawn_at = now
            return
        if not self.total:
            return
        mark = self.done * self.milestones // self.total
        if self._mark < mark < self.milestones:
            self.sink.line(self.text(note if self.eta else ""))
        self._mark = max(self._mark, mark)

    def tick(self, note: str = "") -> None:
        """Nothing more done, time passed: on a terminal the line is redrawn (its seconds), at most every
        `interval_s`; a log gets nothing (for waits with no step to count, e.g. a subprocess working)."""
        now = self._clock()
        if self.sink.tty and not self._closed and (self._drawn_at is None or now - self._drawn_at >= self.interval_s):
            self.sink.rewrite(self.text(note))
            self._drawn_at = now

    def interject(self, write: Callable[[str], None], text: str) -> None:
        """A finished line of other output (`write(text)`, e.g. a result to stdout) while the progress line is
        shown: on a terminal the line is cleared first and drawn again below it, so neither is garbled."""
        if self.sink.tty and self._drawn_at is not None and not self._closed:
            self.sink.rewrite("")
            self.sink.rewrite_start()
            write(text)
            self.sink.rewrite(self.text())
        else:
            write(text)

    def finish(self, summary: str = "") -> None:
        """Close the line: "<label>: <done>[/<total> when short of it] <unit> in <s> s[; summary]" (once; later
        calls do nothing)."""
        if self._closed:
            return
        self._closed = True
        unit = f" {self.unit}" if self.unit else ""
        count = f"{self.done}/{self.total}" if self.done < self.total else f"{self.done}"
        text = f"{self.label}: {count}{unit} in {self.elapsed:.1f} s" + (f"; {summary}" if summary else "")
        if self.sink.tty:
            self.sink.rewrite(text)
            self.sink.end_rewrite()
        else:
            self.sink.line(text)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.finish("" if kind is None else f"stopped ({kind.__name__})")
