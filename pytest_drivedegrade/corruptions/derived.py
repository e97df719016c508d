"""What is derived from a clean image alone, shared by every cell of a process that reads the image: raindrop's
defocused quarter-resolution view of the frame (the same at every severity) and the image's count of 1 bits (the
energy proxy of every cell that delivers it unchanged: the ego cells, clean, null, frame_dropout's held frames,
blackout's lit cameras).

Only images registered as stable are remembered: the run's decode cache registers each array it keeps, which is
read-only, never handed to a planner (it gets a copy) and never changed, so a value derived from it once is the
value derived from it at any later time. Any other image derives its values each time. A value is a function of
the image's pixels alone, so results are bit-identical with or without the memory; only time changes.

Memory: at most `BUDGET_BYTES` (96 MiB) of derived arrays per process (beyond it they are derived each time);
an entry goes with its image (a weak reference), so a finished run's decode cache takes its derived values with
it.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import TypeVar, cast

import numpy as np

T = TypeVar("T")

#: The derived arrays one process keeps at most: raindrop's views of a 204-frame, six-camera run at 800 x 450
#: take 82 MiB (the decode cache's images themselves, 1.08 MB each, up to 512 MiB).
BUDGET_BYTES = 96 << 20

#: Reentrant: a garbage collection inside a locked block may free a registered image, whose `forget` then locks.
_lock = threading.RLock()
#: id(image) -> (a weak reference to it, its derived values by name)
_stable: dict[int, tuple[weakref.ref[np.ndarray], dict[str, object]]] = {}
_held = [0]  # bytes of derived arrays kept


def _size(value: object) -> int:
    return int(value.nbytes) if isinstance(value, np.ndarray) else 0


def register(image: np.ndarray) -> None:
    """Remember what is derived from `image` from now on: the caller guarantees that its pixels never change
    while it lives (a read-only array it keeps and never hands out)."""
    key = id(image)

    def forget(_: object, key: int = key) -> None:
        with _lock:
            entry = _stable.pop(key, None)
            if entry is not None:
                _held[0] -= sum(_size(v) for v in entry[1].values())

    with _lock:
        if key not in _stable:
            _stable[key] = (weakref.ref(image, forget), {})


def derived(image: np.ndarray, name: str, make: Callable[[np.ndarray], T]) -> T:
    """`make(image)`, remembered under `name` when `image` is registered (and arrays fit the budget). An array
    returned is read-only: a caller never changes what another reads."""
    entry = _stable.get(id(image))
    if entry is None or entry[0]() is not image:
        return make(image)
    found = entry[1].get(name)
    if found is not None:
        return cast(T, found)
    value = make(image)
    size = _size(value)
    with _lock:
        if name not in entry[1] and _held[0] + size <= BUDGET_BYTES:
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            entry[1][name] = value
            _held[0] += size
    return value


def held_bytes() -> int:
    """Bytes of derived arrays kept now (for tests and the memory bound)."""
    return _held[0]
