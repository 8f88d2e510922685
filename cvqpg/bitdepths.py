"""Bit depths of the compressed model file's attributes (`BitDepths`): what `cvqpg compress --bits` sets.

Plain data, apart from the codec that uses it, so that the command line's help shows the defaults without
importing PyTorch.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Iterable

from .errors import ConfigError

MAX_POSITION_BITS = 8
MAX_BITS = 16
# The depths of the phase terms beyond the curvature (`phase.TERMS` by name): a file has them only where its model
# has the term. Their defaults are curvature's, so that the search's ladder (`LADDER`) has the rungs it had.
PHASE_TERMS = ("axes", "tilt")


def _limits(name: str) -> tuple[int, int]:
    """Valid bit depths of an attribute: positions from whole pixels (0) to 1/256 px; the others 2..16."""
    return (0, MAX_POSITION_BITS) if name == "position" else (2, MAX_BITS)


@dataclass(frozen=True)
class BitDepths:
    """Bits per attribute. `position` counts fractional bits (grid of 2^-b px); the others count
    levels over the attribute's range: log scale over the model's range, |amplitude·opacity| over
    [0, max], rotation over [0, π), phase over [0, 2π), curvature over [−γ_max, γ_max], and the phase terms
    beyond the curvature (`PHASE_TERMS`: `axes`, `tilt`, cvqpg/phase.py) over [−limit, limit] of each of their
    parameters. Every attribute but scale takes its depth for a value of median importance, and more or fewer
    bits for others (`derived_depths`). A file codes the terms' depths only where its model has the term
    (`coded`)."""

    position: int = 3
    scale: int = 8
    rotation: int = 7
    amplitude: int = 8
    phase: int = 7
    curvature: int = 8
    axes: int = 8
    tilt: int = 8

    def validate(self) -> "BitDepths":
        for name, value in asdict(self).items():
            low, top = _limits(name)
            if not low <= value <= top:
                raise ConfigError(f"`bits` {name}={value}: give {low}..{top} bits")
        return self

    def shifted(self, delta: int) -> "BitDepths":
        """Every attribute `delta` bits finer (coarser when negative), kept within the valid ranges."""
        return BitDepths(**{name: min(max(value + delta, _limits(name)[0]), _limits(name)[1])
                            for name, value in asdict(self).items()})

    def names(self) -> list[str]:
        return [f.name for f in fields(self)]

    def coded(self, terms: Iterable[str] = ()) -> dict[str, int]:
        """The depths a file codes: every attribute but the phase terms, and those of `terms` (names of
        `PHASE_TERMS`), in this class's order."""
        wanted = set(terms)
        return {name: value for name, value in asdict(self).items() if name not in PHASE_TERMS or name in wanted}

    def shifted_one(self, name: str, delta: int = -1) -> "BitDepths | None":
        """`delta` bits finer (coarser when negative, by default one) in attribute `name`, or None beyond its
        valid depths."""
        value = getattr(self, name) + delta
        low, top = _limits(name)
        return replace(self, **{name: value}) if low <= value <= top else None

    @classmethod
    def parse(cls, items: list[str]) -> "BitDepths":
        """`["position=3", "phase=6"]` or `["8"]` (8 bits for every attribute but position)."""
        if len(items) == 1 and items[0].isdigit():
            value = int(items[0])
            return cls(**{f.name: value for f in fields(cls) if f.name != "position"}).validate()
        known, values = {f.name for f in fields(cls)}, {}
        for item in items:
            name, _, value = item.partition("=")
            if name not in known or not value.isdigit():
                raise ConfigError(f"`bits` {item}: give ATTRIBUTE=BITS with ATTRIBUTE one of "
                                  f"{', '.join(sorted(known))}, or one number for all but position")
            if name in values:
                raise ConfigError(f"`bits` {name}={values[name]} and {item}: give each attribute once")
            values[name] = int(value)
        return cls(**values).validate()


# The depths every search tries (`cvqpg.search`): the defaults shifted together, from 3 bits coarser up to every
# attribute's finest depth, so that a budget the whole model fits in at the finest default-shaped depths still has
# rungs.
LADDER = tuple(dict.fromkeys(BitDepths().shifted(delta) for delta in range(-3, MAX_BITS)))
