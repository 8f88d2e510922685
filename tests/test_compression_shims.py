"""The modules that moved in 0.2.0, `cvqpg.compression` and `cvqpg.ratecontrol`, still work for one release:
importing them warns, naming where their names went, and their old calls give what the new ones give."""

import importlib
import sys

import pytest

from cvqpg import FitConfig
from cvqpg.app.compression import compress_model
from cvqpg.app.encoding import stand_in
from cvqpg.codec import BitDepths
from cvqpg.errors import ConfigError
from cvqpg.search import CompressionSettings, MaxDrop, rate_control, reference_for, search
from cvqpg.storage import save_model


def imported(name: str):
    """A fresh import of module `name`, which warns again."""
    sys.modules.pop(name, None)
    return importlib.import_module(name)


@pytest.mark.parametrize("name, new", [("cvqpg.compression", ["cvqpg.search", "cvqpg.app.compression"]),
                                       ("cvqpg.ratecontrol", ["cvqpg.search", "cvqpg.app.encoding"])])
def test_importing_a_moved_module_warns_naming_the_new_ones(name, new):
    with pytest.warns(DeprecationWarning, match=f"^`{name}` moved to .* the old name goes in cvqpg 0.3.0") as warned:
        imported(name)
    assert all(module in str(warned[0].message) for module in new)


@pytest.fixture(scope="module")
def model():
    config = FitConfig.create(width=32, height=24, color="gray", num_planes=1, ratio=0.3, guard_band_px=32).validate()
    primitives = stand_in(config, config.primitive_count)
    return primitives, config, reference_for(primitives, config, None)


@pytest.mark.slow
def test_the_old_searches_give_what_the_new_ones_give(model, tmp_path):
    primitives, config, reference = model
    with pytest.warns(DeprecationWarning):
        compression, ratecontrol = imported("cvqpg.compression"), imported("cvqpg.ratecontrol")
    assert compression.choose_bits(primitives, config, reference, 0.5).data == \
        search(primitives, config, reference, MaxDrop(0.5)).data
    budget = ratecontrol.Budget.of(config, bpp=6.0)
    assert ratecontrol.rate_control(primitives, config, reference, budget).choice.data == \
        rate_control(primitives, config, reference, budget).choice.data
    bare = tmp_path / "bare.safetensors"
    save_model(bare, primitives, config)
    ratecontrol.compress_to_budget(bare, tmp_path / "old.cvq", bpp=6.0)
    compress_model(bare, CompressionSettings(bpp=6.0), tmp_path / "new.cvq")
    assert (tmp_path / "old.cvq").read_bytes() == (tmp_path / "new.cvq").read_bytes()


def test_the_old_checks_and_workflows_take_their_old_arguments(model, tmp_path):
    primitives, config, _ = model
    bare = tmp_path / "bare.safetensors"
    save_model(bare, primitives, config)
    with pytest.warns(DeprecationWarning):
        compression, ratecontrol = imported("cvqpg.compression"), imported("cvqpg.ratecontrol")
    with pytest.raises(ConfigError, match="`prune_fraction` 0.2 needs `finetune_steps` > 0"):
        compression.check_compression_settings(None, 0, 0.2)
    with pytest.raises(ConfigError, match="give one budget"):
        ratecontrol.check_budget_values(None, None)
    with pytest.raises(ConfigError, match="`bits` phase=1"):
        compression.compress_model(bare, bits=BitDepths(phase=1))
    old = compression.compress_model(bare, tmp_path / "old.cvq", bits=BitDepths())
    new = compress_model(bare, CompressionSettings(bits=BitDepths()), tmp_path / "new.cvq")
    assert old["bytes"] == new["bytes"] and ratecontrol.RUNGS == compression.LADDER
    assert (tmp_path / "old.cvq").read_bytes() == (tmp_path / "new.cvq").read_bytes()
