"""Template: copy this file, fill in the three marked places, and run

    pytest --drivedegrade path/to/myplanner.py -n 2

The suite imports this file as a pytest plugin only when ``--drivedegrade`` is given, asks for the fixture
named ``planner`` and calls ``planner.predict(images, ego, cmd)`` once per frame and cell. The same fixture may
live in your own ``conftest.py`` instead; then plain ``pytest --drivedegrade`` certifies it.

The contract (SPEC section 2):

- ``images``: dict camera name -> H x W x 3 uint8 RGB array, read-only, all six cameras, already degraded by
  the suite. Copy before you modify; resize and normalise inside ``predict``.
- ``ego``: ``EgoStatus``: ``velocity`` (vx, vy) m/s, ``acceleration`` (ax, ay) m/s^2, ``yaw_rate`` rad/s,
  ``past_xy`` (4, 2) past positions in the current ego frame, oldest first; ``ego.as_vector()`` flattens it.
- ``cmd``: ``Command`` (RIGHT=0, LEFT=1, STRAIGHT=2).
- return: a finite (6, 2) float array, waypoints at t = 0.5 .. 3.0 s, metres, x forward, y left.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest

from pytest_drivedegrade.constants import HORIZON_STEPS, STEP_SECONDS
from pytest_drivedegrade.planning import Command, EgoStatus

HERE = Path(__file__).resolve().parent


class MyPlanner:
    """Replace the body of ``predict`` with your model's inference."""

    # (1) The cameras your model reads. The null control blacks out the others and demands bit-identical
    #     output, so declare exactly what you read. Omit the attribute to declare all six.
    cameras: tuple[str, ...] = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT")
    # Optional: the report folder name (default: this file's stem).
    name = "my_planner"
    # Optional (default True): the same inputs give the same plan. Then, without a reset(), a frame whose inputs
    # equal the clean cell's on every camera declared above (blackout of cameras it does not read, frame_dropout
    # frames that dropped none of them) reuses the clean plan instead of calling predict. Set False for a
    # sampling planner; a GPU model should seed itself and use deterministic kernels instead.
    deterministic = True

    def __init__(self, weights: Path | None = None) -> None:
        # (2) Load the model here. The fixture is session-scoped, so this runs once per pytest worker
        #     (once per process under -n 2), never once per frame.
        #     e.g. self.model = torch.jit.load(weights).eval(); torch.set_num_threads(1)
        #     The run's --drivedegrade-device (cpu, cuda, cuda:N) is planner_device() (from
        #     pytest_drivedegrade.planning), or drivedegrade_context.device in a fixture that requests it.
        self.weights = weights

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command) -> np.ndarray:
        # (3) Inference. Read only the cameras declared above; never write into `images`.
        #     This placeholder drives straight on at the current speed.
        speed = float(np.hypot(*ego.velocity))
        t = STEP_SECONDS * np.arange(1, HORIZON_STEPS + 1)
        return np.stack([speed * t, np.zeros_like(t)], axis=1)

    def fingerprint(self) -> str:
        """Optional: identifies the weights in the certificate and the run key (the suite adds this file's source
        and any torch state_dict it finds). Hash what you load: a constant here would let a retrained model
        reuse the stored cells of the old one."""
        if self.weights is None or not Path(self.weights).is_file():
            return "my_planner-untrained"
        return hashlib.sha256(Path(self.weights).read_bytes()).hexdigest()


@pytest.fixture(scope="session")
def planner() -> MyPlanner:
    """The planner the suite certifies: built once per worker process."""
    return MyPlanner(HERE / "my_planner.pt")
