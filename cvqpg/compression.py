"""The compressed model file (`.cvq`, docs/format.md): quantised primitives in a spatial order,
entropy-coded with `constriction`'s ANS coder, behind a magic number, a format version and a CRC32.

A primitive is coded as: position on a grid of 2^-b px, sorted in Morton order and coded as gaps
between consecutive Morton codes; log scale over the model's own range; rotation modulo π (an
ellipse turned by π is the same ellipse); amplitude × opacity as a magnitude, its sign folded
into the phase (+π); phase modulo 2π; curvature as a fraction of the primitive's own Nyquist
bound γ_max, computed from the decoded scale so that encoder and decoder agree.
"""

from __future__ import annotations

import json
import math
import struct
import time
import zlib
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import constriction
import numpy as np
import torch

from .config import FitConfig
from .fitting import render
from .metrics import mean_psnr
from .primitives import Primitives, curvature_bound
from .runs import CONFIG_FILE, model_path, read_run, scene_from_source, write_atomic
from .storage import ModelFileError, load_model, save_model

MAGIC = b"\x89CVQ\r\n\x1a\n"
FORMAT_VERSION = 2  # 2 added the `bitlength` coding; a version 1 file reads unchanged
SUFFIX = ".cvq"
PREFIX = struct.Struct("<8sHI")  # magic, format version, header length (bytes)
CHECKSUM = struct.Struct("<I")
MAX_POSITION_BITS = 8
MAX_BITS = 16


def _limits(name: str) -> tuple[int, int]:
    """Valid bit depths of an attribute: positions from whole pixels (0) to 1/256 px; the others 2..16."""
    return (0, MAX_POSITION_BITS) if name == "position" else (2, MAX_BITS)

# Stream codings; each stream takes the smallest that applies, so a coding that does not pay is never used.
RAW, LAPLACE, GAUSSIAN, CATEGORICAL, BIT_LENGTH = "raw", "laplace", "gaussian", "categorical", "bitlength"


@dataclass(frozen=True)
class BitDepths:
    """Bits per attribute. `position` counts fractional bits (grid of 2^-b px); the others count
    levels over the attribute's range: log scale over the model's range, rotation over [0, π),
    |amplitude·opacity| over [0, max], phase over [0, 2π), curvature over [−γ_max, γ_max]."""

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
                raise ModelFileError(f"--bits {name}={value}: give {low}..{top} bits")
        return self

    def shifted(self, delta: int) -> "BitDepths":
        """Every attribute `delta` bits finer (coarser when negative), kept within the valid ranges."""
        return BitDepths(**{name: min(max(value + delta, _limits(name)[0]), _limits(name)[1])
                            for name, value in asdict(self).items()})

    def names(self) -> list[str]:
        return [f.name for f in fields(self)]

    def shifted_one(self, name: str) -> "BitDepths | None":
        """One bit coarser in attribute `name`, or None at its lowest depth."""
        value = getattr(self, name) - 1
        return replace(self, **{name: value}) if value >= _limits(name)[0] else None

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
                raise ModelFileError(f"--bits {item}: give ATTRIBUTE=BITS with ATTRIBUTE one of "
                                     f"{', '.join(sorted(known))}, or one number for all but position")
            values[name] = int(value)
        return cls(**values).validate()


# The budgets `--max-drop` tries, coarsest first: the defaults shifted together.
LADDER = tuple(BitDepths().shifted(delta) for delta in range(-3, 7))


@dataclass
class Encoded:
    """One model's integer symbols per stream, and the side information to dequantise them."""

    streams: dict[str, np.ndarray]
    ranges: dict[str, list[float]]


def _short(value: float, digits: int = 4) -> float:
    """`value` to a few significant digits: the header stores it in few bytes, and encoder and
    decoder both use the stored value."""
    return float(f"{value:.{digits}g}")


def outward_range(low: float, high: float) -> list[float]:
    """[low, high] widened to short values (see `_short`) that still contain it: a margin of 1e-3 of
    the larger magnitude outweighs `_short`'s rounding error of at most 5e-4."""
    margin = 1e-3 * max(abs(low), abs(high), 1e-12)
    return [_short(low) if _short(low) <= low else _short(low - margin),
            _short(high) if _short(high) >= high else _short(high + margin)]


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


