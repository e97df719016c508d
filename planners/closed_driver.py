"""Reference closed-loop driver: a small CNN reads the front camera and tells the few numbers the world expert's
rule needs (`closedloop.percept.Percept`); that rule plans from them. Reads CAM_FRONT only, with ego status and
command.

The front camera is reduced to 80 x 45 (``cv2.INTER_AREA``, a factor of 10 at the world's 800 x 450) and a
second view zooms on the band above its middle (``ZOOM_BOX``: the central 40 % of its width, 12 % to 52 % of its
height, 80 x 45 again), where a standing car 40 m ahead, a pedestrian at the curb or a traffic light's head is
otherwise a few pixels. From both views and the ego features (``floor.ego_features``) the network predicts:

- the lane ahead (x, y at ``percept.LANE_AHEAD``) and the bend speeds (at ``percept.BEND_AHEAD``), regressed;
- the free corridor ahead and the red or yellow stop line ahead, each as ``len(PROFILE_M)`` probabilities "farther
  than d" (``PROFILE_M``: 2 .. 50 m; none within 50 m reads as none), the lead's speed, and whether the light is
  yellow.

The plan is ``percept.plan_arcs`` (IDM to the cruise speed, bends, the obstacle, the light) placed on the predicted
lane; the cruise speed is inferred once per route from the first ego status (``percept.cruise_from_status``). Two
things carry from one call to the next: the decision at a yellow line (``percept.YellowDecision``, as the expert
decides once), and the gap, whose change gives the lead's speed where that is slower than the speed read from one
frame (``percept.tracked_lead_speed``: a standing car a frame reads as moving is not crept up to). So the driver
has ``reset()`` and is streamed scene by scene in the open loop.

Weights are committed beside this file (``closed_driver.pt``; ``closed_driver.json`` holds the recipe's
settings and what it measured). Retrain with ``python planners/train_closed_driver.py`` (docs/how-to/closed-loop.md).

    pytest --drivedegrade planners/closed_driver.py --drivedegrade-loop closed -n 2
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from pytest_drivedegrade.closedloop.percept import (
    BEND_AHEAD,
    FAR_M,
    LANE_AHEAD,
    Percept,
    RulePlanner,
    tracked_lead_speed,
)
from pytest_drivedegrade.floor import FEATURE_SIZE, ego_features
from pytest_drivedegrade.planning import Command, EgoStatus

WEIGHTS = Path(__file__).with_name("closed_driver.pt")
CAMERAS: tuple[str, ...] = ("CAM_FRONT",)
#: Network input size per view (width, height).
VIEW: tuple[int, int] = (80, 45)
#: The zoomed view's crop as shares of the image (left, top, right, bottom): the horizon and the light heads above it.
ZOOM_BOX: tuple[float, float, float, float] = (0.3, 0.12, 0.7, 0.52)
#: Networks in the committed ensemble.
MEMBERS = 1
#: The distances (m) of the corridor's and the stop line's "farther than d" probabilities.
PROFILE_M: tuple[float, ...] = (2.0, 4.0, 6.0, 8.0, 10.0, 13.0, 16.0, 20.0, 25.0, 30.0, 40.0, 50.0)
#: Output layout: regressed lane x, lane y, bend speeds, lead speed; then the probabilities (corridor free farther
#: than each PROFILE_M, no red/yellow line within each PROFILE_M, yellow).
N_LANE, N_BEND, N_PROFILE = len(LANE_AHEAD), len(BEND_AHEAD), len(PROFILE_M)
N_REGRESSED = 2 * N_LANE + N_BEND + 1
OUTPUT_SIZE = N_REGRESSED + 2 * N_PROFILE + 1


def preprocess(images: Mapping[str, np.ndarray]) -> np.ndarray:
    """The two views of CAM_FRONT stacked on channels: (6, 45, 80) uint8."""
    image = images["CAM_FRONT"]
    h, w = image.shape[:2]
    full = cv2.resize(image, VIEW, interpolation=cv2.INTER_AREA)
    x0, y0, x1, y1 = (int(round(f * n)) for f, n in zip(ZOOM_BOX, (w, h, w, h)))
    zoom = cv2.resize(image[y0:y1, x0:x1], VIEW, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(np.concatenate([full, zoom], axis=2).transpose(2, 0, 1))


def profile_distance(prob: np.ndarray) -> float:
    """The distance a "farther than PROFILE_M[j]" profile reads: the sum of each bin's width times its probability
    (made non-increasing first); FAR_M when the last one is more likely than not (nothing within 50 m)."""
    prob = np.minimum.accumulate(np.clip(np.asarray(prob, dtype=np.float64), 0.0, 1.0))
    if prob[-1] > 0.5:
        return FAR_M
    return float((prob * np.diff(np.concatenate([[0.0], PROFILE_M]))).sum())


def percept_of(out: np.ndarray) -> Percept:
    """The `Percept` a network output (OUTPUT_SIZE; regressed values in metres and m/s, then probabilities) reads."""
    out = np.asarray(out, dtype=np.float64)
    lane = np.stack([out[:N_LANE], out[N_LANE:2 * N_LANE]], axis=1)
    bend = out[2 * N_LANE:2 * N_LANE + N_BEND]
    corridor = out[N_REGRESSED:N_REGRESSED + N_PROFILE]
    line = profile_distance(out[N_REGRESSED + N_PROFILE:N_REGRESSED + 2 * N_PROFILE])
    yellow = bool(out[-1] > 0.5) and line < FAR_M
    return Percept(lane, bend, profile_distance(corridor), float(max(out[N_REGRESSED - 1], 0.0)), line,
                   line < FAR_M and not yellow, yellow)


def targets(percepts: list[Percept]) -> tuple[np.ndarray, np.ndarray]:
    """The network's targets (N, OUTPUT_SIZE) of world percepts, and per sample whether its lead speed is learnt
    (an obstacle within 40 m)."""
    profile = np.asarray(PROFILE_M)
    rows, learn_speed = [], []
    for p in percepts:
        stop = p.line if (p.red or p.yellow) else FAR_M
        rows.append(np.concatenate([p.lane[:, 0], p.lane[:, 1], p.bend, [p.lead_speed], p.gap > profile,
                                    stop > profile, [float(p.yellow)]]))
        learn_speed.append(p.gap < 40.0)
    return np.asarray(rows, dtype=np.float32), np.asarray(learn_speed, dtype=np.float32)


class PerceptNet(nn.Module):
    """Convolutions on the two views, pooled to a 3 x 5 grid, joined with the normalised ego features; the
    regressed outputs are normalised by its own buffers, the rest are logits."""

    x_mean: torch.Tensor
    x_std: torch.Tensor
    y_mean: torch.Tensor
    y_std: torch.Tensor

    def __init__(self, hidden: int = 128) -> None:
        super().__init__()
        self.encoder = nn.Sequential(
            nn.Conv2d(6, 16, 5, 2, 2), nn.ReLU(), nn.Conv2d(16, 32, 3, 2, 1), nn.ReLU(),
            nn.Conv2d(32, 32, 3, 2, 1), nn.ReLU(), nn.AdaptiveAvgPool2d((3, 5)), nn.Flatten())
        self.head = nn.Sequential(nn.Linear(32 * 15 + FEATURE_SIZE, hidden), nn.ReLU(), nn.Linear(hidden, hidden),
                                  nn.ReLU(), nn.Linear(hidden, OUTPUT_SIZE))
        self.register_buffer("x_mean", torch.zeros(FEATURE_SIZE))
        self.register_buffer("x_std", torch.ones(FEATURE_SIZE))
        self.register_buffer("y_mean", torch.zeros(N_REGRESSED))
        self.register_buffer("y_std", torch.ones(N_REGRESSED))

    def forward(self, pix: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Normalised regressed outputs and logits (N, OUTPUT_SIZE) from uint8 views (N, 6, 45, 80) and raw
        features (N, F)."""
        x = self.encoder(pix.float() / 255.0 - 0.5)
        z = (feats - self.x_mean) / self.x_std
        return self.head(torch.cat([x, z], dim=1))

    def read(self, pix: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Regressed outputs in their units, then probabilities."""
        out = self.forward(pix, feats)
        return torch.cat([out[:, :N_REGRESSED] * self.y_std + self.y_mean, torch.sigmoid(out[:, N_REGRESSED:])], 1)


class PerceptEnsemble(nn.Module):
    """`members` PerceptNets; the outputs are their mean."""

    def __init__(self, members: int = MEMBERS) -> None:
        super().__init__()
        self.members = nn.ModuleList(PerceptNet() for _ in range(members))

    def read(self, pix: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        return torch.stack([m.read(pix, feats) for m in self.members]).mean(0)


class ClosedDriver:
    """The planner contract around ``PerceptEnsemble`` and ``percept.plan_arcs`` (CPU, one thread; deterministic)."""

    cameras: tuple[str, ...] = CAMERAS
    name = "closed_driver"

    def __init__(self, weights: Path = WEIGHTS, net: PerceptEnsemble | None = None) -> None:
        self.net = net if net is not None else PerceptEnsemble()
        if net is None:
            try:
                self.net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
            except RuntimeError as err:  # weights of another shape: say which file, and how to make new ones
                raise ValueError(f"{weights}: not weights of this driver ({MEMBERS} PerceptNet; "
                                 f"{str(err).splitlines()[0]}); retrain with python planners/train_closed_driver.py "
                                 "--out PATH") from None
        self.net.eval()
        sidecar = Path(weights).with_suffix(".json")
        self.trained_on = json.loads(sidecar.read_text()) if net is None and sidecar.is_file() else {}
        self._rule = RulePlanner()
        self._last: tuple[float, float] | None = None

    def reset(self, scene: str) -> None:
        """A new route or scene: the cruise speed is read again from its first ego status, and what was read at
        the last call (the gap, the yellow decision) is forgotten."""
        self._rule.reset()
        self._last = None

    def percept(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> Percept:
        """What the network reads from the front camera, the ego status and the command."""
        with torch.inference_mode():
            out = self.net.read(torch.from_numpy(preprocess(images)[None]),
                                torch.from_numpy(ego_features(ego, cmd)[None]))
        return percept_of(out[0].double().numpy())

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        p = self.percept(images, ego, cmd)
        v = float(ego.velocity[0])
        last, self._last = self._last, (p.gap, v)
        if last is not None and p.gap < FAR_M and last[0] < FAR_M:  # the slower of the read and the tracked speed
            p = replace(p, lead_speed=min(p.lead_speed, tracked_lead_speed(p.gap, last[0], v, last[1])))
        return self._rule.plan(p, ego)


@pytest.fixture(scope="session")
def planner() -> ClosedDriver:
    """The driver the suite certifies; one torch thread per process (bit-identical on any worker layout)."""
    torch.set_num_threads(1)
    return ClosedDriver()
