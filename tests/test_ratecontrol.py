"""Rate control: `cvqpg compress --bpp/--max-bytes` and `cvqpg encode` write a `.cvq` file that never exceeds
its budget and lands within 5% below it; budgets that cannot work are one line and exit code 2."""

import json
import signal
from dataclasses import asdict

import numpy as np
import pytest
import torch
from PIL import Image

from cvqpg import FitConfig
from cvqpg import cli, ratecontrol
from cvqpg.cli import main
from cvqpg.codec import BitDepths, encode, quantise, range_holders
from cvqpg.compression import kept, reference_for, strongest_first, trial
from cvqpg.errors import ConfigError
from cvqpg.primitives import activate, init_gaussians
from cvqpg.ratecontrol import (CLOSE, RUNGS, Budget, compress_to_budget, largest_fitting, primitives_for_budget,
                               _finer_while_fitting, rate_control, smallest_file, stand_in)
from cvqpg.storage import load_model, read_compressed

W, H = 48, 36
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


@pytest.mark.parametrize("bpp", [2.5, 3.5, 5.0, 6.5])
def test_the_file_never_exceeds_the_budget_and_lands_within_5_percent_below_it(run, tmp_path, bpp):
    out = tmp_path / "m.cvq"
    record = compress_to_budget(run, out, bpp=bpp, finetune_steps=3)
    max_bytes = W * H * bpp // 8
    assert record["max_bytes"] == max_bytes
    assert 0.95 * max_bytes <= out.stat().st_size == record["bytes"] <= max_bytes
    assert record["bits_per_pixel"] <= bpp
    assert read_compressed(out).primitives.count == record["num_primitives"] <= load_model(run / "model.safetensors")[0].count


def test_every_primitive_filled_up_to_the_budget_is_a_candidate_even_where_its_rung_lands_far_below():
    config = FitConfig(width=W, height=H, ratio=0.5).validate()
    primitives = stand_in(config, config.primitive_count)  # all about equally strong: pruning costs most
    reference = reference_for(primitives, config, None)
    sizes = [len(encode(primitives, config, bits)) for bits in RUNGS[:3]]
    budget = Budget(round(sizes[1] + 0.6 * (sizes[2] - sizes[1])), "a budget between two rungs")
    assert sizes[1] < CLOSE * budget.max_bytes  # rung 1 lands more than 5% below the budget
    filled = _finer_while_fitting(primitives, config, reference, budget, trial(primitives, config, RUNGS[1], reference),
                                  check_stop=lambda: None)
    assert filled.decoded.count == primitives.count and len(filled.data) >= CLOSE * budget.max_bytes
    chosen = rate_control(primitives, config, reference, budget).choice
    assert len(chosen.data) <= budget.max_bytes and chosen.psnr >= filled.psnr  # pruned rungs score ~4 dB less


def test_a_budget_beyond_the_whole_model_at_the_finest_depths_gets_that_file(run, tmp_path):
    record = compress_to_budget(run, tmp_path / "m.cvq", bpp=64.0, finetune_steps=0)
    assert record["num_primitives"] == load_model(run / "model.safetensors")[0].count
    assert record["bits"] == asdict(RUNGS[-1]) == {"position": 8, "scale": 16, "rotation": 16, "amplitude": 16,
                                                   "phase": 16, "curvature": 16}
    assert record["bytes"] < 0.95 * W * H * 64 / 8  # the one case where the file lands further below


def test_max_bytes_through_the_command_line_as_info_reports_it(run, tmp_path, capsys):
    out = tmp_path / "m.cvq"
    assert main(["compress", str(run), "--max-bytes", "900", "--finetune", "2", "--out", str(out)]) == 0
    assert "bytes of a budget of 900" in capsys.readouterr().out
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert 0.95 * 900 <= info["file_bytes"] <= 900
    assert info["bits_per_pixel"] == 8 * info["file_bytes"] / (W * H)