def _uniform(values: np.ndarray, low: float, high: float, bits: int) -> np.ndarray:
    levels = 2**bits - 1
    span = high - low if high > low else 1.0
    return np.clip(np.rint((values - low) / span * levels), 0, levels).astype(np.int64)


def _from_uniform(q: np.ndarray, low: float, high: float, bits: int) -> np.ndarray:
    span = high - low if high > low else 1.0
    return (low + q.astype(np.float64) * (span / (2**bits - 1))).astype(np.float32)


def _periodic(values: np.ndarray, period: float, bits: int) -> np.ndarray:
    return np.rint(np.mod(values, period) / period * 2**bits).astype(np.int64) % 2**bits


def _from_periodic(q: np.ndarray, period: float, bits: int) -> np.ndarray:
    return (q.astype(np.float64) * (period / 2**bits)).astype(np.float32)


def _bound(scale_px: np.ndarray, config: FitConfig) -> np.ndarray:
    return curvature_bound(torch.from_numpy(scale_px), config).numpy().astype(np.float64)


def quantise(primitives: Primitives, config: FitConfig, bits: BitDepths) -> Encoded:
    """Integer symbols of every attribute, primitives in Morton order (see the module docstring)."""
    p = {name: t.detach().cpu().double().numpy() for name, t in primitives.tensors().items()}
    step = 2.0**bits.position
    grid = np.clip(np.rint(p["position_px"] * step), 0, None).astype(np.uint64)
    morton = _interleave(grid[:, 0], grid[:, 1])
    order = np.argsort(morton, kind="stable")
    morton = morton[order]
    p = {name: values[order] for name, values in p.items()}
    streams: dict[str, np.ndarray] = {"position": np.diff(morton, prepend=np.uint64(0)).astype(np.int64)}
    ranges: dict[str, list[float]] = {}
    log_scale = np.log(p["scale_px"])
    ranges["scale"] = outward_range(float(log_scale.min()), float(log_scale.max()))
    streams["scale"] = _uniform(log_scale, *ranges["scale"], bits.scale)
    streams["rotation"] = _periodic(p["rotation_rad"], math.pi, bits.rotation)
    weight = p["amplitude"] * p["opacity"][:, None]
    ranges["amplitude"] = [0.0, outward_range(0.0, float(np.abs(weight).max(initial=0.0)))[1]]
    streams["amplitude"] = _uniform(np.abs(weight), *ranges["amplitude"], bits.amplitude)
    streams["phase"] = _periodic(p["phase_rad"] + np.where(weight < 0, math.pi, 0.0), 2 * math.pi, bits.phase)
    if config.primitive == "cvqpg":
        decoded_scale = np.exp(_from_uniform(streams["scale"], *ranges["scale"], bits.scale))
        bound = _bound(decoded_scale, config)
        share = p["curvature_per_m"] / np.where(bound > 0, bound, 1.0)
        half = 2 ** (bits.curvature - 1) - 1
        streams["curvature"] = np.clip(np.rint(share * half), -half, half).astype(np.int64)
    return Encoded(streams, ranges)


def dequantise(encoded: Encoded, config: FitConfig, bits: BitDepths) -> Primitives:
    """Primitives (float32, Morton order) from `quantise`'s symbols; opacity is 1, folded into amplitude."""
    s, r = encoded.streams, encoded.ranges
    morton = np.cumsum(s["position"].astype(np.uint64), dtype=np.uint64)
    x, y = _deinterleave(morton)
    position = (np.stack([x, y], axis=1).astype(np.float64) / 2.0**bits.position).astype(np.float32)
    scale = np.exp(_from_uniform(s["scale"], *r["scale"], bits.scale)).astype(np.float32)
    count = position.shape[0]
    values = {"position_px": position, "scale_px": scale,
              "rotation_rad": _from_periodic(s["rotation"], math.pi, bits.rotation),
              "amplitude": _from_uniform(s["amplitude"], *r["amplitude"], bits.amplitude),
              "phase_rad": _from_periodic(s["phase"], 2 * math.pi, bits.phase),
              "opacity": np.ones(count, np.float32)}
    if "curvature" in s:
        half = 2 ** (bits.curvature - 1) - 1
        values["curvature_per_m"] = (s["curvature"] / half * _bound(scale, config)).astype(np.float32)
    else:
        shape = (count,) if config.curvature == "shared" else (count, config.channels)
        values["curvature_per_m"] = np.zeros(shape, np.float32)
    return Primitives.from_tensors({name: torch.from_numpy(np.ascontiguousarray(v)) for name, v in values.items()})


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


