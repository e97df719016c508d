"""User-facing errors: each says what was wrong, where, and what to do. Never a bare traceback."""

from __future__ import annotations


class DriveDegradeError(Exception):
    """A user mistake or bad input the tool reports as one clear message (CLI exit 2, pytest usage error)."""


class InvalidInput(DriveDegradeError, ValueError):
    """A bad argument to the public API: a wrong array, family, severity or camera name."""


class DataError(DriveDegradeError):
    """A data set problem: a missing table, a missing or truncated image, a dangling token."""


class PlannerOutputError(DriveDegradeError):
    """A planner broke the output contract: not a finite (6, 2) float array. Names the frame and shows the value."""
