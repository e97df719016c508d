"""Measured effect of the PDMS's remaining adaptations to NAVSIM (spec/README "What remains adapted", issue 24).

On the world's expert plans (every frame with eight future keyframes: NAVSIM's 4 s) with N(0, sigma^2) added to
every waypoint coordinate, tracked as the PDMS tracks them (`metrics.tracking`, from the frame's logged state,
the expert's logged headings so that only the adaptation under study differs), each adaptation against NAVSIM's
way:

- horizon: comfort on 3 s (six poses, 31 states) vs 4 s (eight poses, 41 states); and the plans whose box
  touches an agent at 3.5 s or 4 s but at none of the six waypoint times (what a 4 s horizon adds);
- waypoint grid: plans with a box contact at the six waypoint states vs at every 0.1 s state from 0.5 s to 3 s,
  the agents interpolated linearly between keyframes along their tracks (`pdms.agents.agent_tracks`);
- box: plans with a contact (waypoint states) with the suite's box centred on the tracked point vs NAVSIM's
  Pacifica (5.176 m x 2.297 m) centred 1.461 m ahead of it (NAVSIM tracks the rear axle) or on it;
- headings: comfort with headings read off the waypoints (`tracking.waypoint_headings`) vs the logged ones.

A contact is any overlap of the ego box with an agent box (not NAVSIM's at-fault rule): the count of plans the
adaptation can change, an upper bound on how many no-collision verdicts move.

Then (issue 39) the EPDMS's remaining adaptations, each swapped for its alternative on the same plans: mean
EPDMS and retention per sigma (`epdms_study`; `--epdms-only` for that table alone, the quick mode).

    python benchmarks/navsim_adaptations.py [--scenes 2 --seed 7] [--draws 3] [--sigmas 0,0.3,1] [--epdms-only]
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import dataclass, replace

import numpy as np

from pytest_drivedegrade.data.frame import AgentBoxes
from pytest_drivedegrade.metrics import pdms, tracking
from pytest_drivedegrade.metrics.pdms import extended as X  # noqa: N812
from pytest_drivedegrade.metrics.pdms.agents import agent_tracks, hits
from pytest_drivedegrade.metrics.pdms.constants import EGO_BOXES, EGO_SIZE

SIGMAS: tuple[float, ...] = (0.0, 0.3, 1.0)
STEPS = 8  # NAVSIM's 4 s of 0.5 s poses
#: nuPlan's get_pacifica_parameters(): length (front 4.049 + rear 1.127), width, rear axle to the box centre.
PACIFICA = np.array([5.176, 2.297])
REAR_AXLE_TO_CENTRE = 1.461


@dataclass(frozen=True)
class Expert:
    """One frame's expert over 4 s: poses (8, 3) in the current ego frame, the agents at each keyframe, start."""

    poses: np.ndarray
    agents: tuple[AgentBoxes, ...]
    start: tracking.InitialState


def experts(scenes: int, seed: int) -> list[Expert]:
    """The world's frames with eight future keyframes (the reader's scene tables: its frames stop at 3 s)."""
    from pytest_drivedegrade.data import geometry as geo
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import write_world

    reader = NuScenesReader(write_world(tempfile.mkdtemp(prefix="ddadapt-"), scenes=scenes, seed=seed,
                                        val_images=False), split="all")
    out = []
    for scene in reader._select_scenes():
        tokens = reader._scene_samples(scene)
        (xy, yaw, _, _), _ = reader._poses(tokens)
        by_index = {f.index: f for f in reader.scorable_frames() if f.scene_token == scene["token"]}
        for k, frame in sorted(by_index.items()):
            if k + STEPS >= len(tokens):
                continue
            future = range(k + 1, k + STEPS + 1)
            rel = geo.se2_to_ego(xy[list(future)], xy[k], yaw[k])
            poses = np.concatenate([rel, geo.wrap_angle(yaw[list(future)] - yaw[k])[:, None]], axis=1)
            agents = tuple(reader._agents(tokens[i], xy[k], yaw[k]) for i in future)
            out.append(Expert(poses, agents, tracking.InitialState.of(frame.ego)))
    return out


def reference(poses: np.ndarray) -> np.ndarray:
    """Poses (B, n, 3) at 0.5 s after the origin, interpolated linearly at 0.1 s (headings unwrapped)."""
    knots = np.concatenate([np.zeros((len(poses), 1, 3)), poses], axis=1)
    knots[..., 2] = np.unwrap(knots[..., 2], axis=1)
    t = np.arange(5 * poses.shape[1] + 1) / 5.0
    seg = np.minimum(t.astype(int), poses.shape[1] - 1)
    u = (t - seg)[None, :, None]
    return knots[:, seg] * (1.0 - u) + knots[:, seg + 1] * u


