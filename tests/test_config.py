"""FitConfig: settings by concern, every number checked against its range in one message style where a configuration
is made (so one that exists is valid), recipes resolved then, and the records of every earlier version read as the
values they ran with."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest

from cvqpg import ConfigError, CvqpgError, FitConfig
from cvqpg.config import (BOUNDS, CHOICES, COLORS, CURVATURES, FLAT_NAMES, INITS, LONG_RUN_BETAS, MAX_TIME_MINUTES,
                          OPTIONAL, PAPER_BETAS, PRIMITIVES, QPFS, RANGES, SECTION_CLASSES, LearningRates,
                          OptimisationSettings, RunOptions, check_distances, check_time_budget, resolve_backend)

ENUMERATED = {"color": COLORS, "primitive": PRIMITIVES, "bound": BOUNDS, "qpf": QPFS, "curvature": CURVATURES,
              "init": INITS}
CONFIGS = Path(__file__).parent / "data" / "configs"


def made_with(name: str, value: object) -> dict[str, object]:
    """Every way to make a configuration with the setting of flat name `name` at `value`, each a thunk: its section
    constructed, `FitConfig.create`, `FitConfig.replace` and `FitConfig.from_dict` of a record holding it."""
    section, key = FLAT_NAMES[name]
    record = FitConfig.create(steps=30).to_dict()
    record[section][key] = value
    return {"section": lambda: SECTION_CLASSES[section](**{key: value}),
            "create": lambda: FitConfig.create(**{name: value}),
            "replace": lambda: FitConfig.create(steps=30).replace(**{name: value}),
            "from_dict": lambda: FitConfig.from_dict(json.loads(json.dumps(record)))}


def just_outside(low: float, high: float, kind: str) -> tuple[float, float]:
    """The nearest values below and above a range of `config.RANGES` that it refuses."""
    if kind == "integer":
        return low - 1, high + 1
    below = low if kind == "positive" else math.nextafter(low, -math.inf)
    return below, high if kind == "fraction" else math.nextafter(high, math.inf)


@pytest.mark.parametrize("name", sorted(RANGES))
def test_a_value_just_outside_its_range_makes_no_configuration_by_any_route(name):
    for value in just_outside(*RANGES[name]):
        for route, make in made_with(name, value).items():
            with pytest.raises(ConfigError, match=rf"^`{name}` must lie in .*, got {re.escape(repr(value))}$"):
                make()
                pytest.fail(f"{name} = {value!r} made a configuration by {route}")


@pytest.mark.parametrize("name", sorted(CHOICES))
def test_a_value_outside_its_choices_makes_no_configuration_by_any_route(name):
    for route, make in made_with(name, CHOICES[name][-1] + "s").items():
        with pytest.raises(ConfigError, match=f"^`{name}` .* is not one of"):
            make()
            pytest.fail(f"{name} made a configuration by {route}")


def test_every_setting_is_checked_where_it_is_made():
    # the six checked by their own rules in their sections; a new setting needs a row in RANGES or CHOICES
    assert set(FLAT_NAMES) - set(RANGES) - set(CHOICES) == {"wavelengths_m", "lr", "betas", "curvature_warmup",
                                                            "terms_warmup", "phase"}
    assert set(OPTIONAL) <= set(RANGES) and not set(RANGES) & set(CHOICES)
    config = FitConfig.create(steps=30)
    assert config.validate() is config  # kept for callers: a configuration that exists is valid


def test_checks_across_settings_refuse_where_both_are_held():
    with pytest.raises(ConfigError, match=r"^`curvature_warmup` must lie in \[0, 31\], got 32$"):
        OptimisationSettings(steps=30, curvature_warmup=32)
    with pytest.raises(ConfigError, match=r"^`lr.position` must lie in \[0, 10\], got -0.01$"):
        LearningRates(position=-0.01)
    with pytest.raises(ConfigError, match=r"need 1 value\(s\) for `color` 'gray'"):
        FitConfig.create(wavelengths_m=(639e-9, 532e-9, 473e-9)).replace(color="gray")
    with pytest.raises(ConfigError, match="change `ratio` or `num_gaussians`"):
        FitConfig.create(width=16, height=16, num_gaussians=257)


@pytest.mark.parametrize("name", sorted(ENUMERATED))
@pytest.mark.parametrize("bad", ["upper", "typo", "empty", "none"])
def test_every_bad_value_of_an_enumerated_setting_is_refused_listing_the_choices(name, bad):
    good = ENUMERATED[name][-1]
    value = {"upper": good.upper(), "typo": good + "s", "empty": "", "none": None}[bad]
    with pytest.raises(ConfigError) as error:
        FitConfig.create(**{name: value})
    message = str(error.value)
    assert f"`{name}`" in message and all(repr(choice) in message for choice in ENUMERATED[name])
    assert "\n" not in message and isinstance(error.value, CvqpgError)


# Values each setting refuses; every number must be finite too (`test_non_finite_numbers_are_refused`).
OUT_OF_RANGE = {
    "betas": [(0.98, 1.5, 0.99), (-0.1, 0.92, 0.99), (0.98, 0.92, 1.0)],
    "grad_clip_norm": [-1.0, 0.0], "adan_eps": [0.0, -1e-8], "target_noise": [-1e-3, 2.0],
    "defocus_sigma_px": [-8.0], "global_bound": [-200.0], "ssim_weight": [-0.5], "focus_weight": [-0.5],
    "product_weight": [-1.0], "eta": [0.0, -0.9], "ratio": [0.0, -0.2], "depth_exponent": [0.0],
    "pixel_pitch": [1e-30, 0.0, -3.74e-6, 1.0], "wavelengths_m": [(1.0, 1.0, 1.0), (639e-9, 1e-12, 473e-9)],
    "plane_center": [1e6], "plane_span": [-1e-3], "steps": [0, -5, 10**12], "seed": [-1, 10**23, 2**70],
    "num_planes": [0, 10**6], "width": [8, 10**7], "guard_band_px": [-1], "pad_multiple_px": [0],
    "num_gaussians": [0], "curvature_warmup": [-1, 2002],
}


@pytest.mark.parametrize(("name", "value"), [(n, v) for n, values in OUT_OF_RANGE.items() for v in values])
def test_a_value_out_of_its_range_is_refused_naming_the_setting_and_the_range(name, value):
    with pytest.raises(ConfigError) as error:
        FitConfig.create(**{name: value})
    message = str(error.value)
    assert message.startswith("`") and "\n" not in message
    assert name.split("_m")[0] in message.split("`")[1] or "plane distances" in message
    assert "must" in message and ("[" in message or "(" in message)


def test_the_range_message_says_where_a_number_may_lie():
    with pytest.raises(ConfigError, match=r"^`betas\[1\]` must lie in \[0, 1\), got 1.5$"):
        FitConfig.create(betas=(0.98, 1.5, 0.99))
    with pytest.raises(ConfigError, match=r"^`pixel_pitch` must lie in \[1e-07, 0.001\], got 1e-30$"):
        FitConfig.create(pixel_pitch=1e-30)
    with pytest.raises(ConfigError, match=r"^`seed` must lie in \[0, 4611686018427387904\], got 100000000"):
        FitConfig.create(seed=10**23)


@pytest.mark.parametrize("name", ["ratio", "pixel_pitch", "plane_center", "plane_span", "eta", "ssim_weight",
                                  "target_noise", "grad_clip_norm", "adan_eps", "global_bound"])
@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan, "1", True])
def test_non_finite_numbers_are_refused(name, value):
    with pytest.raises(ConfigError, match=f"^`{name}` must be a finite number in"):
        FitConfig.create(**{name: value})


@pytest.mark.parametrize("changes", [{"steps": 2.5}, {"num_planes": True}, {"width": "640"}, {"num_gaussians": 1.5},
                                     {"seed": 1e23}, {"curvature_warmup": 7.0}])
def test_counts_must_be_whole_numbers(changes):
    with pytest.raises(ConfigError, match=f"^`{next(iter(changes))}` must be a whole number in"):
        FitConfig.create(**changes)


def test_settings_live_in_their_concern_and_create_routes_every_flat_name():
    config = FitConfig.create(width=64, pixel_pitch=8e-6, primitive="flat", num_gaussians=50, steps=3000,
                              ssim_weight=0.01)
    assert (config.targets.width, config.optics.pixel_pitch, config.primitives.kind, config.primitives.count,
            config.optimisation.steps, config.loss.ssim_weight) == (64, 8e-6, "flat", 50, 3000, 0.01)
    reference = FitConfig()
    for name in FLAT_NAMES:
        assert config.replace(**{name: reference.setting(name)}).setting(name) == reference.setting(name)
    with pytest.raises(ConfigError, match="`device` is not a setting"):
        FitConfig.create(device="cuda")


def test_the_curvature_warm_up_is_resolved_when_the_configuration_is_made_and_keeps_its_share():
    assert FitConfig.create().optimisation.curvature_warmup == 400
    assert FitConfig.create(steps=300).optimisation.curvature_warmup == 60
    assert FitConfig.create(steps=300).with_steps(3000).optimisation.curvature_warmup == 600
    assert FitConfig.create(steps=300, curvature_warmup=7).optimisation.curvature_warmup == 7
    assert FitConfig.create(steps=300, curvature_warmup=30).with_steps(600).optimisation.curvature_warmup == 60
    with pytest.raises(ConfigError, match=r"`curvature_warmup` must lie in \[0, 301\], got 400"):
        FitConfig.create(steps=300, curvature_warmup=400)


def test_a_first_version_s_warm_up_longer_than_its_run_reads_as_never_training():
    record = json.loads((CONFIGS / "v37bab73-warmup-lr-color.json").read_text())
    assert FitConfig.from_dict({**record, "steps": 300}).validate().optimisation.curvature_warmup == 301


def test_a_configuration_records_concrete_values_and_reads_back():
    config = FitConfig.create(steps=30, color="gray", wavelengths_m=(520e-9,), recipe="beyond-short")
    record = json.loads(json.dumps(config.to_dict()))
    assert None not in (record["optimisation"]["betas"], record["optimisation"]["curvature_warmup"],
                        record["loss"]["focus_weight"], record["loss"]["product_weight"])
    again = FitConfig.from_dict(record)
    assert again == config and again.recipe == "beyond-short"


def test_a_record_lacking_a_setting_added_later_takes_its_default():
    record = FitConfig.create(steps=30).to_dict()
    del record["loss"]["target_noise"], record["optics"]
    record["primitives"]["a_later_setting"] = 1
    assert FitConfig.from_dict(record) == FitConfig.create(steps=30)


# What each stored config.json of an earlier version ran with (tests/data/configs, one per schema):
# recipe, steps, curvature warm-up, Adan's betas, initialisation, loss weights, amplitude learning rate, backend.
LEGACY = {
    "v37bab73-warmup-lr-color": ("paper", 2000, 400, PAPER_BETAS, "uniform", 1.0, 0.0025, "torch"),
    "v92fd24c-wavelengths": ("paper", 500, 100, PAPER_BETAS, "uniform", 1.0, 0.0025, "auto"),
    "v510184f-propagation": ("paper", 2000, 400, PAPER_BETAS, "uniform", 1.0, 0.0025, "auto"),
    "vda10437-curvature-warmup": ("paper", 30, 6, PAPER_BETAS, "uniform", 1.0, 0.0025, "auto"),
    "v6f505d9-init-density": ("paper", 30, 6, PAPER_BETAS, "uniform", 1.0, 0.0025, "auto"),
    "vec7dec3-loss-weights": ("beyond-short", 30, 6, PAPER_BETAS, "targets", 0.0, 0.0025, "auto"),
    "vb8933bb-none-short": ("beyond-short", 30, 6, PAPER_BETAS, "targets", 0.0, 0.0025, "auto"),
    "vb8933bb-none-long": ("beyond", 1000, 200, LONG_RUN_BETAS, "edges", 1.0, 0.0025, "auto"),
}


@pytest.mark.parametrize("name", sorted(LEGACY))
def test_every_earlier_config_json_loads_to_the_values_it_ran_with(name):
    record = json.loads((CONFIGS / f"{name}.json").read_text())
    config = FitConfig.from_dict(record).validate()
    optimisation = config.optimisation
    assert (config.recipe, optimisation.steps, optimisation.curvature_warmup, optimisation.betas, optimisation.init,
            config.loss.focus_weight, optimisation.lr.amplitude, RunOptions.from_dict(record).backend) == LEGACY[name]
    assert config.targets.width == record["width"] and config.optics.pixel_pitch == record["pixel_pitch"]
    assert FitConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config


def test_every_stored_schema_has_its_expectation():
    assert {path.stem for path in CONFIGS.glob("*.json")} == set(LEGACY)


def test_an_early_auto_initialisation_of_a_long_run_started_from_the_paper_s_draws():
    """Before Adan's betas were left to the run's length, `auto` meant the paper's draws in long runs."""
    record = json.loads((CONFIGS / "vec7dec3-loss-weights.json").read_text())
    long = FitConfig.from_dict({**record, "steps": 2000, "focus_weight": 1.0, "product_weight": 1.0})
    assert long.optimisation.init == "uniform" and long.recipe == "paper"


