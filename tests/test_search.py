"""The search for a `.cvq` file (`cvqpg.search`): one ladder, one way of choosing among trials, within a PSNR drop
or a file size; pruning, the count of primitives that fit, and the settings checked where they are made."""

import pytest
import torch

from cvqpg import FitConfig
from cvqpg.app.encoding import stand_in
from cvqpg.codec import BitDepths, decode, encode, quantise, range_holders
from cvqpg.control import RunControl
from cvqpg.errors import ConfigError
from cvqpg.fitting import FitInterrupted
from cvqpg.primitives import activate, field_energy, init_gaussians
from cvqpg.search import (CLOSE, LADDER, Budget, Choice, CompressionSettings, FixedBits, MaxDrop, kept,
                          largest_fitting, prune, pruned_count, rate_control, reference_for, refine, search,
                          strongest_first, trial)

W, H = 48, 36


def choice(size: int, psnr: float, drop: float = 0.0) -> Choice:
    """A stand-in trial of `size` bytes; only its size and scores matter to a goal."""
    return Choice(BitDepths(), bytes(size), None, psnr, drop)


def test_a_drop_prefers_the_smallest_file_that_holds_and_else_the_largest():
    goal = MaxDrop(0.5)
    small_bad, middle, large = choice(100, 20.0, 0.9), choice(200, 21.0, 0.4), choice(300, 22.0, 0.1)
    assert goal.best([large, small_bad, middle]) is middle
    assert goal.best([small_bad, choice(150, 19.0, 2.0)]).data == bytes(150)
    tied = choice(200, 25.0, 0.0)
    assert goal.best([middle, tied]) is middle  # the first where tied


def test_a_budget_prefers_the_best_score_within_5_percent_below_it_and_else_the_largest():
    goal = Budget(1000, "a budget")
    far, close, closer = choice(900, 30.0), choice(960, 25.0), choice(1000, 24.0)
    assert goal.best([far, close, closer]) is close
    assert goal.best([far, choice(500, 40.0)]) is far


def test_at_fixed_depths_the_file_that_drops_less_wins():
    goal = FixedBits()
    plain, tuned = choice(500, 20.0, 0.3), choice(520, 20.2, 0.1)
    assert goal.best([plain, tuned]) is tuned and goal.best([plain, choice(400, 19.0, 0.3)]) is plain


def test_the_ladder_runs_from_3_bits_coarser_to_every_attribute_s_finest_depth():
    assert LADDER[0] == BitDepths().shifted(-3) and LADDER[-1] == BitDepths().shifted(16)
    sizes = [sum(vars(bits).values()) for bits in LADDER]
    assert sizes == sorted(set(sizes))
    # the phase terms' depths, at curvature's, add no rung to a file without them
    assert len({tuple(bits.coded().values()) for bits in LADDER}) == len(LADDER)


@pytest.mark.parametrize("phase, refined", [
    ("quadratic", ["position", "scale", "rotation", "amplitude", "phase", "curvature"]),
    ("axes+tilt", ["position", "scale", "rotation", "amplitude", "phase", "curvature", "axes", "tilt"])])
def test_refining_moves_the_depths_the_file_codes(monkeypatch, phase, refined):
    import cvqpg.search

    config = FitConfig.create(width=W, height=H, color="gray", num_gaussians=10, phase=phase)
    tried = []

    def stand_in_trial(primitives, config, bits, reference):  # a file that drops too much: the search stops
        tried.append(next(name for name, value in vars(bits).items() if value != vars(BitDepths())[name]))
        return choice(10, 20.0, 1.0)

    monkeypatch.setattr(cvqpg.search, "trial", stand_in_trial)
    assert refine(None, config, None, MaxDrop(0.5), choice(10, 20.0, 0.0)).drop == 0.0
    assert tried == refined


@pytest.fixture(scope="module")
def model():
    """A scene-free model whose reference is its own reconstruction: scored with the drop estimated for a fit."""
    config = FitConfig.create(width=W, height=H, color="gray", num_planes=1, ratio=0.5, guard_band_px=32).validate()
    primitives = stand_in(config, config.primitive_count)
    return primitives, config, reference_for(primitives, config, None)


@pytest.mark.slow
def test_within_a_drop_the_search_holds_it_and_no_one_bit_coarser_attribute_does_better(model):
    primitives, config, reference = model
    goal = MaxDrop(0.5)
    found = search(primitives, config, reference, goal)
    assert goal.holds(found) and found.decoded.count == primitives.count
    for name in found.bits.names():
        coarser = found.bits.shifted_one(name)
        if coarser is not None:
            other = trial(primitives, config, coarser, reference)
            assert not goal.holds(other) or len(other.data) >= len(found.data)


@pytest.mark.slow
def test_within_a_budget_every_primitive_filled_up_to_it_is_a_candidate_even_where_its_rung_lands_far_below(model):
    primitives, config, reference = model  # all about equally strong: pruning costs most
    sizes = [len(encode(primitives, config, bits)) for bits in LADDER[:3]]
    budget = Budget(round(sizes[1] + 0.6 * (sizes[2] - sizes[1])), "a budget between two rungs")
    assert sizes[1] < CLOSE * budget.max_bytes  # rung 1 lands more than 5% below the budget
    filled = refine(primitives, config, reference, budget, trial(primitives, config, LADDER[1], reference))
    assert filled.decoded.count == primitives.count and budget.holds(filled)
    chosen = rate_control(primitives, config, reference, budget).choice
    assert len(chosen.data) <= budget.max_bytes and chosen.psnr >= filled.psnr  # pruned rungs score ~4 dB less


