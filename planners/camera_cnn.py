"""Reference planner: a small camera CNN. Reads the three front cameras together with ego status and command.

Design: the ego-only floor's prediction (an MLP on ego status and command) plus a residual that a small
convolutional encoder computes from the front cameras. The residual is what the cameras add: a stopped car or a
crossing pedestrian ahead (braking), a bend or a junction (turning). Each camera is reduced to 160 x 90 with
``cv2.INTER_AREA`` inside ``predict`` (an integer factor of 5 at the default 800 x 450, OpenCV's fast path), and a
fourth view zooms on the middle of CAM_FRONT (the central 40 % x 40 % around the horizon, a factor of 2), where
a car 40 m ahead or a pedestrian at the curb is otherwise only a few pixels; all are normalised by the
network's own buffers.

Weights are committed beside this file (``camera_cnn.pt``, with ``camera_cnn.json`` holding the data set
fingerprint and the training settings) and load without any download. Retrain with
``python planners/train_camera_cnn.py``.

    pytest --drivedegrade planners/camera_cnn.py -n 2
"""

from __future__ import annotations

import copy
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
from pytest_drivedegrade.planning import Command, EgoStatus, deterministic_cuda, planner_device

WEIGHTS = Path(__file__).with_name("camera_cnn.pt")
SIDECAR = WEIGHTS.with_suffix(".json")
#: The cameras this planner reads, in the order the network stacks them.
CNN_CAMERAS: tuple[str, ...] = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT")
#: Network input size per view (width, height).
INPUT_SIZE: tuple[int, int] = (160, 90)
#: The views the network stacks: (camera, crop as fractions (x0, x1, y0, y1) of the image, or None for all of it).
VIEWS: tuple[tuple[str, tuple[float, float, float, float] | None], ...] = (
    ("CAM_FRONT", None), ("CAM_FRONT_LEFT", None), ("CAM_FRONT_RIGHT", None),
    ("CAM_FRONT", (0.3, 0.7, 1 / 3, 11 / 15)),  # 320 x 180 at 800 x 450: the road 10-80 m ahead, zoomed x2
)


def _view(image: np.ndarray, crop: tuple[float, float, float, float] | None) -> np.ndarray:
    if crop is not None:
        h, w = image.shape[:2]
        image = image[round(crop[2] * h): round(crop[3] * h), round(crop[0] * w): round(crop[1] * w)]
    return cv2.resize(image, INPUT_SIZE, interpolation=cv2.INTER_AREA)


def preprocess(images: Mapping[str, np.ndarray]) -> np.ndarray:
    """The views, downsampled with INTER_AREA: uint8 (len(VIEWS), H, W, 3). Never writes its inputs."""
    return np.stack([_view(images[cam], crop) for cam, crop in VIEWS])


def _conv(c_in: int, c_out: int, k: int, stride: int, pad: int) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, k, stride, pad, bias=False), nn.BatchNorm2d(c_out), nn.ReLU()]


#: What the cameras must tell the planner, as a few numbers (trained against annotations, see
#: ``train_camera_cnn.perception_targets``): the vehicle ahead in the ego lane (present, distance), the nearest
#: pedestrian or cyclist at or in the lane ahead (present, distance, lateral offset, in the lane), and where the
#: road goes (lateral offset of the path at 1.5 s and 3 s).
PERCEPTS: tuple[str, ...] = ("vehicle", "vehicle_x", "vru", "vru_x", "vru_y", "vru_in_lane", "path_y15", "path_y30")


