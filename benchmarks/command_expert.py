"""The privileged expert for the open-loop command probe (issue 40), as a planner file for the plugin:

    pytest --drivedegrade benchmarks/command_expert.py --drivedegrade-data WORLD --drivedegrade-split junction \
        --drivedegrade-families command_swap --drivedegrade-severities 5 -n 0

Under the logged command it plans the logged future; told the frame's alternative command it plans the expert's
path for it (`data.junctions.alternative`): the figure's 1 by construction, checked end to end. It reads the data
set itself (privileged: the suite hands it nothing of the truth) and no camera.
"""

from __future__ import annotations

import numpy as np
import pytest


class Expert:
    cameras = ()
    name = "privileged_expert"
    deterministic = True

    def __init__(self, root, split):
        self.root, self.split, self.truth = root, split, None

    def frame_truth(self, token):
        if self.truth is None:
            from pytest_drivedegrade.data.junctions import alternative
            from pytest_drivedegrade.data.nuscenes import NuScenesReader

            reader = NuScenesReader(self.root, split=self.split)
            self.truth = {f.token: (f.gt_future, int(f.command), alternative(reader.lane_map(f), f.pose,
                                                                             f.gt_future, f.command))
                          for f in reader.scorable_frames(agents=False)}
        return self.truth[token]

    def predict(self, images, ego, cmd, context):
        future, logged, alt = self.frame_truth(context.token)
        if int(cmd) != logged and alt is not None and int(cmd) == int(alt.command):
            return np.array(alt.path, dtype=float)
        return np.array(future, dtype=float)


@pytest.fixture(scope="session")
def planner(request):
    return Expert(request.config.getoption("drivedegrade_data"), request.config.getoption("drivedegrade_split"))
