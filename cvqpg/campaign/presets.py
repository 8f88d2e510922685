"""The named benchmark grids (`cvqpg bench --preset`) and the methods they compare, as plain data.

Kept apart from `bench`, which runs them, so that the command line's help lists them without importing
PyTorch.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..config import BEYOND_RECIPE, PAPER_RECIPE, PIXEL_RECIPE
from ..defaults import DEFAULT_APERTURE

COLORS = ("rgb", "gray")
# The budgets of a rate grid's cell (`--preset rate`), as fractions of the rate of the codec's smallest ladder
# file within 0.1 dB of the fit: from where the ladder at full N starts to lose (about 0.6) to below fit − 3 dB.
BUDGET_FRACTIONS = (0.7, 0.5, 0.36, 0.26, 0.19, 0.14)
# The budgets at which the encode grid (`--preset encode`) fits each cell's image afresh, as `cvqpg encode --bpp`
# does: all of `BUDGET_FRACTIONS`, since its files lose less per halving of the rate than pruning does and only
# its lowest budgets reach fit − 3 dB (at 0.26, every grayscale cell was 1.7 to 2.9 dB below its fit).
ENCODE_FRACTIONS = BUDGET_FRACTIONS
# The budgets of the rate-in-the-fit comparison (`--preset rate-fit`): three of the rate grid's, from about 1 dB
# below the fit to below fit − 3 dB, so that a cell takes about half an hour on 2 cores at its 600 steps.
RATE_FIT_FRACTIONS = (0.5, 0.36, 0.26)
RATE_FIT_STEPS = 600
# The paper's training time for grayscale and RGB 10% (8.7 and 17.0 min, its runtime table) as steps of the new
# recipe on our 2-core CPU with 2 threads and the machine to itself, measured once (docs/beyond.md).
PAPER_TIME_STEPS = {"gray": 7745, "rgb": 4503}


# How many steps of the per-pixel hologram take the time of one step of CVQPG at 10% through the DPAC display, at
# 640×480 on our 2-core CPU (`python benchmarks/display_time.py`, docs/bench.md): the display grid's per-pixel fit at
# the CVQPG fit's time runs this many times its steps.
# Measured at 1.01 in both colours (results/pixel-screening/display_time.jsonl): through the display a step's
# propagation and loss cost about as much as the whole step, whether Gaussians at 10% or the 307,200 pixels make the
# hologram.
PIXEL_STEPS_PER_CVQPG_STEP = {"gray": 1.01, "rgb": 1.01}


@dataclass(frozen=True)
class Method:
    """A row of the tables: FitConfig changes, and the changes of the method whose parameter count N grows to match
    (None: N as the setting's ratio gives it); the recipe it fits with (None: the preset's); the display its loss
    sees (an encoding and its 4f aperture, `display.Display.create`'s; None: the ideal complex SLM); the encoding its
    fitted model is
    exported to and shown with after the fit (None: none); and its steps as a multiple of the preset's, per colour
    (none given: the preset's)."""

    label: str
    changes: dict[str, str]
    params_of: dict[str, str] | None = None
    recipe: str | None = None
    display: str | None = None
    aperture: float | None | str = "auto"
    exported: str | None = None
    step_factors: tuple[tuple[str, float], ...] = ()

    def steps_for(self, color: str, steps: int) -> int:
        """The method's steps in a grid of `steps` steps, for `color`."""
        return max(1, round(steps * dict(self.step_factors).get(color, 1.0)))


CVQPG = {"primitive": "cvqpg"}
PER_CHANNEL = {"primitive": "cvqpg", "curvature": "per-channel"}
PIXEL = {"primitive": "pixel"}
METHODS = {
    "baseline": Method("Baseline", {"primitive": "flat"}),
    "baseline+": Method("Baseline⁺", {"primitive": "flat"}, params_of=CVQPG),
    "cvqpg": Method("CVQPG", CVQPG),
    "no-bound": Method("w/o adaptive bound", {"primitive": "cvqpg", "bound": "global"}),
    "no-mahalanobis": Method("w/o Mahalanobis QPF", {"primitive": "cvqpg", "qpf": "standard"}),
    "vanilla": Method("vanilla (neither)", {"primitive": "cvqpg", "bound": "global", "qpf": "standard"}),
    "per-channel": Method("CVQPG, γ per channel", PER_CHANNEL),
    "channel-bound": Method("CVQPG, bound per λ", {"primitive": "cvqpg", "curvature": "channel-bound"}),
    "baseline+pc": Method("Baseline (per-channel's params)", {"primitive": "flat"}, params_of=PER_CHANNEL),
    "cvqpg+pc": Method("CVQPG (per-channel's params)", CVQPG, params_of=PER_CHANNEL),
    # what a phase-only SLM shows (the display grid)
    "cvqpg-exported": Method("CVQPG, fitted complex, then exported", CVQPG, exported="dpac"),
    "cvqpg-dpac": Method("CVQPG through the display", CVQPG, display="dpac"),
    "flat-dpac": Method("flat through the display", {"primitive": "flat"}, display="dpac"),
    "pixel-dpac": Method("per-pixel through the display", PIXEL, recipe=PIXEL_RECIPE, display="dpac"),
    # a phase pattern behind the DPAC rows' 4f aperture, which blocks the light that a phase-only SLM cannot dim
    "pixel-phase": Method("per-pixel, phase-only", PIXEL, recipe=PIXEL_RECIPE, display="phase",
                          aperture=DEFAULT_APERTURE),
    "pixel-dpac-time": Method("per-pixel through the display, CVQPG's time", PIXEL, recipe=PIXEL_RECIPE,
                              display="dpac", step_factors=tuple(PIXEL_STEPS_PER_CVQPG_STEP.items())),
    # The phase terms beyond the curvature (cvqpg/phase.py), and CVQPG at each one's parameter count.
    **{phase: Method(f"phase {phase}", {"primitive": "cvqpg", "phase": phase})
       for phase in ("tilt", "quadratic+tilt", "axes", "axes+tilt")},
    **{f"cvqpg@{phase}": Method(f"CVQPG ({phase}'s params)", CVQPG, params_of={"phase": phase})
       for phase in ("tilt", "quadratic+tilt", "axes", "axes+tilt")},
}
DISPLAY_METHODS = ("cvqpg-exported", "cvqpg-dpac", "flat-dpac", "pixel-dpac", "pixel-phase", "pixel-dpac-time")


@dataclass(frozen=True)
class Preset:
    """Default axes and fit size of a named grid; `builtin_scenes` empty means `--scenes DIR` is needed."""

    description: str
    colors: tuple[str, ...]
    ratios: tuple[float, ...]
    methods: tuple[str, ...]
    builtin_scenes: tuple[str, ...] = ()
    size: tuple[int, int] = (640, 480)
    steps: int = 2000
    rate_distortion: bool = False  # each cell also records the R-D points of its model (`rd.json`)
    recipe: str = PAPER_RECIPE  # every grid that compares with the paper pins its recipe
    steps_by_color: tuple[tuple[str, int], ...] = ()  # where a colour has its own step count
    budget_fractions: tuple[float, ...] = ()  # R-D grids: also the codec at `--bpp` budgets (`RateDistortionOptions`)
    encode_fractions: tuple[float, ...] = ()  # the rate grid's cells encoded afresh at these (`run_encode_cell`)
    encode_rate_losses: tuple[bool, ...] = (False,)  # each budget encoded without / with the rate in the fit
    fits_first: bool = False  # an encode grid whose cells make their own rate grid record (`rd.json`) first

    def steps_for(self, color: str) -> int:
        return dict(self.steps_by_color).get(color, self.steps)


PRESETS = {
    "paper": Preset("Table 1: every scene × {rgb, gray} × ratio {0.1, 0.2} × {baseline, baseline+, cvqpg}",
                    COLORS, (0.1, 0.2), ("baseline", "baseline+", "cvqpg")),
    "ablation": Preset("ablation table: RGB, ratio 0.1, CVQPG and its variants against the baseline",
                       ("rgb",), (0.1,), ("baseline", "cvqpg", "no-bound", "no-mahalanobis", "vanilla")),
    "star": Preset("Siemens star: single plane, grayscale, baseline vs CVQPG at equal N",
                   ("gray",), (0.1,), ("baseline", "cvqpg"), ("star",)),
    "chromatic": Preset("RGB, ratio {0.1, 0.2}: per-channel curvature and its variant against shared "
                        "CVQPG and the baseline, at equal N and at per-channel's parameter count",
                        ("rgb",), (0.1, 0.2), ("baseline", "cvqpg", "per-channel", "channel-bound", "baseline+pc",
                                               "cvqpg+pc")),
    "compression": Preset("the Table 1 CVQPG cells at {rgb, gray} 10%, each with the R-D points of the "
                          ".cvq codec, JPEG 2000 and JPEG XL on its field, and its float32/float16 model files",
                          COLORS, (0.1,), ("cvqpg",), rate_distortion=True),
    "rate": Preset("the Table 1 CVQPG cells at {rgb, gray} 10%, each with the .cvq codec at `--bpp` budgets "
                   "from its fit down to below fit − 3 dB (rate control), beside JPEG 2000 and JPEG XL on its field",
                   COLORS, (0.1,), ("cvqpg",), rate_distortion=True, budget_fractions=BUDGET_FRACTIONS),
    "encode": Preset("`cvqpg encode --bpp` at the rate grid's six budgets per cell, each a fit at the "
                     "budget's primitive count rate-controlled into it; run into the rate grid's folder after "
                     "`--preset rate`, whose tables then show both", COLORS, (0.1,), ("cvqpg",), rate_distortion=True,
                     budget_fractions=BUDGET_FRACTIONS, encode_fractions=ENCODE_FRACTIONS),
    "rate-fit": Preset("`cvqpg encode --bpp` as today (a float fit) and with the rate in the fit (`--rate-loss`) at "
                       "three budgets per cell, beside JPEG 2000 and JPEG XL on the field of the cell's own fit, made "
                       f"first; {RATE_FIT_STEPS} steps, so that a grid of three scenes (`--scene-names`) takes an "
                       "afternoon", COLORS, (0.1,), ("cvqpg",), steps=RATE_FIT_STEPS, rate_distortion=True,
                       budget_fractions=RATE_FIT_FRACTIONS, encode_fractions=RATE_FIT_FRACTIONS,
                       encode_rate_losses=(False, True), fits_first=True),
    "beyond": Preset("the beyond recipe at 2000 steps, {rgb, gray} 10% × {baseline, cvqpg}, beside the "
                     "paper grid's cells", COLORS, (0.1,), ("baseline", "cvqpg"), recipe=BEYOND_RECIPE),
    "beyond-time": Preset("CVQPG with the beyond recipe for the paper's own training time (8.7 min gray, "
                          "17.0 min RGB, its runtime table), as fixed step counts measured on our 2-core CPU",
                          COLORS, (0.1,), ("cvqpg",), recipe=BEYOND_RECIPE,
                          steps_by_color=tuple(PAPER_TIME_STEPS.items())),
    "display": Preset("what a phase-only SLM shows: {rgb, gray} 10%, CVQPG fitted complex then exported, CVQPG, flat "
                      "and the per-pixel hologram fitted through the DPAC display, the per-pixel phase pattern, at "
                      "equal steps, and the per-pixel hologram at the CVQPG display fit's time", COLORS, (0.1,),
                      DISPLAY_METHODS, recipe=BEYOND_RECIPE),
    "beyond-phase": Preset("phase terms beyond the curvature (cvqpg/phase.py) with the beyond recipe at 2000 steps, "
                    "{rgb, gray} 10%: CVQPG, quadratic+tilt and axes+tilt at equal N, and CVQPG at each one's "
                    "parameter count", COLORS, (0.1,),
                    ("cvqpg", "quadratic+tilt", "axes+tilt", "cvqpg@quadratic+tilt", "cvqpg@axes+tilt"),
                    recipe=BEYOND_RECIPE),
    "quick": Preset("smoke test: built-in scenes, 160×120, 60 steps",
                    ("gray",), (0.1,), ("baseline", "cvqpg"), ("demo", "star"), (160, 120), 60),
}
