"""The recipe of planners/closed_driver.py: imitation of the world's privileged expert on the front camera, with
data aggregation (DAgger) from the driver's own closed-loop states. CPU only, deterministic for a given seed.

Training routes are disjoint from the closed loop's default slice: the world's TRAIN scenes (the slice drives the
val scenes) and scenario scenes numbered from 1000 (the slice drives scenarios 0-17). Each round drives every
training route once in the closed loop (`closedloop.run_route`) and, at every planner call, records the front
camera's two views, the ego features and the expert's plan from that state (`closedloop.expert.WorldExpert`).

- Round 0: the expert drives, its executed plans perturbed (a random lateral drift and speed scale held for a
  few steps), so the data hold states beside the log and the expert's way back.
- Rounds 1..R: the driver trained so far drives (the expert's plan at a share `--beta` of the calls), and
  every state it reaches is labelled by the expert.

After each round the network is trained on everything gathered (L1 on the normalised waypoints, Adam).

    python planners/train_closed_driver.py [--routes 50] [--rounds 2] [--epochs 20] [--beta 0.2] [--world CACHE_ROOT]

The committed weights were made with the defaults (5859 samples; 1400 s on this 2-core machine while shared).
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

from pytest_drivedegrade.closedloop import route_of, run_route  # noqa: E402
from pytest_drivedegrade.closedloop.expert import WorldExpert  # noqa: E402
from pytest_drivedegrade.closedloop.routes import Route  # noqa: E402
from pytest_drivedegrade.data.context import FrameContext  # noqa: E402
from pytest_drivedegrade.data.frame import Command, EgoStatus  # noqa: E402
from pytest_drivedegrade.data.world.scenarios import scenario_scene  # noqa: E402
from pytest_drivedegrade.data.world.scene import make_scene  # noqa: E402
from pytest_drivedegrade.floor import ego_features  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


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


def training_routes(world: Path, count: int) -> list[Route]:
    """Half the world's train scenes, half scenario scenes numbered from 1000 (none in the default slice)."""
    manifest = json.loads((world / "drivedegrade_world.json").read_text())
    seed, train = int(manifest["seed"]), list(manifest["splits"]["train"])
    names = train + list(manifest["splits"]["val"])
    half = count // 2
    scenes = [make_scene(seed, names.index(n), n) for n in train[:count - half]]
    scenes += [scenario_scene(seed, 1000 + i) for i in range(half)]
    return [route_of(s) for s in scenes]


def gather(routes: list[Route], learner: ClosedDriver | None, beta: float, seed: int) -> tuple[np.ndarray, ...]:
    expert = WorldExpert(routes)
    c = Collector(expert, learner, beta, np.random.default_rng(seed))
    ds = []
    for route in routes:
        run = run_route(c, route)
        ds.append(run.ds if run.ds is not None else 0.0)
    print(f"  drove {len(routes)} routes: DS {np.mean(ds):.1f} ({'learner' if learner else 'expert, perturbed'}), "
          f"{len(c.pix)} samples", flush=True)
    return np.stack(c.pix), np.stack(c.feats).astype(np.float32), np.stack(c.plans)


def train(net: DriverNet, pix: np.ndarray, feats: np.ndarray, plans: np.ndarray, epochs: int, seed: int) -> None:
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
    for epoch in range(epochs):
        order, total = torch.randperm(len(x), generator=gen), 0.0
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
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--beta", type=float, default=0.2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=WEIGHTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from pytest_drivedegrade.data.world import ensure_default_world

    start = time.perf_counter()
    world = args.world if (args.world / "drivedegrade_world.json").is_file() else Path(ensure_default_world(args.world))
    routes = training_routes(world, args.routes)
    data = [gather(routes, None, 1.0, args.seed)]
    net = DriverNet()
    for r in range(args.rounds + 1):
        pix, feats, plans = (np.concatenate(parts) for parts in zip(*data))
        print(f"round {r}: training on {len(pix)} samples", flush=True)
        train(net, pix, feats, plans, args.epochs, args.seed + r)
        if r < args.rounds:
            data.append(gather(routes, ClosedDriver(net=net), args.beta, args.seed + 100 + r))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), args.out)
    meta = {"recipe": "planners/train_closed_driver.py", "routes": args.routes, "rounds": args.rounds,
            "epochs": args.epochs, "beta": args.beta, "seed": args.seed, "samples": int(len(pix)),
            "seconds": round(time.perf_counter() - start, 1)}
    args.out.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    print(f"wrote {args.out} ({meta['seconds']} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
