"""The compressed model file (`.cvq`, docs/format.md) as a pure codec: bytes ↔ (primitives, configuration).

Quantised primitives in a spatial order, entropy-coded with `constriction`'s ANS coder, behind a magic
number, a format version and a CRC32. A primitive is coded as: position on a grid of 2^-b px, sorted in
Morton order of its whole pixel and coded as gaps between consecutive Morton codes, then its fraction of
a pixel; log scale over the model's own range; amplitude × opacity as a magnitude, its sign folded into the
phase (+π); rotation modulo π (an ellipse turned by π is the same ellipse); phase modulo 2π; curvature as
a fraction of the primitive's own bound γ_max (method.md §4); from format 6 on, each phase term beyond the curvature
(`phase.TERMS`: `axes`, `tilt`) as fractions of the bound its activation keeps it within (`PhaseTerm.limit`).
Every attribute but scale is coded at a depth per value that follows how much its error weighs in the field
(`derived_depths`), computed from the attributes decoded before it, so that encoder and decoder agree
without storing it.

Each attribute's quantiser is written once, in torch (`Quantiser`; `coding` derives them from a model):
the encoder takes their integer codes, quantisation-aware fine-tuning (`finetune`) rounds through them
in its forward pass.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Callable

import constriction
import numpy as np
import torch
from torch import Tensor

from .bitdepths import MAX_BITS, MAX_POSITION_BITS, PHASE_TERMS, BitDepths
from .config import FitConfig
from .defaults import SUFFIX
from .display import Display
from .errors import ConfigError, ModelFileError
from .phase import AXES as AXES_PHASE_TERM, COVARIANCE_REGULARISER_PX2, TERMS, axis_sigmas_px, parse_phase
from .primitives import (REWRITE_MODEL, Primitives, check_settings, check_tensors, curvature_bound,
                         model_shapes, term_bounds)

MAGIC = b"\x89CVQ\r\n\x1a\n"
# 2 added the `bitlength` coding, 3 rotation's depth per primitive, 4 the depths of position, amplitude, rotation,
# phase and curvature by importance, 5 the fit fingerprint and the tools (`TOOLS`); older files read unchanged
FORMAT_VERSION = 6
ROTATION_DEPTH_VERSION = 3  # files from this version on code rotation at a depth per primitive
IMPORTANCE_VERSION = 4  # files from this version on code at `derived_depths`' importance rule
TOOLS_VERSION = 5  # files from this version on carry a fit fingerprint and name the tools they use
DISPLAY_VERSION = 6  # files from this version on keep the display a model was fitted through (none: the complex one)
PHASE_VERSION = 6  # files from this version on keep the phase terms beyond the curvature (none: the paper's phase)
# Format 5's tools, each named in the header where a file uses it. `axes`: the larger scale code first, the
# ellipse turned by a quarter where its axes swap, and the smaller coded as its difference from the larger
# (`elongation`); `turn`: a periodic stream's symbols of each depth turned so that their circular mean lies
# mid-range, which parametric models centred there then fit; `channels` (more than one channel): each channel's
# amplitude and phase after the first coded as its change from the channel before (`channel_changes`).
AXES, TURN, CHANNELS = "axes", "turn", "channels"
AXES_TERM = AXES_PHASE_TERM.name  # the phase term `axes` (two curvatures along the ellipse's axes), not the tool
TOOLS = frozenset({AXES, TURN, CHANNELS})
PERIODIC = ("rotation", "phase", "phase_change")  # the streams whose symbols are angles, `turn`'s
CHANGED = ("amplitude", "phase")  # the attributes `channels` codes as changes
# The order the decoder reads attributes in: each depth derives from attributes read before it. The phase terms
# beyond the curvature (format 6 on, where a model has them) by their names in `phase.TERMS`, before rotation, whose
# depth the astigmatism of `axes` raises.
ATTRIBUTES = ("scale", "amplitude", "position", *PHASE_TERMS, "rotation", "phase", "curvature")
PREFIX = struct.Struct("<8sHI")  # magic, format version, header length (bytes)
FINGERPRINT = struct.Struct("<16s")  # format 5 on, after the prefix: the fit's (`runs.fingerprint_digest`)
NO_FINGERPRINT = bytes(FINGERPRINT.size)  # a model whose fit is not known
CHECKSUM = struct.Struct("<I")
ZLIB_FDICT = 0x20  # the flag of a zlib stream's second byte that says it was deflated with a preset dictionary
# Each depth of a file is a stream of its own in the header (`grouped`): the few values far from the median weight
# share the depths ±MAX_OFFSET bits from it.
MAX_OFFSET = 2


def bits_per_pixel(size_bytes: int, config: FitConfig) -> float:
    """8·bytes / (W·H): a file's bits per hologram pixel, all channels together (`cvqpg info`'s bpp)."""
    return 8 * size_bytes / (config.targets.width * config.targets.height)


# Stream codings; each stream takes the smallest that applies, so a coding that does not pay is never used.
RAW, LAPLACE, GAUSSIAN, CATEGORICAL, BIT_LENGTH = "raw", "laplace", "gaussian", "categorical", "bitlength"
# Streams at a width per symbol that the decoder derives (`_stream_at_widths`): `widths`, raw bits; `grouped`
# (format 4 on), the symbols of each width as a stream of their own.
WIDTHS, GROUPED = "widths", "grouped"
CODINGS = (RAW, LAPLACE, GAUSSIAN, CATEGORICAL, BIT_LENGTH, WIDTHS, GROUPED)
# The largest symbol the encoder gives the entropy coder's models (parametric, categorical): beyond, the coder
# cannot give every symbol a probability, and a decoder given more would make it abort.
MAX_ANS_TOP, MAX_CATEGORICAL_TOP = 2**20, 2**12
MAX_SYMBOL_BITS = 63  # symbols are int64
MAX_HEADER_BYTES = 2**24  # a header decompresses to far less; more is not a file cvqpg wrote
# Format 5 on, the header is deflated with this preset dictionary (RFC 1950's FDICT): the keys, codings and optics
# every header repeats, so that they cost a few bytes each rather than their letters. Part of the format: never
# change it within a version.
HEADER_DICTIONARY = (
    '{"optics":{"width":640,"height":480,"color":"gray","primitive":"flat","curvature":"per-channel",'
    '"qpf":"standard","bound":"global","color":"rgb","primitive":"cvqpg","curvature":"channel-bound",'
    '"curvature":"shared","qpf":"mahalanobis","bound":"adaptive","eta":0.9,"global_bound":200.0,'
    '"pixel_pitch":3.74e-06,"num_planes":2,"plane_center":0.003,"plane_span":0.004,"guard_band_px":144,'
    '"pad_multiple_px":64,"wavelengths":[6.39e-07,5.32e-07,4.73e-07]},"num_primitives":'
    '"bits":{"position":3,"scale":8,"rotation":7,"amplitude":8,"phase":7,"curvature":8},'
    '"ranges":{"scale":[,"amplitude":[0.0,"tools":["axes","turn"],"streams":['
    '{"name":"position","coding":"bitlength","lengths":{"coding":"categorical","histogram_bytes":'
    '{"name":"fraction","coding":"widths","min":0,"max":15,"shape":[,2],"bytes":'
    '{"name":"scale","coding":"laplace","params":[{"name":"elongation","coding":"gaussian","params":['
    '{"name":"amplitude","coding":"grouped","groups":[{"coding":"raw","width":'
    '{"coding":"gaussian","params":[,"bits":7},{"coding":"laplace","params":[,"turn":'
    '{"name":"rotation","coding":"widths",{"name":"phase","coding":"grouped","groups":['
    '{"coding":"categorical","histogram_bytes":{"name":"curvature","coding":"grouped","groups":['
    '"bits":9},"bits":8},"bits":6},,"shape":[,1],"bytes":,"min":0,"max":').encode()


@dataclass(frozen=True)
class Quantiser:
    """One attribute's uniform scalar quantiser: code k stands for `low + k·span/levels`.

    Codes are clipped to `lowest..highest` (None: unbounded) or, for a periodic attribute whose period
    is `span`, taken modulo `levels`. Values are float64, ties round to even. The arithmetic keeps the
    order of operations every file so far was written with, (v − low)/span·levels and not (v − low)/step,
    since a different rounding would move values that lie on a bin edge.
    """

    low: float
    span: float
    levels: int | Tensor  # a tensor: one count per value (`derived_depths`)
    lowest: int | None = 0
    highest: int | None = None
    periodic: bool = False

    @property
    def step(self) -> float:
        """The distance between the values of neighbouring codes."""
        return self.span / self.levels

    def codes(self, values: Tensor) -> Tensor:
        """The code (int64) nearest each value."""
        if self.periodic:
            turns = torch.remainder(values - self.low, self.span) / self.span
            return torch.round(turns * self.levels).long() % self.levels
        codes = torch.round((values - self.low) / self.span * self.levels)
        if isinstance(self.highest, Tensor):  # clamp takes two numbers or two tensors
            return torch.clamp(codes, torch.as_tensor(self.lowest, dtype=codes.dtype), self.highest).long()
        return codes.clamp(self.lowest, self.highest).long()

    def values(self, codes: Tensor) -> Tensor:
        """The value (float64) each code stands for."""
        return self.low + codes.double() * (self.span / self.levels)

    def scaled(self, values: Tensor) -> Tensor:
        """Each value in units of its bin, unrounded (float64, differentiable): what `codes` rounds, clipped to the
        codes' bounds, a periodic value taken into 0 ≤ code < `levels`. The rate model (`cvqpg.rate`) perturbs
        these in place of rounding."""
        if self.periodic:
            return torch.remainder(values - self.low, self.span) / self.span * self.levels
        scaled = (values - self.low) / self.span * self.levels
        low = -math.inf if self.lowest is None else self.lowest
        high = math.inf if self.highest is None else self.highest
        return torch.clamp(scaled, torch.as_tensor(low, dtype=scaled.dtype, device=scaled.device),
                           torch.as_tensor(high, dtype=scaled.dtype, device=scaled.device))

    def on(self, device: torch.device | str) -> "Quantiser":
        """The same quantiser with its per-value counts and bounds on `device`."""
        return replace(self, **{name: value.to(device) for name, value in
                                (("levels", self.levels), ("lowest", self.lowest), ("highest", self.highest))
                                if isinstance(value, Tensor)})


class ShareQuantiser(Quantiser):
    """Curvature as a share of γ_max: codes −h..h, code k standing for k/h (h = `levels`), divided and
    not multiplied by 1/h as in every file so far."""

    def values(self, codes: Tensor) -> Tensor:
        return codes.double() / self.levels


def _short(value: float, digits: int = 4) -> float:
    """`value` to a few significant digits: the header stores it in few bytes, and encoder and
    decoder both use the stored value."""
    return float(f"{value:.{digits}g}")


def _outward_range(low: float, high: float) -> list[float]:
    """[low, high] widened to short values (see `_short`) that still contain it: a margin of 1e-3 of
    the larger magnitude outweighs `_short`'s rounding error of at most 5e-4."""
    margin = 1e-3 * max(abs(low), abs(high), 1e-12)
    return [_short(low) if _short(low) <= low else _short(low - margin),
            _short(high) if _short(high) >= high else _short(high + margin)]


