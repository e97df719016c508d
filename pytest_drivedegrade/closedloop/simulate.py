"""One closed-loop run: planner at 2 Hz on cameras rendered at the simulated pose and degraded by the cell's
corruption, its plan executed at 10 Hz by NAVSIM's LQR tracker and kinematic bicycle model
(`metrics.tracking`), scored as the CARLA leaderboard scores a route (`leaderboard`: every collision by default,
NAVSIM's at-fault rule as `collisions="at_fault"`). Other agents replay their logs (non-reactive, `agents="log"`)
or follow IDM along their logged paths and brake for the ego (`agents="reactive"`, `agents.py`)."""

from __future__ import annotations

import time
from collections.abc import Mapping
from concurrent.futures import Executor
from dataclasses import dataclass, field

import numpy as np

from ..data.world.agents import DT
from ..metrics.tracking import InitialState, interpolate_plan, track
from ..planning import Planner, call_style, planner_cameras, validate_output
from ..stream import time_limit
from . import judge
from .agents import ReactiveAgents, run_world
from .camera import RouteCameras
from .leaderboard import DEVIATION_SHARE, CollisionFilter, Limits, MinSpeed, check_rule, driving_score
from .loop_io import ego_status, frame_context, route_command
from .results import (
    END_BLOCKED,
    END_COMPLETE,
    END_DEVIATED,
    END_SCENE,
    END_UNSCORED,
    CellResult,
    Infraction,
    RunResult,
)
from .routes import Route, lane_progress
from .view import StepImages

#: 10 Hz sim steps per planner call (2 Hz) and executed per plan: the first 0.5 s of each tracked plan.
PLAN_EVERY = 5
#: A planner call slower than this (s) leaves the run unscored when no --drivedegrade-timeout is given.
PLAN_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class Corruption:
    """The cell's corruption: family ("clean", a ladder family or "blind") and severity 0..5."""

    family: str = "clean"
    severity: int = 0

    @property
    def name(self) -> str:
        return "clean" if self.family == "clean" else f"{self.family}-s{self.severity}"


@dataclass
class Timings:
    """Seconds spent, summed over runs: rendering, planning, tracking, scoring."""

    render: float = 0.0
    plan: float = 0.0
    track: float = 0.0
    score: float = 0.0


@dataclass
class _Run:
    """The mutable state of a run in progress (what the leaderboard's criteria track for a route)."""

    route: Route
    pose: judge.Pose
    yaw_rate: float
    limits: Limits
    collisions: str = "all"  # the collision rule (leaderboard.COLLISION_RULES)
    steering: float = 0.0
    best: float = 0.0  # farthest progress along the route (m)
    wrong: float = 0.0  # progress made outside the driving lanes or in an oncoming lane (m)
    wrong_at: tuple[int, int] | None = None  # (route step, sim step) where it began
    out_route: float = 0.0  # progress made farther than half the deviation limit from the route (m)
    still_since: int = 0  # the sim step since which the ego stands (slower than BLOCKED_SPEED)
    history: list[tuple[float, float, float]] = field(default_factory=list)
    trace: list[tuple[float, float, float]] = field(default_factory=list)
    infractions: list[Infraction] = field(default_factory=list)
    touched: set[int] = field(default_factory=set)
    lights_run: set[int] = field(default_factory=set)  # the lights already counted as run (once per light)
    seen: CollisionFilter = field(default_factory=CollisionFilter)
    min_speed: MinSpeed | None = None
    world: ReactiveAgents | None = None  # the reactive agents, None when they replay their logs

    @property
    def xyyaw(self) -> tuple[float, float, float]:
        return (self.pose.x, self.pose.y, self.pose.yaw)

    def completion(self) -> float:
        return float(np.clip(self.best / max(self.route.length, 1e-9), 0.0, 1.0))

    def closing(self) -> list[Infraction]:
        """The percentage infractions the leaderboard records when a route ends: outside route lanes (one, with
        its share of the driven route) and the last min-speed checkpoint."""
        out = []
        if self.wrong > 0 and self.wrong_at is not None:
            out.append(Infraction("outside_route_lanes", *self.wrong_at, value=100.0 * self.wrong / self.best))
        last = self.min_speed.finish(self.best) if self.min_speed is not None else None
        if last is not None:
            k, t = len(self.history), self.route.start_step + len(self.trace) - 1
            out.append(Infraction("min_speed", k, t, value=last))
        return out


