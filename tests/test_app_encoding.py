"""`cvqpg encode` (`cvqpg.app.encoding`): an image fitted straight into a `.cvq` file within a budget, which an
interrupted encode resumes to the same bytes; budgets that cannot work are one line and exit code 2."""

import json
import signal

import numpy as np
import pytest
from PIL import Image

from cvqpg import FitConfig, search
from cvqpg.app import signals
from cvqpg.app.encoding import ENCODE_HEADROOM, encode_steps, primitives_for_budget, stand_in
from cvqpg.cli import main
from cvqpg.codec import BitDepths, encode
from cvqpg.defaults import ENCODE_FINETUNE_STEPS, ENCODE_STEPS
from cvqpg.search import LADDER, trial
from cvqpg.storage import load_model, read_compressed
from stopping import CountedStop

W, H = 48, 36


def one_line_error(capsys) -> str:
    error = capsys.readouterr().err
    assert len(error.strip().splitlines()) == 1 and "Traceback" not in error, error
    return error


def test_the_primitive_count_for_a_budget_fills_it_at_the_default_depths_with_headroom():
    config = FitConfig.create(width=64, height=48, color="gray", num_planes=1)
    counts = [primitives_for_budget(config, size) for size in (1000, 2000, 4000)]
    assert counts == sorted(counts) and counts[0] >= 1
    # the stand-in model of the estimate, less the headroom, takes about the budget
    without_headroom = round(counts[1] / ENCODE_HEADROOM)
    assert len(encode(stand_in(config, without_headroom), config, BitDepths())) == pytest.approx(2000, rel=0.1)
    assert primitives_for_budget(config, 10**9) == 64 * 48


def test_encode_splits_a_fits_steps_into_float_and_quantisation_aware_ones_in_proportion():
    assert encode_steps(FitConfig().optimisation.steps) == (ENCODE_STEPS, ENCODE_FINETUNE_STEPS)
    tenth = FitConfig().optimisation.steps // 10
    assert encode_steps(tenth) == (round(ENCODE_STEPS / 10), round(ENCODE_FINETUNE_STEPS / 10))
    assert encode_steps(1) == (1, 0)


@pytest.fixture(scope="module")
def picture(tmp_path_factory):
    path = tmp_path_factory.mktemp("picture") / "ramp.png"
    y, x = np.mgrid[0:H, 0:W]
    Image.fromarray(np.stack([x * 5, y * 7, (x + y) * 3], axis=-1).astype(np.uint8)).save(path)
    return path


ENCODE = ["encode", "--size", str(W), str(H), "--color", "gray", "--planes", "1", "--steps", "5", "--finetune", "2"]


@pytest.mark.slow
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


STOPPED = [*ENCODE, "--bpp", "4", "--quiet", "--steps", "12"]
FIT_ASKS = 13  # the stop request is asked before each of the fit's 13 steps


@pytest.fixture(scope="module")
def whole(picture, tmp_path_factory):
    """The encode that the stopped ones resume to, run once without a stop: its file and how often it asked."""
    out = tmp_path_factory.mktemp("whole") / "ramp.cvq"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(signals, "StopRequest", CountedStop)
        CountedStop.asked, CountedStop.after = [], None
        assert main([*STOPPED, str(picture), "--out", str(out)]) == 0
    # asked before each step, each rung and each round of finer depths, and before each tuning step
    assert len(CountedStop.asked) > FIT_ASKS + len(LADDER) + 1
    return out.read_bytes(), len(CountedStop.asked)


# 5 asks stop the fit before step 5, 13 rate control before its first rung, 13 + rungs its first round of finer
# depths, and one ask before the whole run's last its last tuning step.
@pytest.mark.parametrize("asks, stopped", [
    pytest.param(5, "stopped before step 5", marks=pytest.mark.slow),
    pytest.param(FIT_ASKS, "stopped during rate control, after the fit's last step", marks=pytest.mark.slow),
    pytest.param(FIT_ASKS + len(LADDER), "stopped during rate control, after the fit's last step",
                 marks=pytest.mark.slow),
    pytest.param(-1, "stopped during fine-tuning, after the fit's last step", marks=pytest.mark.slow)])
def test_a_stopped_encode_resumes_from_its_checkpoint_to_the_same_file(picture, whole, tmp_path, monkeypatch, capsys,
                                                                      asks, stopped):
    whole_file, whole_asks = whole
    monkeypatch.setattr(signals, "StopRequest", CountedStop)
    monkeypatch.setattr(CountedStop, "asked", [])
    monkeypatch.setattr(CountedStop, "after", asks if asks >= 0 else whole_asks + asks)
    tried = []
    monkeypatch.setattr(search, "trial", lambda *args: tried.append(args) or trial(*args))
    out, work = tmp_path / "ramp.cvq", tmp_path / "ramp.cvq.partial"
    assert main([*STOPPED, str(picture), "--out", str(out)]) == 128 + signal.SIGINT
    assert len(CountedStop.asked) == CountedStop.after + 1
    assert asks != FIT_ASKS + len(LADDER) or len(tried) <= len(LADDER)  # stopped before any file of finer depths
    assert f"{stopped}; checkpoint saved. Continue with: cvqpg encode --resume {work}" in one_line_error(capsys)
    assert not out.exists()
    assert sorted(p.name for p in work.iterdir()) == ["budget.json", "checkpoint.pt", "config.json"]
    assert main([*STOPPED, str(picture), "--out", str(out)]) == 2  # the same encode again is told where its work is
    told = one_line_error(capsys)
    assert f"{work} holds an interrupted encode; continue it with cvqpg encode --resume {work}" in told
    monkeypatch.undo()
    assert main(["encode", "--resume", str(work), "--quiet"]) == 0
    assert out.read_bytes() == whole_file and not work.exists()


@pytest.mark.parametrize("checkpointed", [False, True])
def test_a_failed_encode_keeps_its_folder_only_where_a_checkpoint_is_worth_resuming(picture, tmp_path, monkeypatch,
                                                                                   capsys, checkpointed):
    work = tmp_path / "ramp.cvq.partial"

    def failing(folder, *args, **kwargs):
        if checkpointed:
            (folder / "checkpoint.pt").write_bytes(b"")
        raise RuntimeError("a failure after the fit started")

    monkeypatch.setattr("cvqpg.app.encoding.encode_in_folder", failing)
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
    (["--bpp", "4", "--finetune", "-3"], "--finetune -3: give a number of steps ≥ 0"),
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
