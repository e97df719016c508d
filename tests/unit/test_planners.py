"""The ego-only floor and the reference planners in planners/: determinism, caching, known answers, contract."""

from __future__ import annotations

import importlib.util
import io
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

from pytest_drivedegrade import floor
from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.data.frame import Command, EgoStatus, Frame, command_from_future
from pytest_drivedegrade.metrics.trajectory import l2_avg, l2_per_step
from pytest_drivedegrade.planning import planner_cameras, planner_fingerprint, predict_checked

ROOT = Path(__file__).resolve().parents[2]
PLANNERS = ROOT / "planners"
T = 0.5 * np.arange(1, 7)
FAST = {**floor.SETTINGS, "steps": 300}


def synthetic_frames(n: int, seed: int = 0) -> list[Frame]:
    """Frames whose future follows a noisy constant-acceleration, constant-turn-rate model of the ego status."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        v, a, w = rng.uniform(0, 12), rng.uniform(-2, 1.5), rng.uniform(-0.25, 0.25)
        speed = np.maximum(v + a * T, 0.0)
        heading = w * T
        step = 0.5 * speed
        future = np.cumsum(np.stack([step * np.cos(heading), step * np.sin(heading)], axis=1), axis=0)
        past = -np.arange(4, 0, -1)[:, None] * np.array([0.5 * v, 0.0])
        ego = EgoStatus((v, 0.0), (a, 0.0), w, past)
        gt = future + rng.normal(0, 0.05, future.shape)
        frames.append(Frame(f"f{i}", "s", i, {}, ego, command_from_future(gt), gt, np.ones(6, bool), ()))
    return frames


def state_bytes(model: torch.nn.Module) -> bytes:
    buf = io.BytesIO()
    for key, tensor in model.state_dict().items():
        buf.write(key.encode() + tensor.numpy().tobytes())
    return buf.getvalue()


# --- the ego-only floor ------------------------------------------------------------------------------------


def test_floor_training_is_bit_identical_and_seed_dependent() -> None:
    x, y = floor.frames_to_arrays(synthetic_frames(200))
    a = floor.fit_arrays(x, y, seed=0, settings=FAST)
    b = floor.fit_arrays(x, y, seed=0, settings=FAST)
    c = floor.fit_arrays(x, y, seed=1, settings=FAST)
    assert state_bytes(a) == state_bytes(b)
    assert a.fingerprint() == b.fingerprint() != c.fingerprint()
    assert state_bytes(a) != state_bytes(c)


def test_floor_training_leaves_global_torch_state_alone() -> None:
    threads, det = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    floor.fit_arrays(*floor.frames_to_arrays(synthetic_frames(20)), settings={**FAST, "steps": 5})
    assert torch.equal(torch.rand(3), expected)
    assert (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()) == (threads, det)


def test_floor_learns_the_ego_dynamics() -> None:
    """On held-out synthetic frames the floor beats constant velocity (which ignores acceleration and turning)."""
    model = floor.train_floor(synthetic_frames(600, seed=0), settings={**floor.SETTINGS, "steps": 1000})
    test = synthetic_frames(200, seed=1)
    cv = load_planner_module("constant_velocity").ConstantVelocity()
    floor_l2 = np.mean([l2_avg(l2_per_step(model.predict({}, f.ego, f.command), f.gt_future)) for f in test])
    cv_l2 = np.mean([l2_avg(l2_per_step(cv.predict({}, f.ego, f.command), f.gt_future)) for f in test])
    assert floor_l2 < 0.6 * cv_l2
    assert floor_l2 < 0.5


def test_floor_features_and_contract() -> None:
    f = synthetic_frames(1)[0]
    feats = floor.ego_features(f.ego, Command.LEFT)
    assert feats.shape == (floor.FEATURE_SIZE,) and feats.dtype == np.float32
    assert feats[-3:].tolist() == [0.0, 1.0, 0.0]
    model = floor.EgoMLP()
    assert planner_cameras(model) == () and model.name == "ego_mlp"
    out = predict_checked(model, {}, f.ego, f.command, f.token)
    assert out.shape == (6, 2)


def test_no_scorable_frames_is_a_clear_error() -> None:
    f = synthetic_frames(1)[0]
    unscorable = Frame(f.token, "s", 0, {}, f.ego, f.command, f.gt_future, np.zeros(6, bool), ())
    with pytest.raises(ValueError, match="no scorable frames"):
        floor.train_floor([unscorable])


class FakeReader:
    """The part of NuScenesReader the floor uses."""

    def __init__(self, frames: list[Frame], fingerprint: str) -> None:
        self._frames, self._fingerprint, self.calls, self.agents = frames, fingerprint, 0, []

    def fingerprint(self) -> str:
        return self._fingerprint

    def scorable_frames(self, limit=None, *, agents=True):
        self.calls += 1
        self.agents.append(agents)
        return [f for f in self._frames if f.scorable]


def test_floor_is_cached_by_dataset_fingerprint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(floor, "SETTINGS", FAST)
    reader = FakeReader(synthetic_frames(100), "data-A")
    first = floor.load_or_train_floor(reader, tmp_path)
    second = floor.load_or_train_floor(reader, tmp_path)
    assert reader.calls == 1  # the second call loaded the cache
    assert reader.agents == [False]  # the floor reads no boxes (`test_reader`: the same training arrays)
    assert state_bytes(first) == state_bytes(second)
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".pt", ".sha256"]  # the floor, its digest, no temporary
    other = FakeReader(synthetic_frames(100, seed=5), "data-B")
    floor.load_or_train_floor(other, tmp_path)
    assert other.calls == 1 and len(list(tmp_path.iterdir())) == 4
    # A corrupt cache entry is retrained, not fatal.
    for p in tmp_path.iterdir():
        p.write_bytes(b"garbage")
    assert state_bytes(floor.load_or_train_floor(reader, tmp_path)) == state_bytes(first)


def test_a_floor_cache_file_edited_into_other_weights_is_retrained_not_trusted(tmp_path: Path,
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """Attack on the floor's cache: its file replaced by other, well-formed weights (a floor that would put blind's
    L2 below or above it at will, and so steer the floor comparison and the memo check) must not be loaded. The
    file's bytes are checked against the sha256 written beside it; a file whose digest does not match, or that has
    none, is retrained, so the run's floor is the one its data trains, byte for byte."""
    monkeypatch.setattr(floor, "SETTINGS", FAST)
    reader = FakeReader(synthetic_frames(100), "data-A")
    honest = state_bytes(floor.load_or_train_floor(reader, tmp_path))
    (cached,) = tmp_path.glob("*.pt")
    assert {p.name for p in tmp_path.iterdir()} == {cached.name, cached.with_suffix(".sha256").name}
    forged = {k: v + 1.0 if v.is_floating_point() else v for k, v in torch.load(cached, weights_only=True).items()}
    buf = io.BytesIO()
    torch.save(forged, buf)
    cached.write_bytes(buf.getvalue())  # loads cleanly: only its digest gives it away
    assert state_bytes(floor.load_or_train_floor(reader, tmp_path)) == honest
    assert reader.calls == 2  # retrained, and the cache holds the honest floor again
    assert state_bytes(floor.load_or_train_floor(reader, tmp_path)) == honest and reader.calls == 2
    cached.write_bytes(buf.getvalue())
    cached.with_suffix(".sha256").unlink()  # no digest at all: retrained as well
    assert state_bytes(floor.load_or_train_floor(reader, tmp_path)) == honest and reader.calls == 3