def _start(route: Route, collisions: str = "all") -> _Run:
    ego, t = route.scene.ego, route.start_step
    yaw_rate = float((ego.yaw[t + 1] - ego.yaw[t]) / DT)
    pose = judge.Pose(float(ego.xy[t, 0]), float(ego.xy[t, 1]), float(ego.yaw[t]), float(ego.speed[t]),
                      float(ego.accel[t]))
    limits = Limits.of((route.end_step - route.start_step) * DT)
    run = _Run(route, pose, yaw_rate, limits, check_rule(collisions), still_since=t,
               min_speed=MinSpeed(route.length))
    run.trace.append(run.xyyaw)
    return run


def _progress(run: _Run, pose: judge.Pose, k: int, t: int) -> float:
    """Advance the route's progress to `pose` (RouteCompletionTest, OutsideRouteLanesTest, InRouteTest); the
    ego's distance (m) from the route's lane."""
    route = run.route
    s, d = lane_progress(route, pose.xy)
    progress, lateral = float(np.clip(s[0], 0.0, route.length)), abs(float(d[0]))
    if lateral < run.limits.deviation_m and progress > run.best:
        gain = min(progress - run.best, pose.speed * DT + 1.0)
        run.best += gain
        if judge.outside_route_lanes(route, pose):
            run.wrong += gain
            run.wrong_at = run.wrong_at or (k, t)
        if lateral >= run.limits.deviation_m / 2:
            run.out_route += gain
    return lateral


def _collide(run: _Run, pose: judge.Pose, k: int, t: int) -> None:
    """Record step `t`'s collisions: every one the leaderboard's CollisionTest counts, or (rule "at_fault")
    NAVSIM's at-fault ones, an agent judged by its first contact."""
    route = run.route
    astray = run.collisions == "at_fault" and judge.outside_m(route, pose) > 0
    run.seen.update(pose.xy, t * DT)
    for kind, who, fault in judge.collisions(route, pose, t, astray):
        what = route.scene.agents[who].role if who >= 0 else route.scene.props[-1 - who].kind
        if run.collisions == "at_fault":
            if who in run.touched:
                continue
            run.touched.add(who)
            if not fault:
                continue
        elif not run.seen.counts(who if who >= 0 else None, pose.xy, pose.speed, t * DT):
            continue
        run.infractions.append(Infraction(kind, k, t, what))


def _judge_step(run: _Run, pose: judge.Pose, k: int, t: int) -> str | None:
    """Score sim step `t` (the ego moved to `pose` there) as the leaderboard's criteria do: progress, lanes,
    collisions, minimum speed; the end reason if any (complete, route deviation, blocked)."""
    route = run.route
    lateral = _progress(run, pose, k, t)
    _collide(run, pose, k, t)
    for j in judge.red_lights_run(route, pose, t):
        if j not in run.lights_run:
            run.lights_run.add(j)
            run.infractions.append(Infraction("red_light", k, t, f"light {j}"))
    if run.min_speed is not None:
        failed = run.min_speed.tick(run.best, pose.speed, judge.traffic_speed(route, t))
        if failed is not None:
            run.infractions.append(Infraction("min_speed", k, t, value=failed))
    if run.best >= route.length - 1e-6:
        return END_COMPLETE
    if lateral >= run.limits.deviation_m or run.out_route > DEVIATION_SHARE * route.length:
        return END_DEVIATED
    if pose.speed >= judge.BLOCKED_SPEED:
        run.still_since = t
    elif (t - run.still_since) * DT > run.limits.blocked_s:
        if judge.road_ahead_free(route, pose, t):
            return END_BLOCKED
        run.still_since = t
    return None


