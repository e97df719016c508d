"""Reference planner: the camera CNN with a memory. It fuses what the cameras told it on the previous frames of
the scene with what they show now, the way BEV planners carry a previous BEV (UniAD, VAD) or an instance bank
(SparseDrive), and forgets it when the scene changes.

It reuses ``camera_cnn``'s trained network (same weights, no training of its own): the network's scene facts
(``PERCEPTS``: the vehicle ahead, the nearest pedestrian or cyclist, where the road goes) are blended over time,
``fused_t = MEMORY * fused_{t-1} + (1 - MEMORY) * facts_t``, and the plan is made from the fused facts. So a lost
or degraded frame is smoothed by the frames before it, and a stale memory lags a scene that changes quickly.

    pytest --drivedegrade planners/temporal_cnn.py -n 2
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))  # camera_cnn.py beside this file
from camera_cnn import WEIGHTS, CameraCNNPlanner, preprocess  # noqa: E402

from pytest_drivedegrade.constants import HORIZON_STEPS  # noqa: E402
from pytest_drivedegrade.data.context import FrameContext  # noqa: E402
from pytest_drivedegrade.floor import ego_features  # noqa: E402
from pytest_drivedegrade.planning import Command, EgoStatus  # noqa: E402

#: Weight of the memory in the blend (0: camera_cnn itself; the facts of a frame 2 s old weigh MEMORY^4).
MEMORY = 0.4


class TemporalCNNPlanner(CameraCNNPlanner):
    """camera_cnn's network with its scene facts fused over the frames of a scene; ``reset`` forgets them."""

    name = "temporal_cnn"

    def __init__(self, weights: Path = WEIGHTS, memory: float = MEMORY) -> None:
        super().__init__(weights)
        self.memory_weight = float(memory)
        self.facts: torch.Tensor | None = None
        self.scene: str | None = None

    def reset(self, scene_token: str) -> None:
        """A new scene: nothing seen before it is relevant."""
        self.facts, self.scene = None, scene_token

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command,
                context: FrameContext) -> np.ndarray:
        if context.scene_token != self.scene:  # also without a reset call (a stream that starts mid-run)
            self.reset(context.scene_token)
        model = self.model
        pix = torch.from_numpy(np.ascontiguousarray(preprocess(images)[None]))
        with torch.inference_mode():
            z = (torch.from_numpy(ego_features(ego, cmd)[None]) - model.x_mean) / model.x_std
            now = model.perceive(pix, z)
            fused = now if self.facts is None else self.memory_weight * self.facts + (1 - self.memory_weight) * now
            self.facts = fused
            out = model.plan(fused, z)
        return out.numpy().astype(np.float64).reshape(HORIZON_STEPS, 2)


@pytest.fixture(scope="session")
def planner() -> TemporalCNNPlanner:
    """One torch thread per process, as camera_cnn: the same plans under -n 0 and -n 2."""
    torch.set_num_threads(1)
    return TemporalCNNPlanner()