def agents_at(agents: tuple[AgentBoxes, ...], state: int) -> AgentBoxes:
    """The agents at 0.1 s state `state` (>= 5): a keyframe's boxes, or between two keyframes the boxes of the
    tracks seen at both, centre and yaw interpolated linearly."""
    k, r = divmod(state, 5)
    if r == 0:
        return agents[k - 1]
    a, b = agents[k - 1], agents[k]
    ia, ib = agent_tracks([a, b])[0][:2]  # padded to six steps: the first two are these keyframes
    common = [(i, int(np.flatnonzero(ib == t)[0])) for i, t in enumerate(ia) if t >= 0 and (ib == t).any()]
    if not common:
        return AgentBoxes.empty()
    pa, pb = np.array([c[0] for c in common]), np.array([c[1] for c in common])
    u = r / 5.0
    yaw = a.yaw[pa] + u * ((b.yaw[pb] - a.yaw[pa] + np.pi) % (2 * np.pi) - np.pi)
    return AgentBoxes(a.center[pa] * (1 - u) + b.center[pb] * u, a.size[pa], yaw, tuple(a.category[i] for i in pa))


def contact(s: tracking.TrackedStates, b: int, states: range | list[int], agents: tuple[AgentBoxes, ...],
            size: np.ndarray = EGO_SIZE, ahead: float = 0.0) -> bool:
    """Whether plan `b`'s box (`size`, centred `ahead` m along the heading from the tracked point) touches an
    agent at any of `states`."""
    for j in states:
        h = s.heading[b, j]
        centre = np.array([s.x[b, j] + ahead * np.cos(h), s.y[b, j] + ahead * np.sin(h)])
        if len(hits(centre, float(h), agents_at(agents, j), size)):
            return True
    return False


def study(data: list[Expert], sigma: float, draws: int) -> dict[str, float]:
    """Every figure of the table for one sigma, averaged over `draws` noise draws (draw d seeded d)."""
    rows: dict[str, list[float]] = {}
    starts = [e.start for e in data]
    grid3, fine3, late4 = [5 * k for k in range(1, 7)], list(range(5, 31)), [35, 40]
    for d in range(draws):
        rng = np.random.default_rng(d)
        poses = np.stack([e.poses for e in data])
        poses[..., :2] += rng.normal(0.0, sigma, poses[..., :2].shape)
        s3 = tracking.track(reference(poses[:, :6]), starts)
        s4 = tracking.track(reference(poses), starts)
        own = tracking.track_plans(poses[:, :6, :2], starts)  # headings read off the waypoints
        agents = [e.agents for e in data]
        grid = [contact(s3, b, grid3, agents[b]) for b in range(len(data))]
        figures = {
            "comfort_3s": tracking.tracked_comfort(s3).mean(), "comfort_4s": tracking.tracked_comfort(s4).mean(),
            "comfort_own_headings": tracking.tracked_comfort(own).mean(),
            "contact_grid": np.mean(grid),
            "contact_10hz": np.mean([contact(s3, b, fine3, agents[b]) for b in range(len(data))]),
            "contact_4th_second_only": np.mean([not g and contact(s4, b, late4, agents[b])
                                                for b, g in enumerate(grid)]),
            "contact_pacifica_rear_axle": np.mean([contact(s3, b, grid3, agents[b], PACIFICA, REAR_AXLE_TO_CENTRE)
                                                   for b in range(len(data))]),
            "contact_pacifica_centred": np.mean([contact(s3, b, grid3, agents[b], PACIFICA)
                                                 for b in range(len(data))])}
        for key, value in figures.items():
            rows.setdefault(key, []).append(float(value))
    return {k: float(np.mean(v)) for k, v in rows.items()}


#: The EPDMS's variants (issue 39): the suite as it scores (NAVSIM v2.2's terms where the data allow) and each
#: remaining adaptation, or a former rule, swapped in.
EPDMS_VARIANTS: tuple[str, ...] = ("as scored", "no route (nearest same-way lane)", "hc filtered (former rule)",
                                   "no past before the scene's 4th keyframe (hc 1)", "side rule without lanes",
                                   "NAVSIM's Pacifica box (centred)")


#: The lane change plan: the expert moved this far left (m), reached at 1 s and held.
LANE_CHANGE_M: float = 3.5


