"""`cvqpg compress` and `cvqpg decompress` (`cvqpg.app.compression`) over run folders and model files: within a
drop, at fixed depths, within a budget; fine-tuning and pruning kept only where they pay; bad options and bad files
one line, exit code 2, nothing written."""

import json
import struct

import pytest
import torch

from cvqpg import FitConfig, load_model
from cvqpg.app.compression import compress_model
from cvqpg.cli import main
from cvqpg.codec import FORMAT_VERSION, MAGIC, BitDepths, encode
from cvqpg.errors import ConfigError
from cvqpg.fitting import render
from cvqpg.metrics import mean_psnr
from cvqpg.runs import read_run, scene_from_source
from cvqpg.search import LADDER, CompressionSettings, smallest_file
from cvqpg.storage import read_compressed, save_model
from test_codec import random_primitives

# The paper's recipe: the fine-tuning gains asserted below are calibrated on its fit (a barely started one).
SMALL_FIT = ["fit", "--size", "40", "30", "--steps", "30", "--curvature-warmup", "10", "--recipe", "paper", "--quiet"]
W, H = 48, 36


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    """A bare model file of random primitives, in a folder of its own; a narrow guard band renders it at once."""
    config = FitConfig.create(width=W, height=H, color="gray", num_planes=1, ratio=0.3, guard_band_px=32).validate()
    path = tmp_path_factory.mktemp("model") / "model.safetensors"
    save_model(path, random_primitives(config), config)
    return path


@pytest.fixture(scope="module")
def fitted_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("compress") / "run"
    assert main([*SMALL_FIT, "--out", str(out)]) == 0
    return out


def test_compress_decompress_render_round_trip(model_file, tmp_path, capsys):
    packed = tmp_path / "model.cvq"
    assert main(["compress", str(model_file), "--bits", "10", "--out", str(packed)]) == 0
    assert main(["decompress", str(packed), "--out", str(tmp_path / "model.safetensors")]) == 0
    assert main(["render", str(tmp_path / "model.safetensors"), "--out", str(tmp_path / "r")]) == 0
    capsys.readouterr()
    unpacked, config = load_model(tmp_path / "model.safetensors")
    direct, _ = load_model(packed)
    for name, tensor in direct.tensors().items():
        assert torch.equal(tensor, unpacked.tensors()[name]), name
    original, _ = load_model(model_file)
    assert mean_psnr(render(direct, config)[1], render(original, config)[1]) > 40
    assert (tmp_path / "r" / "recon_1mm.png").is_file()


def decoded_psnr(run, model_file) -> float:
    """PSNR (dB) of a model file's render against the run's targets."""
    config, source = read_run(run)
    targets = scene_from_source(source, config).targets
    return mean_psnr(render(load_model(model_file)[0], config)[1], targets)


@pytest.mark.slow
def test_max_drop_is_the_drop_of_the_decoded_file(fitted_run, tmp_path):
    record = compress_model(fitted_run, CompressionSettings(max_drop=0.3), tmp_path / "m.cvq")
    float_psnr = decoded_psnr(fitted_run, fitted_run / "model.safetensors")
    assert record["reference"] == "the run's targets"
    assert record["drop"] == pytest.approx(float_psnr - decoded_psnr(fitted_run, tmp_path / "m.cvq"), abs=1e-9)
    assert record["drop"] <= 0.3
    assert record["bytes"] == (tmp_path / "m.cvq").stat().st_size < record["model_bytes"] / 4


