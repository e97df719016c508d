"""Reference closed-loop driver: a small CNN on the front camera, trained by imitation of the world's privileged
expert on its own closed-loop states (DAgger). Reads CAM_FRONT only, with ego status and command.

The front camera is reduced to 80 x 45 (``cv2.INTER_AREA``, a factor of 10 at the world's 800 x 450) and a
second view zooms on the band above its middle (``ZOOM_BOX``: the central 40 % of its width, 12 % to 52 % of its
height, 80 x 45 again), where a standing car 40 m ahead, a pedestrian at the curb or a traffic light's head is
otherwise a few pixels. Each network regresses the six waypoints (ego frame, 0.5 s
apart) from both views and the ego features (``floor.ego_features``), normalised by its own buffers; the driver
plans the mean of three such networks (``DriverEnsemble``).

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
#: Network input size per view (width, height).
VIEW: tuple[int, int] = (80, 45)
#: The zoomed view's crop as shares of the image (left, top, right, bottom): the horizon and the light heads above it.
ZOOM_BOX: tuple[float, float, float, float] = (0.3, 0.12, 0.7, 0.52)
#: Networks in the committed ensemble.
MEMBERS = 3


def preprocess(images: Mapping[str, np.ndarray]) -> np.ndarray:
    """The two views of CAM_FRONT stacked on channels: (6, 45, 80) uint8."""
    image = images["CAM_FRONT"]
    h, w = image.shape[:2]
    full = cv2.resize(image, VIEW, interpolation=cv2.INTER_AREA)
    x0, y0, x1, y1 = (int(round(f * n)) for f, n in zip(ZOOM_BOX, (w, h, w, h)))
    zoom = cv2.resize(image[y0:y1, x0:x1], VIEW, interpolation=cv2.INTER_AREA)
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


class DriverEnsemble(nn.Module):
    """`members` DriverNets trained from different seeds on the same data; the plan is their mean. Single networks of
    near recipes scored 58.6 to 70.4 DS on the 30-route slice; the mean of three of them scored 70.0, as the best
    did (docs/how-to/closed-loop.md)."""

    def __init__(self, members: int = MEMBERS) -> None:
        super().__init__()
        self.members = nn.ModuleList(DriverNet() for _ in range(members))

    def plan(self, pix: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        return torch.stack([m.plan(pix, feats) for m in self.members]).mean(0)


class ClosedDriver:
    """The planner contract around ``DriverEnsemble`` (CPU, one thread; deterministic)."""

    cameras: tuple[str, ...] = CAMERAS
    name = "closed_driver"

    def __init__(self, weights: Path = WEIGHTS, net: DriverNet | DriverEnsemble | None = None) -> None:
        self.net = net if net is not None else DriverEnsemble()
        if net is None:
            try:
                self.net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
            except RuntimeError as err:  # weights of another shape: say which file, and how to make new ones
                raise ValueError(f"{weights}: not weights of this driver ({MEMBERS} networks of DriverNet; "
                                 f"{str(err).splitlines()[0]}); retrain with python planners/train_closed_driver.py "
                                 "--out PATH") from None
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
