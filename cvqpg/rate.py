"""The rate model of a `.cvq` file: its bytes under the codec's own streams, differentiable in the primitives.

`estimate` takes the symbols the encoder would write (`codec.quantise`: the Morton gaps, the fractions of a pixel,
every attribute at its derived depths, the tools' reorderings) and, stream by stream and depth by depth, the
coding `codec.encode_stream` would choose among the same candidates (raw bits, a Laplace or Gaussian with the
parameters it would fit, a categorical with its histogram, bit lengths), costed at each model's ideal code length
plus the ANS coder's flush, and the header deflated as the codec deflates it. Its `file_bytes` is held to the
bytes `codec.encode` writes (tests/test_rate.py).

Beside the estimate, `coded` gives the same streams as a function of the continuous parameters: every value in
units of its bin (`Quantiser.scaled`), perturbed by additive uniform noise where training stands it for the
quantiser (or rounded straight through), and each stream's symbols costed at −log2 of the chosen model's
probability of their bin, which the encoder's fit of the model makes a smooth function of the symbols (the
model's parameters are taken as fitted: they are the maximum-likelihood ones, so their own gradient adds
nothing to first order). Bits come out per primitive, so that a caller can weigh a primitive's bits by whether
it is kept. A stream whose symbols do not move with the parameters (the Morton gaps, raw bits) counts as a
constant.
"""

from __future__ import annotations

import json
import math
import zlib
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .bitdepths import BitDepths
from .codec import (AXES, BIT_LENGTH, CATEGORICAL, CHANGED, CHANNELS, CHECKSUM, FINGERPRINT, GAUSSIAN, GROUPED,
                    LAPLACE, MAX_ANS_TOP, MAX_CATEGORICAL_TOP, PERIODIC, PREFIX, RAW, TOOLS, TURN, WIDTHS, Quantiser,
                    attribute_shapes, centring_turn, chained_quantisers, coded_values, coding, deflated, file_header,
                    file_order, folded, primitives_from, quantise, _bit_lengths, _short, _varints)
from .config import FitConfig
from .phase import TERMS
from .primitives import Primitives

# constriction's ANS coder writes 32-bit words and flushes its state at the end: measured on Laplace streams of
# 5–5000 symbols, a stream takes ⌈bits/32 + 1/2⌉ words of its ideal length in bits, two at least.
WORD_BITS, FLUSH_WORDS, LEAST_WORDS = 32, 0.5, 2
# The coder's probabilities are fixed point of 24 bits: no symbol costs more.
MOST_SYMBOL_BITS = 24.0


def ans_bytes(bits: float) -> int:
    """Bytes of an ANS stream whose symbols' ideal code length is `bits`."""
    return 4 * max(LEAST_WORDS, math.ceil(bits / WORD_BITS + FLUSH_WORDS))


def _cdf(coding: str, x: Tensor, params: list[float]) -> Tensor:
    mean, scale = params
    if coding == LAPLACE:
        z = (x - mean) / scale
        return torch.where(z < 0, 0.5 * torch.exp(z.clamp(max=0)), 1 - 0.5 * torch.exp(-z.clamp(min=0)))
    return 0.5 * (1 + torch.erf((x - mean) / (scale * math.sqrt(2))))


def parametric_bits(coding: str, symbols: Tensor, top: int, params: list[float]) -> Tensor:
    """−log2 of the probability (float64, `symbols`' shape) that `constriction`'s quantised Laplace or Gaussian on
    0..`top` with `params` (mean, scale) gives each symbol's bin: the distribution's mass within half a unit of
    it, the tails beyond the ends folded into the end bins. Continuous symbols get the mass of the bin they stand
    for, which makes the bits differentiable."""
    upper = torch.where(symbols + 0.5 >= top, torch.ones_like(symbols), _cdf(coding, symbols + 0.5, params))
    lower = torch.where(symbols - 0.5 <= 0, torch.zeros_like(symbols), _cdf(coding, symbols - 0.5, params))
    mass = (upper - lower).clamp(min=2.0**-MOST_SYMBOL_BITS)
    return -torch.log2(mass)


