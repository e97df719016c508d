"""The recipe of planners/closed_driver.py: the front camera taught to read what the world expert's rule needs
(`closedloop.percept.Percept`, labelled by the world at the ego's own state: `WorldPercept`), with data
aggregation (DAgger) from the driver's own closed-loop states. CPU only; a rerun with the same seed, thread count,
torch and OpenCV writes the same weights bit for bit.

Training routes are disjoint from the closed loop's default slice: the world's TRAIN scenes (the slice drives the
val scenes), scenario scenes and light scenes numbered from 1000 (the slice drives scenarios 0-17 and lights 0-5),
shares `--scenario-share` and `--light-share` of them scenario and light routes. Each round drives every training
route once in the closed loop (`closedloop.run_route`; the routes dealt to `--workers` processes, each route's
draws seeded by the round and its index) and, at every planner call, records the front camera's views as the
driver saw them, the ego features and the world's percept at that state.

- Round 0: the percept bound drives (`closedloop.percept.PerceptExpert`), its plans perturbed (a random lateral
  drift and speed scale held for a few steps), so the data hold states beside the lane and the way back.
- Rounds 1..R: the driver trained so far drives (the bound's plan at a share `--beta` of the calls), and every
  state it reaches is labelled (DAgger).

After each round the network (warm-started; first drawn with the seed) is trained on everything gathered: L1 on
the normalised regressed outputs, 0.2 x L1 on the lead's speed where an obstacle is within 40 m, 2 x binary cross
entropy on the profiles and yellow; Adam with a cosine schedule.

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
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
from closed_driver import (  # noqa: E402
    MEMBERS,
    N_REGRESSED,
    WEIGHTS,
    ClosedDriver,
    PerceptEnsemble,
    PerceptNet,
    preprocess,
    targets,
)

from pytest_drivedegrade.closedloop import Corruption, route_of, run_route  # noqa: E402
from pytest_drivedegrade.closedloop.percept import Percept, PerceptExpert  # noqa: E402
from pytest_drivedegrade.closedloop.routes import HELD_OUT_FROM, Route  # noqa: E402
from pytest_drivedegrade.closedloop.simulate import Rules  # noqa: E402
from pytest_drivedegrade.data.context import FrameContext  # noqa: E402
from pytest_drivedegrade.data.frame import Command, EgoStatus  # noqa: E402
from pytest_drivedegrade.data.world.scenarios import light_scene, scenario_scene  # noqa: E402
from pytest_drivedegrade.data.world.scene import make_scene  # noqa: E402
from pytest_drivedegrade.floor import ego_features  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: Share of the training routes that are scenario routes, and light routes (the rest: the world's train scenes).
SCENARIO_SHARE, LIGHT_SHARE = 0.47, 0.47
#: Loss weights of the lead's speed (L1, normalised) and of the probabilities (binary cross entropy).
LEAD_WEIGHT, PROFILE_WEIGHT = 0.2, 2.0


class Collector:
    """Drives a route as the percept bound (perturbed) or as the learner, recording (views, features, percept)."""

    cameras: tuple[str, ...] = ("CAM_FRONT",)

    def __init__(self, routes: list[Route], learner: ClosedDriver | None, beta: float, rng: np.random.Generator):
        self.bound, self.learner, self.beta, self.rng = PerceptExpert(routes), learner, beta, rng
        self.pix: list[np.ndarray] = []
        self.feats: list[np.ndarray] = []
        self.labels: list[Percept] = []
        self.drift, self.scale, self.hold = 0.0, 1.0, 0

    def reset(self, route: str) -> None:
        self.bound.reset(route)
        if self.learner is not None:
            self.learner.reset(route)
        self.drift, self.scale, self.hold = 0.0, 1.0, 0

    def predict(self, images: Mapping[str, np.ndarray], ego: EgoStatus, cmd: Command,
                context: FrameContext | None = None) -> np.ndarray:
        assert context is not None
        label = self.bound.percept(context)
        self.labels.append(label)
        self.pix.append(preprocess(images))
        self.feats.append(ego_features(ego, cmd))
        plan = self.bound.plan(label, ego)  # the label's percept, not read from the world a second time
        if self.learner is not None:
            mine = self.learner.predict(images, ego, cmd)
            return plan if self.rng.random() < self.beta else mine
        if self.hold <= 0:  # round 0: the bound, perturbed
            self.drift, self.scale = float(self.rng.normal(0.0, 0.8)), float(self.rng.uniform(0.75, 1.25))
            self.hold = int(self.rng.integers(2, 6))
        self.hold -= 1
        out = np.array(plan, dtype=np.float64)
        out[:, 0] *= self.scale
        out[:, 1] += self.drift * np.arange(1, len(out) + 1) / len(out)
        return out


def training_specs(world: Path, count: int, scenario_share: float = SCENARIO_SHARE,
                   light_share: float = LIGHT_SHARE) -> list[tuple[str, int, int, str]]:
    """What `count` training routes are, as (kind, world seed, index, name): the world's first train scenes,
    scenario scenes and light scenes numbered from 1000 (none in the default slice, which drives the val scenes,
    scenarios 0-17 and light scenes 0-5), a share `scenario_share` of them scenario routes and `light_share` light
    routes. Cheap: `route_of_spec` builds each route where it is driven."""
    manifest = json.loads((world / "drivedegrade_world.json").read_text())
    seed, train = int(manifest["seed"]), list(manifest["splits"]["train"])
    names = train + list(manifest["splits"]["val"])
    scenarios, lights = int(count * scenario_share + 1e-9), int(count * light_share + 1e-9)
    if max(scenarios, lights) > HELD_OUT_FROM - 1000:
        raise ValueError(f"{max(scenarios, lights)} scenario or light training routes would reach the held-out "
                         f"scenes numbered from {HELD_OUT_FROM} (benchmarks/closedloop.py --held-out): at most "
                         f"{HELD_OUT_FROM - 1000} of each")
    if count - scenarios - lights > len(train):
        raise ValueError(f"{world}: {count - scenarios - lights} train scenes asked for, the world has {len(train)}: "
                         "fewer --routes or larger --scenario-share / --light-share")
    return [*(("train", seed, names.index(n), n) for n in train[:count - scenarios - lights]),
            *(("scenario", seed, 1000 + i, "") for i in range(scenarios)),
            *(("light", seed, 1000 + i, "") for i in range(lights))]


def route_of_spec(spec: tuple[str, int, int, str]) -> Route:
    kind, seed, index, name = spec
    if kind == "train":
        return route_of(make_scene(seed, index, name))
    return route_of(scenario_scene(seed, index) if kind == "scenario" else light_scene(seed, index))


def training_routes(world: Path, count: int, scenario_share: float = SCENARIO_SHARE,
                    light_share: float = LIGHT_SHARE) -> list[Route]:
    """The routes of `training_specs`."""
    return [route_of_spec(spec) for spec in training_specs(world, count, scenario_share, light_share)]


def _gather_part(job: tuple) -> list[tuple[int, np.ndarray, np.ndarray, list[Percept], float]]:
    """One worker's share of a round: routes `part`, `part + workers`, ... driven by the bound or the learner; each
    route's draws seeded by the round's seed and its index, so the data do not depend on the number of workers.
    Per route: (index, views, features, percepts, DS)."""
    specs, weights, members, part, workers, seed, beta = job
    torch.set_num_threads(1)
    learner = None
    if weights is not None:
        learner = ClosedDriver(net=PerceptEnsemble(members))
        learner.net.load_state_dict(weights)
    out = []
    for i in range(part, len(specs), workers):
        route = route_of_spec(specs[i])
        collector = Collector([route], learner, beta, np.random.default_rng([seed, i]))
        run = run_route(collector, route, Corruption(), seed=seed * 1000 + i, rules=Rules(timeout=0))
        if run.error:
            print(f"  {route.name}: unscored ({run.error})", flush=True)
        out.append((i, np.stack(collector.pix), np.stack(collector.feats).astype(np.float32), collector.labels,
                    run.ds if run.ds is not None else 0.0))
    return out


def gather(specs: list, net: PerceptEnsemble | None, beta: float, seed: int, workers: int,
           ) -> tuple[np.ndarray, np.ndarray, list[Percept]]:
    """Drive every route once (the bound perturbed, or the learner with the bound at share `beta`) in `workers`
    processes; the recorded (views, features, percepts), route by route in the routes' order (the same for any
    number of workers)."""
    weights = None if net is None else {k: v.clone() for k, v in net.state_dict().items()}
    members = MEMBERS if net is None else len(net.members)
    jobs = [(specs, weights, members, part, workers, seed, beta) for part in range(workers)]
    if workers == 1:
        threads = torch.get_num_threads()
        parts = [_gather_part(jobs[0])]
        torch.set_num_threads(threads)  # the driver drives on one thread; training goes on with --threads
    else:
        with ProcessPoolExecutor(workers) as pool:
            parts = list(pool.map(_gather_part, jobs))
    routes = sorted((r for part in parts for r in part), key=lambda r: r[0])
    labels = [p for r in routes for p in r[3]]
    print(f"  drove {len(specs)} routes: DS {np.mean([r[4] for r in routes]):.1f} "
          f"({'learner' if net else 'bound, perturbed'}), {len(labels)} samples", flush=True)
    return np.concatenate([r[1] for r in routes]), np.concatenate([r[2] for r in routes]), labels


def initial_network(seed: int, members: int = MEMBERS) -> PerceptEnsemble:
    """The untrained ensemble, its weights drawn from torch's generator seeded with `seed`. torch seeds its default
    generator at random in every process (measured: `torch.initial_seed()` differs run to run), so a network drawn
    unseeded made every rerun of the recipe a different driver."""
    torch.manual_seed(seed)
    return PerceptEnsemble(members)


def train(net: PerceptNet, pix: np.ndarray, feats: np.ndarray, labels: list[Percept], epochs: int, seed: int) -> None:
    """L1 on the normalised regressed outputs, LEAD_WEIGHT x L1 on the lead's speed where it is learnt,
    PROFILE_WEIGHT x binary cross entropy on the probabilities; Adam with a cosine schedule, each epoch a seeded
    permutation of the samples."""
    torch.manual_seed(seed)
    wanted, learn_speed = targets(labels)
    net.x_mean.copy_(torch.from_numpy(feats.mean(0)))
    net.x_std.copy_(torch.from_numpy(feats.std(0) + 1e-3))
    net.y_mean.copy_(torch.from_numpy(wanted[:, :N_REGRESSED].mean(0)))
    net.y_std.copy_(torch.from_numpy(wanted[:, :N_REGRESSED].std(0) + 1e-3))
    x, f, mask = torch.from_numpy(pix), torch.from_numpy(feats), torch.from_numpy(learn_speed)
    y = torch.from_numpy(wanted).clone()
    y[:, :N_REGRESSED] = (y[:, :N_REGRESSED] - net.y_mean) / net.y_std
    opt = torch.optim.Adam(net.parameters(), lr=2e-3, weight_decay=1e-5)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    gen = torch.Generator().manual_seed(seed)
    bce = nn.BCEWithLogitsLoss()
    lead = N_REGRESSED - 1
    net.train()
    for epoch in range(epochs):
        order = torch.randperm(len(x), generator=gen)
        total = 0.0
        for i in range(0, len(x), 64):
            idx = order[i:i + 64]
            out, want, m = net(x[idx], f[idx]), y[idx], mask[idx]
            loss = (out[:, :lead] - want[:, :lead]).abs().mean() \
                + LEAD_WEIGHT * ((out[:, lead] - want[:, lead]).abs() * m).sum() / m.sum().clamp(min=1) \
                + PROFILE_WEIGHT * bce(out[:, N_REGRESSED:], want[:, N_REGRESSED:])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        sched.step()
        if epoch % 4 == 3 or epoch == epochs - 1:
            print(f"  epoch {epoch + 1}: loss {total / len(x):.4f}", flush=True)
    net.eval()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, default=ROOT / ".pytest_cache/d/drivedegrade",
                        help="the cache root the default world is built in, or a world data root")
    parser.add_argument("--routes", type=int, default=1200)
    parser.add_argument("--scenario-share", type=float, default=SCENARIO_SHARE, help="share of scenario routes")
    parser.add_argument("--light-share", type=float, default=LIGHT_SHARE, help="share of light routes")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--epochs", type=int, default=12, help="epochs after each round")
    parser.add_argument("--beta", type=float, default=0.2)
    parser.add_argument("--members", type=int, default=MEMBERS, help="networks in the ensemble")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=WEIGHTS)
    parser.add_argument("--workers", type=int, default=2, help="processes that drive the routes (no effect on "
                        "the weights)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads in training (the weights depend on it)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    from pytest_drivedegrade.data.world import ensure_default_world

    start = time.perf_counter()
    world = args.world if (args.world / "drivedegrade_world.json").is_file() else Path(ensure_default_world(args.world))
    specs = training_specs(world, args.routes, args.scenario_share, args.light_share)
    data = [gather(specs, None, 1.0, args.seed, args.workers)]
    net = initial_network(args.seed, args.members)
    for r in range(args.rounds + 1):
        pix, feats = (np.concatenate([d[i] for d in data]) for i in (0, 1))
        labels = [p for d in data for p in d[2]]
        print(f"round {r}: training on {len(pix)} samples ({time.perf_counter() - start:.0f} s)", flush=True)
        for m, member in enumerate(net.members):  # each member its own sample order
            train(member, pix, feats, labels, args.epochs, args.seed + r + 1000 * m)
        if r < args.rounds:
            data.append(gather(specs, net, args.beta, args.seed + 100 + r, args.workers))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), args.out)
    meta = {"recipe": "planners/train_closed_driver.py", "routes": args.routes, "rounds": args.rounds,
            "epochs": args.epochs, "beta": args.beta, "scenario_share": args.scenario_share,
            "light_share": args.light_share, "seed": args.seed, "members": args.members, "threads": args.threads,
            "samples": int(len(pix)), "seconds": round(time.perf_counter() - start, 1)}
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    print(f"wrote {args.out} ({meta['seconds']} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