Depth = int | Tensor  # bits of every value, or of each value (int64, the values' shape)


def quantiser(name: str, ranges: dict[str, list[float]], depth: Depth) -> Quantiser:
    """Attribute `name`'s quantiser at `depth` bits, given the header's ranges of log scale and
    |amplitude·opacity|."""
    if name in ("scale", "amplitude"):
        low, high = ranges[name]
        return Quantiser(low, high - low if high > low else 1.0, 2**depth - 1, 0, 2**depth - 1)
    if name == "curvature" or name in PHASE_TERMS:
        half = 2 ** (depth - 1) - 1
        return ShareQuantiser(0.0, 1.0, half, -half, half)
    period = {"position": 1.0, "rotation": math.pi, "phase": 2 * math.pi}[name]
    return Quantiser(0.0, period, 2**depth, periodic=name != "position")


def quantisers(ranges: dict[str, list[float]], bits: BitDepths) -> dict[str, Quantiser]:
    """Each attribute's quantiser at its depth in `bits` for every value."""
    return {name: quantiser(name, ranges, getattr(bits, name)) for name in ATTRIBUTES}


def rotation_depths(scale_px: Tensor, depth: Depth, least: int = 0, astigmatism: Tensor | None = None) -> Tensor:
    """Bits of rotation (int64 [N]) for primitives of decoded scale `scale_px` (px, [N, 2]): `depth` for an
    ellipse whose anisotropy a − 1/a (a = σ_max/σ_min) lies in [0.5, 1), one more per doubling of it, one
    fewer per halving, none for a circle, within `least`..MAX_BITS otherwise. Turning an ellipse by Δθ changes
    it by about Δθ·(a − 1/a), so every primitive's rotation then costs about the same error, and nearly round
    ones, many in a fit, cost few bits. With the phase term `axes`, its `astigmatism` (float64 [N]) adds to the
    anisotropy: its phase turns with the ellipse, a circle's too. float64 division and frexp are exact, so every
    machine agrees."""
    scale = scale_px.detach().cpu().double()
    aspect = scale.max(dim=1).values / scale.min(dim=1).values
    anisotropy = aspect - 1 / aspect
    if astigmatism is not None:
        anisotropy = anisotropy + astigmatism
    _, exponent = torch.frexp(anisotropy)
    return torch.where(anisotropy > 0, (depth + exponent.long()).clamp(least, MAX_BITS), 0)


def astigmatism(scale_px: Tensor, shares: Tensor) -> Tensor:
    """How much turning a primitive by Δθ changes its `axes` phase, per radian (float64 [N]), from its decoded scale
    (px, [N, 2]) and its decoded shares s_u, s_v of the axes' bounds (float64 [N, 2]): (π/6)·|s_u σ_v − s_v σ_u|, σ =
    √(s² + 0.1) px, the RMS phase change over the primitive's |field|² of a term that had the whole Nyquist limit
    (γ_max = λ/(6σΔx²) per axis), an upper bound of the term's own. Symmetric in the two axes, so that swapped axes
    (`axes` tool) give the same bits."""
    sigma = axis_sigmas_px(scale_px.detach().cpu().double())
    shares = shares.detach().cpu().double()
    return (math.pi / 6) * (shares[:, 0] * sigma[:, 1] - shares[:, 1] * sigma[:, 0]).abs()


def uses(tool: str, version: int, tools: frozenset[str]) -> bool:
    """Whether a file of `version` naming `tools` uses `tool` (none before format 5)."""
    return version >= TOOLS_VERSION and tool in tools