@pytest.mark.parametrize(("backend", "device", "error"), [("numba", "cuda", "runs on the CPU"),
                                                          ("gpu", "cpu", "`backend`"), ("auto", "mps", "`device`"),
                                                          ("auto", "", "`device`"), ("torch", "CUDA", "`device`")])
def test_a_backend_runs_only_where_it_can_in_one_rule(backend, device, error):
    with pytest.raises(ConfigError, match=error):
        RunOptions(device, backend).validate()
    with pytest.raises(ConfigError, match=error):
        resolve_backend(backend, device)


def test_auto_picks_the_numba_kernels_on_the_cpu():
    assert RunOptions().kernels == "numba" and RunOptions(backend="torch").kernels == "torch"


@pytest.mark.parametrize(("backend", "device", "kept"), [("numba", "cuda", "auto"), ("torch", "cuda", "torch"),
                                                         ("numba", "cpu", "numba")])
def test_run_options_moved_to_another_device_keep_a_backend_only_where_it_runs(backend, device, kept):
    moved = RunOptions(backend=backend).on_device(device)
    assert (moved.device, moved.backend) == (device, kept)


def test_distances_and_time_budgets_outside_their_ranges_are_refused_with_the_range():
    check_distances((1e-3, 10.0), "`distance`")
    for distances in ((0.0,), (1e-3, 1e300), (11.0,)):
        with pytest.raises(ConfigError, match=r"must lie in \[1e-06, 10\] m"):
            check_distances(distances, "`distance`")
    check_time_budget(MAX_TIME_MINUTES)
    for minutes in (0.0, -1.0, 1e307, float("nan")):
        with pytest.raises(ConfigError, match="at most 525600"):
            check_time_budget(minutes)
