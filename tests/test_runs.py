"""Run folders read back: a `config.json` that is missing, damaged or incomplete, and model files checked
against the run folder they are used with."""

import json
import shutil
from pathlib import Path

import pytest

from cvqpg import FitConfig
from cvqpg.cli import main
from cvqpg.errors import InputError, ModelFileError
from cvqpg.primitives import Primitives, activate, init_gaussians
from cvqpg.runs import MODEL_FILE, fit_fingerprint, load_run_model, read_run, run_fit, same_fit, start_run
from cvqpg.storage import model_run, save_model

RUN = FitConfig.create(width=64, height=48, num_gaussians=30, steps=2, guard_band_px=32)
OTHER = RUN.replace(width=32, height=24, color="gray")


def model_of(config: FitConfig) -> Primitives:
    targets = config.targets
    return activate(init_gaussians(config.primitive_count, config.channels, targets.width, targets.height, 1), config)


def run_folder(root: Path, model_config: FitConfig = RUN) -> Path:
    """A run folder of `RUN` (the demo scene) whose model was fitted with `model_config`."""
    folder = start_run(root / "run", RUN, {"scene": "demo"})
    save_model(folder / MODEL_FILE, model_of(model_config), model_config)
    return folder


@pytest.mark.parametrize("change, message", [
    (lambda recorded: "{not json", "config.json is not a readable JSON file"),
    (lambda recorded: [recorded], "config.json holds a JSON list, not an object"),
    (lambda recorded: {k: v for k, v in recorded.items() if k != "targets"}, "config.json lacks targets"),
    (lambda recorded: {k: v for k, v in recorded.items() if k not in ("targets", "config_schema")},
     "config.json lacks width"),
    (lambda recorded: {**recorded, "source": {"depth": "d.png"}}, "names neither a scene nor an image"),
    (lambda recorded: {**recorded, "optics": {"pixel_pitch": 0}}, "`pixel_pitch` must lie in [1e-07, 0.001]"),
    (lambda recorded: {**recorded, "optimisation": {"lr": {"speed": 1}}}, "its settings cannot work"),
    (lambda recorded: {**recorded, "optimisation": {"betas": [0.98, 1.5, 0.99]}}, "`betas[1]` must lie in"),
])
def test_a_damaged_config_json_is_an_input_error_naming_the_file(tmp_path, change, message):
    folder = run_folder(tmp_path)
    changed = change(json.loads((folder / "config.json").read_text()))
    (folder / "config.json").write_text(changed if isinstance(changed, str) else json.dumps(changed))
    with pytest.raises(InputError, match="restore the file or fit the run again") as refused:
        read_run(folder)
    assert message in str(refused.value) and str(folder / "config.json") in str(refused.value)


def test_a_folder_without_config_json_is_not_a_run_folder(tmp_path):
    with pytest.raises(InputError, match=f"{tmp_path} is not a run folder"):
        read_run(tmp_path)


def test_a_model_of_the_run_s_targets_is_accepted(tmp_path):
    folder = run_folder(tmp_path, RUN.replace(num_gaussians=20, primitive="flat"))
    primitives, config, source = load_run_model(folder)
    assert primitives.count == 20 and config.primitives.kind == "flat" and source == {"scene": "demo"}


def test_a_model_of_other_optics_names_them(tmp_path):
    folder = run_folder(tmp_path, RUN.replace(pixel_pitch=2e-6))
    with pytest.raises(ModelFileError) as refused:
        load_run_model(folder)
    assert str(refused.value) == (
        f"{folder / MODEL_FILE} was fitted for 64×48 px, 2 µm pitch, 639/532/473 nm, planes at 1, 5 mm, the run "
        f"folder {folder} is 64×48 px, 3.74 µm pitch, 639/532/473 nm, planes at 1, 5 mm: use it with its own run "
        "folder")


@pytest.mark.parametrize("command", [["eval", "{model}"], ["export", "{model}"], ["compress", "{model}"],
                                     ["eval", "{run}"], ["render", "{run}"], ["info", "{run}", "--half"],
                                     ["view", "{run}", "--quiet"]])