def categorical_bits(symbols: Tensor, counts: np.ndarray) -> Tensor:
    """−log2 of each symbol's frequency among `counts` (one per symbol 0..top), interpolated linearly between
    neighbouring bins for continuous symbols (a bin no symbol fell in counted as half a symbol)."""
    table = torch.from_numpy(-np.log2(np.maximum(counts, 0.5) / counts.sum())).to(symbols)
    position = symbols.clamp(0, len(counts) - 1)
    below = position.detach().floor().long().clamp(max=len(counts) - 1)
    above = (below + 1).clamp(max=len(counts) - 1)
    share = position - below
    return table[below] * (1 - share) + table[above] * share


@dataclass
class StreamRate:
    """One stream's estimate: the descriptor `codec.encode_stream` would write (with the estimated `bytes`),
    and the bits of each symbol (float64, differentiable where the symbols are; the stream's flush and side
    bytes spread over its symbols)."""

    descriptor: dict
    bits: Tensor

    @property
    def bytes(self) -> int:
        return self.descriptor["bytes"]


def _raw_bytes(count: int, width: int) -> int:
    return (count * width + 7) // 8


def _erf(values: np.ndarray) -> np.ndarray:
    return np.fromiter(map(math.erf, values.tolist()), np.float64, values.size)


def exact_bits(coding: str, values: np.ndarray, top: int, params: list[float]) -> np.ndarray:
    """`parametric_bits` of integer symbols `values` (NumPy, float64), as the encoder's choice of coding needs
    them: without torch, whose per-call cost dominates on the few values a stream holds."""
    mean, scale = params

    def cdf(x: np.ndarray) -> np.ndarray:
        if coding == LAPLACE:
            z = (x - mean) / scale
            return np.where(z < 0, 0.5 * np.exp(np.minimum(z, 0)), 1 - 0.5 * np.exp(-np.maximum(z, 0)))
        return 0.5 * (1 + _erf((x - mean) / (scale * math.sqrt(2))))

    upper = np.where(values + 0.5 >= top, 1.0, cdf(values + 0.5))
    lower = np.where(values - 0.5 <= 0, 0.0, cdf(values - 0.5))
    return -np.log2(np.maximum(upper - lower, 2.0**-MOST_SYMBOL_BITS))


def stream_rate(symbols: np.ndarray, soft: Tensor | None = None) -> StreamRate:
    """The estimate of one stream of integer `symbols` (any shape) under the coding `codec.encode_stream` picks:
    the candidates it tries, each costed without coding, the smallest kept. `soft`, the same symbols unrounded
    (float64, differentiable; None: the integers), is what the per-symbol bits are a function of."""
    flat = symbols.ravel()
    low = int(flat.min(initial=0))
    shifted = flat - low
    top = int(shifted.max(initial=0))
    width = max(top.bit_length(), 1)
    count = flat.size
    # each candidate: descriptor, bytes, the bits of each symbol (NumPy) and, for a model of the symbols'
    # values, the same as a function of the unrounded symbols
    candidates = [({"coding": RAW, "width": width}, _raw_bytes(count, width), np.full(count, float(width)), None)]
    if count and 0 < top < MAX_ANS_TOP:
        mean, spread, median = float(shifted.mean()), float(shifted.std()), float(np.median(shifted))
        values, inverse, occurrences = np.unique(shifted, return_inverse=True, return_counts=True)
        values = values.astype(np.float64)
        for coding, params in ((LAPLACE, [_short(median), _short(max(np.abs(shifted - median).mean(), 0.1))]),
                               (LAPLACE, [0.0, _short(max(mean, 0.1))]),
                               (GAUSSIAN, [_short(mean), _short(max(spread, 0.1))])):
            each = exact_bits(coding, values, top, params)
            candidates.append(({"coding": coding, "params": params}, ans_bytes(float(each @ occurrences)),
                               each[inverse], lambda moving, coding=coding, params=params:
                               parametric_bits(coding, moving, top, params)))
        if top < MAX_CATEGORICAL_TOP:
            counts = np.bincount(shifted, minlength=top + 1)
            histogram = len(zlib.compress(_varints(counts), 9))
            each = -np.log2(counts[shifted] / count)
            candidates.append(({"coding": CATEGORICAL, "histogram_bytes": histogram},
                               histogram + ans_bytes(float(each.sum())), each,
                               lambda moving, counts=counts: categorical_bits(moving, counts)))
    if top > 2:
        lengths = _bit_lengths(shifted)
        inner = stream_rate(lengths)
        below = np.maximum(lengths - 1, 0)
        below_bytes = sum(_raw_bytes(int((below == w).sum()), w) for w in range(1, int(below.max(initial=0)) + 1))
        candidates.append(({"coding": BIT_LENGTH, "lengths": {**inner.descriptor}}, inner.bytes + below_bytes,
                           inner.bits.numpy() + below, None))
    descriptor, size, each, model = min(candidates, key=lambda c: c[1])
    bits = torch.from_numpy(each)
    if soft is not None:
        bits = bits.to(soft.device)
        if model is not None:
            bits = model(soft.reshape(-1) - low)
    return StreamRate({**descriptor, "min": low, "max": top + low, "shape": list(symbols.shape), "bytes": size},
                      _spread(bits, size))


