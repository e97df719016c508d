"""Example adapter: an mmdet3d-style temporal planner (UniAD, VAD, BEVFormer-based) under the suite.

Copy this file and replace ``TinyBEVPlanner`` with your model. What a real UniAD / VAD test loop hands the
model, this adapter builds from the suite's inputs, in the same layout and conventions:

- ``img``: (N_cam, 3, H, W) float32, the cameras in the nuScenes info order (``CAMERA_ORDER``), BGR as
  ``mmcv.imread`` loads them, converted to RGB only when ``img_norm_cfg['to_rgb']`` says so, normalised with
  mmdet3d's ImageNet mean/std (``NORM_UNIAD``: caffe-style BGR mean, std 1; ``NORM_VAD``: torchvision-style
  RGB mean/std), resized by one factor for all cameras as ``RandomScaleImageMultiViewImage(scales=[s])`` does
  (VAD tests at 0.4 of 1600 x 900, UniAD at 1.0), then padded to a multiple of 32 (``PadMultiViewImage``).
- ``img_metas``: the keys UniAD's ``NuScenesE2EDataset.get_data_info`` and ``CustomCollect3D`` put there:
  ``sample_idx``, ``scene_token``, ``frame_idx``, ``prev_idx`` / ``next_idx``, ``timestamp`` (seconds),
  ``ego2global_translation`` / ``_rotation``, ``lidar2ego_translation`` / ``_rotation``, ``l2g_r_mat`` /
  ``l2g_t``, ``can_bus`` (18 values), ``lidar2img`` / ``cam_intrinsic`` / ``lidar2cam`` (one 4x4 per camera),
  ``img_shape`` / ``ori_shape`` / ``pad_shape`` (per camera, (h, w, 3)), ``img_norm_cfg``, ``scale_factor``,
  and ``prev_bev_exists``.
- The resize multiplies ``lidar2img`` and ``cam_intrinsic`` by ``diag(s, s, 1, 1)`` on the left, exactly as
  ``RandomScaleImageMultiViewImage`` does: a 3-D point lands at ``s`` times its pixel coordinates.
- Temporal state, as BEVFormer's / UniAD's ``forward_test`` keeps it in ``prev_frame_info``: ``prev_bev`` is
  dropped when ``scene_token`` changes (the suite also calls ``reset(scene_token)`` before each scene; both
  routes lead to the same state), and the CAN-bus delta trick: ``can_bus[:3]`` and ``can_bus[-1]`` become the
  change of position and heading since the previous frame, zero at a scene's first frame.

**No LIDAR_TOP.** UniAD and VAD live in the LIDAR_TOP frame (x right, y forward, z up): their BEV grid, their
``lidar2img`` and their planned trajectory are expressed there. When the data set has no LIDAR_TOP calibration
(``context.lidar2img is None``, as in the embedded world), this adapter places a virtual LIDAR_TOP where
nuScenes mounts it (``NOMINAL_LIDAR2EGO``: 0.94 m ahead of the rear axle, 1.84 m up, rotated -90 deg about z)
and builds ``lidar2img = K @ inv(cam2ego) @ lidar2ego`` from each camera's calibration, as the suite and
mmdet3d do. (Taking the ego frame itself as the "lidar" frame also projects correctly, but it turns the BEV by
90 degrees relative to what a nuScenes-trained checkpoint learned.) The plan comes back in that frame and is
rotated into the suite's ego frame (x forward, y left).

**Wrapping the real thing.** With UniAD or VAD, ``TinyBEVPlanner`` becomes the detector built from its config
with the checkpoint loaded (``build_model(cfg.model)``, ``load_checkpoint``, ``.eval()``), ``forward_test``
below becomes the model's own ``forward_test(img=[img], img_metas=[[metas]], ...)`` (it already keeps
``prev_frame_info`` and applies the CAN-bus delta: then pass the raw ``can_bus`` and let ``reset`` clear
``model.prev_frame_info``), and the plan is read from its output (UniAD: ``planning['result_planning']
['sdc_traj']``; VAD: the ``ego_fut_preds`` mode of the command, cumulated).

    pytest --drivedegrade planners/examples/mmdet3d_style.py -n 2 --drivedegrade-families jpeg,blackout

Deterministic: fixed seed and one torch thread, so -n 0 and -n 2 agree bit for bit.
Set ``DRIVEDEGRADE_EXAMPLE_LOG=path`` to append one line per ``reset`` and ``predict`` (pid first; the tests
check them).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from typing import Any

import cv2
import numpy as np
import pytest
import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812 - the name every torch code base uses

from pytest_drivedegrade.constants import HORIZON_STEPS, STEP_SECONDS
from pytest_drivedegrade.data import geometry as geo
from pytest_drivedegrade.data.context import FrameContext
from pytest_drivedegrade.planning import Command, EgoStatus, deterministic_cuda, planner_device

#: The camera order of mmdet3d's nuScenes infos (``nuscenes_converter``), which UniAD and VAD keep.
CAMERA_ORDER: tuple[str, ...] = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
                                 "CAM_BACK_RIGHT")
#: UniAD / BEVFormer (ResNet-101 caffe weights): BGR, mean only.
NORM_UNIAD: dict[str, Any] = {"mean": [103.530, 116.280, 123.675], "std": [1.0, 1.0, 1.0], "to_rgb": False}
#: VAD (ResNet-50 torchvision weights): RGB, ImageNet mean and std in 0..255.
NORM_VAD: dict[str, Any] = {"mean": [123.675, 116.28, 103.53], "std": [58.395, 57.12, 57.375], "to_rgb": True}
#: PadMultiViewImage(size_divisor=32), as both test pipelines end.
SIZE_DIVISOR = 32
#: Where nuScenes mounts LIDAR_TOP on the ego (used when the data set has none): x right, y forward.
NOMINAL_LIDAR2EGO_ROTATION = geo.yaw_to_quat(-np.pi / 2)
NOMINAL_LIDAR2EGO_TRANSLATION = (0.943713, 0.0, 1.84023)
NOMINAL_LIDAR2EGO = geo.transform(NOMINAL_LIDAR2EGO_ROTATION, NOMINAL_LIDAR2EGO_TRANSLATION)
LOG_ENV = "DRIVEDEGRADE_EXAMPLE_LOG"


# -- the test-time pipeline: images ---------------------------------------------------------------------

def scale_matrix(scale: float) -> np.ndarray:
    """``RandomScaleImageMultiViewImage``'s matrix: ``diag(s, s, 1, 1)``, applied on the left of lidar2img."""
    out = np.eye(4)
    out[0, 0] = out[1, 1] = scale
    return out


