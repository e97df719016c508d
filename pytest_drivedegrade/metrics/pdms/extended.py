"""EPDMS, NAVSIM v2's extended PDM score, on the tracked states (spec 4.1.0; NAVSIM v2 `PDMScorer`,
`pdm_comfort_metrics`, `scene_aggregator`, `evaluate/pdm_score.py`):

    epdms = nc * dac * ddc * tlc * (5 ep + 5 ttc + 2 lk + 2 hc + 2 ec) / 16

with a term that is not scored (NaN: no lanes for ddc and lk, no traffic lights for tlc, no previous plan of the
scene for ec) left out of the product or the weighted mean. The human filter: a term the expert's own plan
scores 0 on is set to 1 for the plan (a rule the human driver also broke is not counted).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...constants import STEP_SECONDS
from .constants import PROGRESS_DISTANCE_THRESHOLD, SIM_DT, TTC_PROJECTIONS_S
from .lanes import LaneQuery, LaneView
from .motion import EgoStates, savgol, within_comfort
from .rules import Contact

#: PDMScorerConfig (v2): driving direction over a 1 s window, compliant below 2 m, violated from 6 m; lane keeping
#: fails after 2 s continuously more than 0.5 m off the centreline.
DDC_HORIZON_S, DDC_COMPLIANT_M, DDC_VIOLATION_M = 1.0, 2.0, 6.0
LK_DEVIATION_M, LK_WINDOW_S = 0.5, 2.0
#: Weights of the averaged terms (EP 5, TTC 5, LK 2, HC 2, EC 2) and the multiplied terms.
EPDMS_WEIGHTS: dict[str, float] = {"ep": 5.0, "ttc": 5.0, "lk": 2.0, "hc": 2.0, "ec": 2.0}
EPDMS_MULTIPLIERS: tuple[str, ...] = ("nc", "dac", "ddc", "tlc")
#: The terms of a plan's `ExtendedTerms`. The human filter looks at each of them, but NAVSIM scores the human
#: without a past, so its hc is always 1 and hc is never filtered; ec is not a term of one frame.
FILTERED: tuple[str, ...] = ("nc", "dac", "ddc", "tlc", "ep", "ttc", "lk", "hc")
#: Two-frame extended comfort: RMS of the difference of consecutive plans' features, at most these
#: (acceleration m/s^2, jerk m/s^3, yaw rate rad/s, yaw acceleration rad/s^2), over their overlap.
EC_THRESHOLDS: tuple[float, float, float, float] = (0.7, 0.5, 0.1, 0.1)
#: History comfort pads the plan with the ego's past keyframes 1.5, 1.0 and 0.5 s back (NAVSIM's
#: ``get_ego_past_trajectory(0, 1.5)``: three past 2 Hz frames) and the current one.
PAST_HC: int = 3
#: NAVSIM's history comfort reads accelerations at the Pacifica's centre, this far ahead of the tracked rear axle
#: (nuPlan's `get_pacifica_parameters().rear_axle_to_center`: (4.049 - 1.127) / 2 m), whatever box is scored.
HC_CENTRE_M: float = (4.049 + 1.127) / 2 - 1.127  # 1.461, as nuPlan computes it (half length - rear length)
#: Consecutive frames at most this far apart (s) are "the previous frame" for EC (NAVSIM asserts < 0.55 s).
EC_MAX_INTERVAL_S: float = 0.55


@dataclass(frozen=True)
class ExtendedTerms:
    """A plan's EPDMS terms before the human filter (NaN: not scored)."""

    nc: float
    dac: float
    ddc: float
    tlc: float
    ep: float
    ttc: float
    lk: float
    hc: float

    def filtered(self, human: ExtendedTerms) -> ExtendedTerms:
        """The human filter: each term the human's plan scores exactly 0 on becomes 1."""
        return ExtendedTerms(**{k: 1.0 if getattr(human, k) == 0.0 else getattr(self, k) for k in FILTERED})


def epdms_score(terms: ExtendedTerms, ec: float) -> float:
    """The product of the scored multipliers times the weighted mean of the scored averaged terms."""
    values: Mapping[str, float] = {**{k: getattr(terms, k) for k in FILTERED}, "ec": ec}
    mult = math.prod(values[k] for k in EPDMS_MULTIPLIERS if math.isfinite(values[k]))
    scored = [k for k in EPDMS_WEIGHTS if math.isfinite(values[k])]
    total = sum(EPDMS_WEIGHTS[k] for k in scored)
    return mult * sum(EPDMS_WEIGHTS[k] * values[k] for k in scored) / total if total else math.nan


def ep_v2(plan_m: float, plan_multiplier: float, expert_m: float, expert_multiplier: float) -> float:
    """NAVSIM v2's progress: raw progress over the larger multiplied progress of plan and reference, clipped to
    [0, 1]; 1 when that larger value is at most the 5 m threshold (v1 gave 0 to a plan multiplied by 0)."""
    top = max(max(plan_m, 0.0) * plan_multiplier, max(expert_m, 0.0) * expert_multiplier)
    return min(max(max(plan_m, 0.0) / top, 0.0), 1.0) if top > PROGRESS_DISTANCE_THRESHOLD else 1.0


