"""Reference closed-loop driver: a small CNN on the front camera, trained by imitation of the world's privileged
expert on its own closed-loop states (DAgger). Reads CAM_FRONT only, with ego status and command.

The front camera is reduced to 80 x 45 (``cv2.INTER_AREA``, a factor of 10 at the world's 800 x 450) and a
second view zooms on its middle (the central 40 % x 40 %, 80 x 45 again), where a standing car 40 m ahead or a
pedestrian at the curb is otherwise a few pixels. The network regresses the six waypoints (ego frame, 0.5 s
apart) from both views and the ego features (``floor.ego_features``), normalised by its own buffers.

Weights are committed beside this file (``closed_driver.pt``; ``closed_driver.json`` holds the recipe's
settings and what it measured). Retrain with ``python planners/train_closed_driver.py`` (docs/how-to/closed-loop.md).

    pytest --drivedegrade planners/closed_driver.py --drivedegrade-loop closed -n 2
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from pytest_drivedegrade.constants import HORIZON_STEPS
from pytest_drivedegrade.floor import FEATURE_SIZE, OUTPUT_SIZE, ego_features
from pytest_drivedegrade.planning import Command, EgoStatus

WEIGHTS = Path(__file__).with_name("closed_driver.pt")
CAMERAS: tuple[str, ...] = ("CAM_FRONT",)
#: Network input size per view (width, height) and the zoomed view's share of the image (width, height).
VIEW: tuple[int, int] = (80, 45)
ZOOM: tuple[float, float] = (0.4, 0.4)


def preprocess(images: Mapping[str, np.ndarray]) -> np.ndarray:
    """The two views of CAM_FRONT stacked on channels: (6, 45, 80) uint8."""
    image = images["CAM_FRONT"]
    h, w = image.shape[:2]
    full = cv2.resize(image, VIEW, interpolation=cv2.INTER_AREA)
    zw, zh = int(w * ZOOM[0]), int(h * ZOOM[1])
    x0, y0 = (w - zw) // 2, (h - zh) // 2
    zoom = cv2.resize(image[y0:y0 + zh, x0:x0 + zw], VIEW, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(np.concatenate([full, zoom], axis=2).transpose(2, 0, 1))


class DriverNet(nn.Module):
    """Convolutions on the two views, pooled to a 3 x 5 grid, joined with the normalised ego features."""

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
        self.register_buffer("y_mean", torch.zeros(OUTPUT_SIZE))
        self.register_buffer("y_std", torch.ones(OUTPUT_SIZE))

    def forward(self, pix: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Normalised waypoints (N, 12) from uint8 views (N, 6, 45, 80) and raw features (N, F)."""
        x = self.encoder(pix.float() / 255.0 - 0.5)
        z = (feats - self.x_mean) / self.x_std
        return self.head(torch.cat([x, z], dim=1))

    def plan(self, pix: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        return self.forward(pix, feats) * self.y_std + self.y_mean


class ClosedDriver:
    """The planner contract around ``DriverNet`` (CPU, one thread; deterministic)."""

    cameras: tuple[str, ...] = CAMERAS
    name = "closed_driver"

    def __init__(self, weights: Path = WEIGHTS, net: DriverNet | None = None) -> None:
        self.net = net if net is not None else DriverNet()
        if net is None:
            self.net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
        self.net.eval()
        sidecar = Path(weights).with_suffix(".json")
        self.trained_on = json.loads(sidecar.read_text()) if net is None and sidecar.is_file() else {}

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        with torch.inference_mode():
            pix = torch.from_numpy(preprocess(images)[None])
            feats = torch.from_numpy(ego_features(ego, cmd)[None])
            out = self.net.plan(pix, feats)
        return out.double().numpy().reshape(HORIZON_STEPS, 2)


@pytest.fixture(scope="session")
def planner() -> ClosedDriver:
    """The driver the suite certifies; one torch thread per process (bit-identical on any worker layout)."""
    torch.set_num_threads(1)
    return ClosedDriver()
