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

Its 95 % interval resamples frames (paired: each frame's two sums together), percentile method, seeded.

Label: ``command-following`` when the interval's lower bound is at or above `FOLLOWING_LINE` (the plan moves at
least half as far toward the told manoeuvre as the expert's); ``command-insensitive`` when its upper bound is below
`INSENSITIVE_LINE` (the plan moves less than a tenth of the way); otherwise ``undetermined`` (partial following,
or too few frames), with the figure. So each label's interval excludes the other label.

Pure functions over arrays; nothing here reads files or touches a planner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

COMMAND_LABELS: tuple[str, ...] = ("command-following", "command-insensitive", "undetermined")
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

    def text(self) -> str:
        if self.value is None:
            return "Command: not measured (no frame where another command is meaningful)."
        spread = "" if self.low is None else f", 95 % interval {self.low:.3f} .. {self.high:.3f}"
        what = {"command-following": "the plan goes where the command says",
                "command-insensitive": "the plan does not go where the command says",
                "undetermined": "partial, or too few frames to tell"}[self.label]
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
    if round(hi, 6) < INSENSITIVE_LINE:
        return "command-insensitive"
    return "undetermined"


def following(p0: np.ndarray, p1: np.ndarray, logged: np.ndarray, target: np.ndarray, *,
              n_resamples: int = 1000, seed: int = 0) -> Following:
    """The command-following figure of a planner's plans at the scored frames (each (F, steps, 2)); frames whose
    plans are not finite in both drop out."""
    num, den = frame_sums(p0, p1, logged, target)
    return from_sums(num, den, n_resamples=n_resamples, seed=seed)


def from_sums(num: np.ndarray, den: np.ndarray, *, n_resamples: int = 1000, seed: int = 0) -> Following:
    """The figure, its interval and label from each frame's two sums (`frame_sums`); a frame whose sums are not
    finite, or whose manoeuvres do not part (den 0), drops out."""
    num, den = np.asarray(num, np.float64), np.asarray(den, np.float64)
    ok = np.isfinite(num) & np.isfinite(den) & (den > 0)
    num, den = num[ok], den[ok]
    if not num.size:
        return Following(None, None, None, 0, "undetermined")
    value = float(num.sum() / den.sum())
    low = high = None
    if n_resamples > 0 and num.size > 1:
        idx = np.random.default_rng(seed).integers(0, num.size, size=(n_resamples, num.size))
        ratios = num[idx].sum(axis=1) / den[idx].sum(axis=1)
        low, high = (float(v) for v in np.percentile(ratios, [2.5, 97.5]))
    return Following(value, low, high, int(num.size), command_label(low, high, value))


@dataclass(frozen=True)
class CommandProbe:
    """The command_swap cell read by the following measure: the figure (`Following`), how many of the run's
    frames are junction frames (an alternative command was given), and each scored frame's two sums rounded to
    `SUM_DIGITS` decimals (``num``, ``den``): the figure is computed from exactly what the certificate stores, so
    ``drivedegrade verify`` recomputes it bit for bit."""

    following: Following
    junction_frames: int
    num: tuple[float, ...]
    den: tuple[float, ...]

    def to_builtins(self) -> dict[str, object]:
        """The certificate's ``command`` section."""
        f = self.following
        return {"cell": "command_swap", "following": f.value, "low": f.low, "high": f.high, "label": f.label,
                "frames": f.frames, "junction_frames": self.junction_frames,
                "sums": [[n, d] for n, d in zip(self.num, self.den)]}


#: The decimals each frame's sums are kept to (the certificate's precision).
SUM_DIGITS = 6


def swap_probe(clean_plans: np.ndarray, swap_plans: np.ndarray, target: np.ndarray, *, n_resamples: int,
               seed: int) -> CommandProbe:
    """The following figure of a run from its clean plans (under the logged command), command_swap's plans (the
    alternative at junction frames) and command_swap's ``command_target`` (the expert's change of path; NaN away
    from junctions: those frames are not scored), each (F, 6, 2)."""
    target = np.asarray(target, np.float64)
    junction = np.isfinite(target).reshape(len(target), -1).all(axis=1)
    zero = np.zeros_like(target[junction])
    num, den = frame_sums(np.asarray(clean_plans)[junction], np.asarray(swap_plans)[junction], zero, target[junction])
    ok = np.isfinite(num) & np.isfinite(den) & (den > 0)
    nums = tuple(round(float(v), SUM_DIGITS) + 0.0 for v in num[ok])
    dens = tuple(round(float(v), SUM_DIGITS) + 0.0 for v in den[ok])
    got = from_sums(np.array(nums), np.array(dens), n_resamples=n_resamples, seed=seed)
    return CommandProbe(got, int(junction.sum()), nums, dens)
