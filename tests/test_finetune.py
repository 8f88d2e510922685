"""Quantisation-aware fine-tuning (`cvqpg.finetune`): through the codec's own quantisers, on the file's own bins."""

import pytest
import torch

from cvqpg import FitConfig
from cvqpg.codec import BitDepths, coding, dequantise, file_order, quantise
from cvqpg.control import RunControl
from cvqpg.finetune import finetune, learning_rate_bins, quantised
from cvqpg.fitting import FitInterrupted, render
from cvqpg.metrics import mean_psnr
from cvqpg.targets import Scene
from test_codec import FINE, random_primitives


@pytest.mark.parametrize("bits", [BitDepths(), BitDepths().shifted(-3), FINE,
                                  BitDepths(position=0, scale=2, rotation=2, amplitude=2, phase=2, curvature=2)])
@pytest.mark.parametrize("color, curvature, primitive", [("gray", "shared", "cvqpg"), ("rgb", "per-channel", "cvqpg"),
                                                         ("rgb", "channel-bound", "cvqpg"), ("rgb", "shared", "flat")])
def test_finetune_rounds_through_the_codec_s_own_quantisers(bits, color, curvature, primitive):
    config = FitConfig.create(width=48, height=32, color=color, ratio=0.3, curvature=curvature, primitive=primitive)
    primitives = random_primitives(config)
    coded = coding(primitives, config, bits)
    values = {name: value.clone().requires_grad_(True) for name, value in coded.values.items()}
    forward = quantised(values, coded.ranges, config, bits)
    decoded = dequantise(quantise(primitives, config, bits), config, bits).tensors()
    order = file_order(coded)
    tuned = {name: tensor.detach()[order] for name, tensor in forward.tensors().items()}
    for name in ("position_px", "amplitude", "phase_rad", "opacity"):
        assert torch.equal(tuned[name], decoded[name]), name
    # the same bins; the scale then goes through torch's float32 exp, the file's through `codec.exact_exp`, which
    # differ in the last bit, and the curvature bound of that scale (float32) by a few. The file orders each
    # ellipse's axes, the larger first, turned by a quarter where they swap: the same ellipse.
    swapped = tuned["scale_px"][:, 1] > tuned["scale_px"][:, 0]
    torch.testing.assert_close(tuned["scale_px"].sort(dim=1, descending=True).values, decoded["scale_px"],
                               rtol=5e-7, atol=0)
    torch.testing.assert_close(torch.remainder(tuned["rotation_rad"] + swapped * torch.pi / 2, torch.pi),
                               decoded["rotation_rad"], rtol=0, atol=1e-6)
    torch.testing.assert_close(tuned["curvature_per_m"], decoded["curvature_per_m"], rtol=5e-7, atol=0)
    forward.position_px.sum().backward()
    assert torch.equal(values["position"].grad, torch.ones_like(values["position"]))


def test_finetune_leaves_its_input_alone_and_trains_on_the_file_s_own_bins():
    from cvqpg.campaign.ratedistortion import Point, finetuned_points

    config = FitConfig.create(width=48, height=32, color="gray", num_planes=1, ratio=0.3, guard_band_px=32)
    primitives = random_primitives(config)
    targets = render(primitives, config)[1].clamp(0.05, 0.95).detach()
    scene = Scene(targets[0], torch.ones(targets.shape[0], 32, 48), targets)
    before = primitives.detached()
    bits = BitDepths().shifted(-3)
    tuned = finetune(primitives, config, scene, bits, 4)
    for name, tensor in primitives.tensors().items():
        assert torch.equal(tensor, before.tensors()[name]), name
    # the file's ranges (and so its bins) are those the loop quantised against
    assert quantise(tuned, config, bits).ranges == quantise(primitives, config, bits).ranges
    assert not torch.equal(tuned.position_px, primitives.position_px)
    fit = mean_psnr(render(primitives, config)[1], targets)
    untuned = [Point("cvqpg", "", 1, 1.0, fit - drop, 0.5, 0.0, 0.0) for drop in (5.0, 1.0, 0.05)]
    points = finetuned_points(primitives, config, scene, fit, 2, [bits, bits.shifted(3), bits.shifted(6)], untuned,
                              prune_fractions=(0.5,))
    assert [p.setting.split(":")[0] for p in points] == ["--finetune 2", "--prune 0.5 --finetune 2"]
    assert points[0].setting.endswith("position=3 scale=8 rotation=7 amplitude=8 phase=7 curvature=8")
    assert points[1].bytes < 0.7 * points[0].bytes


def test_fine_tuning_s_rate_is_a_quarter_bin_for_short_tunings_and_grows_to_four_bins_for_long_ones():
    assert [learning_rate_bins(steps) for steps in (1, 10, 100)] == [0.25, 0.25, 0.25]
    assert learning_rate_bins(200) == pytest.approx(1.0) and learning_rate_bins(400) == pytest.approx(4.0)
    rates = [learning_rate_bins(steps) for steps in range(100, 2001, 50)]
    assert rates == sorted(rates) and max(rates) == 4.0


def test_finetune_tells_its_control_each_step_and_stops_on_request():
    config = FitConfig.create(width=48, height=32, color="gray", num_planes=1, ratio=0.3, guard_band_px=32)
    primitives = random_primitives(config)
    targets = render(primitives, config)[1].clamp(0.05, 0.95).detach()
    scene = Scene(targets[0], torch.ones(targets.shape[0], 32, 48), targets)
    steps = []
    finetune(primitives, config, scene, BitDepths(), 3, control=RunControl(on_step=lambda *step: steps.append(step)))
    assert [step for step, _, _ in steps] == [0, 1, 2] and all(psnr > 0 for _, _, psnr in steps)
    steps.clear()
    stop = RunControl(stop_requested=lambda: len(steps) == 2, on_step=lambda *step: steps.append(step))
    with pytest.raises(FitInterrupted, match="stopped during fine-tuning"):
        finetune(primitives, config, scene, BitDepths(), 5, control=stop)
    assert len(steps) == 2


@pytest.mark.parametrize("phase", ["quadratic+tilt", "axes+tilt"])
def test_finetune_rounds_the_phase_terms_through_their_quantisers_and_keeps_them_within_their_bounds(phase):
    from test_codec import phased_primitives

    primitives, config = phased_primitives(phase)
    bits = BitDepths().shifted(-2)
    coded = coding(primitives, config, bits)
    forward = quantised(coded.values, coded.ranges, config, bits)
    none = frozenset()  # without the tool `axes`, which orders each ellipse's axes and so swaps their curvatures
    decoded = dequantise(quantise(primitives, config, bits, none), config, bits, none)
    order = file_order(coded)
    for name in primitives.terms:
        torch.testing.assert_close(forward.terms[name].detach()[order], decoded.terms[name], rtol=1e-5, atol=0)
    targets = render(primitives, config)[1].clamp(0.05, 0.95).detach()
    scene = Scene(targets[0], torch.ones(targets.shape[0], 24, 32), targets)
    # the tuned shares of the bounds at the scale as decoded, which the codec divides by, within what `activate` reaches
    shares = coding(finetune(primitives, config, scene, bits, 3), config, bits).values
    assert bool((shares["tilt"].norm(dim=1) <= 1 + 1e-6).all())
    if "axes" in shares:
        assert bool((shares["axes"].abs() <= 1 + 1e-6).all())