def test_a_stop_request_ends_the_search_before_its_next_rung(model):
    primitives, config, reference = model
    asked = []
    control = RunControl(progress=False, stop_requested=lambda: asked.append(1) or len(asked) > 2)
    with pytest.raises(FitInterrupted, match="stopped during rate control"):
        search(primitives, config, reference, Budget(10**6, "a budget"), control=control)
    assert len(asked) == 3


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
    config = FitConfig.create(width=W, height=H)
    assert CompressionSettings(bpp=1.0).budget(config).max_bytes == W * H // 8
    assert CompressionSettings(bpp=0.999).budget(config).max_bytes == W * H // 8 - 1  # never rounded up
    assert CompressionSettings(max_bytes=777).budget(config).max_bytes == 777
    with pytest.raises(ConfigError, match="give one budget"):
        CompressionSettings(max_drop=0.2).budget(config)


def test_dropping_primitives_other_than_the_range_holders_keeps_the_file_s_bins():
    config = FitConfig.create(width=W, height=H, color="rgb", ratio=0.3)
    raw = init_gaussians(config.primitive_count, 3, W, H, seed=5)
    raw.amplitude.uniform_(-1, 1, generator=torch.Generator().manual_seed(5))
    primitives = activate(raw, config)
    order = strongest_first(primitives, first=range_holders(primitives))
    assert set(order[:len(range_holders(primitives))].tolist()) == set(range_holders(primitives).tolist())
    few = kept(primitives, order, 5)
    assert quantise(few, config, BitDepths()).ranges == quantise(primitives, config, BitDepths()).ranges


def test_pruning_removes_the_primitives_of_least_field_energy_and_the_file_round_trips():
    config = FitConfig.create(width=48, height=32, color="rgb", ratio=0.3)
    raw = init_gaussians(config.primitive_count, 3, 48, 32, seed=3)
    primitives = activate(raw, config)
    values = primitives.tensors()
    values["amplitude"] = torch.ones_like(values["amplitude"])
    values["scale_px"] = torch.ones_like(values["scale_px"])
    values["opacity"] = torch.linspace(1.0, 0.1, primitives.count).roll(7)  # energy falls with opacity²
    primitives = type(primitives).from_tensors(values)
    pruned = prune(primitives, 0.25)
    count = round(0.75 * primitives.count)
    expected = torch.argsort(values["opacity"], descending=True)[:count].sort().values
    assert torch.equal(pruned.position_px, primitives.position_px[expected])
    assert field_energy(pruned).min() >= field_energy(primitives).sort().values[-count]
    assert decode(encode(pruned, config, BitDepths())).primitives.count == count
    assert prune(primitives, 0.0).count == primitives.count


@pytest.mark.parametrize("settings, message", [
    ({"max_drop": -1.0}, "`max_drop` -1: give a drop in dB ≥ 0"),
    ({"max_drop": float("nan")}, "`max_drop` nan: give a drop in dB ≥ 0"),
    ({"finetune_steps": -2}, "`finetune_steps` -2: give a number of steps ≥ 0"),
    ({"finetune_steps": 2.5}, "`finetune_steps` 2.5: give a number of steps ≥ 0"),
    ({"prune_fraction": 1.5, "finetune_steps": 2}, "`prune_fraction` 1.5: give the fraction"),
    ({"prune_fraction": 0.2}, "`prune_fraction` 0.2 needs `finetune_steps` > 0"),
    ({"bpp": 3.0, "prune_fraction": 0.1, "finetune_steps": 2}, "`prune_fraction` applies to `bits` and `max_drop`"),
    ({"bpp": 0.0}, "`bpp` 0: give a positive, finite number"),
    ({"bpp": float("inf")}, "`bpp` inf: give a positive, finite number"),
    ({"bpp": "3"}, "`bpp` '3': give a positive, finite number"),
    ({"max_bytes": 0}, "`max_bytes` 0: give a positive whole number of bytes"),
    ({"max_bytes": 900.0}, "`max_bytes` 900.0: give a positive whole number of bytes"),
    ({"max_bytes": True}, "`max_bytes` True: give a positive whole number of bytes"),
    ({"bpp": 2.0, "max_bytes": 900}, "give one goal, not `bpp` and `max_bytes`"),
    ({"bits": BitDepths(), "max_drop": 0.1}, "give one goal, not `bits` and `max_drop`"),
    ({"bits": BitDepths(phase=1)}, "`bits` phase=1: give 2..16 bits"),
])
def test_settings_name_the_first_that_cannot_work_where_they_are_made(settings, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        CompressionSettings(**settings)


def test_settings_choose_the_goal_a_drop_of_a_tenth_of_a_db_by_default():
    config = FitConfig.create(width=W, height=H)
    assert CompressionSettings().goal(config) == MaxDrop(0.1)
    assert CompressionSettings(max_drop=0.4).goal(config) == MaxDrop(0.4)
    assert CompressionSettings(bits=BitDepths()).goal(config) == FixedBits()
    assert CompressionSettings(max_bytes=500).goal(config) == Budget(500, "`max_bytes` 500")


def test_budgets_beyond_2_to_the_53_bytes_and_a_prune_of_every_primitive_are_refused():
    config = FitConfig.create(width=32, height=24)
    with pytest.raises(ConfigError, match="`bpp` 1e\\+308 asks for inf bytes"):
        Budget.of(config, bpp=1e308)
    assert Budget.of(config, bpp=8.0).max_bytes == 768
    with pytest.raises(ConfigError, match="`max_bytes` 1152921504606846976: .* at most 9007199254740992"):
        CompressionSettings(max_bytes=2**60)
    assert CompressionSettings(max_bytes=2**53).max_bytes == 2**53
    with pytest.raises(ConfigError, match="`prune_fraction` 0.999 removes all 77 primitives"):
        pruned_count(77, 0.999)
    assert pruned_count(77, 0.5) == 38 and pruned_count(2, 0.7) == 1
