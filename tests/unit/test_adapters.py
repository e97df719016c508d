"""The example adapters in planners/examples: the img_metas the mmdet3d-style adapter builds (resize geometry,
LIDAR_TOP fallback, normalisation, CAN-bus delta, prev_bev across scenes) and NAVSIM's stitching geometry."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import MappingProxyType, ModuleType

import numpy as np
import pytest
import torch

from pytest_drivedegrade.data import geometry as geo
from pytest_drivedegrade.data.context import CameraCalibration, FrameContext
from pytest_drivedegrade.data.frame import Command, EgoStatus

EXAMPLES = Path(__file__).resolve().parents[2] / "planners" / "examples"
#: nuScenes-like mounting yaws (degrees, left positive) of the six cameras.
YAWS = {"CAM_FRONT": 0, "CAM_FRONT_RIGHT": -55, "CAM_FRONT_LEFT": 55, "CAM_BACK": 180, "CAM_BACK_LEFT": 110,
        "CAM_BACK_RIGHT": -110}


def load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def mm() -> ModuleType:
    return load("mmdet3d_style")


@pytest.fixture(scope="module")
def nav() -> ModuleType:
    return load("navsim_style")


@pytest.fixture
def one_thread():
    """As the adapters' fixtures run them."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def context(token: str = "t0", scene: str = "scene-a", index: int = 0, *, size: tuple[int, int] = (1600, 900),
            xy: tuple[float, float] = (100.0, 50.0), yaw: float = 0.3,
            lidar2ego: np.ndarray | None = None) -> FrameContext:
    """A frame context with a nuScenes-like rig at `size`, the ego at `xy` heading `yaw`, speed 5 m/s; with
    `lidar2ego`, a LIDAR_TOP calibration (lidar2img as the suite builds it)."""
    w, h = size
    cal = {}
    for cam, deg in YAWS.items():
        k = geo.intrinsic_matrix(1266.0 * w / 1600, w, h)
        cal[cam] = CameraCalibration(k, geo.transform(geo.camera_rotation(np.radians(deg)), (1.0, 0.0, 1.5)), size)
    lidar2img = None
    if lidar2ego is not None:
        lidar2img = {}
        for cam, c in cal.items():
            pad = np.eye(4)
            pad[:3, :3] = c.intrinsic
            lidar2img[cam] = pad @ geo.invert(c.sensor2ego) @ lidar2ego
    q = geo.yaw_to_quat(yaw)
    degrees = np.degrees(yaw) % 360
    can_bus = np.array([*xy, 0.0, *q, 0.1, 0.0, 0.0, 0.0, 0.0, 0.02, 5.0, 0.0, 0.0, np.radians(degrees), degrees])
    return FrameContext(token, scene, scene, index, 1_500_000_000 + 500_000 * index,
                        geo.transform(q, (*xy, 0.0)), MappingProxyType(cal),
                        None if lidar2img is None else MappingProxyType(lidar2img), can_bus)