# --- reference planners --------------------------------------------------------------------------------------


def load_planner_module(stem: str) -> ModuleType:
    """Import planners/<stem>.py as a module (it is a pytest plugin file, not a package module)."""
    name = f"_drivedegrade_planner_{stem}"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, PLANNERS / f"{stem}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def test_constant_velocity_known_answer() -> None:
    cv = load_planner_module("constant_velocity").ConstantVelocity()
    ego = EgoStatus((4.0, -1.0), (3.0, 0.0), 0.5)
    out = cv.predict({}, ego, Command.LEFT)
    np.testing.assert_allclose(out, np.stack([4.0 * T, -1.0 * T], axis=1))
    assert planner_cameras(cv) == ()


def test_template_runs_through_the_contract() -> None:
    mod = load_planner_module("template")
    plan = mod.MyPlanner()
    ego = EgoStatus((3.0, 4.0), (0.0, 0.0), 0.0)
    out = predict_checked(plan, {}, ego, Command.STRAIGHT, "t")
    np.testing.assert_allclose(out[:, 0], 5.0 * T)
    assert set(planner_cameras(plan)) <= set(CAMERAS)
    assert len(planner_fingerprint(plan, PLANNERS / "template.py")) == 64


def test_retrained_weights_change_the_fingerprint_even_behind_a_constant_one(tmp_path) -> None:
    """Trust case 5: a new weights file must change the run key. The template hashes the file it loads, and a
    planner whose fingerprint() is a constant still changes with the state_dict it actually holds."""
    mod = load_planner_module("template")
    weights = tmp_path / "my_planner.pt"
    weights.write_bytes(b"weights v1")
    fp1 = planner_fingerprint(mod.MyPlanner(weights), PLANNERS / "template.py")
    weights.write_bytes(b"weights v2, retrained")
    assert planner_fingerprint(mod.MyPlanner(weights), PLANNERS / "template.py") != fp1
    assert planner_fingerprint(mod.MyPlanner(), PLANNERS / "template.py") != fp1

    class Constant:
        fingerprint = "my-model"

        def __init__(self) -> None:
            self.model = torch.nn.Linear(2, 2)

    a, b = Constant(), Constant()
    with torch.no_grad():
        b.model.weight.copy_(a.model.weight + 1e-3)
        b.model.bias.copy_(a.model.bias)
    assert planner_fingerprint(a, tmp_path / "p.py") != planner_fingerprint(b, tmp_path / "p.py")
    with torch.no_grad():
        b.model.weight.copy_(a.model.weight)
    assert planner_fingerprint(a, tmp_path / "p.py") == planner_fingerprint(b, tmp_path / "p.py")


