"""The compressed model file (`.cvq`, docs/format.md) as a pure codec: bytes ↔ (primitives, configuration).

Quantised primitives in a spatial order, entropy-coded with `constriction`'s ANS coder, behind a magic
number, a format version and a CRC32. A primitive is coded as: position on a grid of 2^-b px, sorted in
Morton order and coded as gaps between consecutive Morton codes; log scale over the model's own range;
rotation modulo π (an ellipse turned by π is the same ellipse), at a depth that follows each primitive's
anisotropy at its decoded scale (`rotation_depths`); amplitude × opacity as a magnitude, its
sign folded into the phase (+π); phase modulo 2π; curvature as a fraction of the primitive's own bound
γ_max (method.md §4), computed from the decoded scale so that encoder and decoder agree.

Each attribute's quantiser is written once, in torch (`Quantiser`; `coding` derives them from a model):
the encoder takes their integer codes, quantisation-aware fine-tuning (`finetune`) rounds through them
in its forward pass.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import constriction
import numpy as np
import torch
from torch import Tensor

from .config import FitConfig
from .errors import ConfigError, ModelFileError
from .primitives import (REWRITE_MODEL, Primitives, check_settings, check_tensors, curvature_bound,
                         model_shapes)

MAGIC = b"\x89CVQ\r\n\x1a\n"
FORMAT_VERSION = 3  # 2 added the `bitlength` coding, 3 rotation's depth per primitive; older files read unchanged
ROTATION_DEPTH_VERSION = 3  # files from this version on code rotation at `rotation_depths`
SUFFIX = ".cvq"
PREFIX = struct.Struct("<8sHI")  # magic, format version, header length (bytes)
CHECKSUM = struct.Struct("<I")
MAX_POSITION_BITS = 8
MAX_BITS = 16


def bits_per_pixel(size_bytes: int, config: FitConfig) -> float:
    """8·bytes / (W·H): a file's bits per hologram pixel, all channels together (`cvqpg info`'s bpp)."""
    return 8 * size_bytes / (config.width * config.height)


def _limits(name: str) -> tuple[int, int]:
    """Valid bit depths of an attribute: positions from whole pixels (0) to 1/256 px; the others 2..16."""
    return (0, MAX_POSITION_BITS) if name == "position" else (2, MAX_BITS)

# Stream codings; each stream takes the smallest that applies, so a coding that does not pay is never used.
RAW, LAPLACE, GAUSSIAN, CATEGORICAL, BIT_LENGTH = "raw", "laplace", "gaussian", "categorical", "bitlength"
WIDTHS = "widths"  # raw bits of a width per symbol that the decoder derives (rotation's depths)


@dataclass(frozen=True)
class BitDepths:
    """Bits per attribute. `position` counts fractional bits (grid of 2^-b px); the others count
    levels over the attribute's range: log scale over the model's range, rotation over [0, π) (for an
    ellipse of anisotropy a − 1/a in [0.5, 1), see `rotation_depths`), |amplitude·opacity| over
    [0, max], phase over [0, 2π), curvature over [−γ_max, γ_max]."""

    position: int = 3
    scale: int = 8
    rotation: int = 7
    amplitude: int = 8
    phase: int = 7
    curvature: int = 8

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
            values[name] = int(value)
        return cls(**values).validate()


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
    levels: int | Tensor  # a tensor: one count per value (rotation's, `rotation_quantiser`)
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
        return torch.round((values - self.low) / self.span * self.levels).clamp(self.lowest, self.highest).long()

    def values(self, codes: Tensor) -> Tensor:
        """The value (float64) each code stands for."""
        return self.low + codes.double() * (self.span / self.levels)


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


def quantisers(ranges: dict[str, list[float]], bits: BitDepths) -> dict[str, Quantiser]:
    """Each attribute's quantiser at `bits`, given the header's ranges of log scale and |amplitude·opacity|."""

    def over(low: float, high: float, depth: int) -> Quantiser:
        return Quantiser(low, high - low if high > low else 1.0, 2**depth - 1, 0, 2**depth - 1)

    half = 2 ** (bits.curvature - 1) - 1
    return {"position": Quantiser(0.0, 1.0, 2**bits.position),
            "scale": over(*ranges["scale"], bits.scale),
            "rotation": Quantiser(0.0, math.pi, 2**bits.rotation, periodic=True),
            "amplitude": over(*ranges["amplitude"], bits.amplitude),
            "phase": Quantiser(0.0, 2 * math.pi, 2**bits.phase, periodic=True),
            "curvature": ShareQuantiser(0.0, 1.0, half, -half, half)}


def rotation_depths(scale_px: Tensor, depth: int) -> Tensor:
    """Bits of rotation (int64 [N]) for primitives of decoded scale `scale_px` (px, [N, 2]): `depth` for an
    ellipse whose anisotropy a − 1/a (a = σ_max/σ_min) lies in [0.5, 1), one more per doubling of it, one
    fewer per halving, none for a circle, within 0..MAX_BITS. Turning an ellipse by Δθ changes it by about
    Δθ·(a − 1/a), so every primitive's rotation then costs about the same error, and nearly round ones,
    many in a fit, cost few bits. float64 division and frexp are exact, so every machine agrees."""
    scale = scale_px.detach().cpu().double()
    aspect = scale.max(dim=1).values / scale.min(dim=1).values
    anisotropy = aspect - 1 / aspect
    _, exponent = torch.frexp(anisotropy)
    return torch.where(anisotropy > 0, depth + exponent.long(), 0).clamp(0, MAX_BITS)


def rotation_quantiser(depths: Tensor) -> Quantiser:
    """Rotation's quantiser over [0, π) at `depths` bits per primitive (`rotation_depths`)."""
    return Quantiser(0.0, math.pi, 2**depths, periodic=True)