def _plan(planner: Planner, run: _Run, k: int, images: Mapping[str, np.ndarray], takes_context: bool,
          timings: Timings, timeout: float = PLAN_TIMEOUT_S) -> np.ndarray:
    """The planner's validated plan at route step `k` (raises what the planner raises, PlannerOutputError, or
    PlannerTimeout once predict has run `timeout` s: interrupted where the loop runs on the main thread, judged
    after the call elsewhere; 0: no limit)."""
    route = run.route
    status = ego_status(run.history, run.xyyaw, run.pose.speed, run.pose.accel, run.yaw_rate)
    cmd = route_command(route, run.xyyaw, run.pose.speed)
    token = f"{route.name}/closed/{k}"
    t0 = time.perf_counter()
    with time_limit(timeout):
        if takes_context:
            ctx = frame_context(route, k, run.xyyaw, status)
            raw = planner.predict(images, status, cmd, context=ctx)  # type: ignore[call-arg]
        else:
            raw = planner.predict(images, status, cmd)
    elapsed = time.perf_counter() - t0
    timings.plan += elapsed
    if timeout > 0 and elapsed > timeout:
        raise TimeoutError(f"predict took {elapsed:.1f} s (limit {timeout:g} s)")
    return validate_output(raw, token)


@dataclass(frozen=True)
class _Step:
    """The ego at one 10 Hz step of an executed plan: pose, yaw rate and steering angle."""

    pose: judge.Pose
    yaw_rate: float
    steering: float


def _execute(run: _Run, plan: np.ndarray, t: int, timings: Timings, plan_every: int = PLAN_EVERY) -> list[_Step]:
    """Track the plan from the simulated state and drive its first `plan_every` 0.1 s steps (0.5 s at 2 Hz),
    moving reactive agents along; the run's motion state becomes the last step's. Nothing is judged here
    (`_judge`): the next step's cameras depend on the pose only, so they may render while it is judged."""
    t0 = time.perf_counter()
    start = InitialState(run.pose.speed, 0.0, run.pose.accel, 0.0, run.yaw_rate, run.steering)
    states = track(interpolate_plan(plan), start)
    x0, y0, yaw0 = run.xyyaw
    c, s = np.cos(yaw0), np.sin(yaw0)
    steps, pose = [], run.pose
    for i in range(1, plan_every + 1):
        if run.world is not None:  # the agents move to t + i from where the ego was at t + i - 1
            run.world.advance(t + i, pose)
        lx, ly = float(states.x[0, i]), float(states.y[0, i])
        pose = judge.Pose(x0 + c * lx - s * ly, y0 + s * lx + c * ly, yaw0 + float(states.heading[0, i]),
                          max(float(states.velocity_x[0, i]), 0.0), float(states.acceleration_x[0, i]))
        steps.append(_Step(pose, float(states.yaw_rate[0, i]), float(states.steering_angle[0, i])))
    run.pose, run.yaw_rate, run.steering = steps[-1].pose, steps[-1].yaw_rate, steps[-1].steering
    timings.track += time.perf_counter() - t0
    return steps


def _judge(run: _Run, steps: list[_Step], k: int, t: int, timings: Timings) -> str | None:
    """Judge the executed steps of route step `k` (sim steps t + 1 ...) in order, each added to the trace, up to
    the first that ends the run; its end reason, or None."""
    t1 = time.perf_counter()
    try:
        for i, step in enumerate(steps, 1):
            run.trace.append((step.pose.x, step.pose.y, step.pose.yaw))
            end = _judge_step(run, step.pose, k, t + i)
            if end is not None:
                return end
    finally:
        timings.score += time.perf_counter() - t1
    return None


def _judge_while_rendering(pool: Executor, stream: StepImages, run: _Run, steps: list[_Step], k: int, t: int,
                           timings: Timings, more: bool) -> tuple[str | None, Mapping[str, np.ndarray] | None]:
    """Judge route step `k`'s executed steps on the pool while step k + 1's cameras render here (when the run
    may go on: `more`): (the end reason, the next images). Step k + 1 is rendered from the pose alone, so the
    images are those the serial path renders after judging; a rendering failure counts only for a run that goes
    on, as serially it would."""
    judged = pool.submit(_judge, run, steps, k, t, timings)
    try:
        images = stream.at(run.xyyaw, t + len(steps), k + 1) if more else None
    except Exception:
        if judged.result() is None:
            raise
        return judged.result(), None
    return judged.result(), images


