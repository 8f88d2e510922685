"""The `.cvq` codec (`cvqpg.codec`): streams, quantisers and depths, files that decode as they were written, and
files or model files that make no physical sense refused in one line."""

import dataclasses
import json
import math
import re
import zlib

import numpy as np
import pytest
import torch

from cvqpg import FitConfig, load_model
from cvqpg.cli import main
from cvqpg.codec import (AXES, CHANNELS, CHECKSUM, MAGIC, PREFIX, TOOLS, TURN, BitDepths, coding, decode, decode_stream,
                         deflated, derived_depths, encode, encode_stream, exact_exp, file_fingerprint, file_order,
                         header_start, importance_offsets, inflated, optics, rotation_depths, with_fingerprint)
from cvqpg.codec import NO_FINGERPRINT, _file
from cvqpg.errors import ConfigError, ModelFileError
from cvqpg.fitting import render
from cvqpg.primitives import activate, init_gaussians
from cvqpg.storage import save_model

FINE = BitDepths(position=8, scale=16, rotation=16, amplitude=16, phase=16, curvature=16)


def random_primitives(config: FitConfig, seed: int = 3):
    """Initialised primitives with signed amplitudes, wrapped phases and curvature near its bounds."""
    raw = init_gaussians(config.primitive_count, config.channels, config.targets.width, config.targets.height, seed)
    g = torch.Generator().manual_seed(seed)
    raw.amplitude.uniform_(-1, 1, generator=g)
    raw.phase.uniform_(-7, 14, generator=g)
    raw.rotation.uniform_(-7, 7, generator=g)
    raw.curvature.uniform_(-3, 3, generator=g)
    raw.opacity.uniform_(-2, 2, generator=g)
    return activate(raw, config)


@pytest.mark.parametrize("curvature", ["shared", "per-channel"])
def test_fine_budget_renders_like_the_float_model(curvature):
    config = FitConfig.create(width=48, height=32, ratio=0.3, curvature=curvature, guard_band_px=32)
    primitives = random_primitives(config)
    decoded = decode(encode(primitives, config, FINE)).primitives
    assert decoded.count == primitives.count and torch.all(decoded.opacity == 1)
    field, decoded_field = render(primitives, config)[0], render(decoded, config)[0]
    assert (decoded_field - field).abs().max() < 1e-2 * field.abs().max()  # 1/256 px positions, chirps near Nyquist


def test_decoding_is_deterministic_and_encoding_reproducible():
    config = FitConfig.create(width=48, height=32, color="gray", ratio=0.3)
    primitives = random_primitives(config)
    data = encode(primitives, config, BitDepths())
    assert encode(primitives, config, BitDepths()) == data
    first, second = decode(data).primitives, decode(data).primitives
    for name, tensor in first.tensors().items():
        assert torch.equal(tensor, second.tensors()[name]), name


@pytest.mark.parametrize("values", [torch.zeros(7, dtype=torch.long), torch.arange(-5, 300),
                                    torch.tensor([0, 0, 0, 1, 0, 2, 0, 0, 90000]), torch.tensor([2**40, 5, 0, 3]),
                                    torch.tensor([3])])
def test_streams_round_trip_exactly(values):
    array = values.numpy()
    descriptor, data = encode_stream(array)
    assert (decode_stream(descriptor, data) == array).all()


@pytest.mark.parametrize("skewed, coding", [(False, "widths"), (True, "grouped")])
def test_streams_at_derived_widths_round_trip_in_their_smaller_coding(skewed, coding):
    """Symbols whose widths the decoder derives: uniform within their widths, raw bits (`widths`) are smallest;
    peaked, each width's own entropy coding (`grouped`) pays for its descriptors."""
    rng = np.random.default_rng(1)
    widths = rng.integers(0, 7, 5000)
    symbols = (np.minimum(rng.geometric(0.4, widths.shape) - 1, 2**widths - 1) if skewed
               else rng.integers(0, 2**widths))
    descriptor, data = encode_stream(symbols, widths)
    assert descriptor["coding"] == coding
    assert (decode_stream(descriptor, data, widths) == symbols).all()
    with pytest.raises(ValueError):
        decode_stream(descriptor, data, None)