def decoded_scale(log_scale: Tensor) -> Tensor:
    """Scale (px, float32) from dequantised log scale, with numpy's float32 exp: every file so far was
    decoded with it, and torch's differs from it in the last bit for many values."""
    return torch.from_numpy(np.exp(log_scale.float().numpy()))


@dataclass
class Coding:
    """What the encoder codes, and how. `values`, float64 on the CPU in the primitives' order: position
    (px), log scale (ln px), rotation (rad), the signed weight amplitude·opacity, phase (rad) and, for
    `cvqpg` primitives, curvature as a share of γ_max at the decoded scale; `ranges`, the header's;
    each attribute's quantiser, rotation's at the decoded scale; and `rotation_depths`, its bits per
    primitive."""

    values: dict[str, Tensor]
    ranges: dict[str, list[float]]
    quantisers: dict[str, Quantiser]
    rotation_depths: Tensor


def coding(primitives: Primitives, config: FitConfig, bits: BitDepths) -> Coding:
    """The attributes of `primitives`, their ranges, and the quantisers at `bits` (see `Coding`)."""
    p = {name: t.detach().cpu().double() for name, t in primitives.tensors().items()}
    weight = p["amplitude"] * p["opacity"][:, None]
    values = {"position": p["position_px"], "scale": torch.log(p["scale_px"]), "rotation": p["rotation_rad"],
              "amplitude": weight, "phase": p["phase_rad"]}
    ranges = {"scale": _outward_range(float(values["scale"].min()), float(values["scale"].max())),
              "amplitude": [0.0, _outward_range(0.0, float(weight.abs().max()))[1]]}
    chosen = quantisers(ranges, bits)
    # the decoder knows only the decoded scale: rotation's depths and the curvature's bound follow it
    scale = decoded_scale(chosen["scale"].values(chosen["scale"].codes(values["scale"])))
    depths = rotation_depths(scale, bits.rotation)
    chosen["rotation"] = rotation_quantiser(depths)
    if config.primitive == "cvqpg":
        bound = curvature_bound(scale, config).double()
        values["curvature"] = p["curvature_per_m"] / torch.where(bound > 0, bound, 1.0)
    return Coding(values, ranges, chosen, depths)


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
    1, folded into the amplitude, and the curvature its share of γ_max at that scale (0 without one)."""
    count, device = scale_px.shape[0], scale_px.device
    if "curvature" in values:
        # γ_max follows the decoded scale and is not trained: fine-tuning moves the share alone
        curvature = (values["curvature"] * curvature_bound(scale_px.detach(), config).double()).float()
    else:
        curvature = torch.zeros((count,) if config.curvature == "shared" else (count, config.channels), device=device)
    return Primitives(position_px=values["position"].float(), scale_px=scale_px,
                      rotation_rad=values["rotation"].float(), amplitude=values["amplitude"].float(),
                      phase_rad=values["phase"].float(), opacity=torch.ones(count, device=device),
                      curvature_per_m=curvature)


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
    symbol of the streams whose widths the decoder derives (rotation's)."""

    streams: dict[str, np.ndarray]
    ranges: dict[str, list[float]]
    widths: dict[str, np.ndarray] = field(default_factory=dict)


