"""Per-cell seeding: a generator keyed by (seed, frame, camera, family, severity), never global state.

The key is hashed with BLAKE2b and the digest, read as an integer, seeds numpy's PCG64. The same key gives
the same realisation in any process, worker, machine and call order.
"""

from __future__ import annotations

import hashlib

import numpy as np


def seed_key(seed: int, frame: str, camera: str, family: str, severity: int) -> str:
    return f"{seed}|{frame}|{camera}|{family}|{severity}"


def seed_int(seed: int, frame: str, camera: str, family: str, severity: int) -> int:
    """The BLAKE2b digest (64 bytes) of the key, as a big-endian integer."""
    digest = hashlib.blake2b(seed_key(seed, frame, camera, family, severity).encode("utf-8")).digest()
    return int.from_bytes(digest, "big")


def rng_for(seed: int, frame: str, camera: str, family: str, severity: int) -> np.random.Generator:
    """A fresh generator for one (seed, frame, camera, family, severity) realisation."""
    return np.random.Generator(np.random.PCG64(seed_int(seed, frame, camera, family, severity)))
