"""The `.cvq` compressed model: codec, file format, the compress/decompress commands and bad files."""

import json
import math
import re
import struct
import zlib

import numpy as np
import pytest
import torch

from cvqpg import FitConfig, load_model
from cvqpg.cli import main
from cvqpg.codec import (CHECKSUM, FORMAT_VERSION, MAGIC, PREFIX, BitDepths, coding, decode, decode_stream,
                         dequantise, derived_depths, encode, encode_stream, file_order, importance_offsets, quantise,
                         rotation_depths)
from cvqpg.compression import compress_model
from cvqpg.errors import ConfigError, ModelFileError
from cvqpg.finetune import quantised
from cvqpg.fitting import render
from cvqpg.metrics import mean_psnr
from cvqpg.primitives import activate, init_gaussians
from cvqpg.runs import read_run, scene_from_source
from cvqpg.storage import read_compressed, save_model

# The paper's recipe: the fine-tuning gains asserted below are calibrated on its fit (a barely started one).
SMALL_FIT = ["fit", "--size", "40", "30", "--steps", "30", "--curvature-warmup", "10", "--recipe", "paper", "--quiet"]
FINE = BitDepths(position=8, scale=16, rotation=16, amplitude=16, phase=16, curvature=16)


def random_primitives(config: FitConfig, seed: int = 3):
    """Initialised primitives with signed amplitudes, wrapped phases and curvature near its bounds."""
    raw = init_gaussians(config.primitive_count, config.channels, config.width, config.height, seed)
    g = torch.Generator().manual_seed(seed)
    raw.amplitude.uniform_(-1, 1, generator=g)
    raw.phase.uniform_(-7, 14, generator=g)
    raw.rotation.uniform_(-7, 7, generator=g)
    raw.curvature.uniform_(-3, 3, generator=g)
    raw.opacity.uniform_(-2, 2, generator=g)
    return activate(raw, config)


@pytest.mark.parametrize("curvature", ["shared", "per-channel"])
def test_fine_budget_renders_like_the_float_model(curvature):
    config = FitConfig(width=48, height=32, ratio=0.3, curvature=curvature, guard_band_px=32)
    primitives = random_primitives(config)
    decoded = decode(encode(primitives, config, FINE)).primitives
    assert decoded.count == primitives.count and torch.all(decoded.opacity == 1)
    field, decoded_field = render(primitives, config)[0], render(decoded, config)[0]
    assert (decoded_field - field).abs().max() < 1e-2 * field.abs().max()  # 1/256 px positions, chirps near Nyquist


def test_decoding_is_deterministic_and_encoding_reproducible():
    config = FitConfig(width=48, height=32, color="gray", ratio=0.3)
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
    config = FitConfig(width=48, height=32, color="rgb", ratio=0.6)
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


def tampered(data: bytes, change) -> bytes:
    """A `.cvq` file whose header `change` (a function of the header's dict) altered, checksum recomputed."""
    _, version, length = PREFIX.unpack_from(data)
    header = json.loads(zlib.decompress(data[PREFIX.size:PREFIX.size + length]))
    change(header)
    packed = zlib.compress(json.dumps(header).encode())
    body = PREFIX.pack(MAGIC, version, len(packed)) + packed + data[PREFIX.size + length:-CHECKSUM.size]
    return body + CHECKSUM.pack(zlib.crc32(body))