@pytest.mark.slow
def test_finetune_is_kept_only_if_it_pays(fitted_run, tmp_path):
    bits = BitDepths.parse(["5"])
    plain = compress_model(fitted_run, CompressionSettings(bits=bits), tmp_path / "plain.cvq")
    # The 30-step fit is far from converged: 10 steps of fine-tuning at the budget gain tenths of a dB
    paid = compress_model(fitted_run, CompressionSettings(bits=bits, finetune_steps=10), tmp_path / "paid.cvq")
    assert paid["finetune_kept"] and paid["drop"] < plain["drop"] - 0.25
    assert read_compressed(tmp_path / "paid.cvq").bits.coded() == bits.coded()  # no phase terms: none of theirs
    assert paid["psnr"] == pytest.approx(decoded_psnr(fitted_run, tmp_path / "paid.cvq"), abs=1e-9)
    # Halving the primitives costs 0.5 dB, and one warm-up step moves no value by more than 1/44 of a bin
    unpaid = compress_model(fitted_run, CompressionSettings(bits=bits, finetune_steps=1, prune_fraction=0.5),
                            tmp_path / "unpaid.cvq")
    assert not unpaid["finetune_kept"]
    assert (unpaid["drop"], unpaid["num_primitives"]) == (plain["drop"], plain["num_primitives"])
    assert (tmp_path / "unpaid.cvq").read_bytes() == (tmp_path / "plain.cvq").read_bytes()


@pytest.mark.slow
def test_prune_with_finetune_writes_fewer_primitives_where_it_pays(fitted_run, tmp_path):
    # A quarter of the primitives, those of least field energy, cost this fit 0.04 dB at 5 bits; 10 steps of
    # fine-tuning regain tenths of a dB, so the tuned file, with fewer primitives, is the one kept
    record = compress_model(fitted_run, CompressionSettings(bits=BitDepths.parse(["5"]), finetune_steps=10,
                                                        prune_fraction=0.25), tmp_path / "p.cvq")
    count = load_model(fitted_run / "model.safetensors")[0].count
    assert record["finetune_kept"] and record["num_primitives"] == round(0.75 * count)
    assert read_compressed(tmp_path / "p.cvq").primitives.count == record["num_primitives"]