def test_a_bare_model_file_is_rate_controlled_against_its_own_reconstruction(run, tmp_path):
    loose = tmp_path / "loose.safetensors"
    loose.write_bytes((run / "model.safetensors").read_bytes())
    record = compress_to_budget(loose, bpp=4.0)
    assert record["finetune_steps"] == 0 and record["reference"] == "the float model's own reconstruction"
    assert 0.95 * W * H * 4 / 8 <= record["bytes"] <= W * H * 4 / 8
    with pytest.raises(ConfigError, match="`finetune_steps` needs the run folder"):
        compress_to_budget(loose, tmp_path / "x.cvq", bpp=4.0, finetune_steps=2)


@pytest.mark.parametrize("budget", [["--bpp", "0.5"], ["--max-bytes", "100"]])
def test_a_budget_below_the_smallest_file_is_one_line_exit_2(run, tmp_path, budget, capsys):
    out = tmp_path / "m.cvq"
    assert main(["compress", str(run), *budget, "--out", str(out)]) == 2
    error = one_line_error(capsys)
    smallest = smallest_file(load_model(run / "model.safetensors")[0], load_model(run / "model.safetensors")[1])
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
    (["--max-bytes", "1e3"], "argument --max-bytes: invalid int value"),
    (["--bpp", "3", "--finetune", "-1"], "--finetune -1: give a number of steps ≥ 0"),
])
def test_bad_rate_options_are_one_line_exit_2_and_write_nothing(run, tmp_path, arguments, message, capsys):
    assert main(["compress", str(run), *arguments, "--out", str(tmp_path / "m.cvq")]) == 2
    assert message in one_line_error(capsys)
    assert list(tmp_path.iterdir()) == []


def test_largest_fitting_finds_the_boundary_even_where_sizes_are_not_monotonic():
    sizes = [0, 10, 20, 30, 29, 50, 60]  # entropy coding can make a larger model a few bytes smaller
    assert largest_fitting(sizes.__getitem__, 35, 6) == 4
    assert largest_fitting(sizes.__getitem__, 100, 6) == 6
    assert largest_fitting(sizes.__getitem__, 9, 6) == 0
    assert largest_fitting(sizes.__getitem__, 10, 6) == 1


def test_largest_fitting_stops_where_the_successor_does_not_fit_on_any_sizes():
    generator = torch.Generator().manual_seed(0)
    for _ in range(200):
        top = int(torch.randint(2, 400, (1,), generator=generator))
        steps = torch.randint(-3, 40, (top,), generator=generator)
        sizes = [0, *(100 + torch.cumsum(steps, 0)).tolist()]
        max_bytes = int(torch.randint(90, max(sizes) + 20, (1,), generator=generator))
        count = largest_fitting(sizes.__getitem__, max_bytes, top)
        if count == 0:
            assert sizes[1] > max_bytes
        elif count < top:
            assert sizes[count] <= max_bytes < sizes[count + 1]


def test_largest_fitting_needs_few_encodes_where_sizes_grow_about_linearly():
    probes = []

    def size(count: int) -> int:
        probes.append(count)
        return 700 + 52 * count + (count * 7919) % 13  # a header, bytes per primitive, coding noise

    count = largest_fitting(size, 400_000, 30_000)
    assert size(count) <= 400_000 < size(count + 1)
    assert len(probes) - 2 <= 8  # a bisection over 30,000 counts takes 17


def test_a_bpp_budget_is_whole_bytes_of_8_bytes_per_pixel():
    config = FitConfig(width=W, height=H)
    assert Budget.of(config, bpp=1.0).max_bytes == W * H // 8
    assert Budget.of(config, bpp=0.999).max_bytes == W * H // 8 - 1  # never rounded up past the budget
    assert Budget.of(config, max_bytes=777).max_bytes == 777
    with pytest.raises(ConfigError, match="give one budget"):
        Budget.of(config, bpp=1.0, max_bytes=777)


def test_dropping_primitives_other_than_the_range_holders_keeps_the_file_s_bins():
    config = FitConfig(width=W, height=H, color="rgb", ratio=0.3)
    raw = init_gaussians(config.primitive_count, 3, W, H, seed=5)
    raw.amplitude.uniform_(-1, 1, generator=torch.Generator().manual_seed(5))
    primitives = activate(raw, config)
    order = strongest_first(primitives, first=range_holders(primitives))
    assert set(order[:len(range_holders(primitives))].tolist()) == set(range_holders(primitives).tolist())
    few = kept(primitives, order, 5)
    assert quantise(few, config, BitDepths()).ranges == quantise(primitives, config, BitDepths()).ranges


