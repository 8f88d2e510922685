"""The rate model (`cvqpg.rate`) against the encoder it models: the bytes `codec.encode` writes, the primitives
`codec.decode` reads, and its bits' gradients against finite differences."""

import math

import pytest
import torch

from cvqpg import FitConfig
from cvqpg.codec import AXES, TOOLS, TURN, BitDepths, decode, encode
from cvqpg.fitting import fit_scene
from cvqpg.phase import TERMS
from cvqpg.rate import LAPLACE, GAUSSIAN, coded, estimate, parametric_bits, stream_rate
from cvqpg.app.encoding import stand_in
from cvqpg.scenes import builtin_scene

TOLERANCE = 0.03  # the estimate within 3% of the written file


# every primitive kind, and CVQPG with the phase terms beyond the curvature (by the phase's name)
KINDS = [(color, primitive) for color in ("gray", "rgb") for primitive in ("flat", "cvqpg")] + [
    ("gray", "axes+tilt"), ("rgb", "quadratic+tilt")]


def tiny_config(color: str, primitive: str) -> FitConfig:
    kind = {"primitive": primitive} if primitive in ("flat", "cvqpg") else {"phase": primitive}
    return FitConfig.create(width=48, height=32, color=color, num_gaussians=160, steps=12, curvature_warmup=4,
                            guard_band_px=16, **kind)


@pytest.fixture(scope="module")
def models():
    """Models of every kind (grayscale and RGB, flat and `cvqpg` primitives, and phase terms) coded as a fit's are
    (`app.encoding.stand_in`), without fitting."""
    return {kind: (stand_in(tiny_config(*kind), 160, seed=1), tiny_config(*kind)) for kind in KINDS}


@pytest.fixture(scope="module")
def fits():
    """Tiny fits of every kind, a few steps each."""
    models = {}
    for kind in KINDS:
        fitted = fit_scene(builtin_scene("demo", tiny_config(*kind)), tiny_config(*kind))
        models[kind] = fitted.primitives, fitted.config
    return models


def assert_within_tolerance(models, delta):
    bits = BitDepths().shifted(delta)
    for kind, (primitives, config) in models.items():
        written, estimated = len(encode(primitives, config, bits)), estimate(primitives, config, bits).file_bytes
        assert abs(estimated / written - 1) <= TOLERANCE, (kind, delta, estimated, written)


@pytest.mark.parametrize("delta", [-3, 0, pytest.param(2, marks=pytest.mark.slow)])
def test_the_estimate_is_within_3_percent_of_the_written_file(models, delta):
    assert_within_tolerance(models, delta)


@pytest.mark.slow
@pytest.mark.parametrize("delta", [-3, 0, 2])
def test_the_estimate_of_a_fit_is_within_3_percent_of_the_written_file(fits, delta):
    assert_within_tolerance(fits, delta)


@pytest.mark.parametrize("tools", [frozenset(), frozenset({AXES}), frozenset({TURN})])
def test_the_estimate_follows_the_tools(models, tools):
    primitives, config = models["gray", "cvqpg"]
    written = len(encode(primitives, config, BitDepths(), tools=tools))
    assert abs(estimate(primitives, config, BitDepths(), tools).file_bytes / written - 1) <= TOLERANCE


def test_without_noise_the_coded_primitives_are_those_the_file_decodes_to(models):
    """Straight through (noise 0), `coded` renders what a reader of the file gets: the same values, in the
    primitives' own order where the file keeps Morton order."""
    for (color, primitive), (primitives, config) in models.items():
        through = coded(primitives, config, BitDepths()).primitives
        read = decode(encode(primitives, config, BitDepths())).primitives

        def rows(model):  # the file orders each ellipse's axes (`axes`)
            tilt = [model.terms["tilt"]] if "tilt" in model.terms else []
            return torch.cat([model.position_px, model.scale_px.sort(dim=1).values, model.amplitude, *tilt],
                             dim=1).double()

        ours, theirs = rows(through), rows(read)
        ours, theirs = (t[torch.argsort(t[:, 0] * 1e4 + t[:, 1])] for t in (ours, theirs))
        assert torch.allclose(ours, theirs, rtol=1e-5, atol=1e-5), (color, primitive)


@pytest.mark.parametrize("kind, moving", [(("rgb", "cvqpg"), ("scale_px", "phase_rad")),
                                          (("gray", "axes+tilt"), ("axes_curvature_per_m", "tilt_rad"))])
def test_the_coded_rate_matches_the_estimate_and_is_differentiable(models, kind, moving):
    """Scales, phases and phase terms gathered about a value, as a fit's are: modelled streams, whose bits move with
    them."""
    primitives, config = models[kind]
    leaf = {name: tensor.detach().clone().requires_grad_(True) for name, tensor in primitives.tensors().items()}
    with torch.no_grad():
        generator = torch.Generator().manual_seed(1)
        leaf["phase_rad"].copy_(torch.remainder(0.3 * torch.randn(leaf["phase_rad"].shape, generator=generator), 6.28))
        for name in primitives.terms:  # gathered about 0, as a fit's terms are
            leaf[TERMS[name].physical].mul_(0.2)
    result = coded(type(primitives).from_tensors(leaf), config, BitDepths())
    assert result.rate.file_bytes == estimate(type(primitives).from_tensors(leaf), config, BitDepths()).file_bytes
    assert math.isclose(float(result.rate.bits.detach()) / 8, result.rate.file_bytes, rel_tol=1e-9)
    result.rate.bits.backward()
    for name in moving:
        assert leaf[name].grad is not None and bool(leaf[name].grad.abs().sum() > 0), name


def test_noise_moves_the_render_by_at_most_half_a_bin(models):
    primitives, config = models["gray", "flat"]
    generator = torch.Generator().manual_seed(0)
    rounded = coded(primitives, config, BitDepths()).primitives
    noisy = coded(primitives, config, BitDepths(), noise=1.0, generator=generator).primitives
    gap = (noisy.position_px - primitives.position_px).abs()
    assert bool((gap <= 2.0 ** -(BitDepths().position - 2) + 1e-6).all())  # half a bin at the finest depth
    assert not torch.equal(noisy.position_px, rounded.position_px)


@pytest.mark.parametrize("coding", [LAPLACE, GAUSSIAN])
def test_parametric_bits_have_the_gradient_of_their_finite_differences(coding):
    symbols = torch.tensor([0.3, 2.2, 5.0, 7.6, 11.4], dtype=torch.float64, requires_grad=True)
    bits = parametric_bits(coding, symbols, 12, [4.0, 2.5])
    bits.sum().backward()
    step = 1e-6
    numeric = (parametric_bits(coding, symbols.detach() + step, 12, [4.0, 2.5])
               - parametric_bits(coding, symbols.detach() - step, 12, [4.0, 2.5])) / (2 * step)
    assert torch.allclose(symbols.grad, numeric, rtol=1e-5, atol=1e-7)


def test_a_stream_s_estimate_is_what_the_encoder_writes_within_a_word():
    """One stream at a time, the coding the encoder chooses and its bytes to the ANS coder's last word."""
    from cvqpg.codec import encode_stream

    generator = torch.Generator().manual_seed(2)
    for symbols in (torch.randint(0, 40, (500,), generator=generator),
                    (torch.randn(800, generator=generator) * 3 + 20).round().clamp(0, 63).long(),
                    torch.randint(0, 2**30, (300,), generator=generator)):
        values = symbols.numpy()
        descriptor, data = encode_stream(values)
        estimated = stream_rate(values).descriptor
        assert estimated["coding"] == descriptor["coding"]
        assert abs(estimated["bytes"] - len(data)) <= 8