def resized_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """(w, h) after the scale, truncated as ``int(img.shape[i] * rand_scale)`` does."""
    return int(width * scale), int(height * scale)


def multiview_image(images: Mapping[str, np.ndarray], scale: float, norm: Mapping[str, Any],
                    size_divisor: int = SIZE_DIVISOR) -> np.ndarray:
    """The (N_cam, 3, H_pad, W_pad) float32 array the model gets; never writes `images`.

    What the test pipeline does to ``mmcv.imread``'s BGR images: resize (bilinear, ``mmcv.imresize``'s
    default; per channel, so done here on the uint8 image first), ``NormalizeMultiviewImage`` (BGR -> RGB when
    ``to_rgb``, subtract mean, divide by std; the suite delivers RGB, so the channels are flipped exactly when
    ``to_rgb`` is False), zero padding at the bottom and right to a multiple of `size_divisor`.
    """
    resized = []
    for cam in CAMERA_ORDER:
        rgb = images[cam]
        h, w = rgb.shape[:2]
        size = resized_size(w, h, scale)
        resized.append(cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR) if size != (w, h) else rgb)
    batch = np.stack(resized)  # (N, h, w, 3) uint8 RGB, one size for all cameras
    if not norm["to_rgb"]:
        batch = batch[..., ::-1]  # stays BGR, as loaded
    n, h, w = batch.shape[:3]
    ph, pw = -(-h // size_divisor) * size_divisor, -(-w // size_divisor) * size_divisor
    out = np.zeros((n, 3, ph, pw), np.float32)
    pixels = torch.from_numpy(np.ascontiguousarray(batch)).permute(0, 3, 1, 2).float()
    mean = torch.tensor(norm["mean"], dtype=torch.float32).view(1, 3, 1, 1)
    std = torch.tensor(norm["std"], dtype=torch.float32).view(1, 3, 1, 1)
    torch.from_numpy(out)[:, :, :h, :w] = (pixels - mean) / std
    return out


# -- the test-time pipeline: img_metas ------------------------------------------------------------------

def lidar_frame(context: FrameContext) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(lidar2ego 4x4, camera -> lidar2img 4x4) at the delivered image size.

    From the data set's LIDAR_TOP when it has one (lidar2ego recovered as ``cam2ego @ inv(K) @ lidar2img``),
    else the nominal nuScenes mount ``NOMINAL_LIDAR2EGO`` with ``lidar2img = K @ inv(cam2ego) @ lidar2ego``.
    """
    if context.lidar2img is not None:
        cam = CAMERA_ORDER[0]
        cal = context.calibration[cam]
        viewpad = np.eye(4)
        viewpad[:3, :3] = cal.intrinsic
        lidar2ego = cal.sensor2ego @ np.linalg.inv(viewpad) @ context.lidar2img[cam]
        return lidar2ego, {c: np.array(context.lidar2img[c]) for c in CAMERA_ORDER}
    out = {}
    for cam in CAMERA_ORDER:
        cal = context.calibration[cam]
        viewpad = np.eye(4)
        viewpad[:3, :3] = cal.intrinsic
        out[cam] = viewpad @ geo.invert(cal.sensor2ego) @ NOMINAL_LIDAR2EGO
    return NOMINAL_LIDAR2EGO.copy(), out


def build_img_metas(context: FrameContext, *, scale: float, norm: Mapping[str, Any], prev_idx: str = "",
                    size_divisor: int = SIZE_DIVISOR) -> dict[str, Any]:
    """The ``img_metas`` entry of one frame, as UniAD's dataset and test pipeline build it.

    `can_bus` is the raw 18-value vector (absolute position and heading); ``forward_test`` turns it into the
    delta. `prev_idx` is the previous keyframe's token in the stream ('' at a scene's first frame); a
    streaming loop does not know the next keyframe, so `next_idx` is ''.
    """
    lidar2ego, lidar2img = lidar_frame(context)
    s = scale_matrix(scale)
    ego2global = np.asarray(context.ego2global)
    shapes, pads, l2i, intrinsics, l2c = [], [], [], [], []
    for cam in CAMERA_ORDER:
        cal = context.calibration[cam]
        w, h = resized_size(*cal.image_size, scale)
        shapes.append((h, w, 3))
        pads.append((-(-h // size_divisor) * size_divisor, -(-w // size_divisor) * size_divisor, 3))
        viewpad = np.eye(4)
        viewpad[:3, :3] = cal.intrinsic
        l2i.append(s @ lidar2img[cam])
        intrinsics.append(s @ viewpad)
        l2c.append(geo.invert(cal.sensor2ego) @ lidar2ego)
    l2e_r, e2g_r = lidar2ego[:3, :3], ego2global[:3, :3]
    return {
        "sample_idx": context.token,
        "scene_token": context.scene_token,
        "frame_idx": context.index,
        "prev_idx": prev_idx,
        "next_idx": "",
        "timestamp": context.timestamp / 1e6,
        "ego2global_translation": ego2global[:3, 3].tolist(),
        "ego2global_rotation": list(geo.matrix_to_quat(e2g_r)),
        "lidar2ego_translation": lidar2ego[:3, 3].tolist(),
        "lidar2ego_rotation": list(geo.matrix_to_quat(l2e_r)),
        # UniAD's row-vector convention: points @ l2g_r_mat + l2g_t
        "l2g_r_mat": (l2e_r.T @ e2g_r.T).astype(np.float32),
        "l2g_t": (lidar2ego[:3, 3] @ e2g_r.T + ego2global[:3, 3]).astype(np.float32),
        "can_bus": np.array(context.can_bus if context.can_bus is not None else np.zeros(18), dtype=np.float64),
        "lidar2img": l2i,
        "cam_intrinsic": intrinsics,
        "lidar2cam": l2c,
        "img_shape": shapes,
        "ori_shape": list(shapes),
        "pad_shape": pads,
        "scale_factor": scale,
        "img_norm_cfg": dict(norm),
        "camera_order": CAMERA_ORDER,
    }


# -- the stand-in model ---------------------------------------------------------------------------------

class TinyBEVPlanner(nn.Module):
    """A stand-in for UniAD / VAD with the same inputs: multi-view images, lidar2img, img_shape, the CAN-bus
    vector (after the delta), the command, and the previous BEV; returns the plan (6 x 2, lidar frame) and the
    new BEV.

    Image features are sampled at the projections of a BEV grid of pillars (BEVFormer's spatial cross-attention
    reference points, without the attention), averaged over the cameras that see them, mixed with `prev_bev`,
    and read out by an MLP into a bounded residual on a constant-velocity plan. Random-init with a fixed seed:
    it has no skill, only the data flow of the real thing.
    """

    def __init__(self, pixel_scale: float, channels: int = 16, bev: int = 12, extent: float = 40.0) -> None:
        super().__init__()
        self.pixel_scale = pixel_scale  # brings the normalised pixels to about unit scale
        self.backbone = nn.Sequential(
            nn.AvgPool2d(4), nn.Conv2d(3, channels, 3, 2, 1), nn.ReLU(), nn.Conv2d(channels, channels, 3, 2, 1),
            nn.ReLU(),
        )
        xs = torch.linspace(-extent, extent, bev)
        gy, gx = torch.meshgrid(xs, xs, indexing="ij")
        pillars = [torch.stack([gx, gy, torch.full_like(gx, z), torch.ones_like(gx)], -1) for z in (-1.8, 0.0)]
        self.register_buffer("ref_points", torch.stack(pillars).reshape(-1, 4))  # (Z*bev*bev, 4), lidar frame
        self.bev, self.channels = bev, channels
        self.temporal = nn.Conv2d(2 * channels, channels, 1)
        self.head = nn.Sequential(
            nn.Linear(channels * 9 + 10 + 3, 64), nn.ReLU(), nn.Linear(64, 2 * HORIZON_STEPS),
        )

    def forward(self, img: torch.Tensor, lidar2img: torch.Tensor, img_shape: torch.Tensor, can_bus: torch.Tensor,
                command: torch.Tensor, prev_bev: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        feats = self.backbone(img / self.pixel_scale)  # (N, C, h, w)
        pts = torch.einsum("nij,pj->npi", lidar2img, self.ref_points)  # (N, P, 4)
        depth = pts[..., 2:3]
        uv = pts[..., :2] / depth.clamp(min=1e-5)
        uv = uv / img_shape[:, None, [1, 0]]  # normalised by img_shape as BEVFormer does
        visible = ((depth[..., 0] > 1e-5) & (uv > 0).all(-1) & (uv < 1).all(-1)).float()  # (N, P)
        sampled = F.grid_sample(feats, (2 * uv - 1)[:, None], align_corners=False)[:, :, 0]  # (N, C, P)
        bev = (sampled * visible[:, None]).sum(0) / visible.sum(0).clamp(min=1.0)  # (C, P)
        bev = bev.reshape(self.channels, 2, self.bev, self.bev).mean(1)
        prev = torch.zeros_like(bev) if prev_bev is None else prev_bev
        bev = bev + torch.tanh(self.temporal(torch.cat([bev, prev])[None]))[0]
        pooled = F.adaptive_avg_pool2d(bev[None], 3).flatten()
        motion = torch.cat([can_bus[:3] / 5.0, can_bus[-1:] / 10.0, can_bus[10:16] / 5.0])  # delta, rates, vel
        residual = torch.tanh(self.head(torch.cat([pooled, motion, command]))).reshape(HORIZON_STEPS, 2)
        return residual, bev


class Mmdet3dStylePlanner:
    """The suite's contract around an mmdet3d-style temporal model (see the module docstring)."""

    name = "mmdet3d_style"
    cameras: tuple[str, ...] = CAMERA_ORDER  # UniAD and VAD read all six

    def __init__(self, *, input_width: int = 640, norm: Mapping[str, Any] = NORM_VAD, seed: int = 0,
                 device: str = "cpu") -> None:
        """`input_width`: the width the model runs at (VAD: 640, 0.4 of nuScenes' 1600; UniAD: 1600); the
        scale follows from the delivered image width, so the geometry holds on any data set. `device`: where the
        model and its `prev_bev` live (``cpu``, ``cuda``, ``cuda:N``; the fixture passes --drivedegrade-device);
        the weights are made on the CPU with the seed, then moved."""
        self.input_width, self.norm = input_width, dict(norm)
        self.device = torch.device(device)
        if self.device.type == "cuda":
            deterministic_cuda()
        torch.manual_seed(seed)
        # caffe-style (std 1) pixels are about 58 times larger than torchvision-style ones
        self.model = TinyBEVPlanner(pixel_scale=1.0 if max(norm["std"]) > 1 else 58.0)
        self.model.eval().to(self.device)
        self.prev_frame_info: dict[str, Any] = {}
        self.last_img_metas: dict[str, Any] = {}  # what the model got last, CAN-bus delta applied (debugging)
        self.reset(None)
        self._log = os.environ.get(LOG_ENV, "")

    def reset(self, scene_token: str | None) -> None:
        """A new scene starts: forget the previous BEV, position and heading (BEVFormer's ``prev_frame_info``)."""
        self.prev_frame_info = {"prev_bev": None, "scene_token": None, "prev_pos": np.zeros(3), "prev_angle": 0.0,
                                "prev_token": ""}
        if scene_token is not None:
            self._write(f"reset {scene_token}")

    def scale_for(self, context: FrameContext) -> float:
        return self.input_width / context.calibration[CAMERA_ORDER[0]].image_size[0]

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command, context: FrameContext) \
            -> np.ndarray:
        scale = self.scale_for(context)
        if context.scene_token != self.prev_frame_info["scene_token"]:
            self.prev_frame_info["prev_token"] = ""  # a scene change seen in the stream: no previous keyframe
        metas = build_img_metas(context, scale=scale, norm=self.norm, prev_idx=self.prev_frame_info["prev_token"])
        img = multiview_image(images, scale, self.norm)
        plan_lidar = self.forward_test(img, metas, cmd)
        self.last_img_metas = metas
        self.prev_frame_info["prev_token"] = context.token
        rotation = np.asarray(metas["lidar2ego_rotation"])
        l2e = geo.quat_to_matrix(rotation)[:2, :2]
        return plan_lidar @ l2e.T  # lidar (x right, y forward) -> ego (x forward, y left)

    def forward_test(self, img: np.ndarray, metas: dict[str, Any], cmd: Command) -> np.ndarray:
        """BEVFormer's / UniAD's ``forward_test``: scene change -> drop prev_bev; the CAN-bus delta; the model."""
        info = self.prev_frame_info
        if metas["scene_token"] != info["scene_token"]:
            info["prev_bev"] = None
        info["scene_token"] = metas["scene_token"]
        can_bus = metas["can_bus"]
        pos, angle = can_bus[:3].copy(), float(can_bus[-1])
        if info["prev_bev"] is not None:
            can_bus[:3] -= info["prev_pos"]
            can_bus[-1] -= info["prev_angle"]
        else:
            can_bus[:3] = 0.0
            can_bus[-1] = 0.0
        metas["prev_bev_exists"] = info["prev_bev"] is not None
        self._write(f"predict {metas['scene_token']} {metas['frame_idx']} {int(metas['prev_bev_exists'])}")
        lidar2ego = geo.transform(metas["lidar2ego_rotation"], metas["lidar2ego_translation"])
        inputs = (torch.from_numpy(img), torch.from_numpy(np.stack(metas["lidar2img"]).astype(np.float32)),
                  torch.tensor([s[:2] for s in metas["img_shape"]], dtype=torch.float32),
                  torch.from_numpy(can_bus.astype(np.float32)), F.one_hot(torch.tensor(int(cmd)), 3).float())
        with torch.inference_mode():
            residual, bev = self.model(*(x.to(self.device) for x in inputs), info["prev_bev"])
        info.update(prev_bev=bev, prev_pos=pos, prev_angle=angle)
        # the plan: constant velocity (the CAN bus velocity, ego frame, turned into the lidar frame) + residual
        vel_lidar = lidar2ego[:3, :3].T @ can_bus[13:16]
        t = STEP_SECONDS * np.arange(1, HORIZON_STEPS + 1)[:, None]
        return t * vel_lidar[None, :2] + residual.cpu().numpy().astype(np.float64)

    def _write(self, line: str) -> None:
        if self._log:
            with open(self._log, "a") as f:  # one write per line: safe from several workers
                f.write(f"{os.getpid()} {line}\n")


@pytest.fixture(scope="session")
def planner() -> Iterator[Mmdet3dStylePlanner]:
    """Built once per worker, on one torch thread: the CPU kernels this model uses (convolution, pooling,
    grid_sample, linear) are deterministic given the thread count, so every layout gives the same bits. (A
    model with kernels that are not, e.g. on CUDA, also wants ``torch.use_deterministic_algorithms(True)``;
    on CPU it only costs importing torch's compiler stack into every worker.) The model runs on the run's
    --drivedegrade-device (``planner_device()``)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield Mmdet3dStylePlanner(device=planner_device())
    finally:
        torch.set_num_threads(threads)
