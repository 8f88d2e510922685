"""`--depth auto`: the plumbing around Depth Anything V2, with a tiny random network of the same
architecture (nothing is downloaded): size, 0 = near, the saved map, and the offline error."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

import cvqpg
from cvqpg import cli
from cvqpg.runs import read_run
from cvqpg.depth import (DEPTH_LEVELS, DepthModel, DepthModelError, depth_from_disparity, estimate_depth,
                         load_depth_model)

REPO = Path(cvqpg.__file__).resolve().parent.parent


def tiny_depth_anything() -> DepthModel:
    """Depth Anything's architecture (DINOv2 backbone, DPT neck and head) at a few thousand parameters."""
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config, DPTImageProcessor

    torch.manual_seed(0)
    backbone = Dinov2Config(hidden_size=16, num_hidden_layers=4, num_attention_heads=2, intermediate_size=32,
                            patch_size=14, image_size=56, out_features=["stage1", "stage2", "stage3", "stage4"],
                            reshape_hidden_states=False)
    config = DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=16, patch_size=14,
                                 neck_hidden_sizes=[8, 8, 8, 8], fusion_hidden_size=8, head_hidden_size=4)
    processor = DPTImageProcessor(size={"height": 56, "width": 56}, keep_aspect_ratio=True, ensure_multiple_of=14,
                                  do_pad=False)
    return DepthModel(DepthAnythingForDepthEstimation(config).eval(), processor, "tiny-depth-anything")


@pytest.fixture(scope="module")
def model():
    return tiny_depth_anything()


@pytest.fixture
def photo(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "photo.png"
    Image.fromarray(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)).save(path)
    return path


def test_larger_disparity_is_nearer():
    disparity = torch.tensor([[4.0, 2.0], [1.0, 0.0]])
    assert depth_from_disparity(disparity).tolist() == [[0.0, 0.5], [0.75, 1.0]]
    assert depth_from_disparity(torch.full((2, 2), 3.0)).eq(0).all()


def test_map_has_the_image_size_spans_the_range_and_puts_the_largest_disparity_at_zero(model, photo):
    depth = estimate_depth(photo, model)
    assert depth.size == (40, 30) and depth.mode == "I;16"
    values = np.asarray(depth)
    assert values.min() == 0 and values.max() == DEPTH_LEVELS
    inputs = model.processor(images=Image.open(photo).convert("RGB"), return_tensors="pt")
    with torch.no_grad():
        disparity = model.network(**inputs).predicted_depth
    assert disparity.shape[-2:] != (30, 40)  # the network's own grid: the map was resized to the image
    resized = F.interpolate(disparity[:, None], size=(30, 40), mode="bilinear", align_corners=False)[0, 0].numpy()
    assert values.flat[resized.argmax()] == 0 and values.flat[resized.argmin()] == DEPTH_LEVELS


@pytest.mark.slow
def test_fit_with_depth_auto_saves_the_map_and_repeats_with_it(model, photo, tmp_path, monkeypatch):
    monkeypatch.setattr(cvqpg.depth, "load_depth_model", lambda name: model)
    small = ["--size", "48", "36", "--steps", "1", "--quiet"]
    assert cli.main(["fit", str(photo), "--depth", "auto", *small, "--out", str(tmp_path / "auto")]) == 0
    saved = tmp_path / "auto" / "depth.png"
    assert Image.open(saved).size == (40, 30)
    source = json.loads((tmp_path / "auto" / "config.json").read_text())["source"]
    assert source["depth"] == "depth.png" and source["depth_model"] == cvqpg.depth.DEPTH_MODEL  # inside the run
    assert read_run(tmp_path / "auto")[1]["depth"] == str(saved)
    assert cli.main(["fit", str(photo), "--depth", str(saved), *small, "--out", str(tmp_path / "again")]) == 0
    for plane in ("target_plane0.png", "target_plane1.png"):
        assert np.array_equal(np.asarray(Image.open(tmp_path / "auto" / plane)),
                              np.asarray(Image.open(tmp_path / "again" / plane)))


def test_without_transformers_the_error_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "transformers", None)
    with pytest.raises(DepthModelError, match=r"pip install 'cvqpg\[depth\]'"):
        load_depth_model()


@pytest.mark.slow
def test_offline_without_cached_weights_fails_in_one_line_and_writes_nothing(photo, tmp_path):
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf"), "PYTHONPATH": str(REPO)}
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "cvqpg.cli", "fit", str(photo), "--depth", "auto", "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert "cvqpg[depth]" in done.stderr and str(tmp_path / "hf" / "hub") in done.stderr
    assert not out.exists()


def test_weights_neither_cached_nor_downloadable_are_one_error_at_once(monkeypatch):
    """Offline (the Hub does not answer), a model not in the cache is one error, and nothing is downloaded."""
    monkeypatch.setattr(cvqpg.depth, "hub_reachable", lambda: False)
    with pytest.raises(DepthModelError, match="not in the Hugging Face cache"):
        load_depth_model("cvqpg-tests/no-such-model")