def ttc_v2_window(contacts: Iterable[Contact], n_states: int) -> list[Contact]:
    """The projected contacts (in NAVSIM's order) NAVSIM v2.2's TTC looks at among `n_states` tracked states: those
    projected from a state whose longest projection (0.9 s) still ends inside the horizon, states 0 .. n_states - 1
    - 9 (``n_proposal_steps_to_evaluate``: 0 .. 3.1 s on NAVSIM's 4 s, 0 .. 2.1 s on six poses' 3 s). NAVSIM v1.1,
    the PDMS's, projects from every state."""
    last = n_states - 1 - round(max(TTC_PROJECTIONS_S) / SIM_DT)
    return [c for c in contacts if c.state <= last]


def lane_query(states: EgoStates, lanes: LaneView | None) -> LaneQuery | None:
    """The states against the lanes (`LaneView.query`), once for DDC and LK; None without lanes."""
    return lanes.query(states.xy, states.heading) if lanes is not None and len(lanes.start) else None


def driving_direction(states: EgoStates, lanes: LaneView | None, query: LaneQuery | None = None) -> float:
    """DDC in {0, 1/2, 1}: the distance driven in oncoming lanes (outside intersections) within any 1 s window:
    below 2 m 1, below 6 m 1/2, else 0. NaN without lanes. `query`: the states' `LaneView.query`, where the
    caller has it (LK reads the same)."""
    if lanes is None or not len(lanes.start):
        return math.nan
    q = query if query is not None else lanes.query(states.xy, states.heading)
    oncoming = q.oncoming & ~q.in_intersection
    step = np.zeros(len(states.xy))
    step[1:] = np.linalg.norm(np.diff(states.xy, axis=0), axis=1)
    step[~oncoming] = 0.0
    horizon = round(DDC_HORIZON_S / SIM_DT)
    windowed = np.convolve(step, np.ones(horizon + 1))[:len(step)]  # the sum over steps t - horizon .. t
    worst = float(windowed.max())
    return 1.0 if worst < DDC_COMPLIANT_M else 0.5 if worst < DDC_VIOLATION_M else 0.0


def lane_keeping(states: EgoStates, lanes: LaneView | None, query: LaneQuery | None = None) -> float:
    """LK in {0, 1}: 0 when the ego centre stays more than 0.5 m from the nearest centreline running its way (none
    within `lanes.NEAR_M`: off) for 2 s of consecutive states (intersections skipped without resetting the
    count, as NAVSIM skips them). NaN without lanes."""
    if lanes is None or not len(lanes.start):
        return math.nan
    q = query if query is not None else lanes.query(states.xy, states.heading)
    deviation, skip = q.deviation, q.in_intersection
    needed, run = math.ceil(LK_WINDOW_S / SIM_DT - 1e-9), 0
    for far, skipped in zip((deviation > LK_DEVIATION_M).tolist(), skip.tolist()):
        if skipped:
            continue
        run = run + 1 if far else 0
        if run >= needed:
            return 0.0
    return 1.0


def _body_accel(states: EgoStates) -> tuple[np.ndarray, np.ndarray]:
    return states.lon_accel, states.lat_accel


def comfortable_v2(heading: np.ndarray, lon: np.ndarray, lat: np.ndarray, lon_raw: np.ndarray | None = None
                   ) -> float:
    """NAVSIM v2's comfort verdict over any number of 10 Hz states: accelerations smoothed over 8 states, jerks
    their derivative over 15, yaw rate and yaw acceleration from the heading over 5 (orders 2, 3), within
    COMFORT_BOUNDS (strict), values rounded to 1e-8. `lon_raw`: the longitudinal acceleration the jerk's
    magnitude reads where it differs from `lon` (NAVSIM shifts `lon` to the vehicle's centre, not the magnitude's
    input: `centre_lon_accel`)."""
    n = len(heading)
    lon_s, lat_s = savgol(lon, min(8, n), 2), savgol(lat, min(8, n), 2)
    mag = savgol(np.hypot(lon if lon_raw is None else lon_raw, lat), min(8, n), 2)
    terms = {"lon_accel": lon_s, "lat_accel": lat_s, "jerk": savgol(np.round(mag, 8), min(15, n), 2, 1),
             "lon_jerk": savgol(np.round(lon_s, 8), min(15, n), 2, 1),
             "yaw_rate": savgol(heading, min(5, n), 2, 1), "yaw_accel": savgol(heading, min(5, n), 3, 2)}
    return within_comfort(terms)