def _spread(bits: Tensor, size: int) -> Tensor:
    """Per-symbol `bits` with the stream's bytes beyond their sum (flush, histogram, padding) shared among them."""
    if not bits.numel():
        return bits
    return bits + (8 * size - float(bits.detach().sum())) / bits.numel()


def rate_at_widths(symbols: np.ndarray, widths: np.ndarray, soft: Tensor | None = None, periodic: bool = False
                   ) -> StreamRate:
    """The estimate of a stream whose symbols have `widths` bits each (`codec._stream_at_widths`): each width's
    symbols a stream of their own (`stream_rate`; a `periodic` one also turned to its circular mean, where that is
    smaller), or raw bits at their widths, whichever the encoder takes."""
    flat, widths = symbols.ravel(), np.broadcast_to(widths, symbols.shape).ravel()
    soft = None if soft is None else soft.reshape(-1)
    device = torch.device("cpu") if soft is None else soft.device
    common = {"min": int(flat.min(initial=0)), "max": int(flat.max(initial=0)), "shape": list(symbols.shape)}
    bits = torch.zeros(flat.size, dtype=torch.float64, device=device)
    groups, total = [], 0
    for width in np.unique(widths[widths > 0]).tolist():
        chosen = widths == width
        index = torch.from_numpy(np.flatnonzero(chosen)).to(device)
        part = None if soft is None else soft[index]
        group, extra = stream_rate(flat[chosen], part), {}
        if periodic:
            turn = centring_turn(flat[chosen], width)
            turned = stream_rate((flat[chosen] - turn) % 2**width)
            if _group_bytes(turned, {"turn": turn}) < _group_bytes(group, {}):
                group = turned if part is None else stream_rate((flat[chosen] - turn) % 2**width,
                                                                _wrapped(part - turn, 2**width))
                extra = {"turn": turn}
        descriptor = {key: value for key, value in group.descriptor.items() if key != "shape"}
        groups.append({**descriptor, **extra, "bits": width})
        bits = bits.index_put((index,), group.bits)
        total += group.bytes
    grouped = StreamRate({"coding": GROUPED, "groups": groups, **common, "bytes": total}, bits)
    candidates = [grouped]
    if bool(((flat >= 0) & (flat < 2**widths)).all()):  # not curvature's signed codes
        raw = sum(_raw_bytes(int((widths == w).sum()), w) for w in range(1, int(widths.max(initial=0)) + 1))
        candidates.append(StreamRate({"coding": WIDTHS, **common, "bytes": raw},
                                     _spread(torch.from_numpy(widths.astype(np.float64)).to(device), raw)))
    return min(candidates, key=lambda c: c.bytes + len(deflated(c.descriptor)))


def _group_bytes(group: StreamRate, extra: dict) -> int:
    """What the encoder weighs a group by: its bytes and an eighth of its descriptor's JSON."""
    return group.bytes + len(json.dumps({**group.descriptor, **extra})) // 8


