"""The recipe of planners/closed_driver.py: imitation of the world's privileged expert on the front camera, with
data aggregation (DAgger) from the driver's own closed-loop states. CPU only; a rerun with the same seed, torch
and OpenCV writes the same weights bit for bit.

Training routes are disjoint from the closed loop's default slice: the world's TRAIN scenes (the slice drives the
val scenes), scenario scenes and light scenes numbered from 1000 (the slice drives scenarios 0-17 and lights 0-5),
shares `--scenario-share` and `--light-share` of them scenario and light routes. Each round drives every training
route once in the closed loop (`closedloop.run_route`) and, at every planner call, records the front camera's
views as the driver saw them, the ego features and the expert's plan from that state (`ReplanExpert`: the log's
plan on the log; off it, the world's expert rule driven from the ego's own state, catching up while behind).

- Round 0: the expert drives, its executed plans perturbed (a random lateral drift and speed scale held for a
  few steps), so the data hold states beside the log and the expert's way back.
- Rounds 1..R: the driver trained so far drives (the expert's plan at a share `--beta` of the calls), and
  every state it reaches is labelled by the expert (DAgger).

After each round the network (warm-started; first drawn with the seed) is trained on everything gathered: L1 on
the normalised waypoints, Adam with a cosine schedule.

Levers: `--catch-up` (0: the log's positions as labels everywhere, the recipe of the weights before 2026-11-29's
retraining); `--corrupt P` drives (and records) each route under an image-quality corruption of AUGMENT at a random
severity 1-5 with probability P (never blackout); `--brake-weight W` draws the samples where the expert brakes W
times as often; `--final-epochs`, `--threads`.

    python planners/train_closed_driver.py [--routes N] [--rounds R] [--world CACHE_ROOT] [--out PATH]

The committed weights were made with the defaults; docs/how-to/closed-loop.md has what they measure, the
experiments beside them and their cost on this 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from closed_driver import MEMBERS, WEIGHTS, ClosedDriver, DriverEnsemble, DriverNet, preprocess  # noqa: E402

from pytest_drivedegrade.closedloop import Corruption, route_of, run_route  # noqa: E402
from pytest_drivedegrade.closedloop.expert import WorldExpert, log_ahead  # noqa: E402
from pytest_drivedegrade.closedloop.loop_io import to_ego  # noqa: E402
from pytest_drivedegrade.closedloop.routes import Route  # noqa: E402
from pytest_drivedegrade.closedloop.simulate import PLAN_EVERY, Rules  # noqa: E402
from pytest_drivedegrade.constants import HORIZON_STEPS  # noqa: E402
from pytest_drivedegrade.data.context import FrameContext  # noqa: E402
from pytest_drivedegrade.data.frame import Command, EgoStatus  # noqa: E402
from pytest_drivedegrade.data.world.agents import DT  # noqa: E402
from pytest_drivedegrade.data.world.expert import SIM_STEPS, ExpertRule, LightStops  # noqa: E402
from pytest_drivedegrade.data.world.scenarios import light_scene, scenario_scene  # noqa: E402
from pytest_drivedegrade.data.world.scene import make_scene  # noqa: E402
from pytest_drivedegrade.floor import ego_features  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The image-quality families a route may be driven under while gathering (`--corrupt`; the slice's blur cells
#: among them). Not low_light: at S4-S5 it is nearly black, and a driver trained on it drove on blind (measured:
#: blackout S5 completion 0.95, DS 37.2, where the weights of the time stopped at completion 0.11, DS 10.2).
AUGMENT: tuple[str, ...] = ("gaussian_blur", "motion_blur", "gaussian_noise", "jpeg", "downscale")
#: Share of the training routes that are scenario routes.
SCENARIO_SHARE = 0.34
#: Share of the training routes that are light routes (traffic lights).
LIGHT_SHARE = 0.33
#: A sample whose expert plan covers less than BRAKE_SHARE of the ego's current speed x horizon is a braking
#: sample, drawn `--brake-weight` times as often in training (BRAKE_WEIGHT in the experiment of the docs).
BRAKE_SHARE, BRAKE_WEIGHT = 0.8, 2.0
#: Off the log by more than ON_LOG_M (m), a state is labelled by the world's expert rule from the ego's own state,
#: aiming CATCH_UP m/s above the cruise speed while behind the log (`--catch-up`; 0: the log's positions always).
ON_LOG_M, CATCH_UP = 1.0, 2.0
#: Index of the ego's forward speed in `ego_features`.
SPEED_FEATURE = 0


class ReplanExpert(WorldExpert):
    """The labels: the world expert's plan (the log's positions at +0.5 .. +3 s) where the ego is on the log, and
    off it, the world's expert rule (`data.world.expert.ExpertRule`: IDM to the cruise speed, bends, obstacles in
    the corridor, lights) rolled out from the ego's own state. Behind the log it aims `catch_up` m/s above the cruise
    speed and never plans past the log's positions; ahead of it, it drives on at the cruise speed.

    The world expert alone labels a state 20 m behind the log with a first waypoint 20 m away (40 m/s for 0.5 s),
    and a state past the log (a red light run) with "stand until the log catches up": a network trained on those
    labels planned a far first waypoint and a short rest, which the tracker turns into braking (measured: 6.6 ->
    1.7 m/s in 5 s on scenario 10 while the log drove at 7 m/s)."""

    def __init__(self, routes, catch_up: float = CATCH_UP) -> None:
        super().__init__(routes)
        self.catch_up = catch_up
        self._rule: ExpertRule | None = None

    def reset(self, route: str) -> None:
        super().reset(route)
        scene = self._routes[route].scene
        lights = LightStops.on(scene.lane, list(scene.lights), scene.net) if scene.lights else None
        self._rule = ExpertRule.of(scene.lane, scene.agents, scene.v_cruise, lights=lights)

    def replan(self, t: int, s: float, v: float, v_des: float) -> np.ndarray:
        """Arc lengths at +0.5 .. +3 s of the world's expert rule driven from (s, v) at sim step `t`, aiming at
        `v_des`."""
        assert self._rule is not None
        rule, out = self._rule, []
        engaged = rule.fresh()
        for k in range(PLAN_EVERY * HORIZON_STEPS):
            a, _, _ = rule.accel(min(t + k, SIM_STEPS - 1), s, v, engaged, v_des)
            v_next = max(v + a * DT, 0.0)
            s += 0.5 * (v + v_next) * DT
            v = v_next
            if k % PLAN_EVERY == PLAN_EVERY - 1:
                out.append(s)
        return np.array(out)

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command,
                context: FrameContext | None = None) -> np.ndarray:
        plan = super().predict(images, ego, cmd, context=context)
        if self.catch_up <= 0 or context is None or self._route is None:
            return plan
        route, log = self._route, self._route.scene.ego
        here = np.array([[context.ego2global[0, 3], context.ego2global[1, 3]]])
        s_ego = float(route.lane.project(here)[0][0])
        t = route.start_step + PLAN_EVERY * context.index
        lag = float(log.s[min(t, len(log.s) - 1)]) - s_ego
        if abs(lag) <= ON_LOG_M:
            return plan
        v_cruise = route.scene.v_cruise
        s = self.replan(t, s_ego, max(float(ego.velocity[0]), 0.0), v_cruise + (self.catch_up if lag > 0 else 0.0))
        if lag > 0:  # behind: never past the log
            s = np.minimum(s, log_ahead(route, t))
        x, y, _ = route.lane.at(s)
        pose = (float(here[0, 0]), float(here[0, 1]),
                float(np.arctan2(context.ego2global[1, 0], context.ego2global[0, 0])))
        return to_ego(np.stack([x, y], axis=1), pose)


class Collector:
    """Drives a route as the expert (perturbed) or as the learner, recording (views, features, expert plan)."""

    cameras: tuple[str, ...] = ("CAM_FRONT",)

    def __init__(self, expert: WorldExpert, learner: ClosedDriver | None, beta: float, rng: np.random.Generator):
        self.expert, self.learner, self.beta, self.rng = expert, learner, beta, rng
        self.pix: list[np.ndarray] = []
        self.feats: list[np.ndarray] = []
        self.plans: list[np.ndarray] = []
        self.drift, self.scale, self.hold = 0.0, 1.0, 0

    def reset(self, route: str) -> None:
        self.expert.reset(route)
        self.drift, self.scale, self.hold = 0.0, 1.0, 0

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command,
                context: FrameContext | None = None) -> np.ndarray:
        label = self.expert.predict(images, ego, cmd, context=context)
        self.pix.append(preprocess(images))
        self.feats.append(ego_features(ego, cmd))
        self.plans.append(np.asarray(label, dtype=np.float32).reshape(-1))
        if self.learner is not None and self.rng.random() >= self.beta:
            return self.learner.predict(images, ego, cmd)
        if self.learner is None:  # round 0: the expert, perturbed
            if self.hold <= 0:
                self.drift, self.scale = float(self.rng.normal(0.0, 0.8)), float(self.rng.uniform(0.75, 1.25))
                self.hold = int(self.rng.integers(2, 6))
            self.hold -= 1
            out = np.array(label, dtype=np.float64)
            out[:, 0] *= self.scale
            out[:, 1] += self.drift * np.arange(1, len(out) + 1) / len(out)
            return out
        return label


def training_routes(world: Path, count: int, scenario_share: float = SCENARIO_SHARE,
                    light_share: float = LIGHT_SHARE) -> list[Route]:
    """`count` routes: the world's first train scenes, scenario scenes and light scenes numbered from 1000 (none
    in the default slice, which drives the val scenes, scenarios 0-17 and light scenes 0-5), a share
    `scenario_share` of them scenario routes and `light_share` light routes."""
    manifest = json.loads((world / "drivedegrade_world.json").read_text())
    seed, train = int(manifest["seed"]), list(manifest["splits"]["train"])
    names = train + list(manifest["splits"]["val"])
    scenarios, lights = int(count * scenario_share + 1e-9), int(count * light_share + 1e-9)
    if count - scenarios - lights > len(train):
        raise ValueError(f"{world}: {count - scenarios - lights} train scenes asked for, the world has {len(train)}: "
                         "fewer --routes or larger --scenario-share / --light-share")
    scenes = [make_scene(seed, names.index(n), n) for n in train[:count - scenarios - lights]]
    scenes += [scenario_scene(seed, 1000 + i) for i in range(scenarios)]
    scenes += [light_scene(seed, 1000 + i) for i in range(lights)]
    return [route_of(s) for s in scenes]


def route_corruption(rng: np.random.Generator, share: float) -> Corruption:
    """Clean, or (at probability `share`) an image-quality family of AUGMENT at a random severity 1..5: the
    cameras a route is driven and recorded under. Never blackout: the driver must not learn to drive blind."""
    if share <= 0 or rng.random() >= share:  # share 0 draws nothing: the committed weights' sequence
        return Corruption()
    return Corruption(AUGMENT[int(rng.integers(len(AUGMENT)))], int(rng.integers(1, 6)))


def gather(routes: list[Route], learner: ClosedDriver | None, beta: float, seed: int,
           corrupt: float = 0.0, catch_up: float = 0.0) -> tuple[np.ndarray, ...]:
    """Drive every route once (the expert perturbed, or the learner with the expert at share `beta`), each under
    `route_corruption`; the recorded (views, features, expert plans)."""
    expert = ReplanExpert(routes, catch_up)
    rng = np.random.default_rng(seed)
    c = Collector(expert, learner, beta, rng)
    ds = []
    for i, route in enumerate(routes):
        run = run_route(c, route, route_corruption(rng, corrupt), seed=seed * 1000 + i, rules=Rules(timeout=0))
        ds.append(run.ds if run.ds is not None else 0.0)
        if run.error:
            print(f"  {route.name}: unscored ({run.error})", flush=True)
    print(f"  drove {len(routes)} routes: DS {np.mean(ds):.1f} ({'learner' if learner else 'expert, perturbed'}), "
          f"{len(c.pix)} samples", flush=True)
    return np.stack(c.pix), np.stack(c.feats).astype(np.float32), np.stack(c.plans)


def sample_weights(feats: np.ndarray, plans: np.ndarray, weight: float = BRAKE_WEIGHT) -> np.ndarray:
    """`weight` for a sample whose expert plan ends short of BRAKE_SHARE of the way the ego's current speed
    would cover over the horizon (the expert brakes: a stopped vehicle, a crossing, a braking lead), 1 otherwise."""
    speed = feats[:, SPEED_FEATURE]
    reach = plans.reshape(len(plans), -1, 2)[:, -1, 0]
    horizon = HORIZON_STEPS * 0.5
    return np.where(reach < BRAKE_SHARE * speed * horizon, weight, 1.0)


def initial_network(seed: int, members: int = MEMBERS) -> DriverEnsemble:
    """The untrained ensemble, its weights drawn from torch's generator seeded with `seed`. torch seeds its default
    generator at random in every process (measured: `torch.initial_seed()` differs run to run), so a network drawn
    unseeded made every rerun of the recipe a different driver."""
    torch.manual_seed(seed)
    return DriverEnsemble(members)


def train(net: DriverNet, pix: np.ndarray, feats: np.ndarray, plans: np.ndarray, epochs: int, seed: int,
          brake_weight: float = 1.0) -> None:
    """L1 on the normalised waypoints, Adam with a cosine schedule; each epoch a seeded permutation of the
    samples, or (`brake_weight` above 1) len(pix) draws with replacement weighted by `sample_weights`."""
    torch.manual_seed(seed)
    net.x_mean.copy_(torch.from_numpy(feats.mean(0)))
    net.x_std.copy_(torch.from_numpy(feats.std(0) + 1e-3))
    net.y_mean.copy_(torch.from_numpy(plans.mean(0)))
    net.y_std.copy_(torch.from_numpy(plans.std(0) + 1e-3))
    x, f = torch.from_numpy(pix), torch.from_numpy(feats)
    y = (torch.from_numpy(plans) - net.y_mean) / net.y_std
    opt = torch.optim.Adam(net.parameters(), lr=2e-3, weight_decay=1e-5)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    gen = torch.Generator().manual_seed(seed)
    net.train()
    weights = torch.from_numpy(sample_weights(feats, plans, brake_weight))
    for epoch in range(epochs):
        order = torch.randperm(len(x), generator=gen) if brake_weight == 1.0 else \
            torch.multinomial(weights, len(x), replacement=True, generator=gen)
        total = 0.0
        for i in range(0, len(x), 64):
            idx = order[i:i + 64]
            loss = (net(x[idx], f[idx]) - y[idx]).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        sched.step()
        if epoch % 5 == 4 or epoch == epochs - 1:
            print(f"  epoch {epoch + 1}: L1 {total / len(x):.4f}", flush=True)
    net.eval()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, default=ROOT / ".pytest_cache/d/drivedegrade",
                        help="the cache root the default world is built in, or a world data root")
    parser.add_argument("--routes", type=int, default=90)
    parser.add_argument("--scenario-share", type=float, default=SCENARIO_SHARE, help="share of scenario routes")
    parser.add_argument("--light-share", type=float, default=LIGHT_SHARE, help="share of light routes")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--epochs", type=int, default=20, help="epochs after each round but the last")
    parser.add_argument("--final-epochs", type=int, default=None, help="epochs after the last round (--epochs)")
    parser.add_argument("--beta", type=float, default=0.2)
    parser.add_argument("--corrupt", type=float, default=0.0,
                        help="share of routes driven under a random image-quality corruption of AUGMENT")
    parser.add_argument("--brake-weight", type=float, default=1.0, help="how much more often braking samples are "
                        "drawn (1: every sample once an epoch)")
    parser.add_argument("--catch-up", type=float, default=CATCH_UP,
                        help="off the log, label by the world's expert rule from the ego's state, this many m/s above "
                        "the cruise speed while behind (0: the log's positions)")
    parser.add_argument("--members", type=int, default=MEMBERS, help="networks in the ensemble")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=WEIGHTS)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the weights depend on it)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    from pytest_drivedegrade.data.world import ensure_default_world

    start = time.perf_counter()
    world = args.world if (args.world / "drivedegrade_world.json").is_file() else Path(ensure_default_world(args.world))
    routes = training_routes(world, args.routes, args.scenario_share, args.light_share)
    final_epochs = args.epochs if args.final_epochs is None else args.final_epochs
    data = [gather(routes, None, 1.0, args.seed, args.corrupt, args.catch_up)]
    net = initial_network(args.seed, args.members)
    for r in range(args.rounds + 1):
        pix, feats, plans = (np.concatenate(parts) for parts in zip(*data))
        print(f"round {r}: training on {len(pix)} samples", flush=True)
        for m, member in enumerate(net.members):  # each member its own sample order
            train(member, pix, feats, plans, final_epochs if r == args.rounds else args.epochs,
                  args.seed + r + 1000 * m, args.brake_weight)
        if r < args.rounds:
            data.append(gather(routes, ClosedDriver(net=net), args.beta, args.seed + 100 + r, args.corrupt,
                              args.catch_up))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), args.out)
    meta = {"recipe": "planners/train_closed_driver.py", "routes": args.routes, "rounds": args.rounds,
            "epochs": args.epochs, "final_epochs": final_epochs, "beta": args.beta, "corrupt": args.corrupt,
            "scenario_share": args.scenario_share, "light_share": args.light_share,
            "brake_weight": args.brake_weight, "catch_up": args.catch_up,
            "seed": args.seed, "members": args.members, "threads": args.threads, "samples": int(len(pix)),
            "seconds": round(time.perf_counter() - start, 1)}
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    print(f"wrote {args.out} ({meta['seconds']} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