def history(past_motion: npt.ArrayLike, acceleration: npt.ArrayLike = (0.0, 0.0)
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ego's past as NAVSIM v2's history comfort pads the plan with it: the ego states of the keyframes
    1.5, 1.0 and 0.5 s back and of this one (`Frame.past_motion`'s last PAST_HC rows, then this keyframe at time
    0, heading 0, `acceleration`), linearly interpolated (nuPlan's `InterpolatedTrajectory`: heading unwrapped,
    the body-frame accelerations as logged) at every 0.1 s from the first keyframe's time while before this
    one's, less the last sample (NAVSIM's ``history_time_us[:-1]``): 14 states, -1.5 .. -0.2 s, which the plan's
    t = 0 state then follows as if 0.1 s later. Returns heading, longitudinal and lateral acceleration (H,)."""
    rows = np.asarray(past_motion, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != 4 or len(rows) < PAST_HC:
        raise ValueError(f"past motion of shape {rows.shape}: expected ({PAST_HC} or more, 4) rows of (time us, "
                         f"heading, ax, ay), oldest first (`Frame.past_motion`)")
    rows = rows[-PAST_HC:]
    a0 = np.asarray(acceleration, dtype=np.float64).reshape(2)
    knots = np.vstack([rows, [0.0, 0.0, a0[0], a0[1]]])
    t_us = knots[:, 0].astype(np.int64)
    if np.any(np.diff(t_us) <= 0):
        raise ValueError(f"past keyframe times {t_us.tolist()} (us) do not increase to this keyframe's 0")
    samples = np.arange(t_us[0], t_us[-1], round(SIM_DT * 1e6), dtype=np.int64)[:-1]
    heading = np.unwrap(knots[:, 1])
    t = samples.astype(np.float64)
    return (np.interp(t, t_us, heading), np.interp(t, t_us, knots[:, 2]), np.interp(t, t_us, knots[:, 3]))


def centre_lon_accel(lon: np.ndarray, yaw_rate: np.ndarray) -> np.ndarray:
    """The tracked states' longitudinal acceleration (N,) as NAVSIM v2's history comfort reads it: moved from the
    rear axle the bicycle model tracks to the vehicle's centre (`state_array_to_center_state_array` with
    `ego_is_comfortable`'s default vehicle, the Pacifica, HC_CENTRE_M ahead, whatever the scored box), with
    NAVSIM's `get_acceleration_shifted`, which adds both the centripetal and the angular-acceleration term to the
    longitudinal component (lateral unchanged). The yaw rate at t = 0 is 0 (NAVSIM builds that state from the
    ego status, which has none) and the yaw acceleration the bicycle model's difference of yaw rates from there."""
    w = np.array(yaw_rate, dtype=np.float64)
    w[0] = 0.0
    alpha = np.zeros_like(w)
    alpha[1:] = (w[1:] - w[:-1]) / SIM_DT
    return lon + HC_CENTRE_M * w ** 2 + HC_CENTRE_M * alpha


def history_comfort(states: EgoStates, past: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> float:
    """HC in {0, 1}: NAVSIM v2's comfort over the ego's past (`history`) followed by the plan's tracked states;
    1 without a past, as NAVSIM gives it (its human-filter run is scored so, hence HC is never filtered). The
    plan's longitudinal acceleration is read at NAVSIM's centre (`centre_lon_accel`) where the states carry the
    tracker's yaw rate; the past's is not moved (its keyframes' states have no yaw rate in NAVSIM either)."""
    if past is None:
        return 1.0
    lon, lat = _body_accel(states)
    centre = lon if states.yaw_rate is None else centre_lon_accel(lon, states.yaw_rate)
    return comfortable_v2(np.concatenate([past[0], states.heading]), np.concatenate([past[1], centre]),
                          np.concatenate([past[2], lat]), np.concatenate([past[1], lon]))


def _features(states: EgoStates) -> tuple[np.ndarray, ...]:
    """NAVSIM v2's extended-comfort features: the acceleration magnitude (over 8), its derivative (over 15),
    yaw rate and yaw acceleration (over 5, order 2), each rounded to 1e-8."""
    n = len(states.heading)
    acc = np.round(savgol(np.hypot(states.accel[:, 0], states.accel[:, 1]), min(8, n), 2), 8)
    return (acc, np.round(savgol(acc, min(15, n), 2, 1), 8), np.round(savgol(states.heading, min(5, n), 2, 1), 8),
            np.round(savgol(states.heading, min(5, n), 2, 2), 8))


def extended_comfort(current: EgoStates, previous: EgoStates | None, interval_s: float = STEP_SECONDS) -> float:
    """EC in {0, 1}: the previous frame's plan from `interval_s` on against this frame's plan over their overlap,
    each feature's RMS difference within EC_THRESHOLDS. NaN without a previous plan."""
    if previous is None:
        return math.nan
    shift = round(interval_s / SIM_DT)
    cur = EgoStates(current.xy[:-shift], current.velocity[:-shift], current.accel[:-shift],
                    current.heading[:-shift], current.speed[:-shift])
    prev = EgoStates(previous.xy[shift:], previous.velocity[shift:], previous.accel[shift:],
                     previous.heading[shift:], previous.speed[shift:])
    return float(all(float(np.sqrt(np.mean((a - b) ** 2))) <= limit
                     for a, b, limit in zip(_features(cur), _features(prev), EC_THRESHOLDS)))