def test_a_model_fitted_for_other_targets_is_refused_in_one_line(tmp_path, command, capsys):
    own = command[1] == "{run}"
    folder = run_folder(tmp_path, OTHER if own else RUN)
    model = folder / (MODEL_FILE if own else "other.safetensors")
    if not own:
        save_model(model, model_of(OTHER), OTHER)
    before = sorted(folder.rglob("*"))
    assert main([a.format(run=folder, model=model) for a in command]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "Traceback" not in error
    assert (f"{model} was fitted for 32×24 gray, the run folder {folder} is 64×48 rgb: use it with its own run "
            "folder") in error
    assert sorted(folder.rglob("*")) == before


def test_the_history_keeps_every_kth_step_and_the_last_with_its_share_of_the_seconds(tmp_path):
    from cvqpg.runs import HISTORY_ROWS, read_history, save_history

    updates = 2 * HISTORY_ROWS + 3
    history = {"loss": [1.0 / (s + 1) for s in range(updates)], "psnr": [10.0 + s / 100 for s in range(updates)]}
    save_history(history, 60.0, tmp_path / "history.csv")
    table = read_history(tmp_path / "history.csv")
    assert list(table["step"][:3]) == [0, 3, 6] and table["step"][-1] == updates - 1
    assert len(table["step"]) <= HISTORY_ROWS + 1
    assert table["seconds"][-1] == pytest.approx(60.0) and table["seconds"][0] == pytest.approx(60.0 / updates, abs=1e-3)
    assert table["psnr"][1] == pytest.approx(10.03) and table["loss"][2] == pytest.approx(1 / 7, rel=1e-5)



def test_a_model_records_its_fit_and_another_run_s_model_of_the_same_targets_is_refused(finished_run, tmp_path):
    """A model that `write_run` saves records the fit it came from: in a run folder of the same size and optics
    but other settings (another seed) it is refused; a model without the record (an earlier version's) is not."""
    first = finished_run  # read only
    recorded = model_run(first / MODEL_FILE)
    assert same_fit(recorded, run_fit(first)) and recorded["source"] == {"scene": "demo"}
    twin = start_run(tmp_path / "twin", read_run(first)[0].replace(seed=7), {"scene": "demo"})
    shutil.copy(first / MODEL_FILE, twin / MODEL_FILE)
    with pytest.raises(ModelFileError, match="was fitted in another run"):
        load_run_model(twin)
    primitives, config, _ = load_run_model(first)
    save_model(twin / MODEL_FILE, primitives, config)  # no record: accepted as before
    assert load_run_model(twin)[0].count == primitives.count


def test_a_compressed_model_carries_its_fit_s_fingerprint_and_another_run_refuses_it(finished_run, tmp_path, capsys):
    """`cvqpg compress` writes the fit fingerprint of the model into the file; with a run folder of the same size and
    optics but another fit it is refused in one line (exit 2), with its own run it is read."""
    from cvqpg.codec import file_fingerprint
    from cvqpg.runs import fingerprint_digest

    first = tmp_path / "first"
    shutil.copytree(finished_run, first)
    assert main(["compress", str(first), "--bits", "6"]) == 0
    packed = first / "model.cvq"
    assert file_fingerprint(packed.read_bytes()) == fingerprint_digest(run_fit(first)) is not None
    assert load_run_model(first, packed)[0].count == load_run_model(first)[0].count
    twin = start_run(tmp_path / "twin", read_run(first)[0].replace(seed=7), {"scene": "demo"})
    shutil.copy(packed, twin / "model.cvq")
    capsys.readouterr()
    assert main(["eval", str(twin / "model.cvq")]) == 2
    error = capsys.readouterr().err.strip()
    assert "was fitted in another run" in error and "\n" not in error


def test_a_run_s_own_model_must_hold_the_n_of_its_metrics(tmp_path):
    folder = run_folder(tmp_path)
    (folder / "metrics.json").write_text(json.dumps({"num_gaussians": 31}))
    with pytest.raises(ModelFileError, match="holds 30 primitives, the run's metrics.json records a fit of 31"):
        load_run_model(folder)
    (folder / "metrics.json").write_text(json.dumps({"num_gaussians": 30}))
    assert load_run_model(folder)[0].count == 30


def test_fits_that_later_settings_leave_as_they_were_keep_the_fingerprints_0_3_0_gave_them():
    """`tests/data/fit_digests_0.3.0.json`: configurations (and the records of every earlier schema) with the
    `.cvq` fingerprint digests cvqpg 0.3.0 computed of them, so that its files keep binding to their runs."""
    from cvqpg.runs import fingerprint_digest
    cases = json.loads((Path(__file__).parent / "data" / "fit_digests_0.3.0.json").read_text())
    for name, case in cases.items():
        config = FitConfig.from_dict(case["config"])
        assert fingerprint_digest(fit_fingerprint(config, case["source"])).hex() == case["digest"], name
    from cvqpg.display import Display
    dpac = FitConfig.from_dict(cases["default"]["config"]).replace(display=Display.create("dpac"))
    assert fingerprint_digest(fit_fingerprint(dpac, {})) != fingerprint_digest(
        fit_fingerprint(FitConfig.from_dict(cases["default"]["config"]), {}))
