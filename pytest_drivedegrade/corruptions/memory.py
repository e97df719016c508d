"""Approximate-memory family: bit errors in the stored image bytes (e.g. DRAM at a reduced refresh rate)."""

from __future__ import annotations

import numpy as np

from .registry import register


def flip_positions(rng: np.random.Generator, n_bits: int, rate: float) -> np.ndarray:
    """Positions of the flipped bits among `n_bits`, each bit flipping independently with `rate`.

    Exact Bernoulli process: the gaps between flips are geometric, so only the flips are drawn (about
    n_bits * rate numbers), never one random number per bit.
    """
    expected = n_bits * rate
    chunk = int(expected + 6 * np.sqrt(expected) + 16)
    positions: list[np.ndarray] = []
    last = -1
    while True:
        gaps = rng.geometric(rate, chunk)
        pos = last + np.cumsum(gaps)
        positions.append(pos[pos < n_bits])
        if pos[-1] >= n_bits:
            break
        last = int(pos[-1])
    return np.concatenate(positions)


@register("bit_error", group="approximate memory", axis="other", parameter="bit error rate",
          unit="per bit", values=(1e-7, 1e-6, 1e-5, 1e-4, 1e-3), random=True)
def bit_error(image: np.ndarray, rate: float, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Flip each bit of the image's stored bytes (row-major, RGB interleaved) independently at `rate`."""
    out = image.copy()  # C-ordered, whatever the input's layout
    flat = out.reshape(-1)
    pos = flip_positions(rng, flat.size * 8, float(rate))
    np.bitwise_xor.at(flat, pos >> 3, np.left_shift(1, pos & 7).astype(np.uint8))
    return out
