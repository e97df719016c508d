"""Example adapter: a NAVSIM-style agent (TransFuser's camera and status inputs) under the suite.

Copy this file and replace ``TinyTransfuser`` with your agent's model. The inputs are built as NAVSIM's
``TransfuserFeatureBuilder`` builds them:

- ``camera_feature``: the front three cameras, ``cam_l0``, ``cam_f0``, ``cam_r0`` (here CAM_FRONT_LEFT,
  CAM_FRONT, CAM_FRONT_RIGHT), cropped to a 4:1 strip and stitched left, front, right, then resized to
  1024 x 256 (``cv2.resize``, bilinear) and scaled to 0..1 (``ToTensor``). NAVSIM crops 28 px from the top and
  bottom of every 1920 x 1080 image and 416 px from each side of the two side cameras; ``crop_box`` scales
  those numbers to the delivered size (at nuScenes' 1600 x 900: 23 and 347 px; at the embedded world's
  800 x 450: 12 and 173 px). The images stay RGB, as NAVSIM loads them.
- ``status_feature``: the driving command as NAVSIM's 4-way one-hot (left, straight, right, unknown), the ego
  velocity (vx, vy) and acceleration (ax, ay) in the ego frame: 8 values.
- The output is NAVSIM's trajectory, 8 poses (x, y, heading) at 0.5 s steps over 4 s in the ego frame (x
  forward, y left, the suite's frame too). By default the agent hands the suite the first 6 positions (3 s);
  with ``NAVSIM_POSES=8`` in the environment it declares ``poses = 8`` and hands all 8, and the suite scores
  PDMS/EPDMS over NAVSIM's 4 s (L2 stays the first six, nuScenes' 3 s) on data holding 4 s of future: a world
  made with ``drivedegrade world --out WORLD4 --future 4``::

      NAVSIM_POSES=8 pytest --drivedegrade planners/examples/navsim_style.py --drivedegrade-data WORLD4

nuScenes' side cameras look 55 degrees to each side with a 70-degree field of view, close to what NAVSIM's
``l0`` / ``r0`` see; an agent trained on NAVSIM still meets a new camera rig here, so certify what you deploy.

``cameras`` names the three front cameras, so the null control blacks out the three rear ones and demands an
unchanged plan: a check that the agent really reads only these. The agent keeps no state (no ``reset``).

    pytest --drivedegrade planners/examples/navsim_style.py -n 2 --drivedegrade-families jpeg,blackout

**Wrapping the real thing.** Build the agent from its config (``TransfuserAgent(config, lr, checkpoint_path)``,
``initialize()``, ``.eval()``), fill ``features`` as below and call ``agent.forward(features)["trajectory"]``
(batch dimension first); the LiDAR BEV feature has no source here (the suite is camera-only): pass zeros and
say so, or certify a camera-only agent.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from pytest_drivedegrade.constants import HORIZON_STEPS, STEP_SECONDS
from pytest_drivedegrade.planning import Command, EgoStatus, deterministic_cuda, planner_device

#: NAVSIM's cameras, in stitching order: cam_l0, cam_f0, cam_r0.
FRONT_CAMERAS: tuple[str, ...] = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT")
#: NAVSIM's crops at its native 1920 x 1080: rows from top and bottom, columns from each side of l0 / r0.
NAVSIM_SIZE = (1920, 1080)
NAVSIM_CROP_ROWS, NAVSIM_CROP_SIDE = 28, 416
STITCHED_SIZE = (1024, 256)  # (w, h), 4:1
#: NAVSIM's driving command one-hot order, and where the suite's commands go in it.
NAVSIM_COMMANDS = ("left", "straight", "right", "unknown")
COMMAND_INDEX = {Command.LEFT: 0, Command.STRAIGHT: 1, Command.RIGHT: 2}
NUM_POSES = 8  # NAVSIM: 4 s at 2 Hz
#: The poses the agent hands the suite: 6 (3 s, the default) or NAVSIM's 8 (4 s, `NUM_POSES`), from the
#: environment variable of the same name.
NAVSIM_POSES = int(os.environ.get("NAVSIM_POSES", str(HORIZON_STEPS)))


def crop_box(width: int, height: int) -> tuple[int, int]:
    """(rows cut at top and bottom, columns cut at each side of the side cameras) at this image size:
    NAVSIM's (28, 416) at 1920 x 1080, scaled with the image."""
    return round(NAVSIM_CROP_ROWS * height / NAVSIM_SIZE[1]), round(NAVSIM_CROP_SIDE * width / NAVSIM_SIZE[0])


def stitch_front(images: Mapping[str, np.ndarray]) -> np.ndarray:
    """NAVSIM's ``_get_camera_feature`` before ``ToTensor``: uint8 (256, 1024, 3) RGB; never writes `images`."""
    left, front, right = (images[c] for c in FRONT_CAMERAS)
    h, w = front.shape[:2]
    rows, side = crop_box(w, h)
    l0 = left[rows: h - rows, side: w - side]
    f0 = front[rows: h - rows]
    r0 = right[rows: h - rows, side: w - side]
    return cv2.resize(np.concatenate([l0, f0, r0], axis=1), STITCHED_SIZE)