def images(size: tuple[int, int] = (1600, 900), seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = {}
    for cam in YAWS:
        img = rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
        img.setflags(write=False)
        out[cam] = img
    return out


def project(matrix: np.ndarray, point: np.ndarray) -> np.ndarray:
    p = matrix @ np.append(point, 1.0)
    return p[:2] / p[2]


EGO = EgoStatus((5.0, 0.0), (0.1, 0.0), 0.02, np.array([[-8.0, 0], [-6, 0], [-4, 0], [-2, 0]]))


# -- mmdet3d-style: geometry --------------------------------------------------------------------------------

@pytest.mark.parametrize("width, scale", [(640, 0.4), (800, 0.5), (1600, 1.0)])
def test_resize_scales_lidar2img_and_intrinsics(mm, width, scale):
    """A 3-D point projects at `scale` times its 1600 x 900 pixel coordinates with the resized matrices, and the
    shapes are those of RandomScaleImageMultiViewImage then PadMultiViewImage."""
    ctx = context()
    full = mm.build_img_metas(ctx, scale=1.0, norm=mm.NORM_VAD)
    metas = mm.build_img_metas(ctx, scale=width / 1600, norm=mm.NORM_VAD)
    lidar2ego = mm.NOMINAL_LIDAR2EGO
    point_ego = np.array([20.0, 1.5, 0.8])  # 20 m ahead, in CAM_FRONT's view
    point_lidar = geo.apply(geo.invert(lidar2ego), point_ego[None])[0]
    i = mm.CAMERA_ORDER.index("CAM_FRONT")
    u_full = project(full["lidar2img"][i], point_lidar)
    assert 0 < u_full[0] < 1600 and 0 < u_full[1] < 900
    np.testing.assert_allclose(project(metas["lidar2img"][i], point_lidar), scale * u_full, rtol=1e-12)
    # the same point through the camera calibration directly: the virtual LIDAR_TOP is consistent
    cal = ctx.calibration["CAM_FRONT"]
    direct, _ = geo.project(geo.apply(geo.invert(cal.sensor2ego), point_ego[None]), cal.intrinsic)
    np.testing.assert_allclose(u_full, direct[0], rtol=1e-12)
    # intrinsics scale the same way, and lidar2img = cam_intrinsic @ lidar2cam as in UniAD's dataset
    np.testing.assert_allclose(metas["cam_intrinsic"][i][:2, :3], scale * full["cam_intrinsic"][i][:2, :3])
    for l2i, k, l2c in zip(metas["lidar2img"], metas["cam_intrinsic"], metas["lidar2cam"]):
        np.testing.assert_allclose(l2i, k @ l2c, atol=1e-9)
    h, w = int(900 * scale), int(1600 * scale)
    assert metas["img_shape"] == [(h, w, 3)] * 6 and metas["ori_shape"] == metas["img_shape"]
    assert metas["pad_shape"] == [(-(-h // 32) * 32, -(-w // 32) * 32, 3)] * 6
    assert metas["scale_factor"] == scale


def test_resized_image_content_sits_where_the_scaled_matrix_projects(mm):
    """A bright square drawn where a 3-D point projects at 1600 x 900 is found, after the adapter's resize,
    where the scaled lidar2img projects the point (within a pixel)."""
    ctx, scale = context(), 0.4
    metas = mm.build_img_metas(ctx, scale=scale, norm=mm.NORM_VAD)
    full = mm.build_img_metas(ctx, scale=1.0, norm=mm.NORM_VAD)
    i = mm.CAMERA_ORDER.index("CAM_FRONT")
    point = geo.apply(geo.invert(mm.NOMINAL_LIDAR2EGO), np.array([[15.0, -2.0, 1.0]]))[0]
    u, v = np.round(project(full["lidar2img"][i], point)).astype(int)
    imgs = {cam: np.zeros((900, 1600, 3), np.uint8) for cam in YAWS}
    imgs["CAM_FRONT"][v - 10: v + 11, u - 10: u + 11] = 255
    batch = mm.multiview_image(imgs, scale, mm.NORM_VAD)
    rgb = batch[i] * np.array(mm.NORM_VAD["std"])[:, None, None] + np.array(mm.NORM_VAD["mean"])[:, None, None]
    ys, xs = np.nonzero(rgb[0] > 128)
    found = np.array([xs.mean(), ys.mean()])
    np.testing.assert_allclose(found, project(metas["lidar2img"][i], point), atol=1.0)


def test_lidar2img_of_the_data_set_is_used_when_present(mm):
    """With a LIDAR_TOP calibration the adapter passes the data set's lidar2img through (then scales it) and
    recovers its lidar2ego; the nominal mount is only the fallback."""
    lidar2ego = geo.transform(geo.yaw_to_quat(-1.2), (0.5, 0.1, 1.7))
    ctx = context(size=(800, 450), lidar2ego=lidar2ego)
    found, l2i = mm.lidar_frame(ctx)
    np.testing.assert_allclose(found, lidar2ego, atol=1e-9)
    for cam in mm.CAMERA_ORDER:
        np.testing.assert_array_equal(l2i[cam], ctx.lidar2img[cam])
    metas = mm.build_img_metas(ctx, scale=0.8, norm=mm.NORM_VAD)
    np.testing.assert_allclose(metas["lidar2img"][0], mm.scale_matrix(0.8) @ ctx.lidar2img["CAM_FRONT"])
    np.testing.assert_allclose(metas["lidar2ego_translation"], (0.5, 0.1, 1.7), atol=1e-9)


@pytest.mark.parametrize("norm_name", ["NORM_VAD", "NORM_UNIAD"])
def test_normalisation_channel_order_and_padding(mm, norm_name):
    """VAD: RGB, (x - mean) / std; UniAD: BGR (as mmcv.imread loads it), mean only; zero padding below."""
    norm = getattr(mm, norm_name)
    imgs = {cam: np.broadcast_to(np.array([200, 100, 50], np.uint8), (450, 800, 3)) for cam in YAWS}
    batch = mm.multiview_image(imgs, 0.8, norm)
    assert batch.shape == (6, 3, 384, 640) and batch.dtype == np.float32
    channels = (200, 100, 50) if norm["to_rgb"] else (50, 100, 200)
    expected = (np.array(channels) - np.array(norm["mean"])) / np.array(norm["std"])
    np.testing.assert_allclose(batch[:, :, :360, :].mean(axis=(0, 2, 3)), expected, rtol=1e-5)
    assert not batch[:, :, 360:, :].any()


def test_img_metas_keys_and_values(mm):
    ctx = context(token="tok", index=3)
    metas = mm.build_img_metas(ctx, scale=0.5, norm=mm.NORM_UNIAD, prev_idx="prev")
    for key in ("sample_idx", "scene_token", "frame_idx", "prev_idx", "next_idx", "timestamp", "can_bus",
                "ego2global_translation", "ego2global_rotation", "lidar2ego_translation", "lidar2ego_rotation",
                "l2g_r_mat", "l2g_t", "lidar2img", "cam_intrinsic", "lidar2cam", "img_shape", "ori_shape",
                "pad_shape", "img_norm_cfg"):
        assert key in metas, key
    assert (metas["sample_idx"], metas["scene_token"], metas["frame_idx"], metas["prev_idx"]) == \
        ("tok", "scene-a", 3, "prev")
    assert metas["timestamp"] == pytest.approx(1501.5)
    np.testing.assert_allclose(metas["ego2global_rotation"], geo.yaw_to_quat(0.3))
    np.testing.assert_array_equal(metas["can_bus"], ctx.can_bus)
    # UniAD's row-vector lidar -> global: a lidar point through l2g equals lidar -> ego -> global
    p = np.array([1.0, 2.0, 3.0])
    direct = geo.apply(np.asarray(ctx.ego2global) @ mm.NOMINAL_LIDAR2EGO, p[None])[0]
    np.testing.assert_allclose(p @ metas["l2g_r_mat"] + metas["l2g_t"], direct, rtol=1e-5)


# -- mmdet3d-style: temporal state ------------------------------------------------------------------------

def test_can_bus_delta_is_zero_at_the_first_frame_then_the_motion(mm, one_thread):
    planner = mm.Mmdet3dStylePlanner(input_width=320)
    imgs = images((800, 450))
    planner.reset("scene-a")
    planner.predict(imgs, EGO, Command.STRAIGHT, context(size=(800, 450)))
    first = planner.last_img_metas
    assert not first["prev_bev_exists"] and first["prev_idx"] == ""
    np.testing.assert_array_equal(first["can_bus"][:3], 0.0)
    assert first["can_bus"][-1] == 0.0
    np.testing.assert_array_equal(first["can_bus"][3:-1], context().can_bus[3:-1])  # the rest untouched
    planner.predict(imgs, EGO, Command.STRAIGHT, context("t1", index=1, size=(800, 450), xy=(102.0, 50.5),
                                                          yaw=0.35))
    second = planner.last_img_metas
    assert second["prev_bev_exists"] and second["prev_idx"] == "t0"
    np.testing.assert_allclose(second["can_bus"][:3], [2.0, 0.5, 0.0])
    assert second["can_bus"][-1] == pytest.approx(np.degrees(0.05))


def test_prev_bev_is_dropped_on_a_scene_change_with_or_without_reset(mm, one_thread):
    """A new scene seen only in the context, or announced by reset(), leaves the planner exactly as fresh."""
    imgs = images((800, 450))
    frames_a = [context(f"a{i}", "scene-a", i, size=(800, 450), xy=(100.0 + 2 * i, 50.0)) for i in range(3)]
    first_b = context("b0", "scene-b", 0, size=(800, 450), xy=(-40.0, 7.0), yaw=-1.0)
    fresh = mm.Mmdet3dStylePlanner(input_width=320)
    expected = fresh.predict(imgs, EGO, Command.LEFT, first_b)

    for announce in (False, True):
        planner = mm.Mmdet3dStylePlanner(input_width=320)
        planner.reset("scene-a")
        plans = [planner.predict(imgs, EGO, Command.LEFT, c) for c in frames_a]
        assert planner.prev_frame_info["prev_bev"] is not None
        assert not np.array_equal(plans[0], plans[1]) or not np.array_equal(plans[1], plans[2])
        if announce:
            planner.reset("scene-b")
            assert planner.prev_frame_info["prev_bev"] is None
        got = planner.predict(imgs, EGO, Command.LEFT, first_b)
        metas = planner.last_img_metas
        assert not metas["prev_bev_exists"] and metas["prev_idx"] == ""
        np.testing.assert_array_equal(metas["can_bus"][:3], 0.0)
        np.testing.assert_array_equal(got, expected)


def test_mmdet3d_style_plan_is_deterministic_and_leaves_inputs_alone(mm, one_thread):
    imgs = images((800, 450))
    before = {k: v.copy() for k, v in imgs.items()}
    ctxs = [context(f"a{i}", index=i, size=(800, 450), xy=(100.0 + 2 * i, 50.0)) for i in range(2)]
    runs = []
    for _ in range(2):
        planner = mm.Mmdet3dStylePlanner()
        planner.reset("scene-a")
        runs.append([planner.predict(imgs, EGO, Command.STRAIGHT, c) for c in ctxs])
    for a, b in zip(*runs):
        assert a.shape == (6, 2) and a.dtype == np.float64 and np.isfinite(a).all()
        np.testing.assert_array_equal(a, b)
    assert runs[0][0][-1, 0] > 10  # about 5 m/s for 3 s ahead, x forward in the ego frame
    for k, v in imgs.items():
        np.testing.assert_array_equal(v, before[k])


# -- NAVSIM-style ---------------------------------------------------------------------------------------------

def test_navsim_crop_scales_with_the_image(nav):
    assert nav.crop_box(1920, 1080) == (28, 416)  # NAVSIM's own numbers
    assert nav.crop_box(1600, 900) == (23, 347)
    assert nav.crop_box(800, 450) == (12, 173)


@pytest.mark.parametrize("size", [(800, 450), (1600, 900), (1920, 1080)])
def test_navsim_stitching_geometry(nav, size):
    """1024 x 256, left | front | right in NAVSIM's order and proportions; the cropped rows and columns gone."""
    w, h = size
    rows, side = nav.crop_box(w, h)
    colours = {"CAM_FRONT_LEFT": (255, 0, 0), "CAM_FRONT": (0, 255, 0), "CAM_FRONT_RIGHT": (0, 0, 255)}
    imgs = {}
    for cam, colour in colours.items():
        img = np.empty((h, w, 3), np.uint8)
        img[:] = colour
        img[:rows] = img[h - rows:] = 255  # cropped rows: white
        if cam != "CAM_FRONT":
            img[:, :side] = img[:, w - side:] = 255  # cropped side columns: white
        img.setflags(write=False)
        imgs[cam] = img
    for cam in ("CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"):
        imgs[cam] = np.full((h, w, 3), 128, np.uint8)
    out = nav.stitch_front(imgs)
    assert out.shape == (256, 1024, 3) and out.dtype == np.uint8
    assert not (out == 255).all(axis=2).any()  # nothing of the cropped parts survives
    side_w = (w - 2 * side) / (2 * (w - 2 * side) + w) * 1024  # 272 px for NAVSIM's 1088 | 1920 | 1088
    assert side_w == pytest.approx(272, abs=1)
    for x0, x1, colour in ((0, side_w - 2, (255, 0, 0)), (side_w + 2, 1024 - side_w - 2, (0, 255, 0)),
                           (1024 - side_w + 2, 1024, (0, 0, 255))):
        np.testing.assert_array_equal(out[:, int(np.ceil(x0)): int(x1)], np.broadcast_to(colour, (256, int(x1)
                                      - int(np.ceil(x0)), 3)))
    feature = nav.camera_feature(imgs)
    assert feature.shape == (3, 256, 1024) and float(feature.max()) <= 1.0


def test_navsim_status_vector(nav):
    ego = EgoStatus((4.0, 0.5), (-1.0, 0.2), 0.0, np.zeros((4, 2)))
    for cmd, onehot in ((Command.LEFT, [1, 0, 0, 0]), (Command.STRAIGHT, [0, 1, 0, 0]),
                        (Command.RIGHT, [0, 0, 1, 0])):
        np.testing.assert_allclose(nav.status_feature(ego, cmd).numpy(), [*onehot, 4.0, 0.5, -1.0, 0.2])


def test_navsim_agent_reads_only_the_front_and_is_deterministic(nav, one_thread):
    agent = nav.NavsimStyleAgent()
    assert agent.cameras == ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT")
    imgs = images((800, 450))
    plan = agent.predict(imgs, EGO, Command.STRAIGHT)
    assert plan.shape == (6, 2) and plan.dtype == np.float64 and np.isfinite(plan).all()
    rear_black = {k: (np.zeros_like(v) if "BACK" in k else v) for k, v in imgs.items()}
    np.testing.assert_array_equal(nav.NavsimStyleAgent().predict(rear_black, EGO, Command.STRAIGHT), plan)
    front_black = {k: (np.zeros_like(v) if k == "CAM_FRONT" else v) for k, v in imgs.items()}
    assert not np.array_equal(agent.predict(front_black, EGO, Command.STRAIGHT), plan)


# -- both: the run's device -----------------------------------------------------------------------------------

def _example_plans(module: ModuleType, agent) -> list[np.ndarray]:
    imgs = images((800, 450))
    if hasattr(agent, "reset"):
        agent.reset("scene-a")
        ctxs = [context(f"a{i}", index=i, size=(800, 450), xy=(100.0 + 2 * i, 50.0)) for i in range(2)]
        return [agent.predict(imgs, EGO, Command.LEFT, c) for c in ctxs]
    return [agent.predict(imgs, EGO, cmd) for cmd in (Command.LEFT, Command.STRAIGHT)]


@pytest.mark.parametrize("name", ["navsim_style", "mmdet3d_style"])
def test_the_example_fixtures_build_the_model_on_the_run_device(name, monkeypatch, one_thread):
    """The `planner` fixture puts the model on --drivedegrade-device ($DRIVEDEGRADE_DEVICE): every parameter and
    buffer on torch's `meta` device when asked for it; on `cpu` the plans are the default-built adapter's, bit for
    bit; on CUDA (where present) within float rounding of them."""
    module = load(name)
    cls = module.NavsimStyleAgent if name == "navsim_style" else module.Mmdet3dStylePlanner

    def built(device: str):
        monkeypatch.setenv("DRIVEDEGRADE_DEVICE", device)
        fixture = module.planner.__wrapped__()  # the fixture's own generator, as pytest runs it
        agent = next(fixture)
        fixture.close()
        return agent

    meta = built("meta")
    tensors = [*meta.model.parameters(), *meta.model.buffers()]
    assert tensors and {t.device.type for t in tensors} == {"meta"}
    reference = _example_plans(module, cls())
    for got, want in zip(_example_plans(module, built("cpu")), reference):
        np.testing.assert_array_equal(got, want)
    if torch.cuda.is_available():
        for got, want in zip(_example_plans(module, built("cuda")), reference):
            np.testing.assert_allclose(got, want, atol=1e-4)