@pytest.mark.parametrize("change, message", [
    (lambda h: h["optics"].update(pixel_pitch=0), "`pixel_pitch` must be positive"),
    (lambda h: h["optics"].update(pixel_pitch=-3.74e-6), "`pixel_pitch` must be positive"),
    (lambda h: h["optics"].update(width=8), "too small"),
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
    config = FitConfig(width=48, height=32, ratio=0.3)
    data = tampered(encode(random_primitives(config), config, BitDepths()), change)
    with pytest.raises(ModelFileError, match=f"^model.cvq: .*{re.escape(message)}.*write it again") as refused:
        decode(data, "model.cvq")
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize("damage, message", [
    ("nan", "tensor 'phase_rad' holds values that are not finite"),
    ("negative scale", "some scales (px) are not finite and positive"),
    ("pitch", "`pixel_pitch` must be positive"),
    ("config", "holds no readable configuration"),
    ("count", "its metadata says 5 primitives"),
])
def test_a_model_file_that_makes_no_physical_sense_is_refused(tmp_path, damage, message):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    config = FitConfig(width=48, height=32, ratio=0.3)
    path = tmp_path / "model.safetensors"
    save_model(path, random_primitives(config), config.replace(pixel_pitch=0) if damage == "pitch" else config)
    tensors = load_file(path)
    with safe_open(str(path), framework="pt") as handle:
        metadata = handle.metadata()
    if damage == "nan":
        tensors["phase_rad"][2, 1] = math.nan
    elif damage == "negative scale":
        tensors["scale_px"][0, 0] = -1.0
    elif damage == "config":
        metadata["config"] = "{not json"
    elif damage == "count":
        metadata["num_primitives"] = "5"
    save_file(tensors, str(path), metadata=metadata)
    with pytest.raises(ModelFileError, match=re.escape(message)) as refused:
        load_model(path)
    assert str(path) in str(refused.value) and "\n" not in str(refused.value)


def test_a_tampered_file_is_one_line_exit_2_with_the_flag_named(tmp_path, capsys):
    config = FitConfig(width=48, height=32, ratio=0.3)
    (tmp_path / "model.cvq").write_bytes(tampered(encode(random_primitives(config), config, BitDepths()),
                                                  lambda h: h["optics"].update(pixel_pitch=0)))
    assert main(["info", str(tmp_path / "model.cvq")]) == 2
    error = capsys.readouterr().err
    assert "--pitch must be positive" in error and len(error.strip().splitlines()) == 1 and "Traceback" not in error


def test_long_tailed_streams_take_the_bit_length_coding():
    # Morton gaps: geometric, with one jump beyond the parametric models' range, which `raw` pays on every symbol
    gaps = np.random.default_rng(0).geometric(1e-3, 4000)
    gaps[17] = 3 << 21
    descriptor, data = encode_stream(gaps)
    assert descriptor["coding"] == "bitlength" and len(data) < 0.6 * 4000 * 23 / 8
    assert (decode_stream(descriptor, data) == gaps).all()


@pytest.mark.parametrize("bits", [BitDepths(), BitDepths().shifted(-3), FINE,
                                  BitDepths(position=0, scale=2, rotation=2, amplitude=2, phase=2, curvature=2)])
@pytest.mark.parametrize("color, curvature, primitive", [("gray", "shared", "cvqpg"), ("rgb", "per-channel", "cvqpg"),
                                                         ("rgb", "channel-bound", "cvqpg"), ("rgb", "shared", "flat")])
def test_finetune_rounds_through_the_codec_s_own_quantisers(bits, color, curvature, primitive):
    config = FitConfig(width=48, height=32, color=color, ratio=0.3, curvature=curvature, primitive=primitive)
    primitives = random_primitives(config)
    coded = coding(primitives, config, bits)
    values = {name: value.clone().requires_grad_(True) for name, value in coded.values.items()}
    forward = quantised(values, coded.ranges, config, bits)
    decoded = dequantise(quantise(primitives, config, bits), config, bits).tensors()
    order = file_order(coded)
    tuned = {name: tensor.detach()[order] for name, tensor in forward.tensors().items()}
    for name in ("position_px", "rotation_rad", "amplitude", "phase_rad", "opacity"):
        assert torch.equal(tuned[name], decoded[name]), name
    # the same bins; the scale then goes through torch's float32 exp, the file's through numpy's, which
    # differ in the last bit, and the curvature bound of that scale (float32) by a few
    for name in ("scale_px", "curvature_per_m"):
        torch.testing.assert_close(tuned[name], decoded[name], rtol=5e-7, atol=0, msg=name)
    forward.position_px.sum().backward()
    assert torch.equal(values["position"].grad, torch.ones_like(values["position"]))


@pytest.fixture(scope="module")
def fitted_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("compress") / "run"
    assert main([*SMALL_FIT, "--out", str(out)]) == 0
    return out


def test_compress_decompress_render_round_trip(fitted_run, tmp_path, capsys):
    packed = tmp_path / "model.cvq"
    assert main(["compress", str(fitted_run), "--bits", "10", "--out", str(packed)]) == 0
    assert main(["decompress", str(packed), "--out", str(tmp_path / "model.safetensors")]) == 0
    assert main(["render", str(tmp_path / "model.safetensors"), "--out", str(tmp_path / "r")]) == 0
    capsys.readouterr()
    unpacked, config = load_model(tmp_path / "model.safetensors")
    direct, _ = load_model(packed)
    for name, tensor in direct.tensors().items():
        assert torch.equal(tensor, unpacked.tensors()[name]), name
    original, _ = load_model(fitted_run / "model.safetensors")
    assert mean_psnr(render(direct, config)[1], render(original, config)[1]) > 40
    assert (tmp_path / "r" / "recon_1mm.png").is_file()


def decoded_psnr(run, model_file) -> float:
    """PSNR (dB) of a model file's render against the run's targets."""
    config, source = read_run(run)
    targets = scene_from_source(source, config).targets
    return mean_psnr(render(load_model(model_file)[0], config)[1], targets)


def test_max_drop_is_the_drop_of_the_decoded_file(fitted_run, tmp_path):
    record = compress_model(fitted_run, tmp_path / "m.cvq", max_drop=0.3)
    float_psnr = decoded_psnr(fitted_run, fitted_run / "model.safetensors")
    assert record["reference"] == "the run's targets"
    assert record["drop"] == pytest.approx(float_psnr - decoded_psnr(fitted_run, tmp_path / "m.cvq"), abs=1e-9)
    assert record["drop"] <= 0.3
    assert record["bytes"] == (tmp_path / "m.cvq").stat().st_size < record["model_bytes"] / 4


def test_finetune_is_kept_only_if_it_pays(fitted_run, tmp_path):
    bits = BitDepths.parse(["5"])
    plain = compress_model(fitted_run, tmp_path / "plain.cvq", bits=bits)
    # The 30-step fit is far from converged: 10 steps of fine-tuning at the budget gain tenths of a dB
    paid = compress_model(fitted_run, tmp_path / "paid.cvq", bits=bits, finetune_steps=10)
    assert paid["finetune_kept"] and paid["drop"] < plain["drop"] - 0.25
    assert read_compressed(tmp_path / "paid.cvq").bits == bits
    assert paid["psnr"] == pytest.approx(decoded_psnr(fitted_run, tmp_path / "paid.cvq"), abs=1e-9)
    # Halving the primitives costs 0.5 dB, and one warm-up step moves no value by more than 1/44 of a bin
    unpaid = compress_model(fitted_run, tmp_path / "unpaid.cvq", bits=bits, finetune_steps=1, prune_fraction=0.5)
    assert not unpaid["finetune_kept"]
    assert (unpaid["drop"], unpaid["num_primitives"]) == (plain["drop"], plain["num_primitives"])
    assert (tmp_path / "unpaid.cvq").read_bytes() == (tmp_path / "plain.cvq").read_bytes()


def test_finetune_leaves_its_input_alone_and_trains_on_the_file_s_own_bins():
    from cvqpg.finetune import finetune
    from cvqpg.campaign.ratedistortion import Point, finetuned_points
    from cvqpg.targets import Scene

    config = FitConfig(width=48, height=32, color="gray", ratio=0.3, guard_band_px=32)
    primitives = random_primitives(config)
    targets = render(primitives, config)[1].clamp(0.05, 0.95).detach()
    scene = Scene(targets[0], torch.ones(targets.shape[0], 32, 48), targets)
    before = primitives.detached()
    bits = BitDepths().shifted(-3)
    tuned = finetune(primitives, config, scene, bits, 4)
    for name, tensor in primitives.tensors().items():
        assert torch.equal(tensor, before.tensors()[name]), name
    # the file's ranges (and so its bins) are those the loop quantised against
    assert quantise(tuned, config, bits).ranges == quantise(primitives, config, bits).ranges
    assert not torch.equal(tuned.position_px, primitives.position_px)
    fit = mean_psnr(render(primitives, config)[1], targets)
    untuned = [Point("cvqpg", "", 1, 1.0, fit - drop, 0.5, 0.0, 0.0) for drop in (5.0, 1.0, 0.05)]
    points = finetuned_points(primitives, config, scene, fit, 2, [bits, bits.shifted(3), bits.shifted(6)], untuned,
                              prune_fractions=(0.5,))
    assert [p.setting.split(":")[0] for p in points] == ["--finetune 2", "--prune 0.5 --finetune 2"]
    assert points[0].setting.endswith("position=3 scale=8 rotation=7 amplitude=8 phase=7 curvature=8")
    assert points[1].bytes < 0.7 * points[0].bytes


def test_pruning_removes_the_primitives_of_least_field_energy_and_the_file_round_trips():
    from cvqpg.compression import field_energy, prune

    config = FitConfig(width=48, height=32, color="rgb", ratio=0.3)
    primitives = random_primitives(config)
    values = primitives.tensors()
    values["amplitude"] = torch.ones_like(values["amplitude"])
    values["scale_px"] = torch.ones_like(values["scale_px"])
    values["opacity"] = torch.linspace(1.0, 0.1, primitives.count).roll(7)  # energy falls with opacity²
    primitives = type(primitives).from_tensors(values)
    pruned = prune(primitives, 0.25)
    kept = round(0.75 * primitives.count)
    expected = torch.argsort(values["opacity"], descending=True)[:kept].sort().values
    assert torch.equal(pruned.position_px, primitives.position_px[expected])
    assert field_energy(pruned).min() >= field_energy(primitives).sort().values[-kept]
    decoded = decode(encode(pruned, config, BitDepths())).primitives
    assert decoded.count == kept and prune(primitives, 0.0).count == primitives.count
    with pytest.raises(ConfigError, match="`prune_fraction` 1: give the fraction"):
        prune(primitives, 1.0)


def test_prune_with_finetune_writes_fewer_primitives_where_it_pays(fitted_run, tmp_path):
    # A quarter of the primitives, those of least field energy, cost this fit 0.04 dB at 5 bits; 10 steps of
    # fine-tuning regain tenths of a dB, so the tuned file, with fewer primitives, is the one kept
    record = compress_model(fitted_run, tmp_path / "p.cvq", bits=BitDepths.parse(["5"]), finetune_steps=10,
                            prune_fraction=0.25)
    count = load_model(fitted_run / "model.safetensors")[0].count
    assert record["finetune_kept"] and record["num_primitives"] == round(0.75 * count)
    assert read_compressed(tmp_path / "p.cvq").primitives.count == record["num_primitives"]


@pytest.mark.parametrize("settings, message", [
    ({"max_drop": -1.0}, "`max_drop` -1: give a drop in dB ≥ 0"),
    ({"finetune_steps": -2}, "`finetune_steps` -2: give a number of steps ≥ 0"),
    ({"prune_fraction": 1.5, "finetune_steps": 2}, "`prune_fraction` 1.5: give the fraction"),
    ({"prune_fraction": 0.2}, "`prune_fraction` 0.2 needs `finetune_steps` > 0"),
])
def test_compress_model_names_the_setting_at_fault(fitted_run, tmp_path, settings, message):
    with pytest.raises(ConfigError, match=message):
        compress_model(fitted_run, tmp_path / "x.cvq", **settings)
    assert not (tmp_path / "x.cvq").exists()


@pytest.mark.parametrize("arguments, message", [
    (["--prune", "1.5", "--finetune", "2"], "--prune 1.5: give the fraction of primitives to remove"),
    (["--prune", "-0.1", "--finetune", "2"], "--prune -0.1: give the fraction"),
    (["--prune", "0.2"], "--prune 0.2 needs --finetune > 0"),
])
def test_bad_prune_is_one_line_exit_2_and_writes_nothing(fitted_run, tmp_path, arguments, message, capsys):
    out = tmp_path / "x.cvq"
    assert main(["compress", str(fitted_run), "--out", str(out), *arguments]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.strip().splitlines()) == 1 and not out.exists()


def test_eval_info_and_export_read_the_compressed_file(fitted_run, capsys):
    assert main(["compress", str(fitted_run), "--bits", "8"]) == 0
    packed = fitted_run / "model.cvq"
    assert "8.000" not in capsys.readouterr().out
    assert main(["info", str(packed), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["dtype"] == "compressed" and info["bits"]["phase"] == 8 and info["format_version"] == FORMAT_VERSION
    assert info["bits_per_pixel"] == pytest.approx(8 * packed.stat().st_size / (40 * 30))
    assert main(["info", str(packed)]) == 0
    rotation_bits = 8 * info["streams"]["rotation"]["bytes"] / info["num_primitives"]
    assert f"a bit more per doubling, {rotation_bits:.1f} on average" in capsys.readouterr().out
    assert main(["eval", str(packed)]) == 0
    assert json.loads((fitted_run / "model.metrics.json").read_text())["mean"]["psnr"] > 0
    assert main(["export", str(packed)]) == 0
    assert (fitted_run / "export-model" / "metrics.json").is_file()


def _bad_files(good: bytes) -> dict[str, tuple[bytes, str]]:
    flipped = bytearray(good)
    flipped[len(good) // 2] ^= 0x40
    newer = bytearray(good)
    struct.pack_into("<H", newer, len(MAGIC), FORMAT_VERSION + 1)
    return {"truncated": (good[:len(good) - 9], "truncated"), "corrupted": (bytes(flipped), "checksum"),
            "magic": (b"PK\x03\x04" + good[4:], "wrong magic"), "newer": (bytes(newer), "newer"),
            "empty": (b"", "wrong magic")}


@pytest.mark.parametrize("kind", ["truncated", "corrupted", "magic", "newer", "empty"])
@pytest.mark.parametrize("command", ["decompress", "info", "render"])
def test_bad_files_fail_cleanly_and_write_nothing(fitted_run, tmp_path, kind, command, capsys):
    good = fitted_run / "good.cvq"
    if not good.exists():
        assert main(["compress", str(fitted_run), "--bits", "6", "--out", str(good)]) == 0
    data, message = _bad_files(good.read_bytes())[kind]
    bad = tmp_path / "bad.cvq"
    bad.write_bytes(data)
    capsys.readouterr()
    assert main([command, str(bad), "--out", str(tmp_path / "out")] if command != "info" else [command, str(bad)]) == 2
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error and len(error.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.cvq"]


@pytest.mark.parametrize("arguments, message", [
    (["compress", "{run}", "--bits", "phase=1"], "--bits phase=1: give 2..16 bits"),
    (["compress", "{run}", "--bits", "colour=8"], "--bits colour=8"),
    (["compress", "{run}", "--max-drop", "-1"], "--max-drop"),
    (["compress", "{run}/model.cvq6"], "no such"),
    (["decompress", "{run}/none.cvq"], "no such"),
])
def test_bad_compress_options_fail_cleanly(fitted_run, arguments, message, capsys):
    before = sorted(p.name for p in fitted_run.iterdir())
    assert main([a.format(run=fitted_run) for a in arguments]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.strip().splitlines()) == 1
    assert sorted(p.name for p in fitted_run.iterdir()) == before


def test_unknown_option_exits_2(fitted_run, capsys):
    assert main(["compress", str(fitted_run), "--level", "3"]) == 2
    error = capsys.readouterr().err
    assert "unrecognized arguments: --level" in error and error.count("\n") == 1


def test_periodic_attributes_wrap():
    config = FitConfig(width=48, height=32, color="gray", ratio=0.3)
    primitives = random_primitives(config)
    values = primitives.tensors()
    values["rotation_rad"] = values["rotation_rad"] + math.pi
    values["phase_rad"] = values["phase_rad"] + 2 * math.pi
    shifted = type(primitives).from_tensors(values)
    assert encode(shifted, config, BitDepths()) == encode(primitives, config, BitDepths())


def test_rate_distortion_points_and_bd_rate():
    pytest.importorskip("imagecodecs")
    from cvqpg.campaign.ratedistortion import anchor_points, bd_rate, rd_points

    config = FitConfig(width=48, height=32, color="gray", ratio=0.3, guard_band_px=32)
    primitives = random_primitives(config)
    targets = render(primitives, config)[1].clamp(0.05, 0.95)
    points = rd_points(primitives, config, targets, ladder=[BitDepths(), BitDepths().shifted(2)], anchors=False)
    assert [p["codec"] for p in points] == ["model float32", "model float16", "cvqpg", "cvqpg"]
    assert all(p["bpp"] == pytest.approx(8 * p["bytes"] / (48 * 32)) for p in points)
    assert points[3]["bytes"] > points[2]["bytes"] and points[0]["bytes"] > points[2]["bytes"]
    anchors = anchor_points(primitives, config, targets, {"JPEG 2000": [50], "JPEG XL": [1.0]})
    assert [p.codec for p in anchors] == ["JPEG 2000", "JPEG XL"] and all(p.psnr > 20 for p in anchors)
    anchor = [{"bpp": 2 * b, "psnr": q} for b, q in ((1, 30), (2, 33), (3, 35), (4, 36))]
    test = [{"bpp": b, "psnr": q} for b, q in ((1, 30), (2, 33), (3, 35), (4, 36))]
    assert bd_rate(anchor, test, top_psnr=35).percent == pytest.approx(-50, abs=1e-9)


def test_a_bare_model_file_is_scored_against_its_own_reconstruction(fitted_run, tmp_path, capsys):
    bare = tmp_path / "bare.safetensors"
    bare.write_bytes((fitted_run / "model.safetensors").read_bytes())
    assert main(["compress", str(bare), "--max-drop", "0.5"]) == 0
    shown = capsys.readouterr().out
    assert "against the float model's own reconstruction" in shown and "estimated for a fit at 30 dB" in shown
    assert (tmp_path / "bare.cvq").is_file()


def test_fine_tuning_s_rate_is_a_quarter_bin_for_short_tunings_and_grows_to_four_bins_for_long_ones():
    from cvqpg.finetune import learning_rate_bins

    assert [learning_rate_bins(steps) for steps in (1, 10, 100)] == [0.25, 0.25, 0.25]
    assert learning_rate_bins(200) == pytest.approx(1.0) and learning_rate_bins(400) == pytest.approx(4.0)
    rates = [learning_rate_bins(steps) for steps in range(100, 2001, 50)]
    assert rates == sorted(rates) and max(rates) == 4.0