def encode_stream(values: np.ndarray) -> tuple[dict[str, Any], bytes]:
    """The smallest coding for one stream of integers: its descriptor (JSON) and bytes.

    Symbols are offset by their minimum. `raw` packs fixed-width bits; the parametric models carry
    two short parameters; `categorical` carries the histogram, which pays only for skewed streams.
    """
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
    mantissas = b"".join(_raw_bits(shifted[lengths == length] - (1 << (length - 1)), length - 1)
                         for length in range(2, int(lengths.max(initial=0)) + 1))
    return {"coding": BIT_LENGTH, "lengths": descriptor}, data + mantissas


def _bit_lengths(values: np.ndarray) -> np.ndarray:
    lengths = np.zeros(values.shape, np.int64)
    remaining = values.astype(np.uint64)
    while remaining.any():
        lengths += remaining > 0
        remaining >>= np.uint64(1)
    return lengths


def _from_bit_length_coded(descriptor: dict[str, Any], data: bytes, count: int) -> np.ndarray:
    lengths_descriptor = descriptor["lengths"]
    lengths = decode_stream(lengths_descriptor, data[:lengths_descriptor["bytes"]]).ravel()
    values = np.where(lengths > 0, 1, 0).astype(np.int64) << np.maximum(lengths - 1, 0)
    offset = lengths_descriptor["bytes"]
    for length in range(2, int(lengths.max(initial=0)) + 1):
        chosen = lengths == length
        size = (int(chosen.sum()) * (length - 1) + 7) // 8
        values[chosen] += _from_raw_bits(data[offset:offset + size], int(chosen.sum()), length - 1)
        offset += size
    return values


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
        raise ValueError("histogram length")
    return values


def decode_stream(descriptor: dict[str, Any], data: bytes) -> np.ndarray:
    """Inverse of `encode_stream`."""
    shape, low, top = descriptor["shape"], descriptor["min"], descriptor["max"] - descriptor["min"]
    count = int(np.prod(shape))
    coding = descriptor["coding"]
    if coding == RAW:
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
        descriptor, data = encode_stream(values)
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
    """A decoded `.cvq` file: the primitives, their configuration, and how they were coded."""

    primitives: Primitives
    config: FitConfig
    bits: BitDepths
    streams: list[dict[str, Any]]


def decode(data: bytes, name: str = "file") -> Compressed:
    """Parse and decode a `.cvq` file's bytes; `ModelFileError` names what is wrong."""
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
    except (zlib.error, ValueError):
        header = None
    payload_bytes = sum(s["bytes"] for s in header["streams"]) if header else 0
    if header is not None and len(body) < PREFIX.size + header_length + payload_bytes:
        raise ModelFileError(f"{name}: truncated ({len(data)} bytes, the header announces "
                             f"{PREFIX.size + header_length + payload_bytes + CHECKSUM.size})")
    if zlib.crc32(body) != stored or header is None:
        raise ModelFileError(f"{name}: corrupted (CRC32 checksum mismatch)")
    config = config_from_optics(header["optics"])
    bits = BitDepths(**header["bits"])
    offset, streams = PREFIX.size + header_length, {}
    for descriptor in header["streams"]:
        streams[descriptor["name"]] = decode_stream(descriptor, body[offset:offset + descriptor["bytes"]])
        offset += descriptor["bytes"]
    primitives = dequantise(Encoded(streams, header["ranges"]), config, bits)
    return Compressed(primitives, config.replace(num_gaussians=primitives.count), bits, header["streams"])


def is_compressed(path: str | Path) -> bool:
    """Whether the file starts with the `.cvq` magic number."""
    with open(path, "rb") as handle:
        return handle.read(len(MAGIC)) == MAGIC


