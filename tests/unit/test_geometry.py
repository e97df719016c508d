"""Geometry known answers: projection of points ahead and behind, transform round trips, clipping."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pytest_drivedegrade.constants import CAMERAS
from pytest_drivedegrade.data import geometry as geo
from pytest_drivedegrade.data.world.rig import Rig


@pytest.fixture(scope="module")
def rig():
    return Rig.nuscenes_like()


def _in_image(cam, points_ego) -> bool:
    pc = geo.ego_to_camera(points_ego, cam.rotation, cam.translation)
    uv, front = geo.project(pc, cam.intrinsic)
    inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return bool(inside.any())


@pytest.mark.parametrize("distance", [5.0, 20.0, 80.0])
def test_ground_point_ahead_projects_to_front_centre_column(rig, distance):
    cam = rig.cameras["CAM_FRONT"]
    point = np.array([[cam.translation[0] + distance, cam.translation[1], 0.0]])
    uv, front = geo.project(geo.ego_to_camera(point, cam.rotation, cam.translation), cam.intrinsic)
    assert front[0]
    assert int(uv[0, 0]) == cam.width // 2
    # below the horizon row, by f * h / d
    expected_v = cam.intrinsic[1, 2] + cam.intrinsic[1, 1] * cam.translation[2] / distance
    assert uv[0, 1] == pytest.approx(expected_v, abs=1e-6)


def test_box_behind_ego_is_seen_by_back_camera_only(rig):
    corners = np.array([[x, y, z] for x in (-12.0, -8.0) for y in (-1.0, 1.0) for z in (0.0, 1.6)])
    seen = [name for name in CAMERAS if _in_image(rig.cameras[name], corners)]
    assert seen == ["CAM_BACK"]


def test_box_ahead_left_is_seen_by_front_left_not_back(rig):
    corners = np.array([[x, y, z] for x in (14.0, 16.0) for y in (14.0, 16.0) for z in (0.0, 1.6)])
    assert _in_image(rig.cameras["CAM_FRONT_LEFT"], corners)
    assert not _in_image(rig.cameras["CAM_BACK"], corners)


def test_camera_yaws_match_the_rig(rig):
    for name, yaw in (("CAM_FRONT", 0), ("CAM_FRONT_LEFT", 55), ("CAM_BACK", 180), ("CAM_BACK_RIGHT", -110)):
        r = geo.quat_to_matrix(rig.cameras[name].rotation)
        axis = r @ np.array([0.0, 0.0, 1.0])  # optical axis in the ego frame
        # the optical axis is the unit vector at the yaw, exactly (+180 and -180 are the same vector)
        np.testing.assert_allclose(axis, [np.cos(np.radians(yaw)), np.sin(np.radians(yaw)), 0.0], atol=1e-9)


quats = st.tuples(*[st.floats(-1, 1) for _ in range(4)]).filter(lambda q: np.linalg.norm(q) > 0.1)
vec = st.tuples(*[st.floats(-100, 100) for _ in range(3)])


@settings(max_examples=60, deadline=None)
@given(quats, vec, quats, vec)
def test_ego_global_camera_round_trip(q_ego, t_ego, q_cam, t_cam):
    pts = np.array([[1.0, 2.0, 0.5], [-30.0, 4.0, 1.0], [0.0, 0.0, 0.0]])
    g = geo.ego_to_global(pts, q_ego, t_ego)
    c = geo.ego_to_camera(geo.global_to_ego(g, q_ego, t_ego), q_cam, t_cam)
    back = geo.global_to_ego(geo.ego_to_global(geo.camera_to_ego(c, q_cam, t_cam), q_ego, t_ego), q_ego, t_ego)
    np.testing.assert_allclose(back, pts, atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(quats)
def test_quaternion_matrix_round_trip(q):
    q = np.asarray(q) / np.linalg.norm(q)
    back = np.asarray(geo.matrix_to_quat(geo.quat_to_matrix(q)))
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-8  # q and -q are the same rotation
    assert back[0] >= 0


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.5, 3.1])
def test_yaw_quaternion_round_trip(yaw):
    assert geo.quat_yaw(geo.yaw_to_quat(yaw)) == pytest.approx(yaw)
    assert geo.quat_yaws(np.array([geo.yaw_to_quat(yaw)]))[0] == pytest.approx(yaw)


def test_se2_to_ego_known_answer():
    # ego at (10, 5) heading +90 deg: a point 3 m further north is 3 m ahead; one to the east is to the right
    out = geo.se2_to_ego(np.array([[10.0, 8.0], [12.0, 5.0]]), (10.0, 5.0), np.pi / 2)
    np.testing.assert_allclose(out, [[3.0, 0.0], [0.0, -2.0]], atol=1e-12)


def test_near_plane_clipping_keeps_the_front_part():
    quad = np.array([[-1.0, 0.0, -2.0], [1.0, 0.0, -2.0], [1.0, 0.0, 4.0], [-1.0, 0.0, 4.0]])
    clipped = geo.clip_polygon_near(quad)
    assert (clipped[:, 2] >= geo.NEAR_PLANE - 1e-12).all()
    assert len(clipped) == 4
    assert sorted(np.round(clipped[:, 2], 6)) == [geo.NEAR_PLANE, geo.NEAR_PLANE, 4.0, 4.0]
    assert len(geo.clip_polygon_near(quad - [0, 0, 10])) == 0
