"""Shared test fixtures: the six real nuScenes frames shipped in tests/data/nuscenes (see its README)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import settings

DATA = Path(__file__).parent / "data" / "nuscenes"

#: Hypothesis's default deadline (200 ms per example) fails a property test by the clock, not by its values: on a
#: machine at a load of 15 on 2 cores an example that takes 30 ms quiet takes several hundred. The suite's
#: properties judge values only; the tests that set `deadline=None` themselves said so one by one, and the rest
#: (test_settings, test_shard_partition, test_closed_cells) inherited the default.
settings.register_profile("drivedegrade", deadline=None)
settings.load_profile("drivedegrade")


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config: pytest.Config) -> None:
    """Under ``-n`` the tests marked ``xdist_group("ray")`` share one worker (xdist's ``loadgroup``, which spreads
    every other test as ``load`` does): their stray-daemon check counts each Ray daemon that appeared during a
    test, so another worker's Ray run at the same time would be counted as left behind."""
    if getattr(config.option, "dist", "no") == "load":
        config.option.dist = "loadgroup"


@pytest.fixture(scope="session")
def small_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 train scenes and 1 val scene with rendered val images (a few seconds, once per test process): the one
    small world the plugin's end-to-end runs (`plugin_support`) and the content fingerprint tests share. Read
    only: a test that edits files copies it first."""
    from pytest_drivedegrade.data.world import write_world

    return write_world(tmp_path_factory.mktemp("w"), scenes=3, seed=1)


@pytest.fixture(scope="session")
def eleven_scene_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """11 scenes (9 train, tables only; 2 val with rendered images), once per test process: shared by the shard
    runs (tests/e2e/test_shards.py) and the scale tests (tests/unit/test_scale.py). Read only."""
    from pytest_drivedegrade.data.world import write_world

    return write_world(tmp_path_factory.mktemp("w11"), scenes=11, seed=2)


@pytest.fixture(scope="session")
def nuscenes_frames():
    """camera name -> (path, RGB uint8 1600x900 image) for the one real keyframe."""
    from pytest_drivedegrade.corruptions.preview import camera_of, read_rgb

    frames = {camera_of(p): (p, read_rgb(p)) for p in sorted(DATA.glob("*.jpg"))}
    assert len(frames) == 6, f"expected six camera frames in {DATA}"
    return frames


@pytest.fixture(scope="session")
def key_material():
    """key file -> what of it must never be written anywhere: the PEM text, each line of its base64 body, and the
    raw 32-byte private key as hex and base64 (the signing key tests grep every output for these)."""
    import base64

    from cryptography.hazmat.primitives import serialization

    from pytest_drivedegrade.certificate.signing import load_private_key

    def material(key: Path) -> list[str]:
        pem = key.read_text()
        raw = load_private_key(pem.encode(), "k").private_bytes(serialization.Encoding.Raw,
                                                                serialization.PrivateFormat.Raw,
                                                                serialization.NoEncryption())
        body = [line for line in pem.splitlines() if line and not line.startswith("-----")]
        return [pem.strip(), *body, raw.hex(), base64.b64encode(raw).decode()]

    return material


@pytest.fixture(scope="session")
def two_scene_world(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """11 scenes, the last two val (rendered): written once per cache, under a lock so xdist workers share it
    (test_examples and test_trust20b_e2e)."""
    import fcntl
    import os
    import shutil

    from pytest_drivedegrade.data.world import write_world
    from pytest_drivedegrade.data.world.build import GENERATOR_VERSION, MANIFEST

    cache = getattr(request.config, "cache", None)
    root = Path(cache.mkdir("drivedegrade-example-tests")) if cache is not None else tmp_path_factory.mktemp("ex")
    target = root / f"world-{GENERATOR_VERSION}-11-seed1"
    with open(root / ".lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (target / MANIFEST).is_file():
            tmp = root / f".tmp-{os.getpid()}"
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.rmtree(target, ignore_errors=True)
            write_world(tmp, scenes=11, seed=1)
            os.replace(tmp, target)
    return target
