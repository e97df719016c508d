"""A camera planner trained on the embedded world, start to end: the docs' how-to "Train a camera planner on the
embedded world" walks through it.

Train (reads the world's train split: its images are rendered on first use, which takes a while), then certify:

    python planners/examples/tiny_camera.py --steps 300            # writes planners/examples/tiny_camera.pt
    python -m pytest --drivedegrade planners/examples/tiny_camera.py -n 2

The model is small on purpose (the front camera at 64 x 36 and the ego status, a few convolutions): it shows the
reader API and the planner contract, not a good driver.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from pytest_drivedegrade.data.frame import Command, EgoStatus, Frame
from pytest_drivedegrade.floor import ego_features
from pytest_drivedegrade.planning import planner_device

HERE = Path(__file__).resolve().parent
WEIGHTS = HERE / "tiny_camera.pt"
SIZE = (64, 36)  # width, height the front image is shrunk to


def image_input(image: np.ndarray) -> np.ndarray:
    """The front camera's RGB uint8 image as the network reads it: (3, 36, 64) float32 in [0, 1]."""
    small = cv2.resize(image, SIZE, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(small.transpose(2, 0, 1), dtype=np.float32) / 255.0


class TinyCamera(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv2d(3, 8, 5, stride=2), nn.ReLU(), nn.Conv2d(8, 16, 3, stride=2), nn.ReLU(),
                                  nn.AdaptiveAvgPool2d(1), nn.Flatten())
        self.head = nn.Sequential(nn.Linear(16 + 16, 64), nn.ReLU(), nn.Linear(64, 12))

    def forward(self, pixels: torch.Tensor, ego: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat([self.conv(pixels), ego], dim=1))


class TinyCameraPlanner:
    """The planner contract: reads CAM_FRONT only (declared), returns (6, 2) float waypoints."""

    cameras = ("CAM_FRONT",)
    name = "tiny_camera"

    def __init__(self, model: TinyCamera, device: str = "cpu") -> None:
        self.model, self.device = model.to(device).eval(), device

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        pixels = torch.from_numpy(image_input(images["CAM_FRONT"]))[None].to(self.device)
        feats = torch.from_numpy(ego_features(ego, cmd).astype(np.float32))[None].to(self.device)
        with torch.no_grad():
            return self.model(pixels, feats).cpu().numpy().reshape(6, 2).astype(np.float64)


@pytest.fixture(scope="session")
def planner() -> TinyCameraPlanner:
    if not WEIGHTS.is_file():
        raise FileNotFoundError(f"{WEIGHTS} not found: train it first with `python {Path(__file__).name}`")
    torch.set_num_threads(1)
    model = TinyCamera()
    model.load_state_dict(torch.load(WEIGHTS, map_location="cpu", weights_only=True))
    return TinyCameraPlanner(model, planner_device())


def arrays(frames: Sequence[Frame], load: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pixels, ego features, targets) of `frames`: what one training step reads."""
    pixels = np.stack([image_input(load(f.cameras["CAM_FRONT"])) for f in frames])  # type: ignore[operator]
    feats = np.stack([ego_features(f.ego, f.command) for f in frames]).astype(np.float32)
    targets = np.stack([f.gt_future.reshape(-1) for f in frames]).astype(np.float32)
    return pixels, feats, targets


def train(root: Path, split: str, steps: int, seed: int = 0) -> TinyCamera:
    """Train on the scorable frames of `split` under `root` (mean waypoint L2 loss, Adam, full batches)."""
    from pytest_drivedegrade.data.nuscenes import NuScenesReader

    reader = NuScenesReader(root, split=split)
    frames = reader.scorable_frames(agents=False)  # no boxes: training reads only images, ego and the future
    pixels, feats, targets = (torch.from_numpy(a) for a in arrays(frames, reader.load_image))
    torch.manual_seed(seed)
    model = TinyCamera()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for step in range(steps):
        err = (model(pixels, feats) - targets).view(-1, 6, 2)
        loss = torch.sqrt((err ** 2).sum(-1) + 1e-6).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % max(1, steps // 5) == 0 or step == steps - 1:
            print(f"step {step + 1}/{steps}: mean waypoint L2 {loss.item():.3f} m on {len(frames)} frames", flush=True)
    return model.eval()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="train the tiny camera planner on the embedded world")
    parser.add_argument("--data", type=Path, help="a nuScenes-format root (default: the embedded world, with its "
                                                  "train images rendered on first use)")
    parser.add_argument("--split", default="train")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--cache-root", type=Path, default=Path(".pytest_cache/d/drivedegrade"))
    parser.add_argument("--out", type=Path, default=WEIGHTS)
    args = parser.parse_args(argv)
    root = args.data
    if root is None:
        from pytest_drivedegrade.data.world import ensure_default_world
        from pytest_drivedegrade.progress import Sink

        root = ensure_default_world(args.cache_root, train_images=args.split == "train", progress=Sink())
    model = train(root, args.split, args.steps)
    torch.save(model.state_dict(), args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