def _result(run: _Run, seed: int, end: str, steps: int) -> RunResult:
    infractions = (*run.infractions, *run.closing())
    completion = run.completion()
    ds = driving_score(completion, [(i.kind, i.value) for i in infractions])
    return RunResult(run.route.name, seed, ds, completion, end, infractions, np.array(run.trace), steps=steps)


@dataclass(frozen=True)
class Rules:
    """How a run is scored and bounded: the collision rule (leaderboard.COLLISION_RULES) and the seconds one
    predict() may take (--drivedegrade-timeout; 0: no limit)."""

    collisions: str = "all"
    timeout: float = PLAN_TIMEOUT_S


def run_route(planner: Planner, route: Route, corruption: Corruption = Corruption(), seed: int = 0,
              timings: Timings | None = None, *, plan_every: int = PLAN_EVERY,
              max_steps: int | None = None, agents: str = "log", pool: Executor | None = None,
              rules: Rules = Rules()) -> RunResult:
    """Drive `route` with `planner` under `corruption` (corruption seed `seed`, frame key "<route>/<step>"),
    calling it every `plan_every` 0.1 s steps, at most `max_steps` times (then the run ends as at the scene's end),
    the other agents replayed (`agents="log"`) or reactive (`"reactive"`), scored by `rules`. A planner that
    raises, times out or returns a bad plan leaves the run unscored (ds None, `error` set).

    With a thread `pool` (``--drivedegrade-prefetch`` above 0) a step's cameras render and corrupt on its threads,
    and the steps an executed plan drove are judged on one of them while the next step's cameras render (the
    planner is called only once they are judged: a run that ended is never planned further). The same run, bit
    for bit: nothing judged feeds the pose or the cameras."""
    timings = timings if timings is not None else Timings()
    route, world = run_world(route, agents)
    style = call_style(planner)
    t0 = time.perf_counter()
    stream = StepImages(RouteCameras(route, planner_cameras(planner)), corruption, seed, timings, pool)
    timings.render += time.perf_counter() - t0
    if style.resets:
        planner.reset(route.name)  # type: ignore[attr-defined]
    run = _start(route, rules.collisions)
    run.world = world
    k, t = 0, route.start_step
    images: Mapping[str, np.ndarray] | None = None
    while t + plan_every <= route.end_step and (max_steps is None or k < max_steps):
        images = stream.at(run.xyyaw, t, k) if images is None else images
        try:
            plan = _plan(planner, run, k, images, style.takes_context, timings, rules.timeout)
        except Exception as exc:  # noqa: BLE001 - any failure of the planner leaves the run unscored
            return RunResult(route.name, seed, None, None, END_UNSCORED, tuple(run.infractions),
                             np.array(run.trace), f"step {k}: {type(exc).__name__}: {exc}", k)
        run.history.append(run.xyyaw)
        steps = _execute(run, plan, t, timings, plan_every)
        if pool is None:
            end, images = _judge(run, steps, k, t, timings), None
        else:
            more = t + 2 * plan_every <= route.end_step and (max_steps is None or k + 1 < max_steps)
            end, images = _judge_while_rendering(pool, stream, run, steps, k, t, timings, more)
        k, t = k + 1, t + plan_every
        if end is not None:
            return _result(run, seed, end, k)
    return _result(run, seed, END_SCENE, k)


def run_cell(planner: Planner, routes: list[Route], corruption: Corruption = Corruption(),
             seeds: tuple[int, ...] = (0,), timings: Timings | None = None, *, agents: str = "log",
             pool: Executor | None = None, rules: Rules = Rules()) -> CellResult:
    """Every route under every seed: the cell's runs, route-major (`pool`, `rules`: as `run_route` takes them)."""
    runs = [run_route(planner, route, corruption, seed, timings, agents=agents, pool=pool, rules=rules)
            for route in routes for seed in seeds]
    return CellResult.of(f"closed-{corruption.name}", runs)