def test_rotation_s_depth_follows_anisotropy():
    sigma = torch.tensor([[2.0, 2.0], [2.0, 2.1], [2.0, 2.9], [1.0, 2.0], [1.0, 8.0]])
    assert rotation_depths(sigma, 7).tolist() == [0, 4, 7, 8, 10]  # a − 1/a: 0, 0.098, 0.76, 1.5, 7.9
    assert rotation_depths(sigma, torch.tensor([7, 7, 5, 9, 7])).tolist() == [0, 4, 5, 10, 10]


def test_importance_offsets_give_a_bit_per_fourfold_weight_and_none_to_what_does_not_show():
    # binary exponents 1, 2, 3, 5, −1 (frexp: w = m·2^e, 0.5 ≤ m < 1): median 2
    weights = torch.tensor([1.0, 2.0, 4.0, 16.0, 0.25, 0.0], dtype=torch.float64)
    assert importance_offsets(weights).tolist() == [-1, 0, 0, 1, -2, -16]


@pytest.mark.parametrize("attribute", ["position", "rotation", "phase"])
def test_every_value_s_error_costs_about_alike_in_the_field(attribute):
    """Position, rotation and phase errors, weighted by what they cost in the field (√(Σ_c |w_c|²) for position,
    a shifted Gaussian's error energy being independent of its size; √(|w|²·σx·σy) for phase; for rotation
    √(Σ_c |w_c|²·σx·σy) times a − 1/a, whose bits `rotation_depths` gives), stay within twice the half-step of
    a value of median weight, where the depths are not clamped."""
    config = FitConfig.create(width=48, height=32, color="rgb", ratio=0.6)
    primitives = random_primitives(config)
    bits = BitDepths(position=2, rotation=6, phase=6)
    decoded = decode(encode(primitives, config, bits)).primitives
    # at the same positions' depths, in the same order
    reference = decode(encode(primitives, config, BitDepths(position=2, rotation=16, phase=16))).primitives
    scale = decoded.scale_px.double()
    power = (decoded.amplitude.double() ** 2).sum(1)
    weight = {"position": power[:, None].expand(-1, 2), "rotation": power * scale.prod(1),
              "phase": decoded.amplitude.double() ** 2 * scale.prod(1)[:, None]}[attribute]
    _, exponent = torch.frexp(weight)
    median = exponent[weight > 0].sort().values[int((weight > 0).sum()) // 2]
    if attribute == "position":
        # a primitive's two coordinates share one depth; the median is over the primitives
        median = exponent[:, 0].sort().values[weight.shape[0] // 2]
        # against the float positions: a coarser grid may round a primitive into the next pixel, and so change the
        # file's order
        truth = primitives.position_px.double()[file_order(coding(primitives, config, bits))]
        half_step, error = 2.0 ** -(bits.position + 1), decoded.position_px.double() - truth
    else:
        period = math.pi if attribute == "rotation" else 2 * math.pi
        values, truth = ((decoded.rotation_rad, reference.rotation_rad) if attribute == "rotation"
                         else (decoded.phase_rad, reference.phase_rad))
        error = torch.remainder(values.double() - truth.double() + period / 2, period) - period / 2
        half_step = period / 2 ** (getattr(bits, attribute) + 1)
    if attribute == "rotation":
        aspect = scale.max(1).values / scale.min(1).values
        weight = weight * (aspect - 1 / aspect) ** 2
    depths = derived_depths(attribute, {"scale": decoded.scale_px, "amplitude": decoded.amplitude.double()}, bits,
                            tuple(error.shape))
    top = 8 if attribute == "position" else 16
    unclamped = (depths > 0) & (depths < top)
    assert bool((error.abs() * weight.sqrt() <= 2 * half_step * 2.0 ** (median / 2))[unclamped].all())
    base = getattr(bits, attribute)
    assert int((depths < base).sum()) > 0 and int((depths > base).sum()) > 0


def test_periodic_attributes_wrap():
    config = FitConfig.create(width=48, height=32, color="gray", ratio=0.3)
    primitives = random_primitives(config)
    values = primitives.tensors()
    values["rotation_rad"] = values["rotation_rad"] + math.pi
    values["phase_rad"] = values["phase_rad"] + 2 * math.pi
    shifted = type(primitives).from_tensors(values)
    assert encode(shifted, config, BitDepths()) == encode(primitives, config, BitDepths())


def test_long_tailed_streams_take_the_bit_length_coding():
    # Morton gaps: geometric, with one jump beyond the parametric models' range, which `raw` pays on every symbol
    gaps = np.random.default_rng(0).geometric(1e-3, 4000)
    gaps[17] = 3 << 21
    descriptor, data = encode_stream(gaps)
    assert descriptor["coding"] == "bitlength" and len(data) < 0.6 * 4000 * 23 / 8
    assert (decode_stream(descriptor, data) == gaps).all()


def tampered(data: bytes, change) -> bytes:
    """A `.cvq` file whose header `change` (a function of the header's dict) altered, checksum recomputed."""
    _, version, length = PREFIX.unpack_from(data)
    start = header_start(version)
    header = json.loads(inflated(data[start:start + length], version))
    change(header)
    packed = deflated(header, version)
    body = PREFIX.pack(MAGIC, version, len(packed)) + data[PREFIX.size:start] + packed \
        + data[start + length:-CHECKSUM.size]
    return body + CHECKSUM.pack(zlib.crc32(body))


@pytest.mark.parametrize("change, message", [
    (lambda h: h["optics"].update(pixel_pitch=0), "`pixel_pitch` must lie in [1e-07, 0.001]"),
    (lambda h: h["optics"].update(pixel_pitch=-3.74e-6), "`pixel_pitch` must lie in [1e-07, 0.001]"),
    (lambda h: h["optics"].update(width=8), "`width` must lie in [16, 65536], got 8"),
    (lambda h: h["optics"].update(wavelengths=[639e-9, 532e-9]), "`wavelengths_m`"),
    (lambda h: h.update(num_primitives=0), "holds 0 primitives"),
    (lambda h: h.update(num_primitives=h["num_primitives"] + 1), "its streams have shapes"),
    (lambda h: h["streams"][1].update(shape=[h["num_primitives"], 3]), "its streams have shapes"),
    (lambda h: h["bits"].update(scale=40), "`bits` scale=40"),
    (lambda h: h.pop("optics"), "its header is malformed (KeyError: 'optics')"),
    (lambda h: h["ranges"].update(amplitude=[0.0, math.inf]), "its ranges of log scale and amplitude"),
    (lambda h: h["ranges"].update(scale=[math.nan, math.nan]), "are not finite"),
    (lambda h: h["ranges"].update(scale="wide"), "its header is malformed (ValueError"),
    # exp → 0: the depths that derive from the scale are no longer those the streams were grouped by
    (lambda h: h["ranges"].update(scale=[-300.0, -299.0]), "does not decode"),
])
def test_a_file_whose_checksum_holds_is_still_checked_for_physical_sense(change, message):
    config = FitConfig.create(width=48, height=32, ratio=0.3)
    data = tampered(encode(random_primitives(config), config, BitDepths()), change)
    with pytest.raises(ModelFileError, match=f"^model.cvq: .*{re.escape(message)}.*write it again") as refused:
        decode(data, "model.cvq")
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize("damage, message", [
    ("nan", "tensor 'phase_rad' holds values that are not finite"),
    ("negative scale", "some scales (px) are not finite and positive"),
    ("pitch", "`pixel_pitch` must lie in [1e-07, 0.001]"),
    ("config", "holds no readable configuration"),
    ("count", "its metadata says 5 primitives"),
])
def test_a_model_file_that_makes_no_physical_sense_is_refused(tmp_path, damage, message):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    config = FitConfig.create(width=48, height=32, ratio=0.3)
    path = tmp_path / "model.safetensors"
    save_model(path, random_primitives(config), config)
    tensors = load_file(path)
    with safe_open(str(path), framework="pt") as handle:
        metadata = handle.metadata()
    if damage == "nan":
        tensors["phase_rad"][2, 1] = math.nan
    elif damage == "negative scale":
        tensors["scale_px"][0, 0] = -1.0
    elif damage == "config":
        metadata["config"] = "{not json"
    elif damage == "pitch":
        record = json.loads(metadata["config"])
        record["optics"]["pixel_pitch"] = 0
        metadata["config"] = json.dumps(record)
    elif damage == "count":
        metadata["num_primitives"] = "5"
    save_file(tensors, str(path), metadata=metadata)
    with pytest.raises(ModelFileError, match=re.escape(message)) as refused:
        load_model(path)
    assert str(path) in str(refused.value) and "\n" not in str(refused.value)


def test_a_tampered_file_is_one_line_exit_2_with_the_flag_named(tmp_path, capsys):
    config = FitConfig.create(width=48, height=32, ratio=0.3)
    (tmp_path / "model.cvq").write_bytes(tampered(encode(random_primitives(config), config, BitDepths()),
                                                  lambda h: h["optics"].update(pixel_pitch=0)))
    assert main(["info", str(tmp_path / "model.cvq")]) == 2
    error = capsys.readouterr().err
    assert "--pitch must lie in [1e-07, 0.001]" in error
    assert len(error.strip().splitlines()) == 1 and "Traceback" not in error


def ellipses(primitives) -> torch.Tensor:
    """Each primitive's covariance (px², float64 [N, 2, 2]): the same for an ellipse whatever order its axes take."""
    scale, angle = primitives.scale_px.double(), primitives.rotation_rad.double()
    turn = torch.stack([torch.stack([angle.cos(), -angle.sin()], -1), torch.stack([angle.sin(), angle.cos()], -1)], -2)
    return turn @ torch.diag_embed(scale**2) @ turn.transpose(1, 2)


@pytest.mark.parametrize("tools", [frozenset(), frozenset({AXES}), frozenset({TURN}), frozenset({CHANNELS}), TOOLS],
                         ids=["none", "axes", "turn", "channels", "all"])
def test_every_set_of_format_5_tools_decodes_to_the_same_model(tools):
    """The tools change how symbols are coded, not what they decode to: with `axes` an ellipse's axes come larger
    first (turned by a quarter where they swap), and ellipses whose rotation took no bit get one. Phases of
    channels at other depths go through `channels`' rescaling both ways."""
    config = FitConfig.create(width=64, height=48, ratio=0.3, curvature="per-channel")
    primitives = random_primitives(config)
    bits = BitDepths()
    reference = decode(encode(primitives, config, bits, tools=frozenset())).primitives
    decoded = decode(_file(primitives, config, bits, NO_FINGERPRINT, tools))
    assert decoded.tools == tools
    for name in ("position_px", "amplitude", "phase_rad", "curvature_per_m", "opacity"):
        assert torch.equal(getattr(decoded.primitives, name), getattr(reference, name)), name
    if AXES in tools:
        scale = decoded.primitives.scale_px
        assert bool((scale[:, 0] >= scale[:, 1]).all())
        # the same ellipse, but where a rotation took no bit without `axes`
        depths = derived_depths("rotation", {"scale": reference.scale_px, "amplitude": reference.amplitude.double()},
                                bits, (primitives.count,), tools=frozenset())
        assert 0 < int((depths > 0).sum()) < primitives.count
        torch.testing.assert_close(ellipses(decoded.primitives)[depths > 0], ellipses(reference)[depths > 0],
                                   rtol=1e-5, atol=1e-5)
    else:
        assert torch.equal(decoded.primitives.scale_px, reference.scale_px)


def gathered_primitives(config: FitConfig):
    """`random_primitives` with positive weights, phases gathered about 0 across the period's end, and scales spread
    over a wide range, as a fit's are."""
    primitives = random_primitives(config)
    values, generator = primitives.tensors(), torch.Generator().manual_seed(1)
    values["amplitude"] = values["amplitude"].abs()
    values["phase_rad"] = torch.remainder(0.2 * torch.randn(values["phase_rad"].shape, generator=generator),
                                          2 * math.pi)
    values["scale_px"] = torch.exp(1 + 0.8 * torch.randn(values["scale_px"].shape, generator=generator))
    return type(primitives).from_tensors(values)


def test_the_tools_save_bytes_where_their_symbols_gather():
    """Phases gathered about one value across the period's end (positive weights, whose phases are not turned by
    half), and ellipses of either axis order whose scales spread over a wide range, as a fit's do: `turn` and
    `axes` each take fewer bytes than without."""
    config = FitConfig.create(width=160, height=120, color="gray", ratio=0.3)
    primitives = gathered_primitives(config)
    sizes = {tools: len(encode(primitives, config, BitDepths(), tools=frozenset(tools)))
             for tools in ((), (AXES,), (TURN,))}
    assert sizes[(AXES,)] < sizes[()] and sizes[(TURN,)] < sizes[()]


def test_channels_is_used_where_it_makes_the_file_smaller():
    """Amplitudes and phases that follow the channel before take `channels`; independent ones do not."""
    config = FitConfig.create(width=96, height=64, ratio=0.3)
    primitives = gathered_primitives(config)
    values = primitives.tensors()
    assert CHANNELS not in decode(encode(primitives, config, BitDepths())).tools
    values["amplitude"] = values["amplitude"][:, :1].expand(-1, 3) * torch.tensor([1.0, 0.9, 0.8])
    values["phase_rad"] = values["phase_rad"][:, :1].expand(-1, 3).contiguous()
    followed = type(primitives).from_tensors(values)
    assert CHANNELS in decode(encode(followed, config, BitDepths())).tools


def test_exact_exp_is_within_an_ulp_and_gives_the_same_bits_everywhere():
    x = np.linspace(-60.0, 60.0, 200_001)
    assert float((np.abs(exact_exp(x) - np.exp(x)) / np.spacing(np.exp(x))).max()) <= 1.0
    # bits that any IEEE 754 machine reproduces (additions, multiplications and scalings by 2 alone)
    assert [value.hex() for value in exact_exp(np.array([1.0, -0.5, 3.25])).tolist()] == \
        ["0x1.5bf0a8b14576ap+1", "0x1.368b2fc6f960ap-1", "0x1.9ca53b781114bp+4"]
    assert exact_exp(np.array([-1e300, 1e300])).tolist() == [5e-324, math.inf]  # as at ±745, the bound


# NumPy's SIMD paths to leave out (where the CPU has them): without them its float32 exp, which formats 1–4 decode
# the scale with, gives other last bits on an AVX-512 machine
OLDER_SIMD = "AVX512_SKX AVX512_ICL AVX512_SPR X86_V4 AVX2 FMA3 X86_V3"


def test_decoding_gives_the_same_bits_in_other_processes_threads_and_simd_paths(tmp_path):
    """Decode a file in fresh interpreters, of one thread and of four, and with NumPy's AVX2 and AVX-512 paths left
    out, as on an older CPU (which NumPy reads when it is imported), and compare the primitives' bytes."""
    import os
    import subprocess
    import sys

    config = FitConfig.create(width=64, height=48, ratio=0.3)
    path = tmp_path / "model.cvq"
    path.write_bytes(encode(gathered_primitives(config), config, BitDepths()))
    script = ("import hashlib, sys, torch; from cvqpg.codec import decode\n"
              "for threads in sys.argv[2:]:\n"
              "    torch.set_num_threads(int(threads)); p = decode(open(sys.argv[1], 'rb').read()).primitives\n"
              "    print(hashlib.sha256(b''.join(t.numpy().tobytes() for t in p.tensors().values())).hexdigest())")
    digests = [line for threads, simd in ((["1", "4"], {}), (["1"], {"NPY_DISABLE_CPU_FEATURES": OLDER_SIMD}))
               for line in subprocess.run([sys.executable, "-c", script, str(path), *threads], capture_output=True,
                                          text=True, check=True, env={**os.environ, **simd}).stdout.split()]
    assert len(digests) == 3 and len(set(digests)) == 1


def test_the_fit_fingerprint_travels_in_place_and_costs_no_byte_of_the_budget():
    config = FitConfig.create(width=48, height=32, ratio=0.3)
    data = encode(random_primitives(config), config, BitDepths())
    assert file_fingerprint(data) is None and decode(data).fingerprint is None
    stamped = with_fingerprint(data, bytes(range(1, 17)))
    assert len(stamped) == len(data) and file_fingerprint(stamped) == bytes(range(1, 17))
    decoded = decode(stamped)
    assert decoded.fingerprint == bytes(range(1, 17))
    assert torch.equal(decoded.primitives.position_px, decode(data).primitives.position_px)


@pytest.mark.parametrize("change, message", [
    (lambda h: h.update(tools=["axes", "contexts"]), "its tools ['axes', 'contexts'] are not distinct names"),
    (lambda h: h.update(tools=["turn", "turn"]), "are not distinct names"),
    (lambda h: h.update(tools=["axes", "turn", "channels"]), "names the tool `channels` for one channel"),
    (lambda h: h.pop("tools"), "its header is malformed (KeyError: 'tools')"),
    (lambda h: h.update(tools=["axes"]), "a group's turn"),  # turned groups in a file that names no `turn`
    (lambda h: [group.update(turn=1) for s in h["streams"] if s["name"] == "curvature" for group in s["groups"]],
     "a group's turn 1 is not one of its"),
    (lambda h: [group.update(turn=2 ** group["bits"]) for s in h["streams"] if s["name"] == "phase"
                for group in s.get("groups", [])], "is not one of its"),
])
def test_format_5_s_tools_and_turns_are_checked_before_use(change, message):
    config = FitConfig.create(width=160, height=120, color="gray", ratio=0.3, curvature="shared")
    data = encode(gathered_primitives(config), config, BitDepths())
    _, version, length = PREFIX.unpack_from(data)
    header = json.loads(inflated(data[header_start(version):header_start(version) + length], version))
    assert any("turn" in group for s in header["streams"] for group in s.get("groups", []))
    with pytest.raises(ModelFileError, match=f"^model.cvq: .*{re.escape(message)}") as refused:
        decode(tampered(data, change), "model.cvq")
    assert "\n" not in str(refused.value)


def test_an_elongation_beyond_its_scale_is_refused_in_one_line():
    config = FitConfig.create(width=48, height=32, color="gray", ratio=0.3)
    data = encode(random_primitives(config), config, BitDepths(), tools=frozenset({AXES}))
    raw = {"coding": "raw", "width": 9, "min": 0, "max": 300}

    def elongated(header):
        for stream in header["streams"]:
            if stream["name"] == "elongation":
                count = stream["shape"][0]
                stream.clear()
                stream.update(name="elongation", shape=[count], bytes=(9 * count + 7) // 8, **raw)
    _, version, length = PREFIX.unpack_from(data)
    header = json.loads(inflated(data[header_start(version):header_start(version) + length], version))
    elongation = next(s for s in header["streams"] if s["name"] == "elongation")
    start = header_start(version) + length + sum(s["bytes"] for s in header["streams"][:header["streams"].index(
        elongation)])
    count = elongation["shape"][0]
    payload = np.packbits(np.ones(9 * count, np.uint8), bitorder="little").tobytes()  # 511 everywhere
    body = data[:start] + payload + data[start + elongation["bytes"]:-CHECKSUM.size]
    data = body + CHECKSUM.pack(zlib.crc32(body))
    raw["max"] = 511
    with pytest.raises(ModelFileError, match="^model.cvq: .*an elongation beyond its scale code") as refused:
        decode(tampered(data, elongated), "model.cvq")
    assert "\n" not in str(refused.value)


# --------------------------------------------------------------------------- the phase terms beyond the curvature

EXTRA_PHASES = ("quadratic+tilt", "tilt", "axes", "axes+tilt")


def phased_primitives(phase: str, color: str = "gray", seed: int = 3):
    """`random_primitives` of a tiny model with `phase`, its terms spread far into their squash (N(0, 1) raw), and
    no curvature where the phase has no quadratic term (a fit's stays 0 there)."""
    config = FitConfig.create(width=32, height=24, color=color, num_gaussians=40, phase=phase, guard_band_px=16)
    terms = tuple(term.name for term in config.phase.extra_terms)
    raw = init_gaussians(config.primitive_count, config.channels, 32, 24, seed, terms=terms)
    g = torch.Generator().manual_seed(seed)
    raw.amplitude.uniform_(-1, 1, generator=g)
    raw.phase.uniform_(-7, 14, generator=g)
    raw.rotation.uniform_(-7, 7, generator=g)
    if config.phase.has("quadratic"):
        raw.curvature.uniform_(-3, 3, generator=g)
    raw.terms = {name: torch.randn(tensor.shape, generator=g) for name, tensor in raw.terms.items()}
    return activate(raw, config), config


FINEST = BitDepths(**{name: 16 for name in BitDepths().names()})


@pytest.mark.parametrize("phase", EXTRA_PHASES)
def test_a_file_keeps_the_phase_terms_beyond_the_curvature(phase):
    """Each term as shares of its bounds: at the finest depths the decoded model renders like the float one, and the
    header names the phase and the terms' depths."""
    primitives, config = phased_primitives(phase)
    finest = dataclasses.replace(FINEST, position=8)
    data = encode(primitives, config, finest)
    decoded = decode(data)
    assert decoded.config.phase.name == phase and optics(decoded.config) == optics(config)
    assert decoded.primitives.terms.keys() == primitives.terms.keys()
    written = json.loads(inflated(data[header_start(6):header_start(6) + PREFIX.unpack_from(data)[2]], 6))
    assert written["optics"]["phase"] == phase
    assert written["bits"] == finest.coded(decoded.primitives.terms)
    field, decoded_field = render(primitives, config)[0], render(decoded.primitives, config)[0]
    assert (decoded_field - field).abs().max() < 2e-3 * field.abs().max()
    coarse = decode(encode(primitives, config, BitDepths().shifted(-3))).primitives
    assert (render(coarse, config)[0] - field).abs().max() > 10 * (decoded_field - field).abs().max()


def test_the_tilt_s_values_decode_within_half_a_step_of_their_share_and_within_the_bound():
    from cvqpg.primitives import term_bounds

    primitives, config = phased_primitives("quadratic+tilt")
    bits = BitDepths(tilt=5)
    decoded = decode(encode(primitives, config, bits)).primitives
    order = file_order(coding(primitives, config, bits))
    limit = term_bounds(decoded.scale_px, config)["tilt"].double()
    depths = derived_depths("tilt", {"scale": decoded.scale_px, "amplitude": decoded.amplitude.double()}, bits,
                            (primitives.count, 2))
    error = (decoded.terms["tilt"].double() - primitives.terms["tilt"][order].double()) / limit
    assert bool((error.abs() <= 0.5 / (2.0 ** (depths - 1) - 1) + 1e-6).all())
    assert int((depths != 5).sum()) > 0  # by importance: Σ_c|w_c|²·σx·σy·tr Σ
    assert bool((decoded.terms["tilt"].abs() <= limit * (1 + 1e-6)).all())


@pytest.mark.parametrize("tools", [frozenset(), TOOLS - {CHANNELS}], ids=["none", "all"])
def test_the_axes_curvatures_follow_the_ellipse_s_axes_where_the_file_orders_them(tools):
    """With the tool `axes` an ellipse's axes come larger first, turned by a quarter: the two curvatures along them
    swap with them, and the file renders as it does without the tool; a circle's rotation keeps its bits where the
    astigmatism turns with it."""
    primitives, config = phased_primitives("axes+tilt")
    values = primitives.tensors()
    values["scale_px"][:4] = 2.5  # circles: only their astigmatism says how they turn
    primitives = type(primitives).from_tensors(values)
    reference = decode(encode(primitives, config, BitDepths(), tools=frozenset())).primitives
    decoded = decode(_file(primitives, config, BitDepths(), NO_FINGERPRINT, tools)).primitives
    field = render(reference, config)[0]
    assert (render(decoded, config)[0] - field).abs().max() <= 1e-4 * field.abs().max()
    assert torch.equal(decoded.terms["tilt"], reference.terms["tilt"])
    swapped = ~torch.isclose(decoded.scale_px, reference.scale_px).all(dim=1)
    assert (AXES in tools) == bool(swapped.any())
    torch.testing.assert_close(decoded.terms["axes"][swapped], reference.terms["axes"][swapped].flip(1),
                               rtol=1e-5, atol=0)
    circles = reference.scale_px[:, 0] == reference.scale_px[:, 1]
    assert bool(circles.any()) and bool((reference.rotation_rad[circles] != 0).any())


def test_a_phase_without_the_quadratic_term_codes_no_curvature_and_refuses_one():
    primitives, config = phased_primitives("tilt")
    decoded = decode(encode(primitives, config, BitDepths()))
    assert "curvature" not in [stream["name"] for stream in decoded.streams]
    values = primitives.tensors()
    values["curvature_per_m"][0] = 10.0
    with pytest.raises(ConfigError, match="`phase` tilt has no quadratic term, yet the model's curvatures"):
        encode(type(primitives).from_tensors(values), config, BitDepths())


@pytest.mark.parametrize("change, message", [
    (lambda h: h["optics"].update(phase="quadratic"), "phase 'quadratic' is not a phase with terms beyond"),
    (lambda h: h["optics"].update(phase="swirl"), "`phase` 'swirl' is not one of 'constant'"),
    (lambda h: h["optics"].pop("phase"), "bit depths for ['amplitude', 'curvature', 'phase', 'position', 'rotation', "
                                         "'scale', 'tilt'] where its attributes are ['amplitude', 'curvature', 'phase', "
                                         "'position', 'rotation', 'scale']"),
    (lambda h: (h["optics"].pop("phase"), h["bits"].pop("tilt")), "its streams have shapes"),
    (lambda h: h["bits"].pop("tilt"), "bit depths for ['amplitude', 'curvature', 'phase', 'position', 'rotation', "
                                      "'scale'] where"),
    (lambda h: h["bits"].update(axes=8), "bit depths for ['amplitude', 'axes'"),
])
def test_a_file_s_phase_and_its_terms_depths_are_checked(change, message):
    primitives, config = phased_primitives("quadratic+tilt")
    data = tampered(encode(primitives, config, BitDepths()), change)
    with pytest.raises(ModelFileError, match=f"^model.cvq: .*{re.escape(message)}.*write it again"):
        decode(data, "model.cvq")


def test_a_file_without_phase_terms_names_neither_their_phase_nor_their_depths():
    config = FitConfig.create(width=48, height=32, color="gray", ratio=0.3)
    data = encode(random_primitives(config), config, BitDepths(tilt=3, axes=12))
    assert data == encode(random_primitives(config), config, BitDepths())
    written = json.loads(inflated(data[header_start(6):header_start(6) + PREFIX.unpack_from(data)[2]], 6))
    assert "phase" not in written["optics"] and list(written["bits"]) == [
        "position", "scale", "rotation", "amplitude", "phase", "curvature"]