def quantise(primitives: Primitives, config: FitConfig, bits: BitDepths) -> Encoded:
    """Integer symbols of every attribute, primitives in Morton order (see the module docstring)."""
    coded = coding(primitives, config, bits)
    codes = {name: coded.quantisers[name].codes(values) for name, values in folded(coded.values).items()}
    order = morton_order(codes["position"])
    grid = codes.pop("position")[order].numpy().astype(np.uint64)
    morton = _interleave(grid[:, 0], grid[:, 1])
    return Encoded({"position": np.diff(morton, prepend=np.uint64(0)).astype(np.int64),
                    **{name: symbols[order].numpy() for name, symbols in codes.items()}}, coded.ranges,
                   {"rotation": coded.rotation_depths[order].numpy()})


def dequantise(encoded: Encoded, config: FitConfig, bits: BitDepths) -> Primitives:
    """Primitives (float32, Morton order) from `quantise`'s symbols, or from a file's; rotation at
    `encoded.widths`' depths where it has them (format 3 on), else at `bits.rotation`. Opacity is 1, folded
    into amplitude."""
    chosen = quantisers(encoded.ranges, bits)
    if "rotation" in encoded.widths:
        chosen["rotation"] = rotation_quantiser(torch.from_numpy(encoded.widths["rotation"]))
    x, y = _deinterleave(np.cumsum(encoded.streams["position"].astype(np.uint64), dtype=np.uint64))
    codes = {name: torch.from_numpy(symbols) for name, symbols in encoded.streams.items() if name != "position"}
    codes["position"] = torch.from_numpy(np.stack([x, y], axis=1).astype(np.int64))
    values = {name: chosen[name].values(symbols) for name, symbols in codes.items()}
    return primitives_from(values, decoded_scale(values["scale"]), config)


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


def encode_stream(values: np.ndarray, widths: np.ndarray | None = None) -> tuple[dict[str, Any], bytes]:
    """The smallest coding for one stream of integers: its descriptor (JSON) and bytes.

    Symbols are offset by their minimum. `raw` packs fixed-width bits; the parametric models carry
    two short parameters; `categorical` carries the histogram, which pays only for skewed streams. With
    `widths` (bits per symbol, which the decoder derives, as for rotation) the symbols are uniform
    within them and `widths` packs exactly that many bits of each.
    """
    if widths is not None:
        data = _grouped_raw_bits(values.ravel(), widths.ravel())
        return {"coding": WIDTHS, "min": 0, "max": int(values.max(initial=0)), "shape": list(values.shape),
                "bytes": len(data)}, data
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
    lengths = decode_stream(lengths_descriptor, data[:lengths_descriptor["bytes"]]).ravel()
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


