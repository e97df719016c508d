"""Issue 37 (low): a path that is not valid UTF-8 (bytes a file system allows) ended a run in an INTERNALERROR
when the certificate, UTF-8 JSON, recorded it; now it is a usage error naming the option, before anything runs."""

from __future__ import annotations

from pathlib import Path

import pytest


def _shown(text: str) -> str:
    return repr(text.encode("utf-8", "surrogateescape"))


def check_utf8_paths(here: Path, given: dict[str, object]) -> None:
    """The working directory `here` and every path option's value in `given` (flag -> value): valid UTF-8, or a
    usage error naming it."""
    try:
        str(here).encode("utf-8")
    except UnicodeEncodeError:
        raise pytest.UsageError(f"--drivedegrade: the working directory {_shown(str(here))} is not valid UTF-8, and "
                                "the certificate records paths relative to it: run from a folder with a UTF-8 "
                                "path") from None
    for flag, text in given.items():
        if isinstance(text, str) and text:
            try:
                text.encode("utf-8")
            except UnicodeEncodeError:
                raise pytest.UsageError(f"{flag}: the path {_shown(text)} is not valid UTF-8, and the certificate "
                                        "(UTF-8 JSON) records it: rename it, or give a symlink with a UTF-8 name") \
                    from None
