"""Command following (spec 5, issue 40): does the plan go where the command says, at frames where another command
is meaningful (`data.junctions.alternative`)?

Per scored frame: the plan under the logged command ``p0``, the plan under the alternative command ``p1``, the
logged future ``logged`` (the privileged expert under the logged route) and the expert's path for the alternative
(``target``). The planner's change of plan is projected onto the expert's:

    following = sum_frames <p1 - p0, target - logged> / sum_frames |target - logged|^2

over every waypoint. A planner that ignores the command (p1 = p0) scores 0 exactly; the privileged expert with
the swapped route (p0 = logged, p1 = target) scores 1 exactly; a planner that turns the other way scores below 0.
The projection reads the heading change and the lateral offset together: both move the waypoints along the
manoeuvre's path. Frames with larger manoeuvre separations weigh more (a ratio of sums, not a mean of ratios, so a
frame whose manoeuvres barely part cannot dominate).

Its 95 % interval resamples scenes when each frame's scene is known and the frames come from two scenes or more
(a scene-cluster bootstrap, `scoring.clusters`: each drawn scene's frames whole, each frame's two sums together,
read at the expanded percentile levels for that many scenes, as the run's other intervals are, SPEC section 17);
otherwise frames (paired), percentile method. Seeded either way. Frames at one junction share its road and the
planner's state, so a frame bootstrap over them would state a precision the scenes do not have.

Label: ``command-following`` when the interval's lower bound is at or above `FOLLOWING_LINE` (the plan is shown to
move at least half as far toward the told manoeuvre as the expert's); ``command-partial`` when its lower bound is at
or above `INSENSITIVE_LINE` but below `FOLLOWING_LINE` (the command is shown to steer the plan, but not shown to
take it half way: the reference planners that read the command as an input do this); ``command-insensitive`` when
its upper bound is below `INSENSITIVE_LINE` (the plan moves less than a tenth of the way); otherwise
``undetermined`` (the interval straddles the tenth, or the junction frames come from one scene: one junction's
frames share its road and the planner's state, so they cannot label a planner). Each label's interval excludes
every other label's region below it, so ``command-following`` and ``command-partial`` exclude
``command-insensitive``.

Pure functions over arrays; nothing here reads files or touches a planner.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .clusters import MIN_SCENES, cluster_counts, percentile_interval

COMMAND_LABELS: tuple[str, ...] = ("command-following", "command-partial", "command-insensitive", "undetermined")
FOLLOWING_LINE = 0.5
INSENSITIVE_LINE = 0.1


@dataclass(frozen=True)
class Following:
    """The command-following figure over `frames` scored frames, with its 95 % interval (None without
    resamples or frames) and the label it gives."""

    value: float | None
    low: float | None
    high: float | None
    frames: int
    label: str
    #: the scenes the interval's cluster bootstrap drew (None: frames were drawn, or no interval)
    scenes: int | None = None

    def text(self) -> str:
        if self.value is None:
            return "Command: not measured (no frame where another command is meaningful)."
        basis = "" if self.low is None else \
            f" (scene-cluster bootstrap, {self.scenes} scenes)" if self.scenes else " (frame bootstrap)"
        spread = "" if self.low is None else f", 95 % interval {self.low:.3f} .. {self.high:.3f}{basis}"
        what = {"command-following": "the plan goes where the command says",
                "command-partial": "the command steers the plan, but it is not shown to go half as far as the "
                                   "expert's",
                "command-insensitive": "the plan does not go where the command says",
                "undetermined": "too few junctions, or too little movement, to tell"}[self.label]
        return (f"Command: following {self.value:.3f}{spread} over {self.frames} junction frame"
                f"{'s' if self.frames != 1 else ''} (0: ignores the command, 1: the privileged expert given the "
                f"other route); {self.label}: {what}.")


def frame_sums(p0: np.ndarray, p1: np.ndarray, logged: np.ndarray, target: np.ndarray) -> tuple[np.ndarray,
                                                                                                 np.ndarray]:
    """Per frame (F, ...): <p1 - p0, target - logged> and |target - logged|^2 over its waypoints."""
    moved = np.asarray(p1, np.float64) - np.asarray(p0, np.float64)
    wanted = np.asarray(target, np.float64) - np.asarray(logged, np.float64)
    return (moved * wanted).sum(axis=(-2, -1)), (wanted * wanted).sum(axis=(-2, -1))


def command_label(low: float | None, high: float | None, value: float | None) -> str:
    """`COMMAND_LABELS` from the interval (the point value when there is none)."""
    lo = value if low is None else low
    hi = value if high is None else high
    if lo is None or hi is None:
        return "undetermined"
    if round(lo, 6) >= FOLLOWING_LINE:
        return "command-following"
    if round(lo, 6) >= INSENSITIVE_LINE:
        return "command-partial"
    if round(hi, 6) < INSENSITIVE_LINE:
        return "command-insensitive"
    return "undetermined"


def following(p0: np.ndarray, p1: np.ndarray, logged: np.ndarray, target: np.ndarray, *,
              n_resamples: int = 1000, seed: int = 0) -> Following:
    """The command-following figure of a planner's plans at the scored frames (each (F, steps, 2)); frames whose
    plans are not finite in both drop out."""
    num, den = frame_sums(p0, p1, logged, target)
    return from_sums(num, den, n_resamples=n_resamples, seed=seed)


def from_sums(num: np.ndarray, den: np.ndarray, *, n_resamples: int = 1000, seed: int = 0,
              scenes: Sequence[int] | None = None) -> Following:
    """The figure, its interval and label from each frame's two sums (`frame_sums`); a frame whose sums are not
    finite, or whose manoeuvres do not part (den 0), drops out. `scenes` (each frame's scene as a cluster index)
    makes the interval a scene-cluster bootstrap when the kept frames span `clusters.MIN_SCENES` scenes or more."""
    num, den = np.asarray(num, np.float64), np.asarray(den, np.float64)
    ok = np.isfinite(num) & np.isfinite(den) & (den > 0)
    num, den = num[ok], den[ok]
    if not num.size:
        return Following(None, None, None, 0, "undetermined")
    value = float(num.sum() / den.sum())
    labels = None if scenes is None else _relabel(np.asarray(scenes)[ok])
    if labels is not None and n_resamples > 0 and int(labels.max()) + 1 >= MIN_SCENES:
        g = int(labels.max()) + 1
        counts = cluster_counts(np.random.default_rng(seed), n_resamples, labels)
        got = percentile_interval(counts @ num / (counts @ den), clusters=g)
        low, high = got if got is not None else (None, None)
        return Following(value, low, high, int(num.size), command_label(low, high, value), g)
    low = high = None
    if n_resamples > 0 and num.size > 1:
        idx = np.random.default_rng(seed).integers(0, num.size, size=(n_resamples, num.size))
        ratios = num[idx].sum(axis=1) / den[idx].sum(axis=1)
        low, high = (float(v) for v in np.percentile(ratios, [2.5, 97.5]))
    # frames of one known scene are one junction: the frame interval is shown, but it cannot label the planner
    label = "undetermined" if labels is not None else command_label(low, high, value)
    return Following(value, low, high, int(num.size), label)


def _relabel(scenes: np.ndarray) -> np.ndarray:
    """Scene labels as cluster indices 0..G-1 in order of first appearance."""
    index: dict[object, int] = {}
    return np.array([index.setdefault(x.item() if hasattr(x, "item") else x, len(index)) for x in scenes],
                    dtype=np.intp)


@dataclass(frozen=True)
class CommandProbe:
    """The command_swap cell read by the following measure: the figure (`Following`), how many of the run's
    frames are junction frames (an alternative command was given), and each scored frame's two sums rounded to
    `SUM_DIGITS` decimals (``num``, ``den``): the figure is computed from exactly what the certificate stores, so
    ``drivedegrade verify`` recomputes it bit for bit. ``scenes``: each scored frame's scene as a cluster index
    (None when the run's scenes are unknown), which the interval's cluster bootstrap draws."""

    following: Following
    junction_frames: int
    num: tuple[float, ...]
    den: tuple[float, ...]
    scenes: tuple[int, ...] | None = None

    def to_builtins(self) -> dict[str, object]:
        """The certificate's ``command`` section (``scenes`` and ``basis`` where the scenes are known and a frame
        was scored)."""
        f = self.following
        out: dict[str, object] = {
            "cell": "command_swap", "following": f.value, "low": f.low, "high": f.high, "label": f.label,
            "frames": f.frames, "junction_frames": self.junction_frames,
            "sums": [[n, d] for n, d in zip(self.num, self.den)]}
        if self.scenes is not None and self.num:  # nothing scored: the section as before, no basis to name
            out["scenes"] = list(self.scenes)
            out["basis"] = f"scene-cluster bootstrap, {f.scenes} scenes" if f.scenes else \
                "frame bootstrap" if f.low is not None else "no interval"
        return out


#: The decimals each frame's sums are kept to (the certificate's precision).
SUM_DIGITS = 6


def swap_probe(clean_plans: np.ndarray, swap_plans: np.ndarray, target: np.ndarray, *, n_resamples: int,
               seed: int, scenes: Sequence[str] | None = None) -> CommandProbe:
    """The following figure of a run from its clean plans (under the logged command), command_swap's plans (the
    alternative at junction frames) and command_swap's ``command_target`` (the expert's change of path; NaN away
    from junctions: those frames are not scored), each (F, 6, 2); `scenes`: each of the F frames' scene."""
    target = np.asarray(target, np.float64)
    junction = np.isfinite(target).reshape(len(target), -1).all(axis=1)
    zero = np.zeros_like(target[junction])
    num, den = frame_sums(np.asarray(clean_plans)[junction], np.asarray(swap_plans)[junction], zero, target[junction])
    ok = np.isfinite(num) & np.isfinite(den) & (den > 0)
    nums = tuple(round(float(v), SUM_DIGITS) + 0.0 for v in num[ok])
    dens = tuple(round(float(v), SUM_DIGITS) + 0.0 for v in den[ok])
    labels = None if scenes is None else \
        tuple(int(x) for x in _relabel(np.asarray([str(x) for x in scenes], dtype=object)[junction][ok]))
    got = from_sums(np.array(nums), np.array(dens), n_resamples=n_resamples, seed=seed, scenes=labels)
    return CommandProbe(got, int(junction.sum()), nums, dens, labels)