def decode_stream(descriptor: dict[str, Any], data: bytes, widths: np.ndarray | None = None) -> np.ndarray:
    """Inverse of `encode_stream`; a `widths` stream needs the same `widths`."""
    shape, low, top = descriptor["shape"], descriptor["min"], descriptor["max"] - descriptor["min"]
    count = int(np.prod(shape))
    coding = descriptor["coding"]
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
            params = _from_varints(zlib.decompress(data[:split]), top + 1)
            data = data[split:]
        else:
            params = descriptor["params"]
        words = np.frombuffer(data, "<u4").astype(np.uint32)
        decoder = constriction.stream.stack.AnsCoder(words)
        shifted = decoder.decode(_model(coding, 0, top, params), count).astype(np.int64)
    return (shifted + low).reshape(shape)


def encode(primitives: Primitives, config: FitConfig, bits: BitDepths) -> bytes:
    """The whole `.cvq` file (docs/format.md) of `primitives` at `bits`."""
    encoded = quantise(primitives, config, bits)
    descriptors, payload = [], []
    for name, values in encoded.streams.items():
        descriptor, data = encode_stream(values, encoded.widths.get(name))
        descriptors.append({"name": name, **descriptor})
        payload.append(data)
    header = zlib.compress(json.dumps({"optics": optics(config), "num_primitives": primitives.count,
                                       "bits": asdict(bits), "ranges": encoded.ranges, "streams": descriptors},
                                      separators=(",", ":")).encode(), 9)
    body = PREFIX.pack(MAGIC, FORMAT_VERSION, len(header)) + header + b"".join(payload)
    return body + CHECKSUM.pack(zlib.crc32(body))


# What rendering depends on, beside the primitives; the fitting settings stay in the run's config.json.
RENDER_FIELDS = ("width", "height", "color", "primitive", "curvature", "qpf", "bound", "eta", "global_bound",
                 "pixel_pitch", "num_planes", "plane_center", "plane_span", "guard_band_px", "pad_multiple_px")


def optics(config: FitConfig) -> dict[str, Any]:
    """The header's rendering settings, lengths in m (`wavelengths` one per channel)."""
    return {**{name: getattr(config, name) for name in RENDER_FIELDS}, "wavelengths": list(config.wavelengths)}


def config_from_optics(values: dict[str, Any]) -> FitConfig:
    """A configuration that renders like the encoded one; settings that only fitting uses are defaults."""
    values = dict(values)
    return FitConfig(**{name: values[name] for name in RENDER_FIELDS}, wavelengths_m=tuple(values["wavelengths"]))


@dataclass
class Compressed:
    """A decoded `.cvq` file: the primitives, their configuration, how they were coded, and the file's
    format version."""

    primitives: Primitives
    config: FitConfig
    bits: BitDepths
    streams: list[dict[str, Any]]
    version: int


def stream_shapes(count: int, config: FitConfig) -> dict[str, tuple[int, ...]]:
    """The shape of each stream of `count` primitives: one Morton gap per position, the other attributes'
    own shapes (`model_shapes`), curvature for `cvqpg` primitives only."""
    shapes = model_shapes(count, config)
    streams = {"position": (count,), "scale": shapes["scale_px"], "rotation": shapes["rotation_rad"],
               "amplitude": shapes["amplitude"], "phase": shapes["phase_rad"]}
    return {**streams, "curvature": shapes["curvature_per_m"]} if config.primitive == "cvqpg" else streams


def _checked_header(header: Any, name: str) -> tuple[FitConfig, BitDepths]:
    """The configuration (with the file's primitive count) and bit depths of a header whose checksum holds,
    refused (`ModelFileError`) where they make no sense: a file altered with its checksum recomputed, or
    written by another program."""
    try:
        config, count = config_from_optics(header["optics"]), header["num_primitives"]
        bits = BitDepths(**header["bits"])
        shapes = {descriptor["name"]: tuple(descriptor["shape"]) for descriptor in header["streams"]}
    except (KeyError, TypeError, AttributeError) as error:
        raise ModelFileError(f"{name}: its header is malformed ({type(error).__name__}: {error}); "
                             f"{REWRITE_MODEL}") from None
    check_settings(config, count, name)
    try:
        bits.validate()
    except ConfigError as error:
        raise ModelFileError(f"{name}: its bit depths cannot work ({error}); {REWRITE_MODEL}") from None
    expected = stream_shapes(count, config)
    if shapes != expected:
        raise ModelFileError(f"{name}: its streams have shapes {shapes}, {count} primitives need {expected}; "
                             f"{REWRITE_MODEL}")
    return config.replace(num_gaussians=count), bits