def importance_offsets(weight: Tensor) -> Tensor:
    """Bits to add (int64, `weight`'s shape) to the depth of values whose quantisation error weighs `weight`
    (float64, ≥ 0) in the field's energy: half the distance of each weight's binary exponent from the median
    exponent of the positive weights, rounded down, within ±MAX_OFFSET. An error of step Δ costs about
    weight·Δ², so a value weighing 4 times as much takes one bit more and every value's error costs about
    alike; a value of weight 0 does not show and gets −MAX_BITS. The exponents come from frexp, which is exact,
    so every machine agrees."""
    _, exponent = torch.frexp(weight)
    positive = weight > 0
    exponents = exponent[positive].long().sort().values
    median = int(exponents[exponents.numel() // 2]) if exponents.numel() else 0
    offsets = torch.div(exponent.long() - median, 2, rounding_mode="floor").clamp(-MAX_OFFSET, MAX_OFFSET)
    return torch.where(positive, offsets, -MAX_BITS)


def derived_depths(name: str, decoded: dict[str, Tensor], bits: BitDepths, shape: tuple[int, ...],
                   version: int = FORMAT_VERSION, tools: frozenset[str] = TOOLS) -> Tensor | None:
    """Bits of each value (int64, `shape`) of attribute `name` where a file of `version` derives them from the
    attributes decoded before it, else None (`bits`' depth for every value). `decoded` holds "scale", the
    decoded scale σ̂ (px, float32 [N, 2]), and, once decoded, "amplitude", |amplitude·opacity| (float64 [N, C]), and
    the phase term `axes`'s shares (float64 [N, 2]) where the file has it.

    From format 4 on, each value's depth is its attribute's depth in `bits` plus `importance_offsets` of the
    energy its error costs, within 2..16 bits (0..16 for rotation and phase, 0..8 fractional bits for
    position): position by Σ_c |w_c|² (a shifted Gaussian's error energy does not depend on its size);
    amplitude by σ̂x·σ̂y; phase by |w|²·σ̂x·σ̂y of its channel; rotation and shared curvature by
    Σ_c |w_c|²·σ̂x·σ̂y (a channel's curvature by its channel's), rotation on top of its anisotropy's bits
    (`rotation_depths`), and at least 1 bit for an ellipse where `tools` (format 5 on) hold `axes`, which
    orders its axes and so needs a bit to tell a quarter turn, and with the phase term `axes` the term's
    `astigmatism` added to the anisotropy. A phase term's shares (format 6 on), both of a primitive at one depth, by
    Σ_c |w_c|²·σ̂x·σ̂y·(σ̂x² + σ̂y² + 0.2): the phase error of a share's error grows with the footprint's width.
    Format 3 derives rotation's from its anisotropy alone."""
    if version < ROTATION_DEPTH_VERSION or (version < IMPORTANCE_VERSION and name != "rotation"):
        return None
    if version < IMPORTANCE_VERSION:
        return rotation_depths(decoded["scale"], bits.rotation)
    if name == "scale":
        return None
    scale = decoded["scale"].detach().cpu().double()
    area = scale[:, 0] * scale[:, 1]
    if name == "amplitude":
        return (bits.amplitude + importance_offsets(area)).clamp(2, MAX_BITS)[:, None].expand(shape).contiguous()
    amplitude = decoded["amplitude"].detach().cpu().double()
    power = amplitude[:, 0] ** 2
    for channel in range(1, amplitude.shape[1]):  # in a fixed order, so that every machine rounds alike
        power += amplitude[:, channel] ** 2
    if name == "position":
        offsets = importance_offsets(power)
        return (bits.position + offsets).clamp(0, MAX_POSITION_BITS)[:, None].expand(-1, 2).contiguous()
    per_channel, total = amplitude**2 * area[:, None], power * area
    if name == "rotation":
        return rotation_depths(decoded["scale"], bits.rotation + importance_offsets(total),
                               int(uses(AXES, version, tools)),
                               astigmatism(decoded["scale"], decoded[AXES_TERM]) if AXES_TERM in decoded else None)
    if name in PHASE_TERMS:
        spread = scale[:, 0] * scale[:, 0] + scale[:, 1] * scale[:, 1] + 2 * COVARIANCE_REGULARISER_PX2
        depths = (getattr(bits, name) + importance_offsets(total * spread)).clamp(2, MAX_BITS)
        return depths[:, None].expand(shape).contiguous()
    if name == "phase":
        return (bits.phase + importance_offsets(per_channel)).clamp(0, MAX_BITS)
    weight = total if len(shape) == 1 else per_channel
    return (bits.curvature + importance_offsets(weight)).clamp(2, MAX_BITS)


def chained_quantisers(ranges: dict[str, list[float]], bits: BitDepths, shapes: dict[str, tuple[int, ...]],
                       read: Callable[[str, Quantiser, Tensor | None], Tensor], version: int = FORMAT_VERSION,
                       tools: frozenset[str] = TOOLS) -> tuple[dict[str, Quantiser], dict[str, Tensor]]:
    """Each attribute's quantiser and derived depths (`derived_depths`), attribute by attribute in the order
    `ATTRIBUTES` (those absent from `shapes` skipped): `read(name, quantiser, depths)` returns the attribute's
    decoded values (float64), from which the depths of the attributes after it derive. The encoder reads by
    rounding its values, the decoder its stream, fine-tuning straight through."""
    chosen, depths, decoded = quantisers(ranges, bits), {}, {}
    for name in ATTRIBUTES:
        if name not in shapes:
            continue
        derived = derived_depths(name, decoded, bits, shapes[name], version, tools)
        if derived is not None:
            depths[name] = derived
            chosen[name] = quantiser(name, ranges, derived)
        value = read(name, chosen[name], derived)
        if name == "scale":
            decoded["scale"] = decoded_scale(value.detach().cpu(), version)
        elif name == "amplitude":
            decoded["amplitude"] = value.detach().cpu().abs()
        elif name == AXES_TERM:
            decoded[AXES_TERM] = value.detach().cpu()
    return chosen, depths


def decoded_scale(log_scale: Tensor, version: int = FORMAT_VERSION) -> Tensor:
    """Scale (px, float32) from dequantised log scale (float64): from format 5 on `exact_exp`'s, rounded to
    float32, the same on every machine; before, numpy's float32 exp, whose last bit may differ between CPUs
    (and torch's from it for many values), as those files were decoded."""
    if version >= TOOLS_VERSION:
        return torch.from_numpy(exact_exp(log_scale.detach().cpu().double().numpy()).astype(np.float32))
    return torch.from_numpy(np.exp(log_scale.float().numpy()))


# `exact_exp`: ln 2 in two parts, the first with its low 21 bits zero so that k·LN2_HIGH is exact for |k| < 2^11
# (fdlibm's split), and the Taylor coefficients 1/i!, each the float64 nearest it.
LN2_HIGH, LN2_LOW, INVERSE_LN2 = 6.93147180369123816490e-01, 1.90821492927058770002e-10, 1.4426950408889634
EXP_TERMS = tuple(1.0 / math.factorial(i) for i in range(14))
EXP_BOUND = 745.0  # |x| beyond: exp(x) is 0 or beyond float64 (and float32) as at the bound


def exact_exp(x: np.ndarray) -> np.ndarray:
    """e^x (float64) from float64 additions, multiplications and a power-of-two scaling alone, in a fixed order,
    so that every IEEE 754 machine gives the same bits (a library's exp may differ in the last bit between
    CPUs); within 2 ulp of the true value. x is clipped to ±`EXP_BOUND`; k = rint(x/ln 2), r = (x − k·LN2_HIGH)
    − k·LN2_LOW (|r| ≤ 0.35), p = the degree-13 Taylor polynomial of e^r by Horner's rule from the highest term,
    e^x = p·2^k."""
    x = np.clip(np.asarray(x, np.float64), -EXP_BOUND, EXP_BOUND)
    k = np.rint(x * INVERSE_LN2)
    r = (x - k * LN2_HIGH) - k * LN2_LOW
    p = np.full_like(r, EXP_TERMS[-1])
    for term in EXP_TERMS[-2::-1]:
        p = p * r + term
    with np.errstate(over="ignore"):  # beyond float64: inf, as exp gives
        return np.ldexp(p, k.astype(np.int64))


@dataclass
class Coding:
    """What the encoder codes, and how. `values`, float64 on the CPU in the primitives' order: position
    (px), log scale (ln px), rotation (rad), the signed weight amplitude·opacity, phase (rad), for
    `cvqpg` primitives with the quadratic term curvature as a share of γ_max at the decoded scale, and each phase
    term beyond it as shares of its parameters' bounds at the decoded scale (`primitives.term_bounds`), by the
    term's name; `ranges`, the header's;
    each attribute's quantiser; and `depths`, the bits of each value of the attributes whose depths derive
    from those decoded before them (`derived_depths`)."""

    values: dict[str, Tensor]
    ranges: dict[str, list[float]]
    quantisers: dict[str, Quantiser]
    depths: dict[str, Tensor]


def coding(primitives: Primitives, config: FitConfig, bits: BitDepths, tools: frozenset[str] = TOOLS) -> Coding:
    """The attributes of `primitives`, their ranges, and the quantisers at `bits` in a file using `tools`
    (see `Coding`). `ConfigError` where a phase without the quadratic term comes with curvatures: the file codes
    none."""
    if (config.primitives.kind == "cvqpg" and not config.phase.has("quadratic")
            and bool(primitives.curvature_per_m.detach().any())):
        raise ConfigError(f"`phase` {config.phase.name} has no quadratic term, yet the model's curvatures are not all "
                          "0; a .cvq file codes none: fit with that phase (whose curvature stays 0), or with a phase "
                          "that has `quadratic`")
    values, ranges = coded_values({name: t.detach().cpu().double() for name, t in primitives.tensors().items()},
                                  config, bits)
    coded = folded(values)
    chosen, depths = chained_quantisers(ranges, bits, attribute_shapes(primitives.count, config),
                                        lambda name, chosen, _: chosen.values(chosen.codes(coded[name])),
                                        tools=tools)
    return Coding(values, ranges, chosen, depths)


def coded_values(tensors: dict[str, Tensor], config: FitConfig, bits: BitDepths
                 ) -> tuple[dict[str, Tensor], dict[str, list[float]]]:
    """The attributes the codec codes (`Coding.values`) from a model's float64 tensors (`Primitives.tensors()`, on
    any device, differentiable), and the header's ranges, which the values set (taken without their gradient)."""
    weight = tensors["amplitude"] * tensors["opacity"][:, None]
    values = {"position": tensors["position_px"], "scale": torch.log(tensors["scale_px"]),
              "rotation": tensors["rotation_rad"], "amplitude": weight, "phase": tensors["phase_rad"]}
    log_scale = values["scale"].detach()
    ranges = {"scale": _outward_range(float(log_scale.min()), float(log_scale.max())),
              "amplitude": [0.0, _outward_range(0.0, float(weight.detach().abs().max()))[1]]}
    if config.primitives.kind == "cvqpg":
        # the decoder knows only the decoded scale: the curvature's bound, and the terms', follow it
        scale = quantiser("scale", ranges, bits.scale)
        decoded = decoded_scale(scale.values(scale.codes(log_scale.cpu())))
        if config.phase.has("quadratic"):
            bound = curvature_bound(decoded, config).double().to(weight.device)
            values["curvature"] = tensors["curvature_per_m"] / torch.where(bound > 0, bound, 1.0)
        for name, limit in term_bounds(decoded, config).items():
            values[name] = tensors[TERMS[name].physical] / limit.double().to(weight.device)
    return values, ranges


def range_holders(primitives: Primitives) -> Tensor:
    """Indices of the primitives whose values set the header's ranges (`coding`): the smallest and the largest
    scale, and the largest |amplitude·opacity|. Removing any other primitive leaves the ranges, and so every
    attribute's bins, as they were."""
    scale = primitives.scale_px.detach().reshape(-1)
    weight = (primitives.amplitude * primitives.opacity[:, None]).detach().abs().reshape(-1)
    return torch.stack([scale.argmin() // 2, scale.argmax() // 2, weight.argmax() // primitives.channels]).unique()


def folded(values: dict[str, Tensor]) -> dict[str, Tensor]:
    """The values the quantisers take: the weight's sign folded into the phase, a negative weight
    being a positive one at φ + π."""
    weight, phase = values["amplitude"], values["phase"]
    return {**values, "amplitude": weight.abs(), "phase": torch.where(weight < 0, phase + math.pi, phase)}


def primitives_from(values: dict[str, Tensor], scale_px: Tensor, config: FitConfig) -> Primitives:
    """float32 primitives from dequantised, folded values and the scale (px) decoded from them; opacity is
    1, folded into the amplitude, the curvature its share of γ_max at that scale (0 without one), and each phase
    term beyond it its shares of its bounds at that scale."""
    count, device = scale_px.shape[0], scale_px.device
    if "curvature" in values:
        # γ_max follows the decoded scale and is not trained: fine-tuning moves the share alone
        curvature = (values["curvature"] * curvature_bound(scale_px.detach(), config).double()).float()
    else:
        shape = (count,) if config.primitives.curvature == "shared" else (count, config.channels)
        curvature = torch.zeros(shape, device=device)
    terms = {name: (values[name] * limit.double()).float()
             for name, limit in term_bounds(scale_px.detach(), config).items()}
    return Primitives(position_px=values["position"].float(), scale_px=scale_px,
                      rotation_rad=values["rotation"].float(), amplitude=values["amplitude"].float(),
                      phase_rad=values["phase"].float(), opacity=torch.ones(count, device=device),
                      curvature_per_m=curvature, terms=terms)


def _interleave(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    code = np.zeros(x.shape, np.uint64)
    for bit in range(32):
        code |= ((x >> np.uint64(bit)) & np.uint64(1)) << np.uint64(2 * bit)
        code |= ((y >> np.uint64(bit)) & np.uint64(1)) << np.uint64(2 * bit + 1)
    return code


def _deinterleave(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.zeros(code.shape, np.uint64), np.zeros(code.shape, np.uint64)
    for bit in range(32):
        x |= ((code >> np.uint64(2 * bit)) & np.uint64(1)) << np.uint64(bit)
        y |= ((code >> np.uint64(2 * bit + 1)) & np.uint64(1)) << np.uint64(bit)
    return x, y


def morton_order(grid: Tensor) -> Tensor:
    """The order the file stores primitives in: by the Morton code of their grid positions (codes
    [N, 2]), ties in their given order."""
    cells = grid.numpy().astype(np.uint64)
    return torch.from_numpy(np.argsort(_interleave(cells[:, 0], cells[:, 1]), kind="stable"))


@dataclass
class Encoded:
    """One model's integer symbols per stream, the side information to dequantise them, and the bits per
    symbol of the streams whose widths the decoder derives (`derived_depths`)."""

    streams: dict[str, np.ndarray]
    ranges: dict[str, list[float]]
    widths: dict[str, np.ndarray] = field(default_factory=dict)


def whole_pixels(codes: Tensor, depths: Tensor) -> tuple[Tensor, Tensor]:
    """(whole pixels, fraction) of position codes (int64 [N, 2]) on grids of 2^-depths px: codes = whole·2^depths
    + fraction."""
    whole = torch.div(codes, 2**depths, rounding_mode="floor")
    return whole, codes - whole * 2**depths


def file_order(coded: Coding) -> Tensor:
    """The order the file stores primitives in: by the Morton code of their whole pixels."""
    codes = coded.quantisers["position"].codes(coded.values["position"])
    return morton_order(whole_pixels(codes, coded.depths["position"])[0])


def quantise(primitives: Primitives, config: FitConfig, bits: BitDepths, tools: frozenset[str] = TOOLS) -> Encoded:
    """Integer symbols of every stream of a file using `tools`, in the file's order: the Morton gaps of the
    primitives' whole pixels, the fractions of a pixel, then the other attributes in the order `ATTRIBUTES`
    (with `axes`, scale as the larger code and the `elongation`), primitives in `file_order`; with the bits of
    each symbol of the streams whose depths the decoder derives."""
    coded = coding(primitives, config, bits, tools)
    values = folded(coded.values)
    codes = {name: coded.quantisers[name].codes(values[name]) for name in ATTRIBUTES if name in values}
    if AXES in tools:
        per_axis = {name: codes[name] for name in codes if name in TERMS and TERMS[name].per_axis}
        axes, ordered = ordered_axes(codes["scale"], codes["rotation"], coded.depths["rotation"], per_axis), {}
        for name, symbols in codes.items():  # elongation right after scale
            ordered[name] = axes.get(name, symbols)
            if name == "scale":
                ordered["elongation"] = axes["elongation"]
        codes = ordered
    depths = dict(coded.depths)
    if CHANNELS in tools and config.channels > 1:
        ordered = {}
        for name, symbols in codes.items():
            changes = channel_changes(name, symbols, depths[name]) if name in CHANGED else {name: symbols}
            ordered.update(changes)
            depths.update({stream: depths[name][:, :1] if stream == name else depths[name][:, 1:]
                           for stream in changes if name in CHANGED})
        codes = ordered
    order = file_order(coded)
    depths = {name: depth[order].numpy() for name, depth in depths.items()}
    whole, fraction = whole_pixels(codes.pop("position")[order], coded.depths["position"][order])
    grid = whole.numpy().astype(np.uint64)
    gaps = np.diff(_interleave(grid[:, 0], grid[:, 1]), prepend=np.uint64(0)).astype(np.int64)
    return Encoded({"position": gaps, "fraction": fraction.numpy(),
                    **{name: symbols[order].numpy() for name, symbols in codes.items()}}, coded.ranges,
                   {"fraction": depths.pop("position"), **depths})


def rescaled(codes: Tensor, depths: Tensor, target: Tensor) -> Tensor:
    """Codes of angles at `depths` bits as codes at `target` bits (int64, elementwise): shifted left, or right with
    halves rounded up, modulo 2^target."""
    up, down = (target - depths).clamp(min=0), (depths - target).clamp(min=0)
    return (((codes << up) + ((1 << down) >> 1)) >> down) % (1 << target)


def channel_changes(name: str, codes: Tensor, depths: Tensor) -> dict[str, Tensor]:
    """`channels`' symbols of attribute `name` (amplitude or phase, codes [N, C] at `depths` bits): `name`, the first
    channel's codes [N, 1]; `<name>_change` [N, C − 1], each later channel's code less the channel before's: an
    amplitude's as it is (every channel of a primitive has one depth), a phase's `rescaled` to the channel's
    depth and the difference taken modulo its levels."""
    if name == "amplitude":
        change = codes[:, 1:] - codes[:, :-1]
    else:
        change = (codes[:, 1:] - rescaled(codes[:, :-1], depths[:, :-1], depths[:, 1:])) % (1 << depths[:, 1:])
    return {name: codes[:, :1], f"{name}_change": change}


def changed_channels(name: str, first: Tensor, change: Tensor, depths: Tensor) -> Tensor:
    """Inverse of `channel_changes`: the codes [N, C] of attribute `name` at `depths` bits from the first channel's
    [N, 1] and the changes [N, C − 1], channel by channel. `ValueError` where an amplitude code falls outside its
    levels."""
    codes = [first[:, 0]]
    for channel in range(change.shape[1]):
        if name == "amplitude":
            codes.append(codes[-1] + change[:, channel])
        else:
            target = depths[:, channel + 1]
            codes.append((change[:, channel] + rescaled(codes[-1], depths[:, channel], target)) % (1 << target))
    codes = torch.stack(codes, dim=1)
    if name == "amplitude" and not bool(((codes >= 0) & (codes < 1 << depths)).all()):
        raise ValueError("a channel's amplitude code beyond its levels")
    return codes


def ordered_axes(scale: Tensor, rotation: Tensor, depths: Tensor, per_axis: dict[str, Tensor] | None = None
                 ) -> dict[str, Tensor]:
    """`axes`' symbols from scale codes [N, 2] and rotation codes [N] at `depths` bits: `scale`, the larger code
    [N]; `elongation`, the larger minus the smaller [N]; `rotation`, turned by a quarter (half its levels) where
    the axes swap; and the codes [N, 2] of each phase term whose parameters follow the axes (`per_axis`, by name)
    swapped with them. The same ellipse: σ along x at θ is σ along y at θ + π/2. Every ellipse has a rotation bit
    then (`derived_depths`)."""
    swapped = scale[:, 1] > scale[:, 0]
    larger = scale.max(dim=1).values
    levels = 2**depths
    return {"scale": larger, "elongation": larger - scale.min(dim=1).values,
            "rotation": torch.where(swapped, (rotation + levels // 2) % levels, rotation),
            **{name: torch.where(swapped[:, None], codes.flip(1), codes) for name, codes in (per_axis or {}).items()}}


def dequantise(encoded: Encoded, config: FitConfig, bits: BitDepths, tools: frozenset[str] = TOOLS) -> Primitives:
    """Primitives (float32, Morton order) from the symbols `quantise` gave with `tools`."""
    return read_primitives(lambda name, _: encoded.streams[name], len(encoded.streams["position"]), encoded.ranges,
                           config, bits, FORMAT_VERSION, tools)


def read_primitives(symbols: Callable[[str, np.ndarray | None], np.ndarray], count: int,
                    ranges: dict[str, list[float]], config: FitConfig, bits: BitDepths,
                    version: int = FORMAT_VERSION, tools: frozenset[str] = TOOLS) -> Primitives:
    """`count` primitives (float32, Morton order) from the symbols of a file of `version` using `tools`:
    `symbols(name, widths)` returns stream `name`'s, given the bits of each symbol where the decoder derives them
    (else None). Opacity is 1, folded into amplitude. `ValueError` where an elongation exceeds its scale code."""
    values: dict[str, Tensor] = {}

    def read(name: str, chosen: Quantiser, depths: Tensor | None) -> Tensor:
        if name == "scale" and uses(AXES, version, tools):
            larger, elongation = symbols("scale", None), symbols("elongation", None)
            if not ((elongation >= 0) & (elongation <= larger)).all():
                raise ValueError("an elongation beyond its scale code")
            codes = torch.from_numpy(np.stack([larger, larger - elongation], axis=1))
        elif name in CHANGED and uses(CHANNELS, version, tools) and config.channels > 1:
            first, change = (torch.from_numpy(symbols(stream, part.numpy())) for stream, part in
                             ((name, depths[:, :1]), (f"{name}_change", depths[:, 1:])))
            codes = changed_channels(name, first, change, depths)
        elif name == "position":
            x, y = _deinterleave(np.cumsum(symbols(name, None).astype(np.uint64), dtype=np.uint64))
            codes = torch.from_numpy(np.stack([x, y], axis=1).astype(np.int64))
            if depths is not None:
                codes = codes * 2**depths + torch.from_numpy(symbols("fraction", depths.numpy()))
        else:
            codes = torch.from_numpy(symbols(name, None if depths is None else depths.numpy()))
        values[name] = chosen.values(codes)
        return values[name]

    chained_quantisers(ranges, bits, attribute_shapes(count, config, version), read, version, tools)
    return primitives_from(values, decoded_scale(values["scale"], version), config)


def _model(coding: str, low: int, high: int, params: list[float]):
    model = constriction.stream.model
    if coding == LAPLACE:
        return model.QuantizedLaplace(low, high, *params)
    if coding == GAUSSIAN:
        return model.QuantizedGaussian(low, high, *params)
    return model.Categorical(np.asarray(params, np.float64), perfect=False)


def _ans(symbols: np.ndarray, model) -> bytes:
    coder = constriction.stream.stack.AnsCoder()
    coder.encode_reverse(symbols.astype(np.int32), model)
    return coder.get_compressed().astype("<u4").tobytes()


def _raw_bits(values: np.ndarray, width: int) -> bytes:
    bits = (values[:, None].astype(np.uint64) >> np.arange(width, dtype=np.uint64)) & np.uint64(1)
    return np.packbits(bits.astype(np.uint8).ravel(), bitorder="little").tobytes()


def _from_raw_bits(data: bytes, count: int, width: int) -> np.ndarray:
    bits = np.unpackbits(np.frombuffer(data, np.uint8), bitorder="little")[:count * width]
    weights = np.uint64(1) << np.arange(width, dtype=np.uint64)
    return (bits.reshape(count, width).astype(np.uint64) * weights).sum(axis=1, dtype=np.uint64).astype(np.int64)


def _grouped_raw_bits(values: np.ndarray, widths: np.ndarray) -> bytes:
    """Each value's lowest `widths` bits (one width per value): for width 1, 2, … the values of that width in
    their order, as `raw`, each group padded to a byte."""
    return b"".join(_raw_bits(values[widths == width], width) for width in range(1, int(widths.max(initial=0)) + 1))


def _from_grouped_raw_bits(data: bytes, widths: np.ndarray) -> np.ndarray:
    """Inverse of `_grouped_raw_bits`."""
    values, offset = np.zeros(widths.shape, np.int64), 0
    for width in range(1, int(widths.max(initial=0)) + 1):
        chosen = widths == width
        size = (int(chosen.sum()) * width + 7) // 8
        if offset + size > len(data):
            raise ValueError(f"{len(data)} bytes where the widths need more")
        values[chosen] = _from_raw_bits(data[offset:offset + size], int(chosen.sum()), width)
        offset += size
    return values


def encode_stream(values: np.ndarray, widths: np.ndarray | None = None, periodic: bool = False
                  ) -> tuple[dict[str, Any], bytes]:
    """The smallest coding for one stream of integers: its descriptor (JSON) and bytes.

    Symbols are offset by their minimum. `raw` packs fixed-width bits; the parametric models carry
    two short parameters; `categorical` carries the histogram, which pays only for skewed streams. With
    `widths` (bits per symbol, which the decoder derives), see `_stream_at_widths`; `periodic`, symbols of
    width w being angles in 2^w levels, lets each width's symbols be turned (`centring_turn`).
    """
    if widths is not None:
        return _stream_at_widths(values, np.broadcast_to(widths, values.shape), periodic)
    flat = values.ravel()
    low = int(flat.min(initial=0))
    shifted = flat - low
    top = int(shifted.max(initial=0))
    width = max(top.bit_length(), 1)
    candidates = [({"coding": RAW, "width": width}, _raw_bits(shifted, width))]
    if flat.size and top > 0 and top < 2**20:
        mean, spread, median = float(shifted.mean()), float(shifted.std()), float(np.median(shifted))
        # Laplace centred on the median, or at 0 with the mean as scale: a geometric law, as gaps
        # between consecutive Morton codes roughly follow.
        for coding, params in ((LAPLACE, [_short(median), _short(max(np.abs(shifted - median).mean(), 0.1))]),
                               (LAPLACE, [0.0, _short(max(mean, 0.1))]),
                               (GAUSSIAN, [_short(mean), _short(max(spread, 0.1))])):
            candidates.append(({"coding": coding, "params": params}, _ans(shifted, _model(coding, 0, top, params))))
        if top < 2**12:
            counts = np.bincount(shifted, minlength=top + 1)
            histogram = zlib.compress(_varints(counts), 9)
            candidates.append(({"coding": CATEGORICAL, "histogram_bytes": len(histogram)},
                               histogram + _ans(shifted, _model(CATEGORICAL, 0, top, counts.tolist()))))
    if top > 2:  # then the lengths' largest symbol is smaller than `top`, so the recursion ends
        candidates.append(_bit_length_coded(shifted))
    descriptor, data = min(candidates, key=lambda c: len(c[1]))
    return {**descriptor, "min": low, "max": top + low, "shape": list(values.shape), "bytes": len(data)}, data


def _stream_at_widths(values: np.ndarray, widths: np.ndarray, periodic: bool = False
                      ) -> tuple[dict[str, Any], bytes]:
    """A stream whose symbols have `widths` bits each, which the decoder derives: `widths` (raw bits, no parameters;
    for symbols in 0..2^width − 1) or `grouped` (the symbols of each width in their own smallest coding, one
    descriptor per width, `periodic` ones turned where that is smaller), whichever takes fewer bytes with its
    descriptor compressed as the header compresses it. Symbols of width 0, all 0, take none."""
    flat, widths = values.ravel(), widths.ravel()
    common = {"min": int(flat.min(initial=0)), "max": int(flat.max(initial=0)), "shape": list(values.shape)}
    groups, payload = [], []
    for width in np.unique(widths[widths > 0]).tolist():
        symbols = flat[widths == width]
        candidates = [encode_stream(symbols)]
        if periodic:
            turn = centring_turn(symbols, width)
            descriptor, data = encode_stream((symbols - turn) % 2**width)
            candidates.append(({**descriptor, "turn": turn}, data))
        descriptor, data = min(candidates, key=lambda c: len(c[1]) + len(json.dumps(c[0])) // 8)
        del descriptor["shape"]  # the decoder counts the symbols of each width
        groups.append({**descriptor, "bits": width})
        payload.append(data)
    grouped = b"".join(payload)
    candidates = [({"coding": GROUPED, "groups": groups, **common, "bytes": len(grouped)}, grouped)]
    if bool(((flat >= 0) & (flat < 2**widths)).all()):  # not curvature's signed codes
        raw = _grouped_raw_bits(flat, widths)
        candidates.append(({"coding": WIDTHS, **common, "bytes": len(raw)}, raw))
    return min(candidates, key=lambda c: len(c[1]) + len(deflated(c[0])))


def centring_turn(symbols: np.ndarray, width: int) -> int:
    """The turn t (0..2^width − 1) that brings the circular mean of angles in 2^width levels to mid-range: the
    symbols (s − t) mod 2^width then gather about 2^(width − 1), where a model of one mode fits them. The
    encoder's choice alone: the decoder adds the stored t."""
    levels = 2**width
    angle = symbols.astype(np.float64) * (2 * math.pi / levels)
    mean = math.atan2(float(np.sin(angle).sum()), float(np.cos(angle).sum()))
    return (round(mean / (2 * math.pi) * levels) - levels // 2) % levels


def _bit_length_coded(shifted: np.ndarray) -> tuple[dict[str, Any], bytes]:
    """Elias-gamma-like coding of non-negative symbols: each symbol's bit length as a stream of its own
    (coded by `encode_stream`), then the bits below each leading one, raw, grouped by length. It
    serves long-tailed streams, such as the Morton gaps, whose largest symbol is too large for the
    parametric models and costs `raw` its full width on every symbol."""
    lengths = _bit_lengths(shifted)
    descriptor, data = encode_stream(lengths)
    below = _grouped_raw_bits(shifted - _leading_ones(lengths), np.maximum(lengths - 1, 0))
    return {"coding": BIT_LENGTH, "lengths": descriptor}, data + below


def _bit_lengths(values: np.ndarray) -> np.ndarray:
    lengths = np.zeros(values.shape, np.int64)
    remaining = values.astype(np.uint64)
    while remaining.any():
        lengths += remaining > 0
        remaining >>= np.uint64(1)
    return lengths


def _leading_ones(lengths: np.ndarray) -> np.ndarray:
    """The value of each symbol's leading one, from its bit length (0 for length 0)."""
    return np.where(lengths > 0, 1, 0).astype(np.int64) << np.maximum(lengths - 1, 0)


def _from_bit_length_coded(descriptor: dict[str, Any], data: bytes, count: int) -> np.ndarray:
    lengths_descriptor = descriptor["lengths"]
    if lengths_descriptor.get("shape") != [count]:
        raise ValueError(f"its bit lengths are of shape {lengths_descriptor.get('shape')}, not [{count}]")
    lengths = decode_stream(lengths_descriptor, data[:lengths_descriptor["bytes"]]).ravel()
    if lengths.size and not 0 <= lengths.min() <= lengths.max() <= MAX_SYMBOL_BITS:
        raise ValueError(f"bit lengths of {lengths.min()}..{lengths.max()}, beyond 0..{MAX_SYMBOL_BITS}")
    below = _from_grouped_raw_bits(data[lengths_descriptor["bytes"]:], np.maximum(lengths - 1, 0))
    return _leading_ones(lengths) + below


def _varints(counts: np.ndarray) -> bytes:
    out = bytearray()
    for count in counts.tolist():
        while count >= 0x80:
            out.append(count & 0x7F | 0x80)
            count >>= 7
        out.append(count)
    return bytes(out)


def _from_varints(data: bytes, count: int) -> list[int]:
    values, value, shift = [], 0, 0
    for byte in data:
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            values.append(value)
            value, shift = 0, 0
    if len(values) != count:
        raise ModelFileError(f"a categorical stream's histogram holds {len(values)} counts, not {count}")
    return values


def _histogram(data: bytes, count: int) -> list[int]:
    """A categorical stream's `count` symbol counts (zlib-compressed varints), refused (`ValueError`) where they
    are no distribution the entropy coder takes: none positive, or beyond float64's exact integers."""
    inflater = zlib.decompressobj()
    varints = inflater.decompress(data, 10 * count)  # a varint of a count below 2^53 takes at most 8 bytes
    if inflater.unconsumed_tail:
        raise ValueError("its histogram is longer than its symbols need")
    counts = _from_varints(varints, count)
    if not sum(counts) or max(counts) >= 2**53:
        raise ValueError("its histogram is no distribution (no positive count, or counts beyond 2^53)")
    return counts


def _integer(value: Any, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_descriptor(descriptor: Any, in_group: bool = False, turns: bool = False) -> None:
    """Raise `ValueError` unless `descriptor` is a stream descriptor `encode_stream` could have written (a group's
    `in_group`, whose shape the decoder counts; a periodic stream's groups of a file using `turn`, `turns`):
    every field of its type and range, so that no decoder step, and no entropy-coder model, is given what it
    cannot take."""
    if not isinstance(descriptor, dict):
        raise ValueError("a stream descriptor is not an object")
    coding = descriptor.get("coding")
    if coding not in CODINGS:
        raise ValueError(f"unknown coding {coding!r}")
    if coding == BIT_LENGTH:
        check_descriptor(descriptor.get("lengths"))
    low, high = descriptor.get("min"), descriptor.get("max")
    if not (_integer(low, -2**MAX_SYMBOL_BITS, 2**MAX_SYMBOL_BITS - 1) and _integer(high, low, 2**MAX_SYMBOL_BITS - 1)
            and high - low < 2**MAX_SYMBOL_BITS):
        raise ValueError(f"its symbol range {low!r}..{high!r} is not one of int64 integers")
    if not _integer(descriptor.get("bytes"), 0, 2**MAX_SYMBOL_BITS):
        raise ValueError(f"its byte count {descriptor.get('bytes')!r} is not a whole number ≥ 0")
    shape = descriptor.get("shape")
    if not in_group and not (isinstance(shape, list) and all(_integer(n, 0, 2**31) for n in shape)):
        raise ValueError(f"its shape {shape!r} is not a list of sizes")
    top, params = high - low, descriptor.get("params")
    if coding == RAW and not _integer(descriptor.get("width"), 1, MAX_SYMBOL_BITS):
        raise ValueError(f"its raw width {descriptor.get('width')!r} is not 1..{MAX_SYMBOL_BITS} bits")
    if coding in (LAPLACE, GAUSSIAN) and not (1 <= top < MAX_ANS_TOP and isinstance(params, list) and len(params) == 2
                                            and all(map(_number, params)) and params[1] > 0):
        raise ValueError(f"its {coding} model (symbols 0..{top}, parameters {params!r}) is not one the encoder "
                         f"writes: 1..{MAX_ANS_TOP - 1} symbols, a finite mean and a positive finite scale")
    if coding == CATEGORICAL and not (1 <= top < MAX_CATEGORICAL_TOP
                                      and _integer(descriptor.get("histogram_bytes"), 0, descriptor["bytes"])):
        raise ValueError(f"its categorical model (symbols 0..{top}, histogram of "
                         f"{descriptor.get('histogram_bytes')!r} bytes) is not one the encoder writes")
    if coding == GROUPED:
        groups = descriptor.get("groups")
        if not isinstance(groups, list) or not all(isinstance(group, dict) for group in groups):
            raise ValueError("its groups are not a list of descriptors")
        for group in groups:
            if not _integer(group.get("bits"), 1, MAX_SYMBOL_BITS):
                raise ValueError(f"a group's width {group.get('bits')!r} is not 1..{MAX_SYMBOL_BITS} bits")
            if "turn" in group and not (turns and _integer(group["turn"], 0, 2**group["bits"] - 1)):
                raise ValueError(f"a group's turn {group['turn']!r} is not one of its 2^{group['bits']} levels "
                                 f"in a periodic stream of a file using `{TURN}`")
            check_descriptor(group, in_group=True)


def decode_stream(descriptor: dict[str, Any], data: bytes, widths: np.ndarray | None = None, turns: bool = False
                  ) -> np.ndarray:
    """Inverse of `encode_stream`; a `widths` stream needs the same `widths`, a turned one `turns`. `ValueError`
    where the descriptor is not one `encode_stream` writes (`check_descriptor`) or the data do not decode."""
    check_descriptor(descriptor, turns=turns)
    shape, low, top = descriptor["shape"], descriptor["min"], descriptor["max"] - descriptor["min"]
    count = int(np.prod(shape))
    coding = descriptor["coding"]
    if coding == GROUPED:
        return _from_groups(descriptor["groups"], data, widths, count).reshape(shape)
    if coding == WIDTHS:
        if widths is None or widths.size != count:
            raise ValueError("a stream of per-symbol widths where the decoder knows none")
        shifted = _from_grouped_raw_bits(data, widths.ravel())
    elif coding == RAW:
        shifted = _from_raw_bits(data, count, descriptor["width"])
    elif coding == BIT_LENGTH:
        shifted = _from_bit_length_coded(descriptor, data, count)
    else:
        if coding == CATEGORICAL:
            split = descriptor["histogram_bytes"]
            params = _histogram(data[:split], top + 1)
            data = data[split:]
        else:
            params = descriptor["params"]
        words = np.frombuffer(data, "<u4").astype(np.uint32)
        decoder = constriction.stream.stack.AnsCoder(words)
        shifted = decoder.decode(_model(coding, 0, top, params), count).astype(np.int64)
    return (shifted + low).reshape(shape)


def _from_groups(groups: list[dict[str, Any]], data: bytes, widths: np.ndarray | None, count: int) -> np.ndarray:
    """The symbols of a `grouped` stream of `count` symbols at `widths` bits each."""
    if widths is None or widths.size != count:
        raise ValueError("a stream of per-symbol widths where the decoder knows none")
    widths = widths.ravel()
    if sorted(group["bits"] for group in groups) != np.unique(widths[widths > 0]).tolist():
        raise ValueError("its groups are not the widths the decoder derives")
    symbols, offset = np.zeros(count, np.int64), 0
    if sum(group["bytes"] for group in groups) > len(data):
        raise ValueError(f"its groups announce more than its {len(data)} bytes")
    for group in groups:
        chosen = widths == group["bits"]
        decoded = decode_stream({**group, "shape": [int(chosen.sum())]}, data[offset:offset + group["bytes"]])
        symbols[chosen] = (decoded + group["turn"]) % 2 ** group["bits"] if "turn" in group else decoded
        offset += group["bytes"]
    return symbols


def encode(primitives: Primitives, config: FitConfig, bits: BitDepths, fingerprint: bytes = NO_FINGERPRINT,
           tools: frozenset[str] = TOOLS) -> bytes:
    """The whole `.cvq` file (docs/format.md) of `primitives` at `bits`, with the fit's `fingerprint` (16 bytes,
    `runs.fingerprint_digest`; zeros: not known), using `tools` (a subset of `TOOLS`; all by default, fewer to
    measure each). `channels` pays where a primitive's channels follow each other and costs where they do not
    (measured: 2.8% smaller on one RGB fit, 0.1% larger on another), so with more than one channel the file is
    written both with and without it, and the smaller kept."""
    if CHANNELS in tools and config.channels > 1:
        return min((_file(primitives, config, bits, fingerprint, chosen) for chosen in (tools, tools - {CHANNELS})),
                   key=len)
    return _file(primitives, config, bits, fingerprint, tools - {CHANNELS})


def _file(primitives: Primitives, config: FitConfig, bits: BitDepths, fingerprint: bytes, tools: frozenset[str]
          ) -> bytes:
    """The `.cvq` file of `primitives` at `bits`, with `fingerprint`, using exactly `tools` (`encode`)."""
    encoded = quantise(primitives, config, bits, tools)
    descriptors, payload = [], []
    for name, values in encoded.streams.items():
        descriptor, data = encode_stream(values, encoded.widths.get(name), TURN in tools and name in PERIODIC)
        descriptors.append({"name": name, **descriptor})
        payload.append(data)
    header = deflated(file_header(config, primitives.count, bits, encoded.ranges, tools, descriptors))
    body = PREFIX.pack(MAGIC, FORMAT_VERSION, len(header)) + FINGERPRINT.pack(fingerprint) + header \
        + b"".join(payload)
    return body + CHECKSUM.pack(zlib.crc32(body))


def file_header(config: FitConfig, count: int, bits: BitDepths, ranges: dict[str, list[float]], tools: frozenset[str],
                streams: list[dict[str, Any]]) -> dict[str, Any]:
    """The header (JSON-able, docs/format.md) of a file of `count` primitives of `config` at `bits` with `ranges`,
    using `tools`, whose streams `streams` describe."""
    shown = {} if config.display.ideal else {"display": config.display.to_dict()}
    return {"optics": optics(config), **shown, "num_primitives": count, "bits": file_bits(bits, config),
            "ranges": ranges, "tools": sorted(tools), "streams": streams}


def file_bits(bits: BitDepths, config: FitConfig) -> dict[str, int]:
    """The depths of `bits` that a file of a model of `config` codes (the header's `bits`): the phase terms' only
    where the model has them (`BitDepths.coded`)."""
    return bits.coded(term.name for term in config.phase.extra_terms)


def deflated(header: Any, version: int = FORMAT_VERSION) -> bytes:
    """A header (JSON-able) as a file of `version` stores it: compact JSON, deflated by zlib at level 9, from
    format 5 on with `HEADER_DICTIONARY`."""
    deflater = zlib.compressobj(9, **({"zdict": HEADER_DICTIONARY} if version >= TOOLS_VERSION else {}))
    return deflater.compress(json.dumps(header, separators=(",", ":")).encode()) + deflater.flush()


def inflated(data: bytes, version: int) -> bytes:
    """A file of `version`'s header bytes inflated (JSON text); `zlib.error` where they do not inflate, `ValueError`
    where they inflate to more than `MAX_HEADER_BYTES`, or from format 5 on, were deflated without
    `HEADER_DICTIONARY`."""
    dictionary = version >= TOOLS_VERSION
    if dictionary and not with_dictionary(data):  # zlib would inflate it all the same
        raise ValueError("its header is deflated without the format's preset dictionary")
    inflater = zlib.decompressobj(**({"zdict": HEADER_DICTIONARY} if dictionary else {}))
    text = inflater.decompress(data, MAX_HEADER_BYTES)
    if inflater.unconsumed_tail:
        raise ValueError(f"its header inflates to more than {MAX_HEADER_BYTES} bytes")
    return text


def with_dictionary(data: bytes) -> bool:
    """Whether the zlib stream `data` says it was deflated with a preset dictionary (RFC 1950's FDICT flag)."""
    return len(data) > 1 and bool(data[1] & ZLIB_FDICT)


def header_start(version: int) -> int:
    """Where a file of `version`'s compressed header starts: after the prefix and, from format 5 on, the fit
    fingerprint."""
    return PREFIX.size + (FINGERPRINT.size if version >= TOOLS_VERSION else 0)


def file_fingerprint(data: bytes) -> bytes | None:
    """The fit fingerprint a `.cvq` file's bytes carry (16 bytes), or None where it carries none: a file before
    format 5, one written without (zeros), or not a `.cvq` file. Read without decoding; `decode` checks the file."""
    if len(data) < PREFIX.size + FINGERPRINT.size or data[:len(MAGIC)] != MAGIC:
        return None
    _, version, _ = PREFIX.unpack_from(data)
    if version < TOOLS_VERSION:
        return None
    (fingerprint,) = FINGERPRINT.unpack_from(data, PREFIX.size)
    return None if fingerprint == NO_FINGERPRINT else fingerprint


def with_fingerprint(data: bytes, fingerprint: bytes) -> bytes:
    """A file's bytes `data` (format 5 on) (as `encode` wrote them) with the fit fingerprint `fingerprint` (16 bytes)
    in place of the one it held, its checksum recomputed: the same size, so that a budget rate control met
    still holds."""
    body = data[:PREFIX.size] + FINGERPRINT.pack(fingerprint) + data[PREFIX.size + FINGERPRINT.size:-CHECKSUM.size]
    return body + CHECKSUM.pack(zlib.crc32(body))


# What rendering depends on, beside the primitives, by the names the header keeps (`FitConfig.setting`); the
# fitting settings stay in the run's config.json.
RENDER_SETTINGS = ("width", "height", "color", "primitive", "curvature", "qpf", "bound", "eta", "global_bound",
                   "pixel_pitch", "num_planes", "plane_center", "plane_span", "guard_band_px", "pad_multiple_px")


def optics(config: FitConfig) -> dict[str, Any]:
    """The header's rendering settings, lengths in m (`wavelengths` one per channel), and `phase` (format 6 on) where
    the primitives have terms beyond the curvature: absent, the kind's own (`flat`: constant; `cvqpg`: quadratic)."""
    phase = {"phase": config.phase.name} if config.phase.extra_terms else {}
    return {**{name: config.setting(name) for name in RENDER_SETTINGS}, "wavelengths": list(config.wavelengths),
            **phase}


def config_from_optics(values: dict[str, Any], version: int = FORMAT_VERSION) -> FitConfig:
    """A configuration that renders like the encoded one (of a file of `version`); settings that only fitting uses
    are the paper's. `ValueError` where a value is not of the type of its setting (a whole number below 2^31, a
    finite number, a name), or a `phase` names no term beyond the curvature."""
    values, defaults = dict(values), FitConfig()
    for name in RENDER_SETTINGS:
        value, default = values[name], defaults.setting(name)
        valid = (isinstance(value, str) if isinstance(default, str) else _integer(value, 0, 2**31 - 1)
                 if isinstance(default, int) else _number(value))
        if not valid:
            raise ValueError(f"{name} {value!r} is not a {type(default).__name__}")
    if not (isinstance(values["wavelengths"], list) and all(map(_number, values["wavelengths"]))):
        raise ValueError(f"wavelengths {values['wavelengths']!r} are not a list of numbers")
    phase = {}
    if version >= PHASE_VERSION and "phase" in values:
        if not (isinstance(values["phase"], str) and parse_phase(values["phase"]).extra_terms):
            raise ValueError(f"phase {values['phase']!r} is not a phase with terms beyond the curvature")
        phase = {"phase": values["phase"]}
    return defaults.replace(**{name: values[name] for name in RENDER_SETTINGS},
                            wavelengths_m=tuple(values["wavelengths"]), **phase)


@dataclass
class Compressed:
    """A decoded `.cvq` file: the primitives, their configuration, how they were coded, the file's format
    version, the tools it uses and the fit fingerprint it carries (None: none, or before format 5)."""

    primitives: Primitives
    config: FitConfig
    bits: BitDepths
    streams: list[dict[str, Any]]
    version: int
    tools: frozenset[str] = frozenset()
    fingerprint: bytes | None = None


def stream_shapes(count: int, config: FitConfig, version: int = FORMAT_VERSION, tools: frozenset[str] = TOOLS
                  ) -> dict[str, tuple[int, ...]]:
    """The shape of each stream of `count` primitives in a file of `version` using `tools`: one Morton gap per
    position, from format 4 on the fractions of a pixel of each coordinate, the other attributes' own shapes
    (`model_shapes`; with `axes`, scale and elongation one per primitive), curvature for `cvqpg` primitives with the
    quadratic term only, and from format 6 on each phase term beyond it that `config.phase` has, by its name."""
    shapes = model_shapes(count, config)
    streams = {"position": (count,), "scale": shapes["scale_px"], "rotation": shapes["rotation_rad"],
               "amplitude": shapes["amplitude"], "phase": shapes["phase_rad"]}
    if version >= IMPORTANCE_VERSION:
        streams["fraction"] = (count, 2)
    if uses(AXES, version, tools):
        streams.update(scale=(count,), elongation=(count,))
    if uses(CHANNELS, version, tools) and config.channels > 1:
        for name in CHANGED:
            streams.update({name: (count, 1), f"{name}_change": (count, config.channels - 1)})
    if version >= PHASE_VERSION:
        streams.update({term.name: shapes[term.physical] for term in config.phase.extra_terms})
    if config.primitives.kind == "cvqpg" and config.phase.has("quadratic"):
        streams["curvature"] = shapes["curvature_per_m"]
    return streams


def attribute_shapes(count: int, config: FitConfig, version: int = FORMAT_VERSION) -> dict[str, tuple[int, ...]]:
    """The shape of each attribute's codes (`chained_quantisers`' `shapes`): the streams of a file of `version` that
    uses no tool."""
    return stream_shapes(count, config, version, frozenset())


def _tools(header: dict[str, Any], version: int) -> frozenset[str]:
    """The tools a header names (none before format 5): `ValueError` unless a list of distinct names of `TOOLS`."""
    if version < TOOLS_VERSION:
        return frozenset()
    named = header["tools"]
    if not (isinstance(named, list) and all(isinstance(tool, str) for tool in named)
            and len(set(named)) == len(named) and set(named) <= TOOLS):
        raise ValueError(f"its tools {named!r} are not distinct names of {sorted(TOOLS)}")
    return frozenset(named)


def _checked_header(header: Any, name: str, version: int) -> tuple[FitConfig, BitDepths, frozenset[str]]:
    """The configuration (with the file's primitive count), bit depths and tools of a header whose checksum
    holds, refused (`ModelFileError`) where they make no sense: a file altered with its checksum recomputed, or
    written by another program."""
    try:
        config, count = config_from_optics(header["optics"], version), header["num_primitives"]
        if version >= DISPLAY_VERSION and "display" in header:
            if not isinstance(header["display"], dict):
                raise ValueError(f"its display {header['display']!r} is not an object")
            config = config.replace(display=Display.from_dict(header["display"]))
        bits = BitDepths(**header["bits"])
        if not all(isinstance(value, int) and not isinstance(value, bool) for value in asdict(bits).values()):
            raise ValueError(f"bit depths {header['bits']} are not whole numbers")
        if version >= PHASE_VERSION and set(header["bits"]) != set(file_bits(bits, config)):
            raise ValueError(f"bit depths for {sorted(header['bits'])} where its attributes are "
                             f"{sorted(file_bits(bits, config))}")
        tools = _tools(header, version)
        for descriptor in header["streams"]:
            if not isinstance(descriptor.get("name"), str):
                raise ValueError(f"a stream's name {descriptor.get('name')!r} is not a name")
            check_descriptor(descriptor, turns=turned(descriptor["name"], version, tools))
        shapes = {descriptor["name"]: tuple(descriptor["shape"]) for descriptor in header["streams"]}
        if len(shapes) != len(header["streams"]):
            raise ValueError("two streams have the same name")
        pairs = [header["ranges"][key] for key in ("scale", "amplitude")]
        if not all(isinstance(pair, list) and len(pair) == 2 for pair in pairs):
            raise ValueError(f"ranges {header['ranges']} are not pairs")
        ranges = [value for pair in pairs for value in pair]
    except (KeyError, TypeError, AttributeError, ValueError) as error:
        raise ModelFileError(f"{name}: its header is malformed ({type(error).__name__}: {error}); "
                             f"{REWRITE_MODEL}") from None
    except ConfigError as error:
        raise ModelFileError(f"{name}: its settings cannot work ({error}); {REWRITE_MODEL}") from None
    if not all(map(_number, ranges)):
        # every depth of format 4 derives from the decoded scale and amplitude
        raise ModelFileError(f"{name}: its ranges of log scale and amplitude {header['ranges']} are not finite; "
                             f"{REWRITE_MODEL}")
    check_settings(config, count, name)
    if CHANNELS in tools and config.channels == 1:
        raise ModelFileError(f"{name}: it names the tool `{CHANNELS}` for one channel; {REWRITE_MODEL}")
    try:
        bits.validate()
    except ConfigError as error:
        raise ModelFileError(f"{name}: its bit depths cannot work ({error}); {REWRITE_MODEL}") from None
    expected = stream_shapes(count, config, version, tools)
    if shapes != expected:
        raise ModelFileError(f"{name}: its streams have shapes {shapes}, {count} primitives need {expected}; "
                             f"{REWRITE_MODEL}")
    return config.replace(num_gaussians=count), bits, tools


def turned(stream: str, version: int, tools: frozenset[str]) -> bool:
    """Whether stream `stream` of a file of `version` using `tools` may hold turned groups (`centring_turn`)."""
    return uses(TURN, version, tools) and stream in PERIODIC


def decode(data: bytes, name: str = "file") -> Compressed:
    """Parse and decode a `.cvq` file's bytes; `ModelFileError` names what is wrong, also where a file whose
    checksum holds makes no physical sense (`_checked_header`, `check_tensors`)."""
    if len(data) < PREFIX.size or data[:len(MAGIC)] != MAGIC:
        raise ModelFileError(f"{name}: not a cvqpg compressed file (wrong magic number)")
    _, version, header_length = PREFIX.unpack_from(data)
    if version > FORMAT_VERSION:
        raise ModelFileError(f"{name}: format version {version} is newer than this cvqpg reads "
                             f"({FORMAT_VERSION}); update cvqpg")
    start = header_start(version)
    if len(data) < start + header_length + CHECKSUM.size:
        raise ModelFileError(f"{name}: truncated ({len(data)} bytes)")
    body, (stored,) = data[:-CHECKSUM.size], CHECKSUM.unpack(data[-CHECKSUM.size:])
    header_bytes = body[start:start + header_length]
    problem = "its header is not one cvqpg writes"
    if version >= TOOLS_VERSION and not with_dictionary(header_bytes):
        problem = "its header is deflated without the format's preset dictionary"
    try:
        header = json.loads(inflated(header_bytes, version))
        payload_bytes = sum(s["bytes"] for s in header["streams"] if _integer(s["bytes"], 0, len(data)))
    except (zlib.error, ValueError, KeyError, TypeError, AttributeError, RecursionError):
        header, payload_bytes = None, 0
    announced = start + header_length + payload_bytes
    if header is not None and len(body) < announced:
        raise ModelFileError(f"{name}: truncated ({len(data)} bytes, the header announces "
                             f"{announced + CHECKSUM.size})")
    if zlib.crc32(body) != stored:
        raise ModelFileError(f"{name}: corrupted (CRC32 checksum mismatch)")
    if header is None:
        raise ModelFileError(f"{name}: {problem}; {REWRITE_MODEL}")
    if len(body) > announced:
        raise ModelFileError(f"{name}: {len(body) - announced} bytes after its end (the header announces "
                             f"{announced + CHECKSUM.size}); {REWRITE_MODEL}")
    config, bits, tools = _checked_header(header, name, version)
    offset, located = start + header_length, {}
    for descriptor in header["streams"]:
        located[descriptor["name"]] = descriptor, body[offset:offset + descriptor["bytes"]]
        offset += descriptor["bytes"]

    def symbols(stream: str, widths: np.ndarray | None) -> np.ndarray:
        descriptor, payload = located[stream]
        try:
            return decode_stream(descriptor, payload, widths, turned(stream, version, tools))
        except (KeyError, TypeError, ValueError, IndexError, ArithmeticError, zlib.error) as error:
            raise ModelFileError(f"{name}: stream {stream!r} does not decode ({error}); {REWRITE_MODEL}") from None

    try:
        # NumPy's overflow or invalid value from a file's numbers is the file's fault: one error, not a warning
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            primitives = read_primitives(symbols, header["num_primitives"], header["ranges"], config, bits,
                                         version, tools)
    except ModelFileError:
        raise
    except (KeyError, TypeError, IndexError, ValueError, ArithmeticError) as error:
        raise ModelFileError(f"{name}: its ranges or symbols are malformed ({type(error).__name__}: {error}); "
                             f"{REWRITE_MODEL}") from None
    check_tensors(primitives, config, name)
    return Compressed(primitives, config, bits, header["streams"], version, tools, file_fingerprint(data))
