"""The ego-only floor: an AD-MLP-style regressor from ego status and command to the six waypoints, no image.

It answers "how well can one plan without looking?" on the data set at hand, so a camera planner's numbers have
a floor to be read against (SPEC section 5). Training is deterministic (fixed seed, deterministic algorithms,
one thread, a seeded shuffle), so the same frames give bit-identical weights; the weights are cached by the data
set fingerprint and the code version, and written atomically.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Protocol, TypedDict

import numpy as np
import torch
from torch import nn

from .atomic import atomic_write_bytes
from .constants import HORIZON_STEPS
from .data.frame import Command, EgoStatus, Frame
from .progress import Progress

#: Bump when features, network or training change: it is part of the cache key and the fingerprint.
FLOOR_VERSION = "ego_mlp-1"
class FloorSettings(TypedDict):
    """How the floor trains: hidden width, optimiser steps, batch size, learning rate, weight decay."""

    hidden: int
    steps: int
    batch: int
    lr: float
    weight_decay: float


#: Training settings; part of the cache key (as the JSON of this dict).
SETTINGS: FloorSettings = {"hidden": 128, "steps": 3000, "batch": 128, "lr": 2e-3, "weight_decay": 1e-5}
FEATURE_SIZE = EgoStatus.vector_size() + len(Command)
OUTPUT_SIZE = HORIZON_STEPS * 2


def ego_features(ego: EgoStatus, cmd: Command | int) -> np.ndarray:
    """Float32 features of one frame: ``EgoStatus.as_vector()``, then the one-hot command (RIGHT, LEFT, STRAIGHT)."""
    onehot = np.zeros(len(Command), dtype=np.float32)
    onehot[int(cmd)] = 1.0
    return np.concatenate([ego.as_vector(), onehot])


def frames_to_arrays(frames: Sequence[Frame]) -> tuple[np.ndarray, np.ndarray]:
    """Features (N, FEATURE_SIZE) float32 and targets (N, 12) float32 of the scorable frames among `frames`."""
    usable = [f for f in frames if f.scorable]
    if not usable:
        raise ValueError("no scorable frames (with six valid future waypoints) to train the ego-only floor on")
    x = np.stack([ego_features(f.ego, f.command) for f in usable])
    y = np.stack([np.asarray(f.gt_future, dtype=np.float32).reshape(-1) for f in usable])
    return x, y


class EgoMLP(nn.Module):
    """The floor network and a planner at once: ``predict(images, ego, cmd)`` ignores `images` entirely.

    Normalisation statistics live in buffers, so the ``state_dict`` is the whole model.
    """

    cameras: tuple[str, ...] = ()
    name: str = "ego_mlp"
    # the buffers registered in __init__, declared for the type checker (Module.__getattr__ types them loosely)
    x_mean: torch.Tensor
    x_std: torch.Tensor
    y_mean: torch.Tensor
    y_std: torch.Tensor

    def __init__(self, hidden: int = SETTINGS["hidden"]) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(FEATURE_SIZE, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, OUTPUT_SIZE),
        )
        self.register_buffer("x_mean", torch.zeros(FEATURE_SIZE))
        self.register_buffer("x_std", torch.ones(FEATURE_SIZE))
        self.register_buffer("y_mean", torch.zeros(OUTPUT_SIZE))
        self.register_buffer("y_std", torch.ones(OUTPUT_SIZE))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Raw features (N, F) -> waypoints (N, 12) in metres."""
        return self.net((x - self.x_mean) / self.x_std) * self.y_std + self.y_mean

    def predict_many(self, features: np.ndarray) -> np.ndarray:
        """Waypoints (N, 6, 2) float64 for a batch of ``ego_features`` rows."""
        with torch.inference_mode():
            out = self(torch.from_numpy(np.asarray(features, dtype=np.float32)))
        return out.numpy().astype(np.float64).reshape(-1, HORIZON_STEPS, 2)

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        """The planner contract: (6, 2) float64 waypoints from ego status and command alone."""
        return self.predict_many(ego_features(ego, cmd)[None])[0]

    def fingerprint(self) -> str:
        """Code version plus the bytes of every weight and buffer."""
        digest = hashlib.sha256(FLOOR_VERSION.encode())
        for key, tensor in self.state_dict().items():
            digest.update(key.encode() + tensor.detach().contiguous().numpy().tobytes())
        return digest.hexdigest()


@contextmanager
def deterministic_torch(seed: int) -> Iterator[None]:
    """Seeded, single-threaded, deterministic-algorithms torch for the duration; restores the caller's state."""
    threads = torch.get_num_threads()
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        torch.set_num_threads(1)
        torch.use_deterministic_algorithms(True)
        try:
            yield
        finally:
            torch.use_deterministic_algorithms(was_deterministic)
            torch.set_num_threads(threads)


def _set_stats(model: EgoMLP, x: np.ndarray, y: np.ndarray) -> None:
    model.x_mean.copy_(torch.from_numpy(x.mean(0)))
    model.x_std.copy_(torch.from_numpy(np.maximum(x.std(0), 1e-3)))
    model.y_mean.copy_(torch.from_numpy(y.mean(0)))
    model.y_std.copy_(torch.from_numpy(np.maximum(y.std(0), 1e-3)))