def read_compressed(path: str | Path) -> Compressed:
    """Decode a `.cvq` file."""
    path = Path(path)
    return decode(path.read_bytes(), str(path))


ASSUMED_FIT_PSNR_DB = 30.0


@dataclass
class Reference:
    """What a decoded render is scored against: the run's targets, or without a run the float model's
    own reconstruction (then `fit_psnr` is None)."""

    images: torch.Tensor  # [M, C, H, W]
    label: str
    fit_psnr: float | None


def reference_for(primitives: Primitives, config: FitConfig, scene_targets: torch.Tensor | None) -> Reference:
    """The run's targets with the float model's PSNR on them, or the float model's reconstruction."""
    recon = render(primitives, config)[1]
    if scene_targets is not None:
        return Reference(scene_targets, "the run's targets", mean_psnr(recon, scene_targets))
    return Reference(recon, "the float model's own reconstruction", None)


def psnr_drop(primitives: Primitives, config: FitConfig, reference: Reference) -> tuple[float, float]:
    """(PSNR in dB of `primitives`' render against the reference, drop in dB below the float model).

    Against the float model's own reconstruction the drop is estimated for a fit of
    `ASSUMED_FIT_PSNR_DB` whose error adds to the quantisation error:
    10·log10(1 + 10^((P_fit − Q)/10)), Q the PSNR against the float reconstruction.
    """
    value = mean_psnr(render(primitives, config)[1], reference.images)
    if reference.fit_psnr is not None:
        return value, reference.fit_psnr - value
    return value, 10 * math.log10(1 + 10 ** ((ASSUMED_FIT_PSNR_DB - value) / 10))


@dataclass
class Choice:
    """A chosen budget: the file's bytes, the decoded primitives, and its PSNR (dB) and drop (dB)."""

    bits: BitDepths
    data: bytes
    decoded: Primitives
    psnr: float
    drop: float


def trial(primitives: Primitives, config: FitConfig, bits: BitDepths, reference: Reference) -> Choice:
    """Encode at `bits`, decode the bytes as a reader would, and score the decoded render."""
    data = encode(primitives, config, bits)
    decoded = decode(data).primitives
    return Choice(bits, data, decoded, *psnr_drop(decoded, config, reference))


def choose_bits(primitives: Primitives, config: FitConfig, reference: Reference, max_drop: float,
                ladder: tuple[BitDepths, ...] = LADDER) -> Choice:
    """The smallest file found within `max_drop` dB: the coarsest rung of `ladder` that holds, then
    one attribute at a time one bit coarser, keeping the change that saves the most bytes, while the
    drop holds. Falls back to the finest rung when none holds."""
    best = None
    for bits in ladder:
        best = trial(primitives, config, bits, reference)
        if best.drop <= max_drop:
            break
    else:
        return best
    improved = True
    while improved:
        improved = False
        tries = [trial(primitives, config, candidate, reference)
                 for candidate in (best.bits.shifted_one(name) for name in best.bits.names())
                 if candidate is not None]
        holding = [t for t in tries if t.drop <= max_drop and len(t.data) < len(best.data)]
        if holding:
            best, improved = min(holding, key=lambda t: len(t.data)), True
    return best


def field_energy(primitives: Primitives) -> torch.Tensor:
    """Each primitive's field energy up to a constant factor: Σ_c (amplitude_c·opacity)² σx σy [N].

    A primitive's field is a Gaussian of that peak and those scales whatever its curvature (a chirp
    changes only the phase), and propagation to the planes preserves energy, so removing it changes the
    reconstructed fields by this much (squared L2), interference with the others aside."""
    weight = primitives.amplitude * primitives.opacity[:, None]
    return (weight**2).sum(dim=1) * primitives.scale_px.prod(dim=1)


def prune(primitives: Primitives, fraction: float) -> Primitives:
    """The primitives without the `fraction` (0 ≤ fraction < 1) of least field energy (`field_energy`),
    the others in their order. The rest only regain the PSNR lost with fine-tuning (`finetune`)."""
    if not 0 <= fraction < 1:
        raise ValueError(f"prune fraction {fraction}: give 0 ≤ FRACTION < 1")
    kept = round((1 - fraction) * primitives.count)
    order = torch.argsort(field_energy(primitives), descending=True, stable=True)
    chosen = order[:kept].sort().values
    return type(primitives).from_tensors({name: tensor[chosen] for name, tensor in primitives.tensors().items()})