def epdms_variants(prepared: pdms.PreparedFrame, pacifica: pdms.PreparedFrame, index: int,
                   plan: np.ndarray) -> dict[str, float]:
    """One plan's EPDMS (ec not scored, a one-frame figure) under each of EPDMS_VARIANTS (`pacifica`: the same
    frame prepared with NAVSIM's box)."""
    ps = pdms.tracked_states(plan[None], [prepared.initial])[0]
    result = prepared.score_tracked(plan, ps)
    human = prepared.human
    assert human is not None

    def score(frame: pdms.PreparedFrame, res: pdms.PDMSResult, hum: X.ExtendedTerms) -> float:
        return X.epdms_score(frame.extended(ps, res).filtered(hum), float("nan"))

    lanes = prepared.lanes
    no_route = replace(prepared, lanes=None if lanes is None else replace(lanes, route=None), memo={})
    expert = pdms.tracked_states(prepared.expert[None], [prepared.initial])[0]
    human_hc = replace(human, hc=X.history_comfort(expert, prepared.past))
    bare = replace(prepared, lanes=None, memo={})
    return {"as scored": score(prepared, result, human),
            "no route (nearest same-way lane)": score(no_route, result, human),
            "hc filtered (former rule)": score(prepared, result, human_hc),
            "no past before the scene's 4th keyframe (hc 1)":
                score(replace(prepared, past=None) if index < X.PAST_HC else prepared, result, human),
            "side rule without lanes": score(prepared, bare.score_tracked(plan, ps), human),
            "NAVSIM's Pacifica box (centred)": score(pacifica, pacifica.score_tracked(plan, ps), pacifica.human)}


def epdms_study(scenes: int, seed: int, sigmas: tuple[float, ...], draws: int) -> None:
    """Mean EPDMS and its retention (mean at sigma over mean at 0) of the world's noisy expert plans under each
    variant: what each adaptation moves."""
    from pytest_drivedegrade.data.nuscenes import NuScenesReader
    from pytest_drivedegrade.data.world import write_world

    reader = NuScenesReader(write_world(tempfile.mkdtemp(prefix="ddepdms-"), scenes=scenes, seed=seed,
                                        val_images=False), split="all")
    frames = reader.scorable_frames()
    prepared = [pdms.PreparedFrame.of(f, reader.drivable_area(f), lane_map=reader.lane_map(f)) for f in frames]
    pacifica = [pdms.PreparedFrame.of(f, reader.drivable_area(f), lane_map=reader.lane_map(f),
                                      ego_size=EGO_BOXES["pacifica"]) for f in frames]
    means: dict[float, dict[str, float]] = {}
    for sigma in sigmas:
        rows: dict[str, list[float]] = {v: [] for v in EPDMS_VARIANTS}
        for d in range(draws if sigma else 1):
            rng = np.random.default_rng(d)
            for f, p, q in zip(frames, prepared, pacifica):
                plan = f.gt_future + rng.normal(0.0, sigma, f.gt_future.shape)
                for key, value in epdms_variants(p, q, f.index, plan).items():
                    rows[key].append(value)
        means[sigma] = {k: float(np.nanmean(v)) for k, v in rows.items()}
    change: dict[str, list[float]] = {v: [] for v in EPDMS_VARIANTS}
    shift = np.minimum(np.arange(1, 7) * 0.5, 1.0)[:, None] * [0.0, LANE_CHANGE_M]  # 3.5 m left by 1 s, held
    for f, p, q in zip(frames, prepared, pacifica):
        for key, value in epdms_variants(p, q, f.index, f.gt_future + shift).items():
            change[key].append(value)
    print(f"\nEPDMS (ec not scored) of {len(frames)} frames' expert plans + N(0, sigma^2); retention: over sigma 0")
    print("| variant | " + " | ".join(f"EPDMS {s:g} m" for s in sigmas)
          + " | " + " | ".join(f"retention {s:g} m" for s in sigmas if s) + " | EPDMS, lane change left |")
    print("|---|" + "---|" * (2 * len(sigmas) - (0.0 in sigmas) + 1))
    base = sigmas[0]
    for v in EPDMS_VARIANTS:
        print(f"| {v} | " + " | ".join(f"{means[s][v]:.4f}" for s in sigmas) + " | "
              + " | ".join(f"{means[s][v] / means[base][v]:.4f}" for s in sigmas if s)
              + f" | {np.nanmean(change[v]):.4f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--sigmas", default=",".join(f"{x:g}" for x in SIGMAS), help="noise sigmas (m), comma-separated")
    ap.add_argument("--epdms-only", action="store_true", help="only the EPDMS variants (issue 39)")
    args = ap.parse_args()
    sigmas = tuple(float(x) for x in args.sigmas.split(","))
    epdms_study(args.scenes, args.seed, sigmas, args.draws)
    if args.epdms_only:
        return
    data = experts(args.scenes, args.seed)
    print(f"world: {args.scenes} scenes, seed {args.seed}: {len(data)} expert plans with 4 s of future, "
          f"{args.draws} noise draws per sigma (share of plans)")
    results = {sigma: study(data, sigma, args.draws) for sigma in sigmas}
    print("| figure | " + " | ".join(f"sigma {s:g} m" for s in sigmas) + " |")
    print("|---|" + "---|" * len(sigmas))
    for key in results[sigmas[0]]:
        print(f"| {key} | " + " | ".join(f"{results[s][key]:.3f}" for s in sigmas) + " |")


if __name__ == "__main__":
    main()
