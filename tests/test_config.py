"""FitConfig: every enumerated setting is checked with a message naming it and its choices; numbers
must be finite; the curvature warm-up follows the steps; recorded names of earlier versions load."""

from __future__ import annotations

import math

import pytest

from cvqpg import ConfigError, CvqpgError, FitConfig
from cvqpg.config import BACKENDS, BOUNDS, COLORS, CURVATURES, PRIMITIVES, QPFS

ENUMERATED = {"color": COLORS, "primitive": PRIMITIVES, "bound": BOUNDS, "qpf": QPFS, "curvature": CURVATURES,
              "backend": BACKENDS}


@pytest.mark.parametrize("name", sorted(ENUMERATED))
@pytest.mark.parametrize("bad", ["upper", "typo", "empty", "none"])
def test_every_bad_value_of_an_enumerated_setting_is_refused_listing_the_choices(name, bad):
    good = ENUMERATED[name][-1]
    value = {"upper": good.upper(), "typo": good + "s", "empty": "", "none": None}[bad]
    with pytest.raises(ConfigError) as error:
        FitConfig(**{name: value}).validate()
    message = str(error.value)
    assert f"`{name}`" in message and all(repr(choice) in message for choice in ENUMERATED[name])
    assert "\n" not in message and isinstance(error.value, CvqpgError)


@pytest.mark.parametrize("device", ["gpu", "CUDA", "", "mps"])
def test_an_unknown_device_is_refused(device):
    with pytest.raises(ConfigError, match="`device`"):
        FitConfig(device=device).validate()


@pytest.mark.parametrize("name", ["ratio", "pixel_pitch", "plane_center", "plane_span", "eta", "ssim_weight"])
@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan])
def test_non_finite_numbers_are_refused(name, value):
    with pytest.raises(ConfigError, match=f"`{name}`"):
        FitConfig(**{name: value}).validate()


@pytest.mark.parametrize("name", ["ssim_weight", "focus_weight", "product_weight"])
def test_negative_loss_weights_are_refused(name):
    with pytest.raises(ConfigError, match=f"`{name}` must be 0 or more"):
        FitConfig(**{name: -0.5}).validate()


@pytest.mark.parametrize("changes", [{"steps": 2.5}, {"num_planes": True}, {"width": "640"}, {"num_gaussians": 1.5}])
def test_counts_must_be_whole_numbers(changes):
    with pytest.raises(ConfigError, match=f"`{next(iter(changes))}`"):
        FitConfig(**changes).validate()


def test_the_curvature_warm_up_defaults_to_the_papers_share_of_the_steps():
    assert FitConfig().curvature_warmup_steps == 400
    assert FitConfig(steps=300).validate().curvature_warmup_steps == 60
    assert FitConfig(steps=300).replace(steps=3000).curvature_warmup_steps == 600
    assert FitConfig(steps=300, curvature_warmup=7).curvature_warmup_steps == 7
    with pytest.raises(ConfigError, match="`curvature_warmup` 400 must lie in 0..`steps`"):
        FitConfig(steps=300, curvature_warmup=400).validate()


def test_configurations_recorded_under_earlier_names_load():
    recorded = {**FitConfig().to_dict(), "warmup": 123, "propagation": "auto"}
    del recorded["curvature_warmup"]
    recorded["lr"] = {**recorded["lr"], "color": 0.5}
    del recorded["lr"]["amplitude"]
    config = FitConfig.from_dict(recorded)
    assert config.curvature_warmup == 123 and config.lr.amplitude == 0.5


@pytest.mark.parametrize(("backend", "device", "kept"), [("numba", "cuda", "auto"), ("triton", "cpu", "auto"),
                                                         ("torch", "cuda", "torch"), ("numba", "cpu", "numba"),
                                                         ("triton", "cuda:1", "triton")])
def test_a_config_moved_to_another_device_keeps_a_backend_only_where_it_runs(backend, device, kept):
    moved = FitConfig(backend=backend).on_device(device)
    assert (moved.device, moved.backend) == (device, kept)
