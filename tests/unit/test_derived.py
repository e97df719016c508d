"""`corruptions.derived`: values derived from a stable (registered) clean image are made once and are the values made
each time; an unregistered image derives them afresh; memory stays within the budget and leaves with the image."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from pytest_drivedegrade.corruptions import contamination
from pytest_drivedegrade.corruptions import derived as D  # noqa: N812 - D for the module, short in the asserts
from pytest_drivedegrade.corruptions.api import corrupt
from pytest_drivedegrade.metrics.trajectory import bit1_density


def image(seed: int = 0) -> np.ndarray:
    out = np.random.default_rng(seed).integers(0, 256, (90, 160, 3), dtype=np.uint8)
    out.setflags(write=False)
    return out


def counting(calls: list[int], value: object):
    def make(_: np.ndarray) -> object:
        calls.append(1)
        return value
    return make


def test_a_registered_image_derives_each_value_once_and_an_unregistered_one_each_time():
    stable, loose = image(1), image(1)
    D.register(stable)
    calls: list[int] = []
    kept = D.derived(stable, "v", counting(calls, np.arange(4.0)))
    assert D.derived(stable, "v", counting(calls, np.zeros(4))) is kept and len(calls) == 1
    assert not kept.flags.writeable  # no caller can change what the next one reads
    assert D.derived(stable, "other", counting(calls, 7)) == 7 and len(calls) == 2
    D.derived(loose, "v", counting(calls, 0.0))
    D.derived(loose, "v", counting(calls, 0.0))
    assert len(calls) == 4


def pending_garbage() -> None:
    """A registered image with a derived array, left in a reference cycle: unreachable, but held (and counted by
    `held_bytes`) until the next garbage collection, which may come at any allocation."""
    kept = image(5)
    D.register(kept)
    D.derived(kept, "big", lambda im: np.zeros(500))
    cycle: list[object] = [kept]
    cycle.append(cycle)


def test_a_value_leaves_with_its_image_and_the_budget_bounds_what_is_kept(monkeypatch):
    """`held_bytes` counts every live registered image's values in the process, so the baseline is read after a
    full collection: an image of an earlier test waiting in a reference cycle was freed by a collection the test's
    own allocations set off, and `held_bytes` fell below the baseline (67200 where 134400 was expected, on a busy
    machine). `pending_garbage` puts one there on purpose."""
    pending_garbage()
    gc.collect()  # what earlier tests left unreachable goes now, not during the test
    before = D.held_bytes()
    stable = image(2)
    D.register(stable)
    D.derived(stable, "big", lambda im: np.zeros(1000))
    assert D.held_bytes() == before + 8000
    del stable
    gc.collect()
    assert D.held_bytes() == before
    monkeypatch.setattr(D, "BUDGET_BYTES", before + 100)
    other = image(3)
    D.register(other)
    calls: list[int] = []
    first = D.derived(other, "big", counting(calls, np.ones(1000)))
    again = D.derived(other, "big", counting(calls, np.ones(1000)))
    assert len(calls) == 2 and np.array_equal(first, again)  # over the budget: made each time, the same value
    assert D.held_bytes() == before


def test_raindrop_and_the_energy_of_a_registered_image_are_those_of_an_unregistered_copy(monkeypatch):
    made: list[int] = []
    real = contamination._drop_source
    monkeypatch.setattr(contamination, "_drop_source", lambda im, scale: made.append(1) or real(im, scale))
    stable, loose = image(4), image(4).copy()
    D.register(stable)
    for severity in range(1, 6):
        got = corrupt(stable, "raindrop", severity, seed=3, frame="f", camera="CAM_FRONT")
        want = corrupt(loose, "raindrop", severity, seed=3, frame="f", camera="CAM_FRONT")
        assert got.tobytes() == want.tobytes()
    assert len(made) == 1 + 5  # the registered image's view once, the copy's at every severity
    assert bit1_density({"a": stable, "b": stable}) == bit1_density({"a": loose, "b": loose})
    assert bit1_density({"a": stable}) == pytest.approx(np.unpackbits(loose).mean())