class CameraCNN(nn.Module):
    """Floor MLP on ego features plus a camera residual; ``forward(pix, feats)`` -> (N, 12) metres.

    `pix` is uint8 (N, C, H, W, 3) as ``preprocess`` returns; `feats` are ``ego_features`` rows (N, F). The
    cameras reach the residual only through ``perceive``'s few numbers (``PERCEPTS``): a bottleneck that keeps a
    network trained on a hundred scenes from memorising their looks instead of reading the road.
    """

    def __init__(self, hidden: int = 128, cam_dim: int = 48, dropout: float = 0.1) -> None:
        super().__init__()
        self.drop = nn.Dropout(dropout)  # training only
        n_cams = len(VIEWS)
        # A 4 x 4 patchify stem keeps the cost at a few million MACs per view (>= 50 frames/s on one core).
        self.encoder = nn.Sequential(
            *_conv(3, 24, 4, 4, 0), *_conv(24, 32, 3, 2, 1), *_conv(32, 64, 3, 2, 1), *_conv(64, 24, 1, 1, 0),
        )
        w, h = INPUT_SIZE
        cells = (-(-(h // 4) // 4)) * (-(-(w // 4) // 4))  # 90 x 160 -> 22 x 40 -> 11 x 20 -> 6 x 10
        self.project = nn.ModuleList(nn.Linear(24 * cells, cam_dim) for _ in range(n_cams))
        self.percept = nn.Sequential(
            nn.Linear(n_cams * cam_dim + FEATURE_SIZE, hidden), nn.ReLU(), nn.Linear(hidden, len(PERCEPTS))
        )
        self.base = nn.Sequential(
            nn.Linear(FEATURE_SIZE, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, OUTPUT_SIZE),
        )
        self.head = nn.Sequential(
            nn.Linear(len(PERCEPTS) + FEATURE_SIZE, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, OUTPUT_SIZE),
        )
        for name, size in (("x_mean", FEATURE_SIZE), ("x_std", FEATURE_SIZE), ("y_mean", OUTPUT_SIZE),
                           ("y_std", OUTPUT_SIZE), ("pix_mean", 3), ("pix_std", 3)):
            self.register_buffer(name, torch.zeros(size) if "mean" in name else torch.ones(size))

    def normalise(self, pix: torch.Tensor) -> torch.Tensor:
        """uint8 (N, C, H, W, 3) -> float (N * C, 3, H, W) in channels-last memory: ``(v / 255 - mean) / std``.

        Element by element the same operations as a channel-first broadcast (so the same bits), but on rows of
        W * 3 contiguous values against a per-row pattern of the three channels' mean and std: a broadcast of
        (1, 3, 1, 1) over channels-last memory has an inner loop of one element, several times slower.
        """
        n, c, h, w, _ = pix.shape
        mean, std = self.pix_mean.repeat(w), self.pix_std.repeat(w)
        x = pix.reshape(n * c * h, w * 3).float().div_(255.0).sub_(mean).div_(std)
        return x.view(n * c, h, w, 3).permute(0, 3, 1, 2)

    def perceive(self, pix: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """(N, len(PERCEPTS)) scene facts from the views and the normalised ego features `z`."""
        n, c = pix.shape[:2]
        maps = self.encoder(self.normalise(pix)).reshape(n, c, -1)
        cams = torch.cat([torch.relu(proj(maps[:, i])) for i, proj in enumerate(self.project)], dim=1)
        return self.percept(torch.cat([self.drop(cams), z], dim=1))

    def plan(self, facts: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Waypoints (N, 12) in metres from scene facts and normalised ego features."""
        out = self.base(z) + self.head(torch.cat([facts, z], dim=1))
        return out * self.y_std + self.y_mean

    def forward(self, pix: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        z = (feats - self.x_mean) / self.x_std
        return self.plan(self.perceive(pix, z), z)


class PlanHead(nn.Module):
    """``CameraCNN.plan`` (the two MLPs on scene facts and ego features, and the output scale) in float64, with
    the same weights upcast exactly: the planner's output stage.

    In float32 the plan, tens of metres, carries a rounding step of up to 3.8e-6 m, and two summation orders of
    the same facts (one frame, or a batch of frames) ended up to 3 steps apart (1.1e-5 m); in float64 they end
    within the facts' own rounding (3e-6 m measured). Training keeps ``CameraCNN.plan`` in float32.
    """

    def __init__(self, model: CameraCNN) -> None:
        super().__init__()
        self.base, self.head = copy.deepcopy(model.base).double(), copy.deepcopy(model.head).double()
        self.register_buffer("y_mean", model.y_mean.double())
        self.register_buffer("y_std", model.y_std.double())

    def forward(self, facts: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        facts, z = facts.double(), z.double()
        return (self.base(z) + self.head(torch.cat([facts, z], dim=1))) * self.y_std + self.y_mean


class CameraCNNPlanner:
    """The planner contract around ``CameraCNN``: reads CAM_FRONT, CAM_FRONT_LEFT and CAM_FRONT_RIGHT.

    `device` is where the network runs (``cpu``, ``cuda``, ``cuda:N``); the ``planner`` fixture passes the run's
    ``--drivedegrade-device`` (``planner_device()``). Preprocessing stays on the CPU (OpenCV); on CUDA the
    uint8 views go to the GPU and only the (N, 12) plans come back. CUDA plans differ from CPU plans by float
    rounding (another summation order), so the device is part of the run key.
    """

    cameras: tuple[str, ...] = CNN_CAMERAS
    name = "camera_cnn"

    def __init__(self, weights: Path = WEIGHTS, device: str = "cpu") -> None:
        self.device = torch.device(device)
        if self.device.type == "cuda":
            deterministic_cuda()
        self.model = CameraCNN()
        self.model.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
        self.model.eval().to(self.device)
        self.output = PlanHead(self.model).eval().to(self.device)
        for module in self.model.encoder:  # in place at inference: the same values, one pass less over memory
            if isinstance(module, nn.ReLU):
                module.inplace = True
        sidecar = Path(weights).with_suffix(".json")
        self.trained_on = json.loads(sidecar.read_text()) if sidecar.is_file() else {}

    def predict_many(self, pix: np.ndarray, feats: np.ndarray) -> np.ndarray:
        """Waypoints (N, 6, 2) float64 from preprocessed pixels (N, C, H, W, 3) and ego features (N, F)."""
        model = self.model
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(pix)).to(self.device)
            z = (torch.from_numpy(feats).to(self.device) - model.x_mean) / model.x_std
            out = self.output(model.perceive(x, z), z).cpu()
        return out.numpy().reshape(-1, HORIZON_STEPS, 2)

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        return self.predict_many(preprocess(images)[None], ego_features(ego, cmd)[None])[0]

    def predict_batch(self, images: list[Mapping[str, np.ndarray]], egos: list[EgoStatus], cmds: list[Command],
                      contexts: list[object]) -> np.ndarray:
        """(B, 6, 2) for B frames in one forward pass (`--drivedegrade-batch B`): the same plans as `predict`
        within float rounding (batched convolutions and matrix products sum in another order: within 3e-6 m on
        the embedded world, and the test holds them to 1e-5 m)."""
        pix = np.stack([preprocess(im) for im in images])
        feats = np.stack([ego_features(e, c) for e, c in zip(egos, cmds)])
        return self.predict_many(pix, feats)


@pytest.fixture(scope="session")
def planner() -> CameraCNNPlanner:
    """The planner the suite certifies; the weights load once per worker.

    One torch thread per process: under -n 2 the two workers already fill both cores, and the same thread
    count in every layout keeps the plans bit-identical between -n 0 and -n 2. The network runs on the run's
    --drivedegrade-device (``$DRIVEDEGRADE_DEVICE``, set by the plugin; default cpu).
    """
    torch.set_num_threads(1)
    return CameraCNNPlanner(device=planner_device())