def _wrapped(codes: Tensor, levels: Tensor | float) -> Tensor:
    """Periodic codes in units of bins taken into −½ ≤ code < levels − ½, the bins of symbols 0..levels − 1."""
    return torch.remainder(codes + 0.5, levels) - 0.5


@dataclass
class Rate:
    """A file's estimate: its bytes (`file_bytes`, header and framing included), each stream's, the header's,
    and the bits of each primitive (float64 [N], differentiable in the parameters where `coded` gave them; the
    header and framing not included)."""

    file_bytes: int
    header_bytes: int
    streams: dict[str, StreamRate]
    primitive_bits: Tensor

    @property
    def bits(self) -> Tensor:
        """The file's bits, differentiable where the primitives' are (0-dim)."""
        return self.primitive_bits.sum() + 8 * (self.file_bytes - sum(s.bytes for s in self.streams.values()))


@dataclass
class Coded:
    """One forward pass through the file's quantisers: the primitives as they render (`primitives`, float32,
    differentiable), and their rate (`rate`)."""

    primitives: Primitives
    rate: Rate


def coded(primitives: Primitives, config: FitConfig, bits: BitDepths, noise: Tensor | float = 0.0,
          generator: torch.Generator | None = None, tools: frozenset[str] = TOOLS) -> Coded:
    """`primitives` through the quantisers of a `.cvq` file at `bits` (each value at the depth the codec derives
    for it, the ranges those of the model): each value's code is its unrounded position in bins (`Quantiser.scaled`)
    plus `noise` times uniform noise on [−½, ½) drawn from `generator`, plus 1 − `noise` times its rounding taken
    straight through (forward: rounded; backward: the identity); `noise` = 1 is the quantiser's training stand-in,
    0 the quantiser itself. Returns the primitives rendered from those codes and the rate of the file the encoder
    would write (its bytes from the rounded codes, each primitive's bits from the perturbed ones)."""
    detached = primitives.detached().to("cpu")
    with torch.no_grad():
        chosen = _chosen_tools(detached, config, bits, tools)
    encoded = quantise(detached, config, bits, chosen)
    device = primitives.position_px.device
    values, ranges = coded_values({name: t.double() for name, t in primitives.tensors().items()}, config, bits)
    values = folded(values)
    perturbed, decoded = {}, {}
    share = torch.as_tensor(noise, dtype=torch.float64, device=device)

    def read(name: str, quantiser: Quantiser, _) -> Tensor:
        quantiser = quantiser.on(device)
        scaled = quantiser.scaled(values[name])
        rounded = quantiser.codes(values[name].detach()).double()
        if quantiser.periodic:  # the rounding of the top bin wraps to 0: the same angle
            rounded = torch.where(rounded < scaled.detach() - 0.5, rounded + quantiser.levels, rounded)
        uniform = torch.rand(scaled.shape, generator=generator, dtype=torch.float64, device=device) - 0.5 \
            if float(noise) else torch.zeros_like(scaled)
        perturbed[name] = scaled + share * uniform + (1 - share) * (rounded - scaled).detach()
        decoded[name] = quantiser.values(perturbed[name])
        return decoded[name]

    quantisers, depths = chained_quantisers(ranges, bits, attribute_shapes(primitives.count, config), read,
                                            tools=chosen)
    rendered = primitives_from(decoded, torch.exp(decoded["scale"]).float(), config)
    soft = _soft_streams(perturbed, {name: d.to(device) for name, d in depths.items()}, quantisers, config, chosen)
    order = file_order(coding(detached, config, bits, chosen)).to(device)
    return Coded(rendered, _rate(encoded, config, bits, chosen, {k: v[order] for k, v in soft.items()}, order))


def estimate(primitives: Primitives, config: FitConfig, bits: BitDepths, tools: frozenset[str] = TOOLS) -> Rate:
    """The rate of the file `codec.encode(primitives, config, bits, tools=tools)` writes, from its symbols alone
    (no bit of it coded); with more than one channel, the smaller of the files with and without `channels`, as the
    encoder keeps."""
    detached = primitives.detached().to("cpu")
    chosen = _chosen_tools(detached, config, bits, tools)
    return _rate(quantise(detached, config, bits, chosen), config, bits, chosen)