def camera_feature(images: Mapping[str, np.ndarray]) -> torch.Tensor:
    """(3, 256, 1024) float32 in 0..1, as ``transforms.ToTensor()`` makes it (without torchvision)."""
    return torch.from_numpy(stitch_front(images)).permute(2, 0, 1).float().div(255.0)


def status_feature(ego: EgoStatus, cmd: Command) -> torch.Tensor:
    """NAVSIM's 8-value status: driving command one-hot (left, straight, right, unknown), velocity, acceleration."""
    command = np.zeros(len(NAVSIM_COMMANDS), np.float32)
    command[COMMAND_INDEX.get(Command(int(cmd)), len(NAVSIM_COMMANDS) - 1)] = 1.0
    return torch.from_numpy(np.concatenate([command, np.asarray(ego.velocity, np.float32),
                                            np.asarray(ego.acceleration, np.float32)]))


class TinyTransfuser(nn.Module):
    """A stand-in for TransFuser's camera branch and trajectory head: a small CNN on the stitched image, an MLP
    on the status, out come NUM_POSES poses (x, y, heading). Random-init with a fixed seed: no skill, the data
    flow only. The plan is a rollout of the status (constant longitudinal acceleration, constant lateral
    velocity) plus a bounded residual from the image and the status."""

    def __init__(self, channels: int = 16) -> None:
        super().__init__()
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
        self.image = nn.Sequential(
            nn.AvgPool2d(4), nn.Conv2d(3, channels, 3, 2, 1), nn.ReLU(), nn.Conv2d(channels, channels, 3, 2, 1),
            nn.ReLU(), nn.AdaptiveAvgPool2d((2, 8)), nn.Flatten(),
        )
        self.status = nn.Sequential(nn.Linear(8, 32), nn.ReLU())
        self.head = nn.Sequential(nn.Linear(channels * 16 + 32, 64), nn.ReLU(), nn.Linear(64, NUM_POSES * 3))

    def forward(self, camera: torch.Tensor, status: torch.Tensor) -> torch.Tensor:
        """camera (B, 3, 256, 1024) in 0..1, status (B, 8) -> trajectory (B, NUM_POSES, 3)."""
        feats = torch.cat([self.image((camera - self.mean) / self.std), self.status(status)], dim=1)
        residual = torch.tanh(self.head(feats)).view(-1, NUM_POSES, 3)
        t = STEP_SECONDS * torch.arange(1, NUM_POSES + 1, dtype=torch.float32, device=status.device).view(1, -1, 1)
        vx, vy, ax = status[:, None, 4:5], status[:, None, 5:6], status[:, None, 6:7]
        # longitudinal: constant acceleration, stopping where the speed reaches zero; lateral: constant velocity
        stop = torch.where(ax < -1e-3, -vx / ax.clamp(max=-1e-3), torch.full_like(vx, float("inf")))
        t_x = torch.minimum(t, stop)
        xy = torch.cat([vx * t_x + 0.5 * ax * t_x**2, vy * t], dim=2)
        heading = torch.zeros_like(t)
        return torch.cat([xy, heading], dim=2) + residual * torch.tensor([1.0, 1.0, 0.1], device=status.device)


class NavsimStyleAgent:
    """The suite's contract around a NAVSIM-style agent: reads the three front cameras only.

    `device` is where the model runs (``cpu``, ``cuda``, ``cuda:N``): the fixture passes the run's
    ``--drivedegrade-device``. The weights are made on the CPU with the seed, then moved, so every device starts
    from the same weights; features go to the device, the plan comes back to the CPU."""

    name = "navsim_style"
    cameras: tuple[str, ...] = FRONT_CAMERAS

    def __init__(self, seed: int = 0, device: str = "cpu", poses: int = HORIZON_STEPS) -> None:
        self.poses = poses  # 6, or 8: NAVSIM's whole 4 s, scored by the PDMS/EPDMS over 4 s
        self.device = torch.device(device)
        if self.device.type == "cuda":
            deterministic_cuda()
        torch.manual_seed(seed)
        self.model = TinyTransfuser().eval().to(self.device)

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        features = {"camera_feature": camera_feature(images)[None], "status_feature": status_feature(ego, cmd)[None]}
        with torch.inference_mode():
            trajectory = self.model(*(features[k].to(self.device) for k in ("camera_feature", "status_feature")))[0]
        return trajectory[:self.poses, :2].cpu().numpy().astype(np.float64)  # NAVSIM's 4 s, or its first 3 s


@pytest.fixture(scope="session")
def planner() -> Iterator[NavsimStyleAgent]:
    """Built once per worker, on one torch thread: the CPU kernels this model uses (convolution, pooling,
    linear) are deterministic given the thread count, so every layout gives the same bits. (A
    model with kernels that are not, e.g. on CUDA, also wants ``torch.use_deterministic_algorithms(True)``;
    on CPU it only costs importing torch's compiler stack into every worker.) The model runs on the run's
    --drivedegrade-device (``planner_device()``)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield NavsimStyleAgent(device=planner_device(), poses=NAVSIM_POSES)
    finally:
        torch.set_num_threads(threads)
