"""What an SLM shows (method.md §8): the display a hologram is shown on, and the pattern it is sent.

A `Display` is one definition that the fit's loss, `eval`, `export`, `view` and `bench` share: the encoding of the
SLM field (`complex`, an ideal complex SLM; `dpac`, double-phase amplitude coding on a phase-only SLM; `phase`,
the field's bare phase on one), the phase levels a phase-only SLM shows (uniform levels, or a measured lookup
table), the circular aperture of the 4f system behind it, and the SLM's canvas. The functions here turn an SLM
field into the field the display shows on its canvas, with gradients defined on purpose where the encoding has
none (method.md §8); `optics.reconstruct` propagates it to the planes, the 4f aperture folded into the
propagation's transfer functions. The patterns themselves, which need PyTorch, are `cvqpg.patterns`': this module
stays free of it, since the configuration (and with it the command line's parser) holds a `Display`.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal, get_args


from .defaults import DEFAULT_APERTURE, DEFAULT_LEVELS
from .errors import ConfigError, InputError, choices_error
from .files import input_file

Encoding = Literal["complex", "dpac", "phase"]
ENCODINGS: tuple[str, ...] = get_args(Encoding)
PHASE_ENCODINGS = ("dpac", "phase")
MAX_LEVELS = 2**16
MAX_CANVAS_PX = 65536
MAX_APERTURE = math.sqrt(2)  # the spectrum's corners: from there on the aperture passes every frequency
TWO_PI = 2 * math.pi
MAX_LUT_PHASE = 4 * math.pi  # rad: a turn or two is what SLMs show; 360 would be degrees
# DPAC's offset arccos(A) has slope −1/√(1 − A²), unbounded as the amplitude A reaches 1: above this amplitude
# its gradient keeps the slope it has here (−22.4), and the value stays exact.
DPAC_SLOPE_AMPLITUDE = 1 - 1e-3


@dataclass(frozen=True)
class Display:
    """A display: the `encoding` of the SLM field, the phase `levels` of a phase-only SLM (or `lut`, the phase in
    rad that each gray level shows, `levels` of them), the 4f system's circular Fourier `aperture` as a fraction
    of the Nyquist frequency (None: no filter) and the SLM's `canvas` (H, W) px (None: the hologram's own size).

    The default, an ideal complex SLM with neither aperture nor canvas, is the fit of method.md §3: the hologram
    with its guard band. Any other display shows its canvas alone, with no light around it. Checked where made
    (`ConfigError`); `Display.create` gives `dpac` its measured aperture.
    """

    encoding: Encoding = "complex"
    levels: int = DEFAULT_LEVELS
    lut: tuple[float, ...] | None = None
    aperture: float | None = None
    canvas: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise choices_error("display", self.encoding, ENCODINGS)
        if isinstance(self.levels, bool) or not isinstance(self.levels, int) or not 2 <= self.levels <= MAX_LEVELS:
            raise ConfigError(f"`levels` {self.levels!r}: an SLM has between 2 and {MAX_LEVELS} phase levels")
        if self.lut is not None:
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in self.lut):
                raise ConfigError("`lut`: every gray level's phase must be a finite number (rad)")
            reach = max(abs(v) for v in self.lut) if self.lut else 0.0
            if reach > MAX_LUT_PHASE:
                raise ConfigError(f"`lut`: a gray level's phase of {reach:g} rad lies beyond ±4π (±{MAX_LUT_PHASE:.4g} "
                                  "rad), where a measured table's phases lie; give them in rad (not degrees)")
            if len(self.lut) != self.levels:
                raise ConfigError(f"`lut` holds {len(self.lut)} phases for {self.levels} `levels`: give one phase per "
                                  "gray level (`Display.create` counts them)")
        if self.aperture is not None and not (isinstance(self.aperture, (int, float))
                                              and not isinstance(self.aperture, bool)
                                              and 0 < self.aperture <= MAX_APERTURE):
            raise ConfigError(f"`aperture` {self.aperture!r}: give a radius in (0, √2] (a fraction of the Nyquist "
                              "frequency), or none for no filter")
        if self.canvas is not None and not (isinstance(self.canvas, tuple) and len(self.canvas) == 2 and all(
                isinstance(n, int) and not isinstance(n, bool) and 1 <= n <= MAX_CANVAS_PX for n in self.canvas)):
            shown = (f"{self.canvas[1]}×{self.canvas[0]}" if isinstance(self.canvas, tuple) and len(self.canvas) == 2
                     else repr(self.canvas))
            raise ConfigError(f"`canvas` {shown}: each side of the SLM (W×H) takes 1 to {MAX_CANVAS_PX} px")
        if self.encoding == "complex" and (self.levels != DEFAULT_LEVELS or self.lut is not None):
            raise ConfigError("`levels` and `lut` are a phase-only SLM's: use them with the `dpac` or `phase` display")

    @classmethod
    def create(cls, encoding: Encoding = "complex", levels: int | None = None, lut: tuple[float, ...] | None = None,
               aperture: float | None | Literal["auto"] = "auto", canvas: tuple[int, int] | None = None
               ) -> "Display":
        """A display with its encoding's defaults where not given: `levels` that of the `lut` (else 256), and the
        `auto` aperture `DEFAULT_APERTURE` for `dpac` (which removes the checkerboard's carrier), none otherwise."""
        lut = None if lut is None else tuple(float(v) for v in lut)
        if levels is None:
            levels = DEFAULT_LEVELS if lut is None else len(lut)
        if aperture == "auto":
            aperture = DEFAULT_APERTURE if encoding == "dpac" else None
        return cls(encoding, levels, lut, aperture, None if canvas is None else tuple(canvas))

    @classmethod
    def from_options(cls, encoding: Encoding = "complex", levels: int | None = None, lut: str | Path | None = None,
                     aperture: float | None = None, slm: tuple[int, int] | None = None) -> "Display":
        """The display that the command line's options describe (`create`'s defaults where None): `lut` a file
        (`read_lut`), `aperture` 0 for no filter, `slm` the SLM's (W, H) px."""
        return cls.create(encoding, levels, None if lut is None else read_lut(lut),
                          "auto" if aperture is None else aperture or None, None if slm is None else (slm[1], slm[0]))

    @property
    def ideal(self) -> bool:
        """Whether this is the default display, the complex hologram of method.md §3 (guard band and all)."""
        return self == Display()

    @property
    def phase_only(self) -> bool:
        return self.encoding in PHASE_ENCODINGS

    def canvas_for(self, height: int, width: int) -> tuple[int, int]:
        """The canvas (H, W) px of a `height`×`width` hologram on this display; `ConfigError` where it is smaller."""
        canvas = self.canvas or (height, width)
        if canvas[0] < height or canvas[1] < width:
            raise ConfigError(f"`canvas` {canvas[1]}×{canvas[0]} is smaller than the {width}×{height} hologram; "
                              "give an SLM at least that large")
        return canvas

    def label(self) -> str:
        """E.g. `dpac, 256 levels, aperture 0.5` or `complex`."""
        if self.ideal:
            return "complex"
        parts = [self.encoding]
        if self.phase_only:
            parts.append(f"{self.levels}-level LUT" if self.lut is not None else f"{self.levels} levels")
        parts.append("no aperture" if self.aperture is None else f"aperture {self.aperture:g}")
        if self.canvas is not None:
            parts.append(f"canvas {self.canvas[1]}×{self.canvas[0]}")
        return ", ".join(parts)

    def to_dict(self) -> dict[str, Any]:
        """The record `config.json` keeps (JSON types)."""
        record = asdict(self)
        return {**record, "lut": None if self.lut is None else list(self.lut),
                "canvas": None if self.canvas is None else list(self.canvas)}

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> "Display":
        """The display a `to_dict` recorded; a record without one (every run before displays) is the complex one."""
        if not data:
            return cls()
        lut, canvas = data.get("lut"), data.get("canvas")
        return cls(data.get("encoding", "complex"), data.get("levels", DEFAULT_LEVELS),
                   None if lut is None else tuple(lut), data.get("aperture"),
                   None if canvas is None else tuple(canvas))


def read_lut(path: str | Path) -> tuple[float, ...]:
    """A measured lookup table: the phase (rad) that each gray level of the SLM shows, from a text or CSV file.

    One row per gray level, from level 0 up: either the phase alone, or the gray level and its phase (separated
    by a comma, semicolon, tab or spaces; the levels 0, 1, 2, … in order). Blank lines, `#` comments and a header
    row of names are skipped. `InputError` naming the file and the row where it cannot be read.
    """
    path = Path(path)
    if path.exists() and not (path.is_file() or path.is_dir()):  # a pipe or a device: never read
        input_file(path, "the lookup table", "a text file of one phase (rad) per gray level")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read the lookup table ({error}); give a text file of one phase (rad) per "
                         "gray level") from None
    phases: list[float] = []
    for number, line in enumerate(text.splitlines(), 1):
        fields = [f for f in re.split(r"[,;\s]+", line.split("#", 1)[0].strip()) if f]
        if not fields:
            continue
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if not phases and all(re.match(r"^[A-Za-z_]", f) for f in fields):
                continue  # a header row
            raise InputError(f"{path}, row {number}: {line.strip()!r} is not a number; give one phase (rad) per "
                             "gray level, or the gray level and its phase") from None
        if len(values) > 2 or (len(values) == 2 and values[0] != len(phases)) or not math.isfinite(values[-1]):
            raise InputError(f"{path}, row {number}: {line.strip()!r}; give gray level {len(phases)}'s phase (rad) "
                             "as `PHASE` or `GRAY, PHASE`, the levels in order from 0")
        phases.append(values[-1])
    if not 2 <= len(phases) <= MAX_LEVELS:
        raise InputError(f"{path}: {len(phases)} gray levels; a lookup table holds between 2 and {MAX_LEVELS}")
    return tuple(phases)
