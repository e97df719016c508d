"""The world's LIDAR_TOP and visibility come from ray casts, not constants: a car hidden behind a truck is
invisible and gets no lidar points; an open car is fully visible and hit; the ego poses do not move."""

from __future__ import annotations

import numpy as np
import pytest

from pytest_drivedegrade.data import geometry as geo
from pytest_drivedegrade.data.world import sensing
from pytest_drivedegrade.data.world.rig import Rig

TRUCK = (12.0, 0.0, 0.0, 8.0, 2.5, 3.2)  # x, y, yaw, length, width, height in the ego frame
HIDDEN_CAR = (20.0, 0.0, 0.0, 4.5, 1.8, 1.5)  # right behind the truck
OPEN_CAR = (0.0, 8.0, 0.0, 4.5, 1.8, 1.5)  # alone, to the left


def test_a_car_behind_a_truck_is_hidden_and_gets_no_points():
    boxes = np.array([TRUCK, HIDDEN_CAR, OPEN_CAR])
    frac = sensing.visible_fractions(boxes, [0, 1, 2], Rig.nuscenes_like())
    assert frac[0] > 0.95 and frac[2] > 0.95
    assert frac[1] == 0.0
    assert [sensing.visibility_token(f) for f in frac] == ["4", "1", "4"]
    cloud, counts = sensing.lidar_scan(boxes)
    assert counts[1] == 0 and counts[0] > 50 and counts[2] > 50
    assert cloud.dtype == np.float32 and cloud.shape[1] == 5
    assert counts.sum() == int((cloud[:, 3] == sensing.INTENSITY["box"]).sum())


def test_points_lie_on_what_they_hit():
    boxes = np.array([OPEN_CAR])
    cloud, counts = sensing.lidar_scan(boxes)
    lidar2ego = geo.transform(sensing.LIDAR_ROTATION, sensing.LIDAR_TRANSLATION)
    ego = cloud[:, :3] @ lidar2ego[:3, :3].T + lidar2ego[:3, 3]
    on_box = cloud[:, 3] == sensing.INTENSITY["box"]
    assert on_box.sum() == counts[0]
    np.testing.assert_allclose(ego[~on_box, 2], 0.0, atol=1e-3)  # ground returns on the ground
    x, y, _, length, width, height = OPEN_CAR
    inside = (np.abs(ego[on_box, 0] - x) <= length / 2 + 1e-3) & (np.abs(ego[on_box, 1] - y) <= width / 2 + 1e-3)
    assert inside.all() and (ego[on_box, 2] <= height + 1e-3).all()


@pytest.mark.parametrize(("fraction", "token"), [(0.0, "1"), (0.39, "1"), (0.4, "2"), (0.6, "3"), (0.8, "4"),
                                                 (1.0, "4")])
def test_visibility_tokens_follow_nuscenes_bins(fraction, token):
    assert sensing.visibility_token(fraction) == token
