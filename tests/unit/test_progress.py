"""The progress line: rewritten in place on a terminal (throttled), milestone lines in a log, one closing line;
through pytest's terminal reporter in a pytest run."""

from __future__ import annotations

import io

import pytest

from pytest_drivedegrade.progress import Progress, Sink


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_log_gets_milestones_and_a_closing_line_not_a_line_per_step():
    out, clock = io.StringIO(), Clock()
    with Progress("world", 100, unit="scenes", sink=Sink(out, tty=False), clock=clock) as bar:
        for _ in range(100):
            clock.now += 0.5
            bar.advance(note="scene")
    lines = out.getvalue().splitlines()
    assert lines == ["world: 25/100 scenes (25 %) 12.5 s", "world: 50/100 scenes (50 %) 25.0 s",
                     "world: 75/100 scenes (75 %) 37.5 s", "world: 100 scenes in 50.0 s"]
    assert "\r" not in out.getvalue()


def test_a_terminal_line_is_rewritten_in_place_at_most_every_interval():
    out, clock = io.StringIO(), Clock()
    bar = Progress("merge", 10, sink=Sink(out, tty=True), interval_s=1.0, clock=clock)
    for _ in range(10):
        clock.now += 0.3
        bar.advance(note="a long note" if bar.done < 5 else "x")
    bar.finish("3 files")
    text = out.getvalue()
    draws = text.split("\r")[1:]
    # the first step, then every 1.0 s (steps 5 and 9: 0.3 s apart), the last step, and the closing line
    assert [d.split(":")[1].split()[0] for d in draws[:-1]] == ["1/10", "5/10", "9/10", "10/10"]
    assert draws[-1].rstrip(" \n") == "merge: 10 in 3.0 s; 3 files"
    assert text.endswith("\n") and text.count("\n") == 1  # one line on screen
    assert draws[1].startswith("merge: 5/10 (50 %) 1.5 s, a long note")
    for before, after in zip(draws, draws[1:]):  # a shorter line is padded over what the longer one left
        assert len(after.rstrip("\n")) >= len(before.rstrip(" "))


def test_finish_is_once_and_an_error_says_it_stopped():
    out = io.StringIO()
    with pytest.raises(KeyError), Progress("run", 4, sink=Sink(out, tty=False), clock=Clock()) as bar:
        bar.advance()
        raise KeyError("x")
    bar.finish()
    assert out.getvalue().splitlines() == ["run: 1/4 (25 %) 0.0 s", "run: 1/4 in 0.0 s; stopped (KeyError)"]


def test_unknown_total_and_silent_sink_write_nothing_per_step():
    out = io.StringIO()
    bar = Progress("frames", 0, sink=Sink(out, tty=False), clock=Clock())
    for _ in range(7):
        bar.advance()
    bar.finish()
    assert out.getvalue() == "frames: 7 in 0.0 s\n"
    quiet = Progress("x", 3, sink=Sink.silent())
    quiet.advance(3)
    quiet.finish()  # nothing to assert on: it must simply not fail nor write to stderr


def test_the_pytest_sink_uses_the_terminal_reporter(pytester):
    pytester.makeconftest("""
        import pytest
        from pytest_drivedegrade.progress import Progress, Sink

        def pytest_sessionstart(session):
            sink = Sink.for_pytest(session.config)
            assert type(sink).__name__ == "_ReporterSink" and sink.tty is False  # pytester's output is no tty
            with Progress("building", 8, unit="parts", sink=sink) as bar:
                for _ in range(8):
                    bar.advance()
    """)
    pytester.makepyfile("def test_ok(): pass")
    result = pytester.runpytest_subprocess("-p", "no:randomly")
    result.assert_outcomes(passed=1)
    result.stdout.re_match_lines([r"building: 2/8 parts \(25 %\)", r"building: 8 parts in \d+\.\d s"])
    assert len([ln for ln in result.stdout.lines if ln.startswith("building")]) == 4


def test_tick_redraws_the_clock_on_a_terminal_only_and_throttled():
    out, clock = io.StringIO(), Clock()
    bar = Progress("reproduce", 3, unit="cells", sink=Sink(out, tty=True), interval_s=1.0, clock=clock)
    for _ in range(5):  # a subprocess working: no step done, 0.4 s apart
        bar.tick()
        clock.now += 0.4
    draws = out.getvalue().split("\r")[1:]
    assert [d.strip() for d in draws] == ["reproduce: 0/3 cells (0 %) 0.0 s", "reproduce: 0/3 cells (0 %) 1.2 s"]
    log = io.StringIO()
    quiet = Progress("reproduce", 3, sink=Sink(log, tty=False), clock=clock)
    quiet.tick()
    assert log.getvalue() == ""


def test_a_line_said_while_the_bar_shows_is_not_garbled():
    out, clock = io.StringIO(), Clock()
    bar = Progress("reproduce", 2, unit="cells", sink=Sink(out, tty=True), clock=clock)
    bar.advance(note="clean")
    bar.interject(lambda s: out.write(s + "\n"), "clean: identical")
    bar.finish()
    # the bar cleared, the line at the start of its own line, the bar drawn again below it, then closed
    screen = out.getvalue()
    assert "\rclean: identical\n" in screen
    after = screen.split("clean: identical\n")[1]
    assert after.startswith("\rreproduce: 1/2 cells (50 %)") and screen.endswith("\n")
    log = io.StringIO()
    plain = Progress("reproduce", 2, sink=Sink(log, tty=False), milestones=1, clock=clock)
    plain.advance()
    plain.interject(lambda s: log.write(s + "\n"), "clean: identical")
    plain.finish()
    assert log.getvalue().splitlines() == ["clean: identical", "reproduce: 1/2 in 0.0 s"]
