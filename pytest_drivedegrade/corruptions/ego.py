"""The ego ladder (SPEC section 10): the ego status and the context's CAN bus perturbed or removed, the images clean.

- ``ego_noise`` S1..S5 adds seeded Gaussian noise: velocity sigma 0.1, 0.2, 0.4, 0.8, 1.6 m/s (each component),
  acceleration sigma the same numbers in m/s^2, yaw-rate sigma 0.01, 0.02, 0.04, 0.08, 0.16 rad/s, past-position
  sigma 0.05, 0.1, 0.2, 0.4, 0.8 m (each point, each coordinate). One generator per frame,
  ``rng_for(seed, frame, "EGO", "ego_noise", severity)``, draws velocity (2), acceleration (2), yaw rate (1)
  and past positions (PAST_STEPS x 2) in that order; the CAN bus gets the same draws on its motion terms
  (acceleration x / y, yaw rate about z, velocity x / y), so both views of the ego agree.
- ``ego_blind`` zeroes velocity, acceleration, yaw rate and the past trajectory, and the CAN bus's motion terms
  (acceleration, rotation rate, velocity); the pose, the heading and the command are kept.

Pure functions over the frame's data; the null control never comes here.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from ..constants import EGO_BLIND, EGO_NOISE
from .seeding import rng_for

#: The camera name in the seed of the ego ladder's generator.
EGO_CAMERA = "EGO"
#: ego_noise sigmas per severity 1..5: velocity (m/s), acceleration (m/s^2), yaw rate (rad/s), past xy (m).
VELOCITY_SIGMA: tuple[float, ...] = (0.1, 0.2, 0.4, 0.8, 1.6)
ACCELERATION_SIGMA: tuple[float, ...] = (0.1, 0.2, 0.4, 0.8, 1.6)
YAW_RATE_SIGMA: tuple[float, ...] = (0.01, 0.02, 0.04, 0.08, 0.16)
PAST_SIGMA: tuple[float, ...] = (0.05, 0.1, 0.2, 0.4, 0.8)
#: BEVFormer's CAN-bus layout (data.context.can_bus): accel 7..9, rotation rate 10..12, velocity 13..15.
CAN_ACCEL, CAN_RATE, CAN_VEL = slice(7, 10), slice(10, 13), slice(13, 16)


def sigmas(severity: int) -> dict[str, float]:
    """The ego_noise sigmas of one severity (1..5)."""
    k = int(severity) - 1
    if not 0 <= k < len(VELOCITY_SIGMA):
        raise ValueError(f"ego_noise severity must be 1..5, got {severity}")
    return {"velocity": VELOCITY_SIGMA[k], "acceleration": ACCELERATION_SIGMA[k], "yaw_rate": YAW_RATE_SIGMA[k],
            "past_xy": PAST_SIGMA[k]}


def _draws(seed: int, frame: str, severity: int, past_shape: tuple[int, ...]) -> dict[str, Any]:
    sd = sigmas(severity)
    rng = rng_for(seed, frame, EGO_CAMERA, EGO_NOISE, severity)
    return {"velocity": rng.normal(0.0, sd["velocity"], 2), "acceleration": rng.normal(0.0, sd["acceleration"], 2),
            "yaw_rate": float(rng.normal(0.0, sd["yaw_rate"])), "past_xy": rng.normal(0.0, sd["past_xy"], past_shape)}


def perturb(ego: Any, can_bus: np.ndarray | None, family: str, severity: int, *, seed: int,
            frame: str) -> tuple[Any, np.ndarray | None]:
    """(ego status, CAN bus) under an ego cell: `ego` an `EgoStatus`, `can_bus` the 18-vector or None. Other
    families return both unchanged. The returned arrays are new and read-only."""
    if family not in (EGO_NOISE, EGO_BLIND):
        return ego, can_bus
    past = np.asarray(ego.past_xy, dtype=np.float64)
    bus = None if can_bus is None else np.array(can_bus, dtype=np.float64, copy=True)
    if family == EGO_BLIND:
        out = replace(ego, velocity=(0.0, 0.0), acceleration=(0.0, 0.0), yaw_rate=0.0, past_xy=np.zeros_like(past))
        if bus is not None:
            bus[CAN_ACCEL] = bus[CAN_RATE] = bus[CAN_VEL] = 0.0
    else:
        d = _draws(seed, frame, severity, past.shape)
        vel = np.asarray(ego.velocity, dtype=np.float64) + d["velocity"]
        acc = np.asarray(ego.acceleration, dtype=np.float64) + d["acceleration"]
        out = replace(ego, velocity=(float(vel[0]), float(vel[1])), acceleration=(float(acc[0]), float(acc[1])),
                      yaw_rate=float(ego.yaw_rate) + d["yaw_rate"], past_xy=past + d["past_xy"])
        if bus is not None:
            bus[7:9] += d["acceleration"]
            bus[12] += d["yaw_rate"]
            bus[13:15] += d["velocity"]
    out.past_xy.setflags(write=False)
    if bus is not None:
        bus.setflags(write=False)
    return out, bus
