"""One place for every constant the pipeline shares: cameras, geometry, horizons."""

from __future__ import annotations

#: nuScenes camera names, in the order the suite iterates them.
CAMERAS: tuple[str, ...] = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_FRONT_LEFT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)

#: Spatial corruption parameters (pixels) are defined at this image width and scale linearly with it.
REFERENCE_WIDTH: int = 1600

#: nuScenes ego vehicle footprint (Renault Zoe), metres: length along x, width along y.
EGO_LENGTH: float = 4.084
EGO_WIDTH: float = 1.85

#: Planning horizon: six waypoints, 0.5 s apart (t = 0.5 .. 3.0 s); keyframes run at 2 Hz.
HORIZON_STEPS: int = 6
STEP_SECONDS: float = 0.5
#: The physical bound of a plan: a waypoint farther than this (metres) from the ego is a contract failure (3 s
#: at any road speed stays far inside it), so a huge but finite output (1e200) cannot overflow the metrics.
MAX_WAYPOINT_M: float = 1000.0
#: Past trajectory handed to the planner: the last four keyframes (2 s).
PAST_STEPS: int = 4
#: The high-level command is LEFT / RIGHT when the final ground-truth waypoint is this far to the side.
COMMAND_THRESHOLD_M: float = 2.0
#: Horizons (seconds) at which L2 and collision are reported; each is an index into the six steps.
REPORT_HORIZONS_S: tuple[int, ...] = (1, 2, 3)

#: Agent categories that count as vulnerable road users for the VRU collision rate.
VRU_CATEGORIES: tuple[str, ...] = ("pedestrian", "cyclist")
#: Defaults of the verdict's flat line (an axis at or above it counts as flat) and of the baseline gate's
#: allowed retention drop; run options and the analysis share them.
DEFAULT_FLAT: float = 0.95
DEFAULT_TOLERANCE: float = 0.02
#: The ego ladder's families (SPEC section 10), cells outside the camera axes: `ego_noise` S1..S5 and the
#: diagnostic `ego_blind` (cell ids ``ego_noise-s1`` .. ``ego_noise-s5``, ``ego_blind``).
EGO_NOISE, EGO_BLIND = "ego_noise", "ego_blind"
#: The command cell (spec 5, issue 40), outside the camera axes: every frame given the same command (STRAIGHT, the
#: lane-following command), so the command carries no information about the frame (cell id ``command_blind``).
COMMAND_BLIND = "command_blind"
#: The command-swap cell (spec 5, issue 40): at a frame where another command is meaningful (`data.junctions`) the
#: planner is given that alternative command; elsewhere the logged one (cell id ``command_swap``). Its record
#: keeps, per junction frame, the privileged expert's change of path for the alternative (``command_target``).
COMMAND_SWAP = "command_swap"
#: The confidence sequence adaptive cells stop on (`scoring.sequential.METHOD`): part of an adaptive run's key,
#: so a changed stopping rule never reuses cells a former rule stopped.
ADAPTIVE_METHOD = "betting"

#: A planner whose clean L2 is above this many times the ego-only floor's, and above it by `WORSE_MARGIN` m, is
#: warned about (the terminal, compare.html): a floor that reads no camera plans far better, which points to a
#: miswired adapter, among other causes.
WORSE_FACTOR = 2.0
WORSE_MARGIN = 0.1