@pytest.mark.parametrize("arguments, message", [
    (["--prune", "1.5", "--finetune", "2"], "--prune 1.5: give the fraction of primitives to remove"),
    (["--prune", "-0.1", "--finetune", "2"], "--prune -0.1: give the fraction"),
    (["--prune", "0.2"], "--prune 0.2 needs --finetune > 0"),
])
def test_bad_prune_is_one_line_exit_2_and_writes_nothing(model_file, tmp_path, arguments, message, capsys):
    out = tmp_path / "x.cvq"
    assert main(["compress", str(model_file), "--out", str(out), *arguments]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.slow
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
def test_bad_files_fail_cleanly_and_write_nothing(model_file, tmp_path, kind, command, capsys):
    primitives, config = load_model(model_file)
    data, message = _bad_files(encode(primitives, config, BitDepths.parse(["6"])))[kind]
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
def test_bad_compress_options_fail_cleanly(model_file, arguments, message, capsys):
    folder = model_file.parent
    before = sorted(p.name for p in folder.iterdir())
    assert main([a.format(run=folder) for a in arguments]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.strip().splitlines()) == 1
    assert sorted(p.name for p in folder.iterdir()) == before


def test_unknown_option_exits_2(model_file, capsys):
    assert main(["compress", str(model_file), "--level", "3"]) == 2
    error = capsys.readouterr().err
    assert "unrecognized arguments: --level" in error and error.count("\n") == 1


@pytest.mark.slow
def test_a_bare_model_file_is_scored_against_its_own_reconstruction(fitted_run, tmp_path, capsys):
    bare = tmp_path / "bare.safetensors"
    bare.write_bytes((fitted_run / "model.safetensors").read_bytes())
    assert main(["compress", str(bare), "--max-drop", "0.5"]) == 0
    shown = capsys.readouterr().out
    assert "against the float model's own reconstruction" in shown and "estimated for a fit at 30 dB" in shown
    assert (tmp_path / "bare.cvq").is_file()


@pytest.mark.slow
def test_rate_distortion_points_and_bd_rate():
    pytest.importorskip("imagecodecs")
    from cvqpg.campaign.ratedistortion import anchor_points, bd_rate, rd_points

    config = FitConfig.create(width=48, height=32, color="gray", ratio=0.3, guard_band_px=32)
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


# A grayscale single-plane fit with 216 primitives: its float file at the default depths takes about 7 bpp
TINY_FIT = ["fit", "--scene", "star", "--size", str(W), str(H), "--ratio", "0.5", "--steps", "20", "--quiet"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("rate") / "run"
    assert main([*TINY_FIT, "--out", str(out)]) == 0
    return out


def one_line_error(capsys) -> str:
    error = capsys.readouterr().err
    assert len(error.strip().splitlines()) == 1 and "Traceback" not in error, error
    return error


@pytest.mark.slow
@pytest.mark.parametrize("bpp", [2.5, 3.5, 5.0, 6.5])
def test_the_file_never_exceeds_the_budget_and_lands_within_5_percent_below_it(run, tmp_path, bpp):
    out = tmp_path / "m.cvq"
    record = compress_model(run, CompressionSettings(bpp=bpp, finetune_steps=3), out)
    max_bytes = W * H * bpp // 8
    assert record["max_bytes"] == max_bytes
    assert 0.95 * max_bytes <= out.stat().st_size == record["bytes"] <= max_bytes
    assert record["bits_per_pixel"] <= bpp
    fitted = load_model(run / "model.safetensors")[0].count
    assert read_compressed(out).primitives.count == record["num_primitives"] <= fitted


@pytest.mark.slow
def test_a_budget_beyond_the_whole_model_at_the_finest_depths_gets_that_file(run, tmp_path):
    record = compress_model(run, CompressionSettings(bpp=64.0, finetune_steps=0), tmp_path / "m.cvq")
    assert record["num_primitives"] == load_model(run / "model.safetensors")[0].count
    assert record["bits"] == LADDER[-1].coded() == {"position": 8, "scale": 16, "rotation": 16, "amplitude": 16,
                                                    "phase": 16, "curvature": 16}
    assert record["bytes"] < 0.95 * W * H * 64 / 8  # the one case where the file lands further below


@pytest.mark.slow
def test_max_bytes_through_the_command_line_as_info_reports_it(run, tmp_path, capsys):
    out = tmp_path / "m.cvq"
    assert main(["compress", str(run), "--max-bytes", "900", "--finetune", "2", "--out", str(out)]) == 0
    assert "bytes of a budget of 900" in capsys.readouterr().out
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert 0.95 * 900 <= info["file_bytes"] <= 900
    assert info["bits_per_pixel"] == 8 * info["file_bytes"] / (W * H)


@pytest.mark.slow
def test_a_bare_model_file_is_rate_controlled_against_its_own_reconstruction(run, tmp_path):
    loose = tmp_path / "loose.safetensors"
    loose.write_bytes((run / "model.safetensors").read_bytes())
    record = compress_model(loose, CompressionSettings(bpp=4.0))
    assert record["finetune_steps"] == 0 and record["reference"] == "the float model's own reconstruction"
    assert 0.95 * W * H * 4 / 8 <= record["bytes"] <= W * H * 4 / 8
    with pytest.raises(ConfigError, match="`finetune_steps` needs the run folder"):
        compress_model(loose, CompressionSettings(bpp=4.0, finetune_steps=2), tmp_path / "x.cvq")


@pytest.mark.parametrize("budget", [["--bpp", "0.5"], ["--max-bytes", "100"]])
def test_a_budget_below_the_smallest_file_is_one_line_exit_2(model_file, tmp_path, budget, capsys):
    out = tmp_path / "m.cvq"
    assert main(["compress", str(model_file), *budget, "--out", str(out)]) == 2
    error = one_line_error(capsys)
    smallest = smallest_file(*load_model(model_file))
    assert f"{budget[0]} {budget[1]}" in error and f"smallest file the format can write for this model: {smallest} " \
        f"bytes ({8 * smallest / (W * H):.3f} bpp), its header" in error
    assert not out.exists()


@pytest.mark.parametrize("arguments, message", [
    (["--bpp", "3", "--max-drop", "0.1"], "argument --max-drop: not allowed with argument --bpp"),
    (["--max-drop", "0.1", "--bpp", "3"], "argument --bpp: not allowed with argument --max-drop"),
    (["--bpp", "3", "--bits", "8"], "not allowed with argument --bpp"),
    (["--bpp", "3", "--max-bytes", "900"], "not allowed with argument --bpp"),
    (["--bpp", "3", "--finetune", "2", "--prune", "0.1"], "--prune applies to --bits and --max-drop"),
    (["--bpp", "0"], "--bpp 0: give a positive, finite number"),
    (["--bpp", "-2"], "--bpp -2: give a positive, finite number"),
    (["--bpp", "inf"], "--bpp: 'inf' is not a finite number"),
    (["--bpp", "nan"], "--bpp: 'nan' is not a finite number"),
    (["--max-bytes", "0"], "--max-bytes 0: give a positive whole number of bytes"),
    (["--max-bytes", "1e3"], "argument --max-bytes: '1e3' is not a whole number"),
    (["--bpp", "3", "--finetune", "-1"], "--finetune -1: give a number of steps ≥ 0"),
])
def test_bad_rate_options_are_one_line_exit_2_and_write_nothing(model_file, tmp_path, arguments, message, capsys):
    assert main(["compress", str(model_file), *arguments, "--out", str(tmp_path / "m.cvq")]) == 2
    assert message in one_line_error(capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("phase", ["quadratic+tilt", "axes+tilt"])
def test_a_model_with_phase_terms_compresses_decompresses_and_counts_its_parameters(tmp_path, capsys, phase):
    from test_codec import phased_primitives

    primitives, config = phased_primitives(phase)
    model = tmp_path / "model.safetensors"
    save_model(model, primitives, config)
    packed = tmp_path / "model.cvq"
    assert main(["compress", str(model), "--bits", "10", "--out", str(packed)]) == 0
    assert main(["decompress", str(packed), "--out", str(tmp_path / "back.safetensors")]) == 0
    capsys.readouterr()
    unpacked, unpacked_config = load_model(tmp_path / "back.safetensors")
    assert unpacked_config.phase.name == phase and unpacked.terms.keys() == primitives.terms.keys()
    assert mean_psnr(render(unpacked, config)[1], render(primitives, config)[1]) > 35
    for path in (model, packed):
        assert main(["info", str(path), "--json"]) == 0
        info = json.loads(capsys.readouterr().out)
        assert (info["phase"], info["params_per_primitive"]) == (phase, config.params_per_primitive)
    assert info["bits"] == BitDepths(**{name: 10 for name in ("scale", "rotation", "amplitude", "phase", "curvature",
                                                              "axes", "tilt")}).coded(primitives.terms)
    assert main(["info", str(packed)]) == 0
    assert f"{config.params_per_primitive} per primitive, phase {phase}" in capsys.readouterr().out


@pytest.mark.slow
def test_a_fit_with_phase_terms_goes_through_every_command_of_a_cvq_file(tmp_path, capsys):
    """fit, compress within a budget (rate control and fine-tuning), eval and view of the compressed model in its
    run, decompress, and encode straight into a file: each with the phase's terms in the file."""
    run = tmp_path / "run"
    tiny = ["--size", "32", "24", "--color", "gray", "--planes", "1", "--quiet"]
    assert main(["fit", *tiny, "--steps", "8", "--curvature-warmup", "2", "--phase", "axes+tilt", "--out",
                 str(run)]) == 0
    packed = run / "tuned.cvq"
    assert main(["compress", str(run), "--max-bytes", "700", "--finetune", "2", "--out", str(packed)]) == 0
    assert read_compressed(packed).config.phase.name == "axes+tilt" and packed.stat().st_size <= 700
    assert main(["eval", str(packed)]) == 0
    assert json.loads((run / "tuned.metrics.json").read_text())["mean"]["psnr"] > 0
    assert main(["view", str(packed), "--distances", "0.002", "0.004", "2", "--quiet"]) == 0
    assert (run / "tuned.view.html").is_file()
    assert main(["decompress", str(packed), "--out", str(tmp_path / "back.safetensors")]) == 0
    assert load_model(tmp_path / "back.safetensors")[1].phase.name == "axes+tilt"
    encoded = tmp_path / "encoded.cvq"
    assert main(["encode", "--scene", "demo", *tiny, "--steps", "6", "--finetune", "2", "--phase", "quadratic+tilt",
                 "--bpp", "6", "--out", str(encoded)]) == 0
    assert read_compressed(encoded).primitives.terms.keys() == {"tilt"}
    capsys.readouterr()
