"""The pytest11 entry point. Thin and light: it imports nothing heavy (no OpenCV, torch or pandas) so that
every pytest run of a user who has the plugin installed stays fast."""

from __future__ import annotations
