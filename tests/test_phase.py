"""The phase terms beyond the curvature (cvqpg/phase.py): settings, the one Nyquist bound of their sum (method.md §4),
the reference rasterizer against ψ written out by hand, and its gradients against finite differences."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from cvqpg.config import FitConfig
from cvqpg.errors import ConfigError
from cvqpg.fitting import trainable_groups
from cvqpg.ops.rasterize import rasterize
from cvqpg.phase import PHASES, TERMS, parse_phase
from cvqpg.primitives import Gaussians, Primitives, activate, init_gaussians

from test_ops_rasterize import F64, FIELDS, PITCH, WAVELENGTHS, direct_hologram, footprint_margin, random_prims

TERM_PHASES = [phase for phase in PHASES if parse_phase(phase).extra_terms]


def config_of(phase: str, color: str = "rgb", **settings) -> FitConfig:
    return FitConfig.create(width=24, height=18, color=color, num_gaussians=20, phase=phase, **settings).validate()


def central_difference(loss, base: dict[str, torch.Tensor], name: str, index: tuple[int, ...]) -> float:
    """The central difference of `loss` in one element of `base[name]`, at a step relative to its size."""
    eps = 1e-6 * max(1.0, abs(float(base[name][index])))
    plus, minus = ({n: t.clone() for n, t in base.items()} for _ in range(2))
    plus[name][index] += eps
    minus[name][index] -= eps
    return float(loss(plus) - loss(minus)) / (2 * eps)


# --------------------------------------------------------------------------- settings


def test_phases_map_onto_the_primitive_kinds():
    assert config_of("constant") == FitConfig.create(width=24, height=18, num_gaussians=20, primitive="flat")
    assert config_of("constant").primitives.kind == "flat"
    assert config_of("quadratic") == FitConfig.create(width=24, height=18, num_gaussians=20)
    assert config_of("quadratic").primitives.phase is None  # today's record, unchanged
    assert config_of("axes+tilt").primitives.kind == "cvqpg"
    assert [config_of(p).phase.name for p in PHASES] == list(PHASES)


@pytest.mark.parametrize("color, counts", [("rgb", (12, 13, 14, 15, 14, 16)), ("gray", (8, 9, 10, 11, 10, 12))])
def test_each_term_adds_its_parameters(color, counts):
    assert tuple(config_of(p, color).params_per_primitive for p in PHASES) == counts


def test_settings_that_do_not_go_with_a_phase_are_refused_in_one_line():
    for settings, words in (({"phase": "tilt", "primitive": "flat"}, "flat primitive"),
                            ({"phase": "axes", "curvature": "per-channel"}, "`curvature` per-channel"),
                            ({"phase": "quadratic+tilt", "bound": "global"}, "`bound` adaptive"),
                            ({"phase": "quadratic+axes"}, "`phase`"), ({"phase": "twist"}, "`phase`")):
        with pytest.raises(ConfigError, match=words):
            FitConfig.create(width=24, height=18, num_gaussians=20, **settings).validate()


def test_a_record_without_a_phase_loads_as_its_kind():
    for kind, phase in (("flat", "constant"), ("cvqpg", "quadratic")):
        record = FitConfig.create(primitive=kind).to_dict()
        del record["primitives"]["phase"]
        assert FitConfig.from_dict(record).phase.name == phase
    assert FitConfig.from_dict(config_of("axes+tilt").to_dict()) == config_of("axes+tilt")


def test_the_terms_start_at_zero_and_train_in_their_own_groups():
    config = config_of("axes+tilt")
    raw = init_gaussians(20, 3, 24, 18, seed=1, terms=("axes", "tilt"))
    assert all(float(t.abs().max()) == 0 for t in raw.terms.values())
    assert all(float(t.abs().max()) == 0 for t in activate(raw, config).terms.values())
    assert trainable_groups(config)[-2:] == ("axes", "tilt")
    assert "curvature" not in trainable_groups(config)
    assert config.with_steps(1000).terms_warmup == 200
    assert config_of("tilt", terms_warmup=0).with_steps(1000).terms_warmup == 0


# --------------------------------------------------------------------------- the bound


def random_raw(count: int, channels: int, phase: str, seed: int, spread: float = 6.0) -> Gaussians:
    """Primitives from tiny to huge and needle-like, every phase parameter far out into its squash."""
    generator = torch.Generator().manual_seed(seed)
    terms = tuple(term.name for term in parse_phase(phase).extra_terms)
    raw = init_gaussians(count, channels, 64, 48, seed, per_channel_curvature=False, terms=terms)
    raw.scale = torch.empty(count, 2).uniform_(math.log(0.05), math.log(60.0), generator=generator)
    raw.curvature = spread * (2 * torch.rand(count, generator=generator) - 1)
    raw.terms = {name: spread * torch.randn(count, TERMS[name].parameters, generator=generator) for name in terms}
    return raw


def edge_frequencies(primitives: Primitives, config: FitConfig, samples: int = 256) -> torch.Tensor:
    """max over the 3σ ellipse D² ≤ 9 of |∇ψ|·k_c/(2π) (cycles/px) per primitive and channel [N, C], ψ written out
    from method.md §2 (float64): its gradient is affine in the offset, so its largest norm lies on the edge."""
    p = primitives.to("cpu", F64)
    pitch = config.optics.pixel_pitch
    angle = torch.linspace(0, 2 * math.pi, samples, dtype=F64)
    cos, sin = torch.cos(p.rotation_rad)[:, None], torch.sin(p.rotation_rad)[:, None]
    sigma = torch.sqrt(p.scale_px**2 + 0.1)
    u, v = 3 * sigma[:, :1] * torch.cos(angle), 3 * sigma[:, 1:] * torch.sin(angle)  # along the axes, [N, S]
    gradient_u = torch.zeros_like(u)
    gradient_v = torch.zeros_like(v)
    gradient_x = torch.zeros_like(u)
    gradient_y = torch.zeros_like(u)
    if config.phase.has("quadratic"):  # ½γ s_x s_y Δx² (u²/σ_u² + v²/σ_v²)
        gamma = p.curvature_per_m if p.curvature_per_m.dim() == 2 else p.curvature_per_m[:, None]
        factor = pitch**2 * p.scale_px.prod(dim=1, keepdim=True)
        quadratic = [(factor * gamma[:, c:c + 1] * u / sigma[:, :1] ** 2, factor * gamma[:, c:c + 1] * v / sigma[:, 1:] ** 2)
                     for c in range(gamma.shape[1])]
    else:
        quadratic = [(gradient_u, gradient_v)]
    if "axes" in p.terms:
        gradient_u = gradient_u + pitch**2 * p.terms["axes"][:, :1] * u
        gradient_v = gradient_v + pitch**2 * p.terms["axes"][:, 1:] * v
    if "tilt" in p.terms:
        gradient_x = gradient_x + pitch * p.terms["tilt"][:, :1]
        gradient_y = gradient_y + pitch * p.terms["tilt"][:, 1:]
    result = []
    for c, wavelength in enumerate(config.wavelengths):
        qu, qv = quadratic[min(c, len(quadratic) - 1)]
        along, across = gradient_u + qu, gradient_v + qv  # m/px along the axes
        gx = cos * along - sin * across + gradient_x
        gy = sin * along + cos * across + gradient_y
        result.append(torch.sqrt(gx * gx + gy * gy).max(dim=1).values / wavelength)
    return torch.stack(result, dim=1)


@pytest.mark.parametrize("phase", PHASES[1:])
@pytest.mark.parametrize("color, curvature", [("rgb", "shared"), ("rgb", "per-channel"), ("gray", "shared")])
def test_the_summed_phase_never_exceeds_nyquist_on_the_footprint(phase, color, curvature):
    if curvature != "shared" and not parse_phase(phase).has("quadratic"):
        pytest.skip("the curvature setting shapes the quadratic term")
    config = config_of(phase, color, curvature=curvature)
    raw = random_raw(150, config.channels, phase, seed=5)
    if curvature == "per-channel":
        raw.curvature = raw.curvature[:, None] * torch.linspace(-1, 1, config.channels)
    frequencies = edge_frequencies(activate(raw, config), config)
    assert float(frequencies.max()) <= 0.5 * config.primitives.eta * (1 + 1e-6) < 0.5  # float32 activations
    # and the bound is not loose: far out in the squash the sum nears it
    assert float(frequencies.max()) > 0.4 * config.primitives.eta


def test_each_term_takes_its_share():
    config = config_of("axes+tilt", "gray")
    raw = random_raw(200, 1, "axes+tilt", seed=2, spread=50.0)
    prims = activate(raw, config)
    only_tilt = Primitives(**{**{name: getattr(prims, name) for name in FIELDS},
                              "terms": {"tilt": prims.terms["tilt"], "axes": 0 * prims.terms["axes"]}})
    assert float(edge_frequencies(only_tilt, config).max()) == pytest.approx(0.25 * config.primitives.eta, rel=1e-3)


def test_each_term_s_limit_is_the_largest_magnitude_its_activation_reaches():
    """What a `.cvq` file codes the terms as shares of: the activation's values over `limit` lie within the set
    `within` keeps, and far out in the squash they reach its edge."""
    from cvqpg.primitives import term_bounds

    config = config_of("axes+tilt", "gray")
    raw = random_raw(200, 1, "axes+tilt", seed=4, spread=50.0)
    prims = activate(raw, config)
    limits = term_bounds(prims.scale_px, config)
    for name, limit in limits.items():
        shares = prims.terms[name] / limit
        torch.testing.assert_close(TERMS[name].within(shares), shares)
        edge = shares.norm(dim=1) if name == "tilt" else shares.abs()
        assert float(edge.max()) <= 1 + 1e-6 and float(edge.max()) > 0.999, name
    from cvqpg.bitdepths import PHASE_TERMS

    assert set(PHASE_TERMS) == set(TERMS) - {"quadratic"}  # every term has its depth in a .cvq file
    beyond = torch.tensor([[3.0, 4.0], [0.3, -0.4]])
    assert torch.allclose(TERMS["tilt"].within(beyond), torch.tensor([[0.6, 0.8], [0.3, -0.4]]))
    assert torch.equal(TERMS["axes"].within(beyond), torch.tensor([[1.0, 1.0], [0.3, -0.4]]))


# --------------------------------------------------------------------------- the reference rasterizer


def with_terms(prims: Primitives, seed: int, tilt: float = 0.02, axes: float = 4000.0) -> Primitives:
    """`prims` with random tilts (rad) and curvatures along the axes (1/m) of those magnitudes."""
    generator = torch.Generator().manual_seed(seed)
    count = prims.count
    terms = {"tilt": tilt * (2 * torch.rand(count, 2, generator=generator, dtype=F64) - 1),
             "axes": axes * (2 * torch.rand(count, 2, generator=generator, dtype=F64) - 1)}
    return Primitives(**{name: getattr(prims, name) for name in FIELDS}, terms=terms)


def direct_with_terms(prims: Primitives, width: int, height: int, qpf: str) -> torch.Tensor:
    """method.md §2's hologram with ψ's terms beyond the curvature, each pixel by hand: tilt Δx·t·d and
    ½Δx²(γ_u u² + γ_v v²), u, v the offset along the axes (cos θ, sin θ) and (−sin θ, cos θ)."""
    ys, xs = torch.meshgrid(torch.arange(height, dtype=F64), torch.arange(width, dtype=F64), indexing="ij")
    dx = xs.reshape(1, -1) - prims.position_px[:, :1]
    dy = ys.reshape(1, -1) - prims.position_px[:, 1:]
    cos, sin = torch.cos(prims.rotation_rad)[:, None], torch.sin(prims.rotation_rad)[:, None]
    u, v = cos * dx + sin * dy, -sin * dx + cos * dy
    psi = torch.zeros_like(dx)
    if "tilt" in prims.terms:
        psi = psi + PITCH * (prims.terms["tilt"][:, :1] * dx + prims.terms["tilt"][:, 1:] * dy)
    if "axes" in prims.terms:
        psi = psi + 0.5 * PITCH**2 * (prims.terms["axes"][:, :1] * u * u + prims.terms["axes"][:, 1:] * v * v)
    channels = []
    for c, wavelength in enumerate(WAVELENGTHS):
        rotation = torch.exp(1j * 2 * math.pi / wavelength * psi)  # [N, P]
        per_primitive = torch.stack([direct_hologram(_one(prims, n), width, height, WAVELENGTHS, PITCH, qpf)[c]
                                     .reshape(-1) for n in range(prims.count)])
        channels.append((per_primitive * rotation).sum(0))
    return torch.stack(channels).reshape(len(WAVELENGTHS), height, width)


def _one(prims: Primitives, n: int) -> Primitives:
    return Primitives(**{name: getattr(prims, name)[n:n + 1] for name in FIELDS})


@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
def test_the_reference_sums_the_terms_as_written(qpf):
    width, height = 16, 12
    prims = with_terms(random_prims(6, width, height, seed=31), seed=32)
    ours = rasterize(prims, width, height, WAVELENGTHS, PITCH, qpf, "torch")
    assert float((ours - direct_with_terms(prims, width, height, qpf)).abs().max()) < 1e-9


def test_a_tilt_moves_a_primitive_s_light_sideways():
    """A tilted primitive's field is the flat one's times the carrier exp(i k Δx t·d): its spectrum peaks at t·Δx/λ."""
    width = height = 64
    flat = random_prims(1, width, height, seed=3, scale_range=(6.0, 6.0))
    flat = Primitives(**{**{name: getattr(flat, name) for name in FIELDS},
                         "position_px": torch.tensor([[32.0, 32.0]], dtype=F64), "curvature_per_m": torch.zeros(1, dtype=F64)})
    wavelength = WAVELENGTHS[:1]
    tilt = torch.tensor([[8 / 64 * wavelength[0] / PITCH, -4 / 64 * wavelength[0] / PITCH]], dtype=F64)
    tilted = Primitives(**{name: getattr(flat, name) for name in FIELDS}, terms={"tilt": tilt})
    spectrum = torch.fft.fft2(rasterize(tilted, width, height, wavelength, PITCH, "mahalanobis", "torch")[0]).abs()
    peak = divmod(int(spectrum.argmax()), width)
    assert peak == (64 - 4, 8)  # (row: f_y = −4/64, column: f_x = 8/64) cycles/px


def test_reference_gradients_of_the_terms_match_finite_differences():
    width, height = 12, 10
    prims = with_terms(random_prims(3, width, height, seed=41, scale_range=(1.0, 2.2), position_margin=-2.0), seed=42,
                       tilt=0.03, axes=6000.0)
    assert footprint_margin(prims, width, height) > 1e-3
    leaves = [getattr(prims, name).detach().clone().requires_grad_(True) for name in FIELDS]
    term_leaves = [prims.terms[name].detach().clone().requires_grad_(True) for name in ("tilt", "axes")]

    def render(*params):
        values = Primitives(*params[:7], terms={"tilt": params[7], "axes": params[8]})
        return torch.view_as_real(rasterize(values, width, height, WAVELENGTHS, PITCH, "mahalanobis", "torch"))

    assert torch.autograd.gradcheck(render, leaves + term_leaves, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_raw_terms_take_gradients_through_their_activation():
    config = FitConfig.create(width=16, height=16, color="gray", num_gaussians=6, phase="axes+tilt").validate()
    raw = init_gaussians(6, 1, 16, 16, seed=4, terms=("axes", "tilt")).to("cpu", F64)
    generator = torch.Generator().manual_seed(4)
    leaves = [(0.3 * torch.randn(6, 2, generator=generator, dtype=F64)).requires_grad_(True) for _ in range(2)]

    def render(axes, tilt):
        tensors = {**raw.tensors(), "axes": axes, "tilt": tilt}
        field = rasterize(activate(Gaussians.from_tensors(tensors), config), 16, 16, config.wavelengths,
                          config.optics.pixel_pitch, "mahalanobis", "torch")
        return torch.view_as_real(field)

    assert torch.autograd.gradcheck(render, leaves, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


# --------------------------------------------------------------------------- the Numba kernels


def term_gaussians(config: FitConfig, count: int, seed: int) -> Gaussians:
    """test_ops_cpu's assorted primitives (tiny, huge, needles, at the edges, strongly curved) with random phase
    terms, a third of them at 0 (the kernels' real lanes where the curvature is 0 too)."""
    from test_ops_cpu import random_gaussians

    raw = random_gaussians(count, config.channels, seed, per_channel=config.primitives.curvature == "per-channel")
    if not config.phase.has("quadratic"):
        raw.curvature = torch.zeros_like(raw.curvature)
    generator = torch.Generator().manual_seed(seed + 1)
    raw.terms = {term.name: torch.randn(count, term.parameters, generator=generator, dtype=F64)
                 for term in config.phase.extra_terms}
    for tensor in raw.terms.values():
        tensor[1::3] = 0.0
    return raw


FAST_PHASES = {("axes+tilt", "rgb", "mahalanobis"), ("quadratic+tilt", "gray", "standard"), ("axes", "gray", "mahalanobis")}


@pytest.mark.parametrize("phase, color, qpf", [
    pytest.param(phase, color, qpf, id=f"{phase}-{color}-{qpf}",
                 marks=[] if (phase, color, qpf) in FAST_PHASES else pytest.mark.slow)
    for phase in TERM_PHASES for color in ("rgb", "gray") for qpf in ("mahalanobis", "standard")])
def test_numba_kernels_match_the_reference_with_the_terms(phase, color, qpf):
    import cvqpg.ops.rasterize.cpu as kernels
    from test_ops_cpu import HEIGHT, WIDTH, assert_fused_matches_reference, ways
    from cvqpg.ops.rasterize import wavenumbers_for

    config = FitConfig.create(width=WIDTH, height=HEIGHT, color=color, qpf=qpf, phase=phase).validate()
    prims = activate(term_gaussians(config, 200, seed=5), config)
    offsets = torch.tensor([[-9.0, 3.0], [WIDTH + 4.0, 0.0], [0.0, -HEIGHT - 1.0], [0.0, 30.0]], dtype=F64)
    prims.position_px = torch.cat([prims.position_px[:5], prims.position_px[5:9] + offsets, prims.position_px[9:]])
    assert {kernels.OFF_IMAGE, kernels.TABULATED, kernels.WALKED} <= set(ways(prims, qpf).tolist())
    assert_fused_matches_reference(prims, wavenumbers_for(config.wavelengths), qpf)


def test_needles_walked_from_each_row_s_maximum_carry_the_terms():
    import cvqpg.ops.rasterize.cpu as kernels
    from test_ops_cpu import HEIGHT, WIDTH, assert_fused_matches_reference, ways
    from cvqpg.ops.rasterize import wavenumbers_for

    config = FitConfig.create(width=WIDTH, height=HEIGHT, phase="quadratic+tilt").validate()
    raw = term_gaussians(config, 24, seed=4)
    aspect = torch.linspace(math.log(10.0), math.log(60.0), 24, dtype=F64)
    raw.scale = torch.stack([torch.full_like(aspect, 2.5), 2.5 - aspect], dim=1)
    raw.rotation = torch.linspace(0.0, math.pi, 24, dtype=F64)
    prims = activate(raw, config)
    assert (ways(prims).eq(kernels.WALKED_FROM_RIDGE)).sum() >= 18
    assert_fused_matches_reference(prims, wavenumbers_for(config.wavelengths))


def test_numba_gradients_of_the_terms_match_finite_differences():
    from test_ops_cpu import HEIGHT, WIDTH, outputs_and_gradients, weighted_sum
    from cvqpg.ops.rasterize import splat_fused, splat_reference, wavenumbers_for

    config = FitConfig.create(width=WIDTH, height=HEIGHT, phase="axes+tilt").validate()
    raw = term_gaussians(config, 30, seed=2)
    raw.terms = {name: tensor + 0.1 for name, tensor in raw.terms.items()}
    prims = activate(raw, config)
    k = wavenumbers_for(config.wavelengths)
    _, grads = outputs_and_gradients(splat_fused, prims, k)
    by_name = dict(zip(prims.tensors(), grads))

    def loss(tensors: dict[str, torch.Tensor]) -> float:
        return float(weighted_sum(splat_reference(Primitives.from_tensors(tensors), WIDTH, HEIGHT, k, PITCH,
                                                  "mahalanobis")))

    base = prims.tensors()
    for name, index in (("tilt_rad", (7, 0)), ("tilt_rad", (0, 1)), ("axes_curvature_per_m", (7, 1)),
                        ("axes_curvature_per_m", (2, 0)), ("position_px", (7, 0)), ("rotation_rad", (7,))):
        numeric = central_difference(loss, base, name, index)
        assert math.isclose(float(by_name[name][index]), numeric, rel_tol=1e-3, abs_tol=1e-6), name


# --------------------------------------------------------------------------- the Triton kernels (interpreted on the CPU)


def triton_raw(config: FitConfig, seed: int) -> Gaussians:
    """test_ops_gpu's primitives (tiny, reach beyond the image, a needle) with random phase terms."""
    from test_ops_gpu import COUNT, gaussians

    raw = gaussians(config.channels, "shared" if config.phase.has("quadratic") else "flat", seed)
    generator = torch.Generator().manual_seed(seed + 1)
    terms = {term.name: torch.randn(COUNT, term.parameters, generator=generator, dtype=F64).to(raw.position.device)
             for term in config.phase.extra_terms}
    return Gaussians.from_tensors({**raw.tensors(), **terms})


@pytest.mark.parametrize("phase, color, qpf", [
    pytest.param("axes+tilt", "rgb", "mahalanobis", id="axes+tilt-rgb-mahalanobis"),
    pytest.param("quadratic+tilt", "gray", "standard", id="quadratic+tilt-gray-standard", marks=pytest.mark.slow),
    pytest.param("tilt", "rgb", "standard", id="tilt-rgb-standard", marks=pytest.mark.slow),
    pytest.param("axes", "gray", "mahalanobis", id="axes-gray-mahalanobis", marks=pytest.mark.slow)])
def test_triton_kernels_match_the_reference_with_the_terms(phase, color, qpf):
    from test_ops_gpu import HEIGHT as GPU_HEIGHT, WIDTH as GPU_WIDTH, hologram_and_gradients, relative

    config = FitConfig.create(width=GPU_WIDTH, height=GPU_HEIGHT, color=color, qpf=qpf, phase=phase).validate()
    raw = triton_raw(config, seed=5)
    expected, expected_grads = hologram_and_gradients("torch", raw, config)
    actual, actual_grads = hologram_and_gradients("triton", raw, config)
    assert expected.abs().max() > 0.1 and relative(actual, expected) < 1e-4
    for name, got, want in zip(raw.tensors(), actual_grads, expected_grads):
        assert want.abs().max() > 0 and relative(got, want) < 1e-4, name


def test_triton_gradients_of_the_terms_match_finite_differences():
    from test_ops_gpu import DEVICE, HEIGHT as GPU_HEIGHT, WIDTH as GPU_WIDTH
    from cvqpg.ops.rasterize import splat_reference, splat_triton, wavenumbers_for

    config = FitConfig.create(width=GPU_WIDTH, height=GPU_HEIGHT, phase="axes+tilt").validate()
    prims = activate(triton_raw(config, seed=2), config)
    k = wavenumbers_for(config.wavelengths)
    weights = torch.randn(3, GPU_HEIGHT, GPU_WIDTH, generator=torch.Generator().manual_seed(4), dtype=torch.complex128)

    def loss(backend, tensors: dict[str, torch.Tensor]) -> torch.Tensor:
        hologram = backend(Primitives.from_tensors(tensors), GPU_WIDTH, GPU_HEIGHT, k, PITCH, "mahalanobis")
        return (hologram.to(torch.complex128) * weights.to(DEVICE).conj()).real.sum()

    base = prims.tensors()
    leaves = {name: t.clone().requires_grad_() for name, t in base.items()}
    grads = dict(zip(leaves, torch.autograd.grad(loss(splat_triton, leaves), list(leaves.values()))))
    for name, index in (("tilt_rad", (7, 0)), ("tilt_rad", (8, 1)), ("axes_curvature_per_m", (7, 1)),
                        ("axes_curvature_per_m", (9, 0)), ("position_px", (7, 0)), ("rotation_rad", (7,))):
        numeric = central_difference(lambda tensors: loss(splat_reference, tensors), base, name, index)
        assert math.isclose(float(grads[name][index]), numeric, rel_tol=1e-3, abs_tol=1e-6), name


# --------------------------------------------------------------------------- files


def test_model_files_and_checkpoints_carry_the_terms(tmp_path):
    from cvqpg.errors import CvqpgError
    from cvqpg.fitting import blank_state, state_from_payload
    from cvqpg.storage import load_model, model_info, save_model
    from cvqpg.codec import decode, encode
    from cvqpg.bitdepths import BitDepths

    config = config_of("axes+tilt", "gray")
    raw = random_raw(20, 1, "axes+tilt", seed=3, spread=1.0)
    prims = activate(raw, config)
    save_model(tmp_path / "model.safetensors", prims, config)
    loaded, loaded_config = load_model(tmp_path / "model.safetensors")
    assert loaded_config == config and loaded.tensors().keys() == prims.tensors().keys()
    assert all(torch.equal(loaded.terms[name], prims.terms[name]) for name in prims.terms)
    info = model_info(tmp_path / "model.safetensors")
    assert (info["phase"], info["params_per_primitive"], info["learnable_params"]) == ("axes+tilt", 12, 240)
    state = blank_state(config)
    with torch.no_grad():
        state.gaussians.terms["tilt"].copy_(raw.terms["tilt"])
    restored = state_from_payload(state.to_payload(), config)
    assert torch.equal(restored.gaussians.terms["tilt"], raw.terms["tilt"])
    # a .cvq file keeps the terms (tests/test_codec.py), and codes no curvature for a phase without `quadratic`
    with pytest.raises(CvqpgError, match="`phase` axes\\+tilt has no quadratic term, yet the model's curvatures"):
        encode(prims, config, BitDepths())
    flat = dataclasses.replace(prims, curvature_per_m=torch.zeros_like(prims.curvature_per_m))
    decoded = decode(encode(flat, config, BitDepths()))
    assert decoded.config.phase.name == "axes+tilt" and decoded.primitives.terms.keys() == prims.terms.keys()
    assert not decoded.primitives.curvature_per_m.any()