def _derived_widths(stream: str, decoded: dict[str, np.ndarray], ranges: dict[str, list[float]], bits: BitDepths,
                    version: int) -> np.ndarray | None:
    """Bits per symbol of `stream` where the decoder derives them, else None: rotation's depths, from the scale
    streams decoded before it (`decoded`)."""
    if stream != "rotation" or version < ROTATION_DEPTH_VERSION:
        return None
    scale = decoded_scale(quantisers(ranges, bits)["scale"].values(torch.from_numpy(decoded["scale"])))
    return rotation_depths(scale, bits.rotation).numpy()


def decode(data: bytes, name: str = "file") -> Compressed:
    """Parse and decode a `.cvq` file's bytes; `ModelFileError` names what is wrong, also where a file whose
    checksum holds makes no physical sense (`_checked_header`, `check_tensors`)."""
    if len(data) < PREFIX.size or data[:len(MAGIC)] != MAGIC:
        raise ModelFileError(f"{name}: not a cvqpg compressed file (wrong magic number)")
    _, version, header_length = PREFIX.unpack_from(data)
    if version > FORMAT_VERSION:
        raise ModelFileError(f"{name}: format version {version} is newer than this cvqpg reads "
                             f"({FORMAT_VERSION}); update cvqpg")
    if len(data) < PREFIX.size + header_length + CHECKSUM.size:
        raise ModelFileError(f"{name}: truncated ({len(data)} bytes)")
    body, (stored,) = data[:-CHECKSUM.size], CHECKSUM.unpack(data[-CHECKSUM.size:])
    try:
        header = json.loads(zlib.decompress(body[PREFIX.size:PREFIX.size + header_length]))
        payload_bytes = sum(int(s["bytes"]) for s in header["streams"])
    except (zlib.error, ValueError, KeyError, TypeError):
        header, payload_bytes = None, 0
    if header is not None and len(body) < PREFIX.size + header_length + payload_bytes:
        raise ModelFileError(f"{name}: truncated ({len(data)} bytes, the header announces "
                             f"{PREFIX.size + header_length + payload_bytes + CHECKSUM.size})")
    if zlib.crc32(body) != stored:
        raise ModelFileError(f"{name}: corrupted (CRC32 checksum mismatch)")
    if header is None:
        raise ModelFileError(f"{name}: its header is not one cvqpg writes; {REWRITE_MODEL}")
    config, bits = _checked_header(header, name)
    offset, streams, widths = PREFIX.size + header_length, {}, {}
    for descriptor in header["streams"]:
        try:
            derived = _derived_widths(descriptor["name"], streams, header["ranges"], bits, version)
            if derived is not None:
                widths[descriptor["name"]] = derived
            streams[descriptor["name"]] = decode_stream(descriptor, body[offset:offset + descriptor["bytes"]], derived)
        except (KeyError, TypeError, ValueError, IndexError, zlib.error) as error:
            raise ModelFileError(f"{name}: stream {descriptor['name']!r} does not decode ({error}); "
                                 f"{REWRITE_MODEL}") from None
        offset += descriptor["bytes"]
    try:
        primitives = dequantise(Encoded(streams, header["ranges"], widths), config, bits)
    except (KeyError, TypeError, IndexError) as error:
        raise ModelFileError(f"{name}: its ranges are malformed ({type(error).__name__}: {error}); "
                             f"{REWRITE_MODEL}") from None
    check_tensors(primitives, config, name)
    return Compressed(primitives, config, bits, header["streams"], version)