#: What shows training's progress: called with the number of steps, returns a `Progress` to advance per step.
ProgressFactory = Callable[[int], Progress]


def fit_arrays(
    x: np.ndarray, y: np.ndarray, *, seed: int = 0, settings: FloorSettings | None = None,
    progress: ProgressFactory | None = None,
) -> EgoMLP:
    """Train an ``EgoMLP`` on features `x` and targets `y` deterministically; loss is the mean waypoint L2 (m).
    `progress` shows the steps (the weights are the same with or without it)."""
    settings = SETTINGS if settings is None else settings
    bar = progress(settings["steps"]) if progress is not None else None
    with deterministic_torch(seed):
        model = EgoMLP(settings["hidden"])
        _set_stats(model, x.astype(np.float32), y.astype(np.float32))
        opt = torch.optim.Adam(model.parameters(), lr=settings["lr"], weight_decay=settings["weight_decay"])
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=settings["steps"])
        xt, yt = torch.from_numpy(x.astype(np.float32)), torch.from_numpy(y.astype(np.float32))
        gen = torch.Generator().manual_seed(seed)
        order, cursor = torch.randperm(len(xt), generator=gen), 0
        batch = min(settings["batch"], len(xt))
        model.train()
        for _ in range(settings["steps"]):
            if cursor + batch > len(order):
                order, cursor = torch.randperm(len(xt), generator=gen), 0
            idx = order[cursor : cursor + batch]
            cursor += batch
            err = (model(xt[idx]) - yt[idx]).view(-1, HORIZON_STEPS, 2)
            loss = torch.sqrt((err**2).sum(-1) + 1e-6).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()  # type: ignore[no-untyped-call]  # torch's Tensor.backward is unannotated
            opt.step()
            sched.step()
            if bar is not None:
                bar.advance()
        model.eval()
    if bar is not None:
        bar.finish()
    return model


def train_floor(
    frames_train: Sequence[Frame], *, seed: int = 0, settings: FloorSettings | None = None,
    progress: ProgressFactory | None = None,
) -> EgoMLP:
    """Train the floor on the scorable frames of a train split; same frames and seed give bit-identical weights."""
    x, y = frames_to_arrays(list(frames_train))
    return fit_arrays(x, y, seed=seed, settings=settings, progress=progress)


def cache_key(dataset_fingerprint: str, seed: int = 0) -> str:
    """The cache file key: data set fingerprint, code version, training settings and seed."""
    blob = json.dumps([dataset_fingerprint, FLOOR_VERSION, SETTINGS, seed], sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def save_atomic(model: nn.Module, path: Path) -> bytes:
    """Write a state_dict to `path` atomically (see `atomic.atomic_write_bytes`); returns the bytes written."""
    buffer = io.BytesIO()
    torch.save(model.state_dict(), buffer)
    atomic_write_bytes(path, buffer.getvalue())
    return buffer.getvalue()


def train_split_for(split: str) -> str:
    """The split the floor trains on when `split` is evaluated: ``val`` -> ``train``, ``mini_val`` -> ``mini_train``.

    Any other split (``train``, ``test``, custom) maps to ``train``; the floor never trains on what it scores
    unless the user evaluates on ``train`` itself.
    """
    return "mini_train" if split.startswith("mini") else "train"


class TrainSplit(Protocol):
    """What the floor reads of a train split (a ``NuScenesReader``): its fingerprint and its scorable frames."""

    def fingerprint(self) -> str: ...

    def scorable_frames(self, *, agents: bool = True) -> Sequence[Frame]: ...


def load_or_train_floor(reader_train: TrainSplit, cache_dir: Path, *, seed: int = 0,
                        progress: ProgressFactory | None = None) -> EgoMLP:
    """The floor for a train split: loaded from `cache_dir` when trained before on the same data, else trained.

    `reader_train` is a ``NuScenesReader`` on the train split (``fingerprint()`` and ``scorable_frames()``, read
    without the agents' boxes, which the floor never looks at). The cached file is loaded only when its bytes hash
    to the sha256 written beside it (`_floor_digest_path`): a file edited into other weights, cut short or left
    without its digest is retrained, so the floor that judges blind and the removal axis is the one the data
    trains (integrity only, as the store's record digests: whoever rewrites both files is not stopped here).
    """
    path = Path(cache_dir) / f"ego_mlp-{cache_key(reader_train.fingerprint(), seed)}.pt"
    if path.is_file():
        model = EgoMLP(SETTINGS["hidden"])
        try:
            data = path.read_bytes()
            if _floor_digest_path(path).read_text().strip() == hashlib.sha256(data).hexdigest():
                model.load_state_dict(torch.load(io.BytesIO(data), map_location="cpu", weights_only=True))
                return model.eval()
        except Exception:  # noqa: BLE001 - a corrupt or unchecked cache entry is retrained, not fatal
            pass
    model = train_floor(list(reader_train.scorable_frames(agents=False)), seed=seed, progress=progress)
    data = save_atomic(model, path)  # the weights first: a digest never vouches for a file not yet written
    atomic_write_bytes(_floor_digest_path(path), hashlib.sha256(data).hexdigest().encode())
    return model


def _floor_digest_path(path: Path) -> Path:
    """The sha256 (hex) of a cached floor file's bytes, beside it."""
    return path.with_suffix(".sha256")