def test_the_primitive_count_for_a_budget_fills_it_at_the_default_depths_with_headroom():
    config = FitConfig(width=64, height=48, color="gray", num_planes=1)
    counts = [primitives_for_budget(config, size) for size in (1000, 2000, 4000)]
    assert counts == sorted(counts) and counts[0] >= 1
    # the stand-in model of the estimate, less the headroom, takes about the budget
    assert len(encode(stand_in(config, round(counts[1] / 1.2)), config, BitDepths())) == pytest.approx(2000, rel=0.1)
    assert primitives_for_budget(config, 10**9) == 64 * 48


def test_encode_splits_a_table_1_fits_steps_into_float_and_quantisation_aware_ones_in_proportion():
    from cvqpg.ratecontrol import ENCODE_FINETUNE_STEPS, ENCODE_STEPS, encode_steps

    assert encode_steps(2000) == (ENCODE_STEPS, ENCODE_FINETUNE_STEPS) == (1500, 600)
    assert encode_steps(200) == (150, 60) and encode_steps(1) == (1, 0)


@pytest.fixture(scope="module")
def picture(tmp_path_factory):
    path = tmp_path_factory.mktemp("picture") / "ramp.png"
    y, x = np.mgrid[0:H, 0:W]
    Image.fromarray(np.stack([x * 5, y * 7, (x + y) * 3], axis=-1).astype(np.uint8)).save(path)
    return path


ENCODE = ["encode", "--size", str(W), str(H), "--color", "gray", "--planes", "1", "--steps", "5", "--finetune", "2"]


