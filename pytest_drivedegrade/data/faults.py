"""Data faults outside the images (issue 37): a non-finite value in what a frame hands the planner or in what it
is scored against is the data set's fault, named with the frame's token, never the planner's.

- `input_fault`: the ego status, the CAN bus message, the cameras' and the LiDAR's calibration. A frame with
  one is a data fault in every cell (`stream`), whatever the planner then returned (it may have planned
  around the NaN, or passed it on): counted in the cell's data errors, not its contract failures.
- `truth_fault`: the ego pose, the global pose and the ground-truth future. Without them the frame cannot be
  scored at all, so `RunContext.open` refuses the run naming the frame (before any cell runs), where it used
  to fail every cell with a traceback.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .frame import Frame


def _bad(values: object) -> bool:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        return True
    return not bool(np.isfinite(arr).all())


def _inputs(frame: Frame) -> Iterator[tuple[str, object]]:
    ego = frame.ego
    yield from (("ego status velocity", ego.velocity), ("ego status acceleration", ego.acceleration),
                ("ego status yaw rate", ego.yaw_rate), ("ego status past trajectory", ego.past_xy))
    for key, values in (frame.can or {}).items():
        yield f"CAN bus {key} (can_bus/{frame.scene_name}_pose.json)", values
    for name, cam in frame.cameras.items():
        yield f"{name} calibration intrinsic (calibrated_sensor.json)", cam.intrinsic
        yield f"{name} calibration rotation/translation (calibrated_sensor.json)", (*cam.rotation,
                                                                                   *cam.translation)
    if frame.lidar is not None:
        yield "LIDAR_TOP calibration (calibrated_sensor.json)", (*frame.lidar[0], *frame.lidar[1])


def input_fault(frame: Frame) -> str | None:
    """What of `frame`'s planner inputs (but the images) holds a NaN or inf, or None."""
    bad = [what for what, values in _inputs(frame) if _bad(values)]
    if not bad:
        return None
    return (f"the data set holds a non-finite value (NaN or inf) in {', '.join(bad)}: a data fault, not the "
            "planner's; fix or re-extract the data set")


def truth_fault(frame: Frame) -> str | None:
    """What of `frame`'s scoring truth (its ego pose, global pose, ground-truth future) is not finite, or None."""
    parts = {"ego pose (ego_pose.json)": (*frame.ego_pose[0], *frame.ego_pose[1]),
             "global pose": frame.pose if frame.pose is not None else (0.0,),
             "ground-truth future (the next six keyframes' ego poses)": frame.gt_future}
    bad = [what for what, values in parts.items() if _bad(values)]
    if not bad:
        return None
    return (f"frame {frame.token!r} (scene {frame.scene_name}): the data set holds a non-finite value (NaN or inf) "
            f"in its {', '.join(bad)}, so it cannot be scored; fix or re-extract the data set")
