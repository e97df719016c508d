"""Walk a world with the official nuscenes-devkit the way a converter does; print a JSON summary.

Run by tests/unit/test_devkit.py in a separate interpreter that has nuscenes-devkit (which pins numpy < 2, so it
never enters the project's environment): ``python devkit_walk.py DATAROOT``. The walk follows mmdet3d's
`create_nuscenes_infos` (tools/dataset_converters/nuscenes_converter.py; UniAD's and VAD's copies add the CAN bus):
`get_available_scenes` (the first LIDAR_TOP file of each scene exists), the official split lists filtered to the
available scenes, then for every sample `_fill_trainval_infos`' look-ups: LIDAR_TOP's sample_data,
calibrated_sensor and ego_pose, `get_sample_data` (the file, the boxes in the sensor frame), the six cameras'
`get_sample_data` and their calibration, the annotations with `box_velocity`, visibility and point counts.
"""

from __future__ import annotations

import json
import os
import sys
from collections import Counter

import numpy as np
from nuscenes.can_bus.can_bus_api import NuScenesCanBus
from nuscenes.nuscenes import NuScenes
from nuscenes.utils import splits
from nuscenes.utils.data_classes import LidarPointCloud
from nuscenes.utils.geometry_utils import points_in_box

CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")


def main(root: str) -> dict:
    nusc = NuScenes(version="v1.0-trainval", dataroot=root, verbose=False)
    can_bus = NuScenesCanBus(dataroot=root)
    available = []
    for scene in nusc.scene:  # mmdet3d's get_available_scenes
        sample = nusc.get("sample", scene["first_sample_token"])
        lidar_path, _, _ = nusc.get_sample_data(sample["data"]["LIDAR_TOP"])
        if os.path.isfile(lidar_path):
            available.append(scene["name"])
    train = [s for s in splits.train if s in available]
    val = [s for s in splits.val if s in available]
    split_of = {nusc.field2token("scene", "name", s)[0]: "train" for s in train}
    split_of.update({nusc.field2token("scene", "name", s)[0]: "val" for s in val})
    out: dict = {"scenes": [s["name"] for s in nusc.scene], "available": available, "train": train, "val": val,
                 "samples": 0, "samples_per_split": Counter(), "missing_files": [], "pose_mismatch": 0,
                 "lidar_points": 0, "annotations": 0, "boxes_mismatch": 0, "visibility": Counter(),
                 "zero_lidar_pts": 0, "num_lidar_pts": 0, "points_in_boxes": 0, "can_bus_scenes": 0,
                 "categories": sorted((c["name"], c["index"]) for c in nusc.category),
                 "lidar_calibration": None, "camera_boxes": 0}
    for scene in nusc.scene:
        pose = can_bus.get_messages(scene["name"], "pose")
        out["can_bus_scenes"] += bool(pose)
    for sample in nusc.sample:
        out["samples"] += 1
        out["samples_per_split"][split_of.get(sample["scene_token"], "none")] += 1
        lidar_token = sample["data"]["LIDAR_TOP"]
        sd = nusc.get("sample_data", lidar_token)
        cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
        ego = nusc.get("ego_pose", sd["ego_pose_token"])
        out["lidar_calibration"] = [cs["translation"], cs["rotation"]]
        lidar_path, boxes, _ = nusc.get_sample_data(lidar_token)
        if not os.path.isfile(lidar_path):
            out["missing_files"].append(lidar_path)
            continue
        cloud = LidarPointCloud.from_file(lidar_path)
        out["lidar_points"] += cloud.points.shape[1]
        for cam in CAMERAS:
            cam_token = sample["data"][cam]
            cam_path, cam_boxes, intrinsic = nusc.get_sample_data(cam_token)
            out["camera_boxes"] += len(cam_boxes)
            cam_sd = nusc.get("sample_data", cam_token)
            nusc.get("calibrated_sensor", cam_sd["calibrated_sensor_token"])
            cam_ego = nusc.get("ego_pose", cam_sd["ego_pose_token"])
            if cam_ego["timestamp"] != ego["timestamp"] or cam_ego["translation"] != ego["translation"]:
                out["pose_mismatch"] += 1
            if not os.path.isfile(cam_path) or np.asarray(intrinsic).shape != (3, 3):
                out["missing_files"].append(cam_path)
        anns = [nusc.get("sample_annotation", t) for t in sample["anns"]]
        [nusc.box_velocity(t) for t in sample["anns"]]
        out["annotations"] += len(anns)
        out["boxes_mismatch"] += len(nusc.get_boxes(lidar_token)) != len(anns) or len(boxes) != len(anns)
        for ann, box in zip(anns, boxes):
            out["visibility"][nusc.get("visibility", ann["visibility_token"])["level"]] += 1
            out["zero_lidar_pts"] += ann["num_lidar_pts"] == 0
            out["num_lidar_pts"] += ann["num_lidar_pts"]
            out["points_in_boxes"] += int(points_in_box(box, cloud.points[:3], wlh_factor=1.01).sum())
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1]), sort_keys=True))
