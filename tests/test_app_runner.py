"""Fits in a run folder: checkpoints record the run they belong to, and a resume trusts nothing it reads."""

import hashlib
import json
import shutil
from pathlib import Path

import pytest
import torch

from cvqpg import FitConfig
from cvqpg.app.runner import FINGERPRINT_KEY, fit_in_folder, resumed_state
from cvqpg.cli import main
from cvqpg.errors import ModelFileError
from cvqpg.fitting import blank_state
from cvqpg.control import SILENT
from cvqpg.runs import (CHECKPOINT_FILE, CONFIG_FILE, FINGERPRINT_SCHEMA, fit_fingerprint, read_run, read_run_options,
                        scene_from_source, start_run)
from cvqpg.storage import load_checkpoint, save_checkpoint

CONFIG = FitConfig.create(width=32, height=24, num_gaussians=20, steps=2, curvature_warmup=1, guard_band_px=16)
SOURCE = {"scene": "demo"}
DATA = Path(__file__).parent / "data"


@pytest.fixture
def run(tmp_path):
    """A started run folder of `CONFIG` on the demo scene, without a checkpoint."""
    return start_run(tmp_path / "run", CONFIG, SOURCE)


def checkpoint_of(config: FitConfig, fingerprint: object = None) -> dict:
    """The payload of a fresh loop state of `config` at step 1, with `fingerprint` where given."""
    state = blank_state(config)
    state.step = 1
    payload = state.to_payload()
    return payload if fingerprint is None else {**payload, FINGERPRINT_KEY: fingerprint}


def test_checkpoints_record_the_fingerprint_of_the_run(run):
    fit_in_folder(run, scene_from_source(SOURCE, CONFIG), CONFIG, control=SILENT, checkpoint_every_steps=1)
    payload = load_checkpoint(run / CHECKPOINT_FILE)
    assert payload[FINGERPRINT_KEY] == fit_fingerprint(CONFIG, SOURCE)
    assert resumed_state(run, CONFIG).step == payload["step"] > 0


def test_a_checkpoint_written_before_recipes_still_resumes(tmp_path):
    """Versions before recipes fingerprinted configurations without `init` and `density`; their runs fitted
    with the values those fields now record for them."""
    folder = tmp_path / "old"
    folder.mkdir()
    record = {"cvqpg_version": "0.1.0", "source": SOURCE, **json.loads(
        (DATA / "configs" / "vda10437-curvature-warmup.json").read_text()), "num_gaussians": 20, "steps": 2,
        "curvature_warmup": 1, "guard_band_px": 16, "width": 32, "height": 24}
    (folder / CONFIG_FILE).write_text(json.dumps(record))
    settings = {k: v for k, v in record.items() if k not in ("cvqpg_version", "source", "device", "backend")}
    old = hashlib.sha256(json.dumps({"config": settings, "source": SOURCE}, sort_keys=True).encode()).hexdigest()
    config = read_run(folder)[0]
    save_checkpoint(folder / CHECKPOINT_FILE, checkpoint_of(config, old))
    assert resumed_state(folder, config).step == 1
    with pytest.raises(ModelFileError, match="belongs to another run"):
        resumed_state(folder, config.replace(seed=5))


def test_a_checkpoint_of_an_earlier_schema_resumes_and_finishes(tmp_path):
    """A run folder stopped at step 3 by a version from before the loss weights (config.json and checkpoint as it
    wrote them), whose settings lack fields added since: it resumes where it stopped and finishes."""
    folder = tmp_path / "run"
    shutil.copytree(DATA / "checkpoint-69573d2", folder)
    config, source = read_run(folder)
    run = read_run_options(folder)
    assert run.backend == "torch" and config.optimisation.steps == 8 and config.recipe == "paper"
    state = resumed_state(folder, config, run)
    assert state.step == 3 and len(state.history["loss"]) == 3
    result = fit_in_folder(folder, scene_from_source(source, config), config, run, SILENT, state)
    assert len(result.history["loss"]) == 9 and result.history["loss"][:3] == state.history["loss"][:3]


