"""The corruption registry: the `Family` declaration and the `register` decorator each operator uses to state
its parameter, unit and five values beside its code.

The family modules import `register` from here; `ladder` imports the family modules and builds the ordered
table `FAMILIES`, so nothing imports back into this module's importers (no cycle).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

#: Version of the ladder (operators and values) and of the scores certified on it. A new value is a minor bump; a
#: changed operator is major; a changed score with the ladder unchanged is minor (4.1.0: PDMS on tracked states;
#: 4.2.0: the tracker's velocity fit with NAVSIM's penalty as its code applies it; 5.0.0, the ladder unchanged: what
#: a stated probability means (scene-cluster intervals, non-asymptotic adaptive cells and gate, closed-loop
#: statistics over routes), EPDMS equal to NAVSIM v2.2's terms, the leaderboard's Driving Score, plan movement beside
#: accuracy and the command cells; 5.1.0, the ladder unchanged: EPDMS's ep along the route centreline, hc's
#: acceleration at NAVSIM's centre and v2.2's TTC window, found by running NAVSIM's own scorer; the command label
#: command-partial; traffic lights in the closed loop's default slice, 30 routes).
SPEC_VERSION = "5.1.0"

#: Order of SPEC section 3: the twelve core families first, then the four contamination families.
ORDER: tuple[str, ...] = (
    "gaussian_blur", "motion_blur", "gaussian_noise", "low_light", "jpeg", "downscale", "color_quant",
    "fog", "snow", "frame_dropout", "blackout", "bit_error",
    "raindrop", "occlusion", "mud_splash", "lens_dirt",
)
CORE: frozenset[str] = frozenset(ORDER[:12])
SEVERITIES: tuple[int, ...] = (1, 2, 3, 4, 5)

#: An image operator: (image, value, rng, scale) -> new image. `rng` is None for deterministic families;
#: `scale` is image width / 1600 for spatial parameters.
ImageOp = Callable[..., Any]


@dataclass(frozen=True)
class Family:
    """One corruption family: a single physical parameter with a value at each severity S1..S5.

    `scope` is "image" for operators on one camera image, "sample" for those that need the whole
    six-camera sample (blackout) or the previous delivered frame (frame_dropout).
    """

    name: str
    group: str
    axis: str
    parameter: str
    unit: str
    values: tuple[Any, ...]
    random: bool
    scope: str
    op: ImageOp = field(repr=False, compare=False)
    spatial: bool = False

    @property
    def core(self) -> bool:
        return self.name in CORE

    def value(self, severity: int) -> Any:
        """The parameter value at severity 1..5."""
        return self.values[severity - 1]

    def describe(self, severity: int) -> str:
        """A short human label such as 'defocus sigma = 2.0 px'."""
        value = self.value(severity)
        if isinstance(value, tuple):
            value = "+".join(c.replace("CAM_", "") for c in value)
        # no unit the parameter already names ("JPEG quality = 12", not "= 12 quality"; "bits per channel = 3")
        named = bool(self.unit) and self.unit.split()[0].strip(",") in self.parameter.split()
        unit = f" {self.unit}" if self.unit and self.unit not in ("level", "cameras") and not named else ""
        return f"{self.parameter} = {value}{unit}"


#: Filled by `register` as the family modules are imported (by `ladder`).
REGISTERED: dict[str, Family] = {}


def register(name: str, *, group: str, axis: str, parameter: str, unit: str, values: tuple[Any, ...],
             random: bool, scope: str = "image", spatial: bool = False) -> Callable[[ImageOp], ImageOp]:
    """Class-free declaration: decorate the operator with its parameter, unit and ladder values."""
    if len(values) != len(SEVERITIES):
        raise AssertionError(f"{name}: a family needs exactly five values, got {len(values)}")

    def decorate(op: ImageOp) -> ImageOp:
        REGISTERED[name] = Family(name, group, axis, parameter, unit, tuple(values), random, scope, op,
                                 spatial)
        return op

    return decorate