def compress_model(target: str | Path, out: str | Path | None = None, bits: BitDepths | None = None,
                   max_drop: float | None = None, finetune_steps: int = 0, prune_fraction: float = 0.0
                   ) -> dict[str, Any]:
    """Compress a run folder's model or a model file into a `.cvq` file (atomically) and report it.

    `bits` fixes the budget; otherwise `max_drop` (dB, default 0.1) picks it with `choose_bits`. A
    model inside a run folder is scored against the run's targets, a bare model file against its own
    reconstruction. `finetune_steps` > 0 first tunes the model at the budget (needs the run folder),
    after removing the `prune_fraction` of its primitives of least field energy (`prune`; it needs
    fine-tuning, and like it is kept only where it pays).
    """
    model_file = model_path(target)
    if not model_file.is_file():
        raise ModelFileError(f"{target}: no such run folder or model file")
    if is_compressed(model_file):
        raise ModelFileError(f"{model_file}: already compressed; give the float model")
    primitives, config = load_model(model_file)
    folder = model_file.parent if (model_file.parent / CONFIG_FILE).is_file() else None
    if finetune_steps and folder is None:
        raise ModelFileError(f"--finetune needs the run folder's inputs; {model_file} is not in a run folder")
    if prune_fraction and not finetune_steps:
        raise ModelFileError(f"--prune {prune_fraction:g} needs --finetune STEPS: pruned primitives cost PSNR "
                             "that only fine-tuning regains")
    scene = scene_from_source(read_run(folder)[1], config) if folder is not None else None
    out = Path(out) if out is not None else model_file.with_suffix(SUFFIX)
    started = time.perf_counter()
    reference = reference_for(primitives, config, None if scene is None else scene.targets)
    max_drop = 0.1 if bits is None and max_drop is None else max_drop
    choice = (trial(primitives, config, bits, reference) if bits is not None
              else choose_bits(primitives, config, reference, max_drop))
    tuned = False
    if finetune_steps:
        from .finetune import finetune

        # Tuned models hold coarser budgets: first try one bit below the choice everywhere, then the choice.
        start = prune(primitives, prune_fraction)
        for bits_tried in ((choice.bits,) if max_drop is None else (choice.bits.shifted(-1), choice.bits)):
            candidate = trial(finetune(start, config, scene, bits_tried, finetune_steps), config, bits_tried,
                              reference)
            if max_drop is None or candidate.drop <= max_drop:
                break
        if max_drop is not None and candidate.drop <= max_drop:
            candidate = choose_bits(candidate.decoded, config, reference, max_drop, ladder=(candidate.bits,))
        # Kept only where it pays: smaller within the drop, or a smaller drop at a fixed budget.
        tuned = (len(candidate.data) <= len(choice.data) and candidate.drop <= max(max_drop, choice.drop)
                 if max_drop is not None else candidate.drop < choice.drop)
        choice = candidate if tuned else choice
    seconds = time.perf_counter() - started
    write_atomic(out, choice.data)
    pixels = config.width * config.height
    return {"file": str(out), "model": str(model_file), "bytes": len(choice.data),
            "bits_per_pixel": 8 * len(choice.data) / pixels, "model_bytes": model_file.stat().st_size,
            "ratio": model_file.stat().st_size / len(choice.data), "bits": asdict(choice.bits),
            "reference": reference.label, "psnr_float": reference.fit_psnr, "psnr": choice.psnr,
            "drop": choice.drop, "max_drop": max_drop, "finetune_steps": finetune_steps, "finetune_kept": tuned,
            "prune_fraction": prune_fraction, "num_primitives": choice.decoded.count,
            "seconds": seconds}


def decompress_file(path: str | Path, out: str | Path | None = None) -> Path:
    """Decode a `.cvq` file into a float32 `model.safetensors`-format file (atomically)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: no such file")
    compressed = read_compressed(path)
    out = Path(out) if out is not None else path.with_name(f"{path.stem}.decoded.safetensors")
    save_model(out, compressed.primitives, compressed.config)
    return out