@pytest.mark.parametrize("recorded", [100.0, None])
def test_a_resumed_fit_adds_its_cpu_seconds_to_the_checkpoints_and_an_unmeasured_segment_leaves_none(run, recorded):
    """A checkpoint of a version that did not measure CPU time (no `cpu_seconds`) leaves the fit's unknown."""
    payload = checkpoint_of(CONFIG, fit_fingerprint(CONFIG, SOURCE))
    payload = {**payload, "seconds": 50.0, "cpu_seconds": recorded}
    if recorded is None:
        del payload["cpu_seconds"]
    save_checkpoint(run / CHECKPOINT_FILE, payload)
    result = fit_in_folder(run, scene_from_source(SOURCE, CONFIG), CONFIG, state=resumed_state(run, CONFIG),
                           control=SILENT)
    assert result.seconds > 50.0
    if recorded is None:
        assert result.cpu_seconds is None
    else:
        assert result.cpu_seconds > recorded


def test_a_fit_measures_its_cpu_seconds_beside_its_wall_seconds(run):
    """Both over the same spans: a fit alone on its threads spends CPU time of the order of its wall time."""
    result = fit_in_folder(run, scene_from_source(SOURCE, CONFIG), CONFIG.replace(steps=10), control=SILENT)
    assert 0 < result.cpu_seconds < 1.5 * torch.get_num_threads() * result.seconds + 0.05


def test_the_fingerprint_records_the_settings_and_inputs_with_its_schema(run):
    fingerprint = fit_fingerprint(CONFIG, SOURCE)
    assert fingerprint["schema"] == FINGERPRINT_SCHEMA and FitConfig.from_dict(fingerprint["config"]) == CONFIG
    assert fit_fingerprint(CONFIG.replace(seed=101), SOURCE) != fingerprint
    assert fit_fingerprint(CONFIG, {"scene": "star"}) != fingerprint


def test_a_checkpoint_survives_a_setting_added_after_it_was_written(run):
    fingerprint = fit_fingerprint(CONFIG, SOURCE)
    fingerprint["config"]["loss"].pop("target_noise")
    fingerprint["config"]["optics"]["a_setting_this_version_lacks"] = 1
    save_checkpoint(run / CHECKPOINT_FILE, checkpoint_of(CONFIG, fingerprint))
    assert resumed_state(run, CONFIG, source=SOURCE).step == 1


@pytest.mark.parametrize("fingerprint", [fit_fingerprint(CONFIG.replace(seed=101), SOURCE),
                                         fit_fingerprint(CONFIG, {"scene": "star"})])
def test_a_checkpoint_of_another_run_is_refused(run, fingerprint):
    save_checkpoint(run / CHECKPOINT_FILE, checkpoint_of(CONFIG, fingerprint))
    with pytest.raises(ModelFileError, match="belongs to another run .*: delete it to restart from step 0"):
        resumed_state(run, CONFIG, source=SOURCE)


def test_a_checkpoint_without_fingerprint_is_resumed_where_its_shapes_fit(run):
    save_checkpoint(run / CHECKPOINT_FILE, checkpoint_of(CONFIG))
    assert resumed_state(run, CONFIG, source=SOURCE).step == 1


@pytest.mark.parametrize("other", [CONFIG.replace(num_gaussians=30), CONFIG.replace(color="gray"),
                                   CONFIG.replace(curvature="per-channel")])
def test_a_checkpoint_of_other_shapes_is_refused_cleanly(run, other):
    save_checkpoint(run / CHECKPOINT_FILE, checkpoint_of(other))
    with pytest.raises(ModelFileError, match=f"^{run / CHECKPOINT_FILE} belongs to another run \\(its .* has shape"):
        resumed_state(run, CONFIG, source=SOURCE)


@pytest.mark.parametrize("payload", [{"gaussians": {}}, ["not", "a", "dict"],
                                     {**checkpoint_of(CONFIG), "optimizer": {"state": {}}}])
def test_a_payload_of_other_content_is_refused(run, payload):
    save_checkpoint(run / CHECKPOINT_FILE, payload)
    with pytest.raises(ModelFileError, match="is not a loop state this version wrote .*: delete it to restart"):
        resumed_state(run, CONFIG, source=SOURCE)


def test_resuming_with_another_run_s_checkpoint_is_one_line_and_keeps_it(run, capsys):
    save_checkpoint(run / CHECKPOINT_FILE, checkpoint_of(CONFIG, fit_fingerprint(CONFIG, {"scene": "star"})))
    before = (run / CHECKPOINT_FILE).read_bytes()
    assert main(["fit", "--resume", str(run), "--quiet"]) == 2
    error = capsys.readouterr().err
    assert f"{run / CHECKPOINT_FILE} belongs to another run" in error and error.count("\n") == 1
    assert (run / CHECKPOINT_FILE).read_bytes() == before and torch.load(run / CHECKPOINT_FILE)["step"] == 1