# --- planner files through a pytest fixture ------------------------------------------------------------------

CONTRACT_TEST = """
import numpy as np
from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.planning import Command, EgoStatus, planner_cameras, predict_checked

def test_contract(planner):
    rng = np.random.default_rng(0)
    images = {c: rng.integers(0, 256, (450, 800, 3), dtype=np.uint8) for c in CAMERAS}
    for img in images.values():
        img.flags.writeable = False  # as the suite delivers them: a planner that writes raises here
    ego = EgoStatus((6.0, 0.1), (0.5, 0.0), 0.02, np.array([[-12.0, 0], [-9, 0], [-6, 0], [-3, 0]]))
    outs = [predict_checked(planner, images, ego, cmd, "tok") for cmd in Command]
    assert all(o.shape == (6, 2) and np.isfinite(o).all() for o in outs)
    assert 0.5 < outs[2][-1, 0] < 40.0  # driving forward at 6 m/s covers a plausible distance in 3 s
    dark = {c: np.zeros((450, 800, 3), np.uint8) for c in CAMERAS}
    assert np.isfinite(predict_checked(planner, dark, ego, Command.STRAIGHT, "dark")).all()
    again = predict_checked(planner, images, ego, Command.STRAIGHT, "tok")
    assert np.array_equal(again, outs[2])  # deterministic: the null control needs bit-identical reruns
    assert set(planner_cameras(planner)) <= set(CAMERAS)
"""


@pytest.mark.parametrize("stem", ["constant_velocity", "camera_cnn", "template"])
def test_planner_file_fixture_runs_through_the_contract(pytester: pytest.Pytester, stem: str) -> None:
    """Each planner file, loaded as a pytest plugin (-p), provides a `planner` fixture that meets the contract."""
    pytester.syspathinsert(PLANNERS)
    pytester.makepyfile(test_contract=CONTRACT_TEST)
    result = pytester.runpytest_inprocess("-p", stem, "-p", "no:cacheprovider", "-q")
    result.assert_outcomes(passed=1)


def test_committed_camera_weights_are_small_traceable_and_load_offline() -> None:
    """camera_cnn.pt is under 2 MB, its sidecar names the data set and matches its bytes, and it loads locally."""
    import hashlib
    import json

    weights = PLANNERS / "camera_cnn.pt"
    sidecar = json.loads(weights.with_suffix(".json").read_text())
    assert weights.stat().st_size < 2_000_000
    assert sidecar["weights_sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    assert len(sidecar["dataset_fingerprint"]) >= 16 and sidecar["split"] == "train"
    mod = load_planner_module("camera_cnn")
    plan = mod.CameraCNNPlanner()
    assert planner_cameras(plan) == ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT")
    assert plan.trained_on["settings"] == sidecar["settings"]
