"""The recipe of planners/closed_driver.py: imitation of the world's privileged expert on the front camera, with
data aggregation (DAgger) from the driver's own closed-loop states. CPU only, deterministic for a given seed.

Training routes are disjoint from the closed loop's default slice: the world's TRAIN scenes (the slice drives the
val scenes) and scenario scenes numbered from 1000 (the slice drives scenarios 0-17), a share `--scenario-share`
of them scenario routes. Each round drives every training route once in the closed loop (`closedloop.run_route`)
and, at every planner call, records the front camera's two views as the driver saw them, the ego features and the
expert's plan from that state (`closedloop.expert.WorldExpert`).

- Round 0: the expert drives, its executed plans perturbed (a random lateral drift and speed scale held for a
  few steps), so the data hold states beside the log and the expert's way back.
- Rounds 1..R: the driver trained so far drives (the expert's plan at a share `--beta` of the calls), and
  every state it reaches is labelled by the expert (DAgger).

After each round the network (warm-started) is trained on everything gathered: L1 on the normalised waypoints,
Adam with a cosine schedule.

Levers, off by default: `--corrupt P` drives (and records) each route under an image-quality corruption of AUGMENT
at a random severity 1-5 with probability P (never blackout); `--brake-weight W` draws the samples where the
expert brakes W times as often; `--final-epochs`, `--threads`.

    python planners/train_closed_driver.py [--routes 50] [--rounds 2] [--epochs 20] [--beta 0.2] [--world CACHE_ROOT]

The committed weights were made with the defaults (5859 samples; 1400 s on this 2-core machine while shared).
Reruns gather the same data but do not train bit-identical weights across processes (cause not found;
docs/how-to/closed-loop.md gives the spread). One experiment with the levers (54 routes,
two thirds scenario, 3 rounds, --corrupt 0.3 with low light, --brake-weight 2: 2567 s) scored worse on the slice
and is documented in docs/how-to/closed-loop.md.
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
from closed_driver import WEIGHTS, ClosedDriver, DriverNet, preprocess  # noqa: E402

from pytest_drivedegrade.closedloop import Corruption, route_of, run_route  # noqa: E402
from pytest_drivedegrade.closedloop.expert import WorldExpert  # noqa: E402
from pytest_drivedegrade.closedloop.routes import Route  # noqa: E402
from pytest_drivedegrade.closedloop.simulate import Rules  # noqa: E402
from pytest_drivedegrade.constants import HORIZON_STEPS  # noqa: E402
from pytest_drivedegrade.data.context import FrameContext  # noqa: E402
from pytest_drivedegrade.data.frame import Command, EgoStatus  # noqa: E402
from pytest_drivedegrade.data.world.scenarios import scenario_scene  # noqa: E402
from pytest_drivedegrade.data.world.scene import make_scene  # noqa: E402
from pytest_drivedegrade.floor import ego_features  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The image-quality families a route may be driven under while gathering (`--corrupt`; the slice's blur cells
#: among them). Not low_light: at S4-S5 it is nearly black, and a driver trained on it drove on blind (measured:
#: blackout S5 completion 0.95, DS 37.2, where the committed weights stop at completion 0.11, DS 10.2).
AUGMENT: tuple[str, ...] = ("gaussian_blur", "motion_blur", "gaussian_noise", "jpeg", "downscale")
#: Share of the training routes that are scenario routes (the committed weights: half).
SCENARIO_SHARE = 0.5
#: A sample whose expert plan covers less than BRAKE_SHARE of the ego's current speed x horizon is a braking
#: sample, drawn `--brake-weight` times as often in training (BRAKE_WEIGHT in the experiment of the docs).
BRAKE_SHARE, BRAKE_WEIGHT = 0.8, 2.0
#: Index of the ego's forward speed in `ego_features`.
SPEED_FEATURE = 0


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


def training_routes(world: Path, count: int, scenario_share: float = SCENARIO_SHARE) -> list[Route]:
    """`count` routes: the world's first train scenes and scenario scenes numbered from 1000 (none in the default
    slice, which drives the val scenes and scenarios 0-17), a share `scenario_share` of them scenario routes."""
    manifest = json.loads((world / "drivedegrade_world.json").read_text())
    seed, train = int(manifest["seed"]), list(manifest["splits"]["train"])
    names = train + list(manifest["splits"]["val"])
    scenarios = int(count * scenario_share + 1e-9)
    scenes = [make_scene(seed, names.index(n), n) for n in train[:count - scenarios]]
    scenes += [scenario_scene(seed, 1000 + i) for i in range(scenarios)]
    return [route_of(s) for s in scenes]


def route_corruption(rng: np.random.Generator, share: float) -> Corruption:
    """Clean, or (at probability `share`) an image-quality family of AUGMENT at a random severity 1..5: the
    cameras a route is driven and recorded under. Never blackout: the driver must not learn to drive blind."""
    if share <= 0 or rng.random() >= share:  # share 0 draws nothing: the committed weights' sequence
        return Corruption()
    return Corruption(AUGMENT[int(rng.integers(len(AUGMENT)))], int(rng.integers(1, 6)))


def gather(routes: list[Route], learner: ClosedDriver | None, beta: float, seed: int,
           corrupt: float = 0.0) -> tuple[np.ndarray, ...]:
    """Drive every route once (the expert perturbed, or the learner with the expert at share `beta`), each under
    `route_corruption`; the recorded (views, features, expert plans)."""
    expert = WorldExpert(routes)
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
    parser.add_argument("--routes", type=int, default=50)
    parser.add_argument("--scenario-share", type=float, default=SCENARIO_SHARE, help="share of scenario routes")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--epochs", type=int, default=20, help="epochs after each round but the last")
    parser.add_argument("--final-epochs", type=int, default=None, help="epochs after the last round (--epochs)")
    parser.add_argument("--beta", type=float, default=0.2)
    parser.add_argument("--corrupt", type=float, default=0.0,
                        help="share of routes driven under a random image-quality corruption of AUGMENT")
    parser.add_argument("--brake-weight", type=float, default=1.0, help="how much more often braking samples are "
                        "drawn (1: every sample once an epoch)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=WEIGHTS)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the weights depend on it)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    from pytest_drivedegrade.data.world import ensure_default_world

    start = time.perf_counter()
    world = args.world if (args.world / "drivedegrade_world.json").is_file() else Path(ensure_default_world(args.world))
    routes = training_routes(world, args.routes, args.scenario_share)
    final_epochs = args.epochs if args.final_epochs is None else args.final_epochs
    data = [gather(routes, None, 1.0, args.seed, args.corrupt)]
    net = DriverNet()
    for r in range(args.rounds + 1):
        pix, feats, plans = (np.concatenate(parts) for parts in zip(*data))
        print(f"round {r}: training on {len(pix)} samples", flush=True)
        train(net, pix, feats, plans, final_epochs if r == args.rounds else args.epochs, args.seed + r,
              args.brake_weight)
        if r < args.rounds:
            data.append(gather(routes, ClosedDriver(net=net), args.beta, args.seed + 100 + r, args.corrupt))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), args.out)
    meta = {"recipe": "planners/train_closed_driver.py", "routes": args.routes, "rounds": args.rounds,
            "epochs": args.epochs, "final_epochs": final_epochs, "beta": args.beta, "corrupt": args.corrupt,
            "scenario_share": args.scenario_share, "brake_weight": args.brake_weight,
            "seed": args.seed, "threads": args.threads, "samples": int(len(pix)),
            "seconds": round(time.perf_counter() - start, 1)}
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    print(f"wrote {args.out} ({meta['seconds']} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