def _chosen_tools(primitives: Primitives, config: FitConfig, bits: BitDepths, tools: frozenset[str]
                  ) -> frozenset[str]:
    """The tools the encoder's file uses: `tools`, with `channels` only where its file is the smaller."""
    if CHANNELS not in tools or config.channels == 1:
        return tools - {CHANNELS}
    return min((tools, tools - {CHANNELS}),
               key=lambda chosen: _rate(quantise(primitives, config, bits, chosen), config, bits, chosen).file_bytes)


def _soft_streams(perturbed: dict[str, Tensor], depths: dict[str, Tensor], quantisers: dict[str, Quantiser],
                  config: FitConfig, tools: frozenset[str]) -> dict[str, Tensor]:
    """The streams' symbols (float64, primitives in the given order) from the perturbed codes, as
    `codec.quantise` derives the integer ones from the rounded codes; the position's are not differentiable and
    are left out."""
    codes = {name: _wrapped(value, quantisers[name].on(value.device).levels) if quantisers[name].periodic else value
             for name, value in perturbed.items() if name != "position"}
    if AXES in tools:
        scale, rotation = codes["scale"], codes["rotation"]
        levels = 2.0 ** depths["rotation"].double()
        swapped = (scale[:, 1] > scale[:, 0]).detach()
        codes["scale"] = scale.max(dim=1).values
        codes["elongation"] = codes["scale"] - scale.min(dim=1).values
        codes["rotation"] = torch.where(swapped, torch.remainder(rotation + levels / 2, levels), rotation)
        for name in [name for name in codes if name in TERMS and TERMS[name].per_axis]:
            codes[name] = torch.where(swapped[:, None], codes[name].flip(1), codes[name])
    if CHANNELS in tools and config.channels > 1:
        for name in CHANGED:
            value, depth = codes[name], depths[name].double()
            if name == "amplitude":
                change = value[:, 1:] - value[:, :-1]
            else:
                change = _wrapped(value[:, 1:] - value[:, :-1] * 2.0 ** (depth[:, 1:] - depth[:, :-1]),
                                  2.0 ** depth[:, 1:])
            codes[name], codes[f"{name}_change"] = value[:, :1], change
    return codes


def _rate(encoded, config: FitConfig, bits: BitDepths, tools: frozenset[str],
          soft: dict[str, Tensor] | None = None, order: Tensor | None = None) -> Rate:
    """The estimate of the file of `encoded`'s symbols (file order): each stream's (`soft`: the same symbols
    unrounded, file order; None: the integers), the header as the codec writes it with those descriptors, and
    each primitive's bits in the primitives' own order (`order`: the file's order of them)."""
    count = len(encoded.streams["position"])
    device = next(iter(soft.values())).device if soft else torch.device("cpu")
    streams, per_primitive = {}, torch.zeros(count, dtype=torch.float64, device=device)
    for name, symbols in encoded.streams.items():
        moving = None if soft is None or name not in soft else soft[name]
        widths = encoded.widths.get(name)
        if widths is None:
            rate = stream_rate(symbols, moving)
        else:
            rate = rate_at_widths(symbols, widths, moving, TURN in tools and name in PERIODIC)
        streams[name] = rate
        per_primitive = per_primitive + rate.bits.to(device).reshape(count, -1).sum(dim=1)
    descriptors = [{"name": name, **rate.descriptor} for name, rate in streams.items()]
    header = len(deflated(file_header(config, count, bits, encoded.ranges, tools, descriptors)))
    size = PREFIX.size + FINGERPRINT.size + header + sum(rate.bytes for rate in streams.values()) + CHECKSUM.size
    if order is not None:  # back from the file's order to the primitives'
        per_primitive = torch.zeros_like(per_primitive).index_put((order,), per_primitive)
    return Rate(size, header, streams, per_primitive)