def test_encode_writes_one_file_within_the_budget_that_decompress_and_info_read(picture, tmp_path, capsys):
    out = tmp_path / "ramp.cvq"
    assert main([*ENCODE, str(picture), "--bpp", "4", "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ramp.cvq"]
    assert 0.95 * W * H * 4 / 8 <= out.stat().st_size <= W * H * 4 / 8
    assert main(["info", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["bits_per_pixel"] <= 4
    assert main(["decompress", str(out), "--out", str(tmp_path / "ramp.safetensors")]) == 0
    assert load_model(tmp_path / "ramp.safetensors")[0].count == read_compressed(out).primitives.count
    before = out.read_bytes()
    assert main([*ENCODE, str(picture), "--bpp", "4", "--out", str(out), "--quiet"]) == 2
    assert "exists" in one_line_error(capsys) and out.read_bytes() == before


# The stop request is asked before each of the fit's 13 steps, then before each rung, each round of finer bit
# depths and after each tuning step's render: 5 calls stop the fit before step 5, 13 rate control before its first
# rung, 13 + rungs its first round of finer depths, and one call before the whole run's last its last tuning step.
@pytest.mark.parametrize("calls, stopped", [(5, "stopped before step 5"),
                                            (13, "stopped during rate control, after the fit's last step"),
                                            (13 + len(RUNGS), "stopped during rate control, after the fit's last step"),
                                            (-1, "stopped during rate control, after the fit's last step")])
def test_a_stopped_encode_resumes_from_its_checkpoint_to_the_same_file(picture, tmp_path, monkeypatch, capsys, calls,
                                                                      stopped):
    command = [*ENCODE, str(picture), "--bpp", "4", "--quiet", "--steps", "12"]
    whole = tmp_path / "whole" / "ramp.cvq"
    whole.parent.mkdir()
    asked, stop_after = [], []  # no stop while `stop_after` is empty

    class StopAfterSomeCalls(cli.StopRequest):
        def __call__(self) -> bool:
            asked.append(True)
            self.signals = [signal.SIGINT] if stop_after and len(asked) > stop_after[0] else []
            return bool(self.signals)

    monkeypatch.setattr(cli, "StopRequest", StopAfterSomeCalls)
    assert main([*command, "--out", str(whole)]) == 0
    assert len(asked) > 13 + len(RUNGS) + 1  # the whole encode asked in a round of finer depths and while tuning
    stop_after.append(calls if calls >= 0 else len(asked) + calls)
    asked.clear()
    tried = []
    monkeypatch.setattr(ratecontrol, "trial", lambda *args: tried.append(args) or trial(*args))
    out, work = tmp_path / "ramp.cvq", tmp_path / "ramp.cvq.partial"
    assert main([*command, "--out", str(out)]) == 128 + signal.SIGINT
    assert len(asked) == stop_after[0] + 1
    assert calls != 13 + len(RUNGS) or len(tried) <= len(RUNGS)  # stopped before any file of finer depths
    assert f"{stopped}; checkpoint saved. Continue with: cvqpg encode --resume {work}" in one_line_error(capsys)
    assert not out.exists() and sorted(p.name for p in work.iterdir()) == ["budget.json", "checkpoint.pt", "config.json"]
    assert main([*command, "--out", str(out)]) == 2  # the same encode again is told where its work is
    assert f"{work} holds an interrupted encode; continue it with cvqpg encode --resume {work}" in one_line_error(capsys)
    monkeypatch.undo()
    assert main(["encode", "--resume", str(work), "--quiet"]) == 0
    assert out.read_bytes() == whole.read_bytes() and not work.exists()


@pytest.mark.parametrize("checkpointed", [False, True])
def test_a_failed_encode_keeps_its_folder_only_where_a_checkpoint_is_worth_resuming(picture, tmp_path, monkeypatch,
                                                                                   capsys, checkpointed):
    work = tmp_path / "ramp.cvq.partial"

    def failing(folder, *args, **kwargs):
        if checkpointed:
            (folder / "checkpoint.pt").write_bytes(b"")
        raise RuntimeError("a failure after the fit started")

    monkeypatch.setattr("cvqpg.app.runner.encode_in_folder", failing)
    assert main([*ENCODE, str(picture), "--bpp", "4", "--out", str(tmp_path / "ramp.cvq"), "--quiet"]) == 1
    error = capsys.readouterr().err
    assert "internal error (RuntimeError: a failure after the fit started)" in error
    assert (f"failed; the fit's last checkpoint is kept: cvqpg encode --resume {work}" in error) == checkpointed
    assert sorted(p.name for p in tmp_path.iterdir()) == (["ramp.cvq.partial"] if checkpointed else [])


def test_encode_needs_a_file_to_write_and_resumes_only_an_encodes_folder(picture, tmp_path, capsys):
    assert main([*ENCODE, str(picture), "--bpp", "4"]) == 2
    assert "give the .cvq file to write with --out FILE" in one_line_error(capsys)
    assert main(["encode", "--resume", str(tmp_path)]) == 2
    assert "holds no encode (no budget.json)" in one_line_error(capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("arguments, message", [
    (["--bpp", "0.5"], "--bpp 0.5 (108 bytes for 48×36 px) is below the smallest file the format can write"),
    (["--bpp", "nan"], "--bpp: 'nan' is not a finite number"),
    (["--bpp", "-1"], "--bpp -1: give a positive"),
    (["--max-bytes", "0"], "--max-bytes 0: give a positive"),
    (["--bpp", "4", "--max-drop", "0.1"], "unrecognized arguments: --max-drop"),
    (["--bpp", "4", "--out", "{picture}", "--overwrite"], "is this command's own input"),
    ([], "one of the arguments --bpp --max-bytes is required"),
])
def test_encode_refuses_what_cannot_work_in_one_line_before_fitting(picture, tmp_path, arguments, message, capsys):
    arguments = [a.format(picture=picture) for a in arguments]
    out = [] if "--out" in arguments else ["--out", str(tmp_path / "x.cvq")]
    before = picture.read_bytes()
    assert main([*ENCODE, str(picture), *arguments, *out]) == 2
    assert message in one_line_error(capsys)
    assert list(tmp_path.iterdir()) == [] and picture.read_bytes() == before
