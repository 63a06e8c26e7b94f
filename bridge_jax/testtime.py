"""What a predictor does at test time besides running the network once: one frozen record, `TestTime`.

    TestTime()                                        # the network's maps as they are
    TestTime(refine=1, symmetry="flips", polish="photometric")
    TestTime.from_card(zoo.info("long"))              # what a shipped model's card recommends

Fields, each one stage of `bridge_jax.stages` (run in this order, `stages.predicted_maps`):

* `symmetry`: average every network call over mirrored (and transposed) copies of the pair (`SYMMETRY_MODES`);
* `refine`: run the network K more times per pair on `b` warped by the maps so far, composing what it still
  finds with them (0 .. `MAX_REFINE`);
* `polish`: correct the final maps after the network (`POLISH_MODES`): "photometric" against the images at
  their own size (`bridge_jax.polish`; `PolishConfig.resolution`), "fill" by the left-right check of stereo
  maps and the forward-backward check of flow maps at the input resolution (`confidence.left_right_fill`,
  `confidence.forward_backward_fill`), or both ("photometric+fill", in that order).
  "none" = the network's own maps.

A record is checked when it is made, so a `Predictor` never holds an unknown setting; it is hashable and
compares by value, so compiled programs are kept per record. `with_given` applies the settings a user gave
(None = not given) to a default record, naming the option of a bad value. This module imports no jax: the
command-line parsers use it.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Optional

MAX_REFINE = 8
"""The most refinement passes a `TestTime` accepts (each costs one more network call per pair)."""
SYMMETRY_MODES = ("none", "flips", "dihedral")
"""Test-time symmetry averaging (`stages.symmetric_maps`): "none"; "flips" = the pair as given and flipped
left-right, upside-down and both (4 network calls' worth); "dihedral" = those 4 and the same 4 transposed (8).
Stereo pairs count only the copies that are still left -> right stereo pairs: as given and upside-down."""
POLISH_STEPS = ("photometric", "fill")
"""The steps a polish may run, in the order they run: "photometric" (`polish.polish_maps`, every map, at the size
`PolishConfig.resolution` says) and "fill" (each pair's reverse pair is predicted too: for stereo maps the right
view's disparity, and the left view's pixels that fail the left-right check take their row's background
disparity unless it is much nearer than their own, a run of them with a nearer surface on its right reaching a few
pixels further left first, `confidence.left_right_fill`; for flow maps the backward flow, and the pixels that fail
the forward-backward check take the flow of their consistent neighbours of the same colour,
`confidence.forward_backward_fill`)."""
FILL_MAX_RAISE = 4.0
"""How much nearer than an in-view pixel failing the left-right check its row's background may be and still replace
it, pixels of the input resolution (`confidence.left_right_fill`): a background farther than the pixel always does
(a bled foreground comes down to it); one this much nearer or more says that the pixel lies between two parts of a
nearer surface, and it keeps its own value. Chosen among 0, 2, 4 and 8 px and no limit (the devkit's rule for a
matcher's holes) on Middlebury Motorcycle and the held-out synthetic frames (4 px improved both against no limit,
0 and 2 px only the first), and reported on the kept-out check."""
FILL_OCCLUSION_STEP = 3.0
"""How much nearer the passing pixel at the right end of a run of left-view pixels that fail the left-right check
must be than the one at its left end for the run to count as an occlusion (`confidence.widen_occlusion_runs`):
background the right camera cannot see, left of a nearer surface's left edge. Pixels of the input resolution."""
FILL_OCCLUSION_REACH = 3
"""How many pixels an occlusion run (`FILL_OCCLUSION_STEP`) is widened to its left before the fill
(`confidence.widen_occlusion_runs`): a network's map climbs to the nearer surface over a few pixels, and the
check passes the climb's lower part, which would otherwise give the run its background. Chosen with the step
(reaches of 1-4 px at a step of 1 px, of 2, 3, 4 and 6 px at a step of 3 px) on Middlebury Motorcycle and the
held-out synthetic frames, and reported on the kept-out check."""
FILL_MAX_DIFFERENCE = 1.0
"""The flow fill's fixed tolerance, pixels of the input resolution: a flow is allowed this plus the
forward-backward check's relative part (`confidence.forward_backward_fill`). The value the standard semi-global
matcher uses for its left-right check (`eval.baselines.sgbm_disparity`, ``disp12MaxDiff`` 1), taken as it is."""
FILL_MAX_DIFFERENCE_STEREO = 0.75
"""The stereo fill's tolerance, pixels of the input resolution: a left disparity that differs from the right
view's disparity at its match by more than this fails the left-right check (`confidence.left_right_fill`). Chosen
among 0.5, 0.6, 0.75, 0.9, 1 (SGBM's value, used before), 1.5 and 2 px on Middlebury Motorcycle and the held-out
synthetic frames (0.75 px was the best on Motorcycle and better than 1 px on both), and reported on the kept-out
check: a looser check fills fewer of the pixels the network bled a nearer disparity over."""
POLISH_MODES = ("none", "photometric", "fill", "photometric+fill")
"""Test-time polish of a predictor's maps: "none", or "+"-joined `POLISH_STEPS` in their order."""
OPTIONS = {"refine": "--refine", "symmetry": "--symmetry", "polish": "--polish"}
"""The command-line option of each field."""
CARD_KEYS = {"refine": "default_refine", "symmetry": "default_symmetry", "polish": "default_polish"}
"""The entry of a shipped model's card (`zoo.info`) that recommends each field."""


def _check(field: str, value: Any, name: str) -> Any:
    """`value` of `field` as the record holds it; ValueError naming `name` (a field or an option) otherwise."""
    if field == "refine":
        if isinstance(value, bool) or not hasattr(value, "__index__") or not 0 <= int(value) <= MAX_REFINE:
            raise ValueError(f"{name} {value!r}: expected a whole number of refinement passes from 0 to {MAX_REFINE}")
        return int(value)
    modes = SYMMETRY_MODES if field == "symmetry" else POLISH_MODES
    if value not in modes:
        raise ValueError(f"{name} {value!r}: expected one of {', '.join(modes)}")
    return str(value)


@dataclasses.dataclass(frozen=True)
class TestTime:
    """The test-time stages of a predictor (see the module docstring); validated on construction."""

    __test__ = False  # a library class, not a pytest test class

    refine: int = 0
    symmetry: str = "none"
    polish: str = "none"

    def __post_init__(self):
        for field in dataclasses.fields(self):
            object.__setattr__(self, field.name, _check(field.name, getattr(self, field.name), field.name))

    def with_given(self, given: Mapping[str, Any], options: Optional[Mapping[str, str]] = None) -> "TestTime":
        """This record with the fields of `given` that are not None replaced; a bad value is a ValueError
        naming its option (`options[field]`, default the field's name)."""
        names = {**{f: f for f in CARD_KEYS}, **(options or {})}
        unknown = sorted(set(given) - set(CARD_KEYS))
        if unknown:
            raise TypeError(f"unknown test-time setting(s) {', '.join(unknown)}; expected {', '.join(CARD_KEYS)}")
        return dataclasses.replace(self, **{f: _check(f, v, names[f]) for f, v in given.items() if v is not None})

    @property
    def polish_steps(self) -> tuple[str, ...]:
        """The steps of `polish` (`POLISH_STEPS`), in the order they run; () for "none"."""
        return () if self.polish == "none" else tuple(self.polish.split("+"))

    @property
    def photometric(self) -> bool:
        """Whether the polish runs its photometric step (`bridge_jax.polish`)."""
        return "photometric" in self.polish_steps

    @property
    def fill(self) -> bool:
        """Whether the polish runs its fill step: stereo maps by the left-right check (`confidence.left_right_fill`),
        flow maps by the forward-backward check (`confidence.forward_backward_fill`)."""
        return "fill" in self.polish_steps

    @property
    def photometric_part(self) -> "TestTime":
        """This record with the polish cut to its photometric step: what the compiled polish program runs (the
        fill runs on the host afterwards), so "photometric" and "photometric+fill" share one program."""
        return dataclasses.replace(self, polish="photometric" if self.photometric else "none")

    @property
    def network_part(self) -> "TestTime":
        """The stages that run inside the network program (all but the polish: `stages.POLISH_APART`)."""
        return dataclasses.replace(self, polish="none")

    def to_dict(self) -> dict:
        """{"refine": int, "symmetry": str, "polish": str}, as info files write it."""
        return dataclasses.asdict(self)

    @classmethod
    def from_card(cls, card: Optional[Mapping]) -> "TestTime":
        """The settings a shipped model's card (`zoo.info`) recommends; the defaults where it names none."""
        card = card or {}
        return cls(**{f: card[key] for f, key in CARD_KEYS.items() if card.get(key) is not None})


__all__ = ["TestTime", "MAX_REFINE", "SYMMETRY_MODES", "POLISH_MODES", "POLISH_STEPS", "FILL_MAX_DIFFERENCE",
           "FILL_MAX_DIFFERENCE_STEREO", "FILL_MAX_RAISE", "FILL_OCCLUSION_STEP", "FILL_OCCLUSION_REACH", "OPTIONS",
           "CARD_KEYS"]
