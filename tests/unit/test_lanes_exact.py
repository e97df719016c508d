"""`LaneView._distances`, written per coordinate for speed (issue 23), gives the bits of the vector formula it
replaced (a dot product and `np.linalg.norm` over a length-2 axis): DDC and LK, and so every EPDMS, stay as
they were, whatever the segments (degenerate ones included), points and scale."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.metrics.pdms.lanes import LaneView


def vector_formula(start: np.ndarray, end: np.ndarray, pts: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """The distances as the suite computed them before (spec 4.1.0 to 4.2.0)."""
    a, ab = start[segments], end[segments] - start[segments]
    t = np.clip(((pts[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(a[None] + t[..., None] * ab[None] - pts[:, None], axis=-1)


def view(start: np.ndarray, end: np.ndarray) -> LaneView:
    d = end - start
    return LaneView(start, end, np.arctan2(d[:, 1], d[:, 0]), np.zeros(len(start), int), (None,), ())


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), segments=st.integers(1, 300), points=st.integers(1, 40),
       log_scale=st.floats(-3.0, 4.0), degenerate=st.floats(0.0, 0.5))
def test_distances_equal_the_vector_formula_bit_for_bit(seed, segments, points, log_scale, degenerate):
    rng = np.random.default_rng(seed)
    scale = 10.0**log_scale
    start = rng.normal(0.0, scale, (segments, 2))
    end = start + rng.normal(0.0, scale, (segments, 2)) * (rng.random((segments, 1)) >= degenerate)
    pts = rng.normal(0.0, scale, (points, 2))
    chosen = np.flatnonzero(rng.random(segments) < 0.7)
    if not len(chosen):
        chosen = np.arange(segments)
    got = view(start, end)._distances(pts, chosen)
    assert got.shape == (points, len(chosen))
    assert got.tobytes() == vector_formula(start, end, pts, chosen).tobytes()


def test_known_distances_to_a_segment():
    lanes = view(np.array([[0.0, 0.0], [5.0, 5.0]]), np.array([[10.0, 0.0], [5.0, 5.0]]))  # the second: a point
    pts = np.array([[5.0, 3.0], [-3.0, 4.0], [13.0, -4.0], [5.0, 5.0]])
    got = lanes._distances(pts, np.array([0, 1]))
    np.testing.assert_array_equal(got[:, 0], [3.0, 5.0, 5.0, 5.0])  # foot inside, before the start, past the end
    np.testing.assert_array_equal(got[:, 1], [2.0, np.hypot(8.0, 1.0), np.hypot(8.0, 9.0), 0.0])
