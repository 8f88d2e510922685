"""Rasterizer against an independent per-pixel evaluation of method.md §2, gradients, Nyquist bound (method.md §4)."""

from __future__ import annotations

import gc
import math
import threading
import weakref
from typing import Sequence

import numpy as np
import pytest
import torch

import cvqpg.ops.rasterize as rasterize_module
from cvqpg.config import FitConfig
from cvqpg.primitives import Gaussians, Primitives, activate, curvature_bound, init_gaussians, major_sigma_px
from cvqpg.fitting import render_hologram
from cvqpg.ops.rasterize import rasterize as _rasterize


def rasterize(*args, backend="torch"):
    """These tests hold the PyTorch reference (float64) against method.md §2 written out by hand."""
    return _rasterize(*args, backend=backend)


PITCH = 3.74e-6
WAVELENGTHS = (639e-9, 473e-9)
F64 = torch.float64
FIELDS = ("position_px", "scale_px", "rotation_rad", "amplitude", "phase_rad", "opacity", "curvature_per_m")


# --------------------------------------------------------------------------- independent reference


def sigma_major_reference(scale: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """σ_major from the eigenvalues of the explicitly built 2×2 Σ (no gradient needed: the cutoff is a step)."""
    with torch.no_grad():
        cov = covariance_matrices(scale, rotation)
        return torch.linalg.eigvalsh(cov)[:, -1].sqrt()


def covariance_matrices(scale: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Σ = R S Sᵀ Rᵀ + 0.1 I as [N, 2, 2] matrices, R = [[cos, −sin], [sin, cos]]."""
    cos, sin = torch.cos(rotation), torch.sin(rotation)
    rot = torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)
    s = torch.diag_embed(scale)
    return rot @ s @ s.transpose(-1, -2) @ rot.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=scale.dtype)


def direct_hologram(prims: Primitives, width: int, height: int, wavelengths, pitch: float, qpf: str) -> torch.Tensor:
    """Every primitive at every pixel centre (integer coordinates), complex [C, H, W]; method.md §2 verbatim."""
    cov = covariance_matrices(prims.scale_px, prims.rotation_rad)
    det = torch.clamp(cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0], min=1e-10)
    adj = torch.stack([torch.stack([cov[:, 1, 1], -cov[:, 0, 1]], -1),
                       torch.stack([-cov[:, 1, 0], cov[:, 0, 0]], -1)], -2)
    inverse = adj / det[:, None, None]  # [N, 2, 2]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=F64), torch.arange(width, dtype=F64), indexing="ij")
    pixels = torch.stack([xs, ys], -1).reshape(-1, 2)  # [P, 2] (x, y)
    delta = pixels[None] - prims.position_px[:, None]  # [N, P, 2]
    d2 = torch.einsum("npi,nij,npj->np", delta, inverse, delta)
    r2 = (delta**2).sum(-1)
    reach = 3 * sigma_major_reference(prims.scale_px, prims.rotation_rad)
    inside = torch.sqrt(r2) <= reach[:, None]
    envelope = torch.exp(torch.clamp(-d2 / 2, min=-50.0)) * inside
    k = torch.tensor([2 * math.pi / w for w in wavelengths], dtype=F64)
    channels = []
    for c in range(len(wavelengths)):
        gamma = prims.curvature_per_m if prims.curvature_per_m.dim() == 1 else prims.curvature_per_m[:, c]
        if qpf == "mahalanobis":
            psi = 0.5 * gamma[:, None] * prims.scale_px.prod(-1)[:, None] * pitch**2 * d2
        elif qpf == "standard":
            psi = 0.5 * gamma[:, None] * pitch**2 * r2
        else:
            raise ValueError(qpf)
        amplitude = prims.opacity[:, None] * prims.amplitude[:, c:c + 1] * envelope
        phase = prims.phase_rad[:, c:c + 1] + k[c] * psi
        channels.append((amplitude * torch.exp(1j * phase)).sum(0))
    return torch.stack(channels).reshape(len(wavelengths), height, width)


def footprint_margin(prims: Primitives, width: int, height: int) -> float:
    """Smallest | |p − x| − 3σ_major | over all pixels and primitives (px)."""
    ys, xs = torch.meshgrid(torch.arange(height, dtype=F64), torch.arange(width, dtype=F64), indexing="ij")
    pixels = torch.stack([xs, ys], -1).reshape(-1, 2)
    with torch.no_grad():
        dist = (pixels[None] - prims.position_px[:, None]).norm(dim=-1)
        reach = 3 * sigma_major_reference(prims.scale_px, prims.rotation_rad)
        return float((dist - reach[:, None]).abs().min())


def make_prims(position, scale, rotation, amplitude, phase, opacity, curvature) -> Primitives:
    t = lambda v: torch.as_tensor(v, dtype=F64).clone()  # noqa: E731
    return Primitives(position_px=t(position), scale_px=t(scale), rotation_rad=t(rotation), amplitude=t(amplitude),
                      phase_rad=t(phase), opacity=t(opacity), curvature_per_m=t(curvature))


def random_prims(count: int, width: int, height: int, seed: int, scale_range=(0.3, 4.0),
                 position_margin: float = 4.0, curvature: float = 3000.0) -> Primitives:
    g = torch.Generator().manual_seed(seed)
    u = lambda *shape: torch.rand(*shape, generator=g, dtype=F64)  # noqa: E731
    low, high = scale_range
    position = torch.stack([u(count) * (width + 2 * position_margin) - position_margin,
                            u(count) * (height + 2 * position_margin) - position_margin], -1)
    return Primitives(
        position_px=position,
        scale_px=low + (high - low) * u(count, 2),
        rotation_rad=(2 * u(count) - 1) * math.pi,
        amplitude=u(count, len(WAVELENGTHS)),
        phase_rad=2 * math.pi * u(count, len(WAVELENGTHS)),
        opacity=0.2 + 0.8 * u(count),
        curvature_per_m=(2 * u(count) - 1) * curvature,
    )


def concat(*groups: Primitives) -> Primitives:
    return Primitives(**{name: torch.cat([getattr(g, name) for g in groups]) for name in FIELDS})


def assorted_prims(width: int, height: int) -> Primitives:
    """Rotated anisotropic, tiny, huge (bigger than the image), partly and fully off-image primitives."""
    mixed = random_prims(25, width, height, seed=11)
    tiny = random_prims(6, width, height, seed=12, scale_range=(0.05, 0.3), position_margin=0.0)
    huge = make_prims(
        position=[[width * 0.4, height * 0.6], [-3.0, height + 2.0], [width + 30.0, -20.0]],
        scale=[[14.0, 6.0], [30.0, 25.0], [12.0, 10.0]],
        rotation=[0.7, -2.1, 1.3],
        amplitude=[[0.9, 0.3], [0.5, 0.8], [0.6, 0.4]],
        phase=[[0.3, 5.0], [2.0, 1.0], [4.0, 0.1]],
        opacity=[0.7, 0.4, 0.9],
        curvature=[150.0, -90.0, 60.0],
    )
    off_image = make_prims(
        position=[[-2.5, 5.2], [width + 1.7, 3.3], [6.4, -3.1], [-40.0, -40.0], [width + 25.0, height / 2]],
        scale=[[2.0, 1.2], [1.5, 2.5], [3.0, 0.8], [2.0, 2.0], [1.0, 1.0]],
        rotation=[0.4, 1.1, -0.6, 0.0, 0.2],
        amplitude=[[0.8, 0.2], [0.3, 0.9], [0.5, 0.5], [1.0, 1.0], [1.0, 1.0]],
        phase=[[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [0.0, 0.0], [0.0, 0.0]],
        opacity=[0.6, 0.5, 0.4, 0.9, 0.9],
        curvature=[2000.0, -1500.0, 800.0, 0.0, 0.0],
    )
    return concat(mixed, tiny, huge, off_image)


def with_curvature(prims: Primitives, curvature: torch.Tensor) -> Primitives:
    values = {name: getattr(prims, name) for name in FIELDS}
    values["curvature_per_m"] = curvature
    return Primitives(**values)


def max_abs(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max())


# --------------------------------------------------------------------------- values


@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
@pytest.mark.parametrize("curvature", ["flat", "shared", "per-channel"])
def test_rasterizer_matches_direct_evaluation(qpf, curvature):
    width, height = 24, 18
    prims = assorted_prims(width, height)
    if curvature == "flat":
        prims = with_curvature(prims, torch.zeros_like(prims.curvature_per_m))
    if curvature == "per-channel":
        prims = with_curvature(prims, torch.stack([prims.curvature_per_m, 0.3 - 0.7 * prims.curvature_per_m], 1))
    assert footprint_margin(prims, width, height) > 1e-6
    ours = rasterize(prims, width, height, WAVELENGTHS, PITCH, qpf, backend="torch")
    reference = direct_hologram(prims, width, height, WAVELENGTHS, PITCH, qpf)
    assert ours.shape == (2, height, width) and ours.dtype == torch.complex128
    assert reference.abs().max() > 0.5
    assert max_abs(ours, reference) < 1e-10


@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
def test_single_primitives_each_match(qpf):
    """Each primitive alone (so an error cannot hide in a sum), including the full-image path."""
    width, height = 24, 18
    prims = assorted_prims(width, height)
    for index in range(prims.position_px.shape[0]):
        one = Primitives(**{name: getattr(prims, name)[index:index + 1] for name in FIELDS})
        ours = rasterize(one, width, height, WAVELENGTHS, PITCH, qpf)
        reference = direct_hologram(one, width, height, WAVELENGTHS, PITCH, qpf)
        assert max_abs(ours, reference) < 1e-10, index


def test_fully_off_image_primitive_renders_zero():
    width, height = 16, 12
    prims = make_prims([[-30.0, -30.0], [width + 20.0, 5.0]], [[2.0, 2.0], [1.5, 3.0]], [0.3, 0.0],
                       [[1.0, 1.0], [1.0, 1.0]], [[0.0, 0.0], [0.0, 0.0]], [0.9, 0.9], [100.0, 100.0])
    ours = rasterize(prims, width, height, WAVELENGTHS, PITCH)
    assert torch.all(ours == 0)


def test_exponent_clamp_and_footprint_cutoff():
    """A needle primitive: inside its 3σ_major circle but many σ_minor away the exponent is clamped at −50;
    outside the circle the contribution is exactly zero."""
    width, height = 56, 52
    # major axis along x: σ_major² = 100.1, σ_minor² = 0.01 + 0.1
    prims = make_prims([[20.0, 20.0]], [[10.0, 0.1]], [0.0], [[1e20, 1.0]], [[0.0, 0.0]], [1.0], [0.0])
    ours = rasterize(prims, width, height, WAVELENGTHS, PITCH)
    reference = direct_hologram(prims, width, height, WAVELENGTHS, PITCH, "mahalanobis")
    # (x=20, y=30): D²/2 = 100/(2·0.11) ≫ 50 → clamped: 1e20·e^−50
    clamped = 1e20 * math.exp(-50.0)
    assert ours[0, 30, 20].real.item() == pytest.approx(clamped, rel=1e-12)
    reach = 3 * math.sqrt(100.1)
    ys, xs = np.mgrid[0:height, 0:width]
    outside = np.hypot(xs - 20, ys - 20) > reach
    assert outside.any()
    assert torch.all(ours[:, torch.from_numpy(outside)] == 0)
    assert torch.all(ours[0, torch.from_numpy(~outside)].abs() >= clamped * (1 - 1e-12))
    scale = reference.abs().max().item()
    assert max_abs(ours, reference) <= 1e-12 * scale


def test_major_sigma_is_the_root_of_the_largest_eigenvalue():
    """The footprint's σ_major from the scales alone against the eigenvalues of the built Σ, for
    round, elongated and needle-like primitives at every rotation."""
    gen = torch.Generator().manual_seed(8)
    scale = torch.exp(torch.empty(200, 2, dtype=torch.float64).uniform_(-2.5, 6.0, generator=gen))
    rotation = torch.empty(200, dtype=torch.float64).uniform_(-math.pi, math.pi, generator=gen)
    torch.testing.assert_close(major_sigma_px(scale), sigma_major_reference(scale, rotation), rtol=1e-10, atol=0)


def test_degenerate_covariance_uses_clamped_determinant():
    """Zero scales: Σ = 0.1·I (the +0.1 regulariser keeps det = 0.01 above the 1e-10 floor); the
    rasterizer still matches the direct evaluation."""
    width, height = 9, 7
    prims = make_prims([[4.2, 3.1]], [[0.0, 0.0]], [0.5], [[1.0, 0.5]], [[0.0, 1.0]], [1.0], [500.0])
    ours = rasterize(prims, width, height, WAVELENGTHS, PITCH)
    reference = direct_hologram(prims, width, height, WAVELENGTHS, PITCH, "mahalanobis")
    assert max_abs(ours, reference) < 1e-12


# --------------------------------------------------------------------------- gradients


def gradcheck_prims(qpf: str) -> tuple[Primitives, int, int]:
    width, height = 12, 10
    prims = make_prims(
        position=[[4.3, 3.6], [8.15, 6.4], [2.7, 7.8]],
        scale=[[1.7, 1.1], [1.3, 2.2], [1.05, 0.9]],
        rotation=[0.35, -1.2, 2.4],
        amplitude=[[0.8, 0.4], [0.5, 0.9], [0.7, 0.6]],
        phase=[[0.4, 1.9], [2.6, 5.1], [3.3, 0.7]],
        opacity=[0.7, 0.55, 0.8],
        curvature=[2500.0, -1800.0, 3200.0],
    )
    return prims, width, height


@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
def test_gradcheck_all_activated_parameters(qpf):
    prims, width, height = gradcheck_prims(qpf)
    margin = footprint_margin(prims, width, height)
    assert margin > 1e-3, f"a pixel lies {margin} px from a footprint boundary"
    # exponent clamp is inactive within the footprint for these primitives
    d = direct_hologram(prims, width, height, WAVELENGTHS, PITCH, qpf)
    assert d.abs().max() > 0.1
    leaves = [getattr(prims, name).detach().clone().requires_grad_(True) for name in FIELDS]

    def render(*params):
        return torch.view_as_real(rasterize(Primitives(*params), width, height, WAVELENGTHS, PITCH, qpf))

    assert torch.autograd.gradcheck(render, leaves, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
def test_gradcheck_full_jacobian_small(qpf):
    """Slow-mode gradcheck on a 1-primitive, 1-channel problem (every Jacobian entry)."""
    width, height = 8, 7
    prims = make_prims([[3.4, 3.2]], [[1.6, 1.0]], [0.6], [[0.9]], [[1.2]], [0.75], [2800.0])
    assert footprint_margin(prims, width, height) > 1e-3
    leaves = [getattr(prims, name).detach().clone().requires_grad_(True) for name in FIELDS]

    def render(*params):
        return torch.view_as_real(rasterize(Primitives(*params), width, height, WAVELENGTHS[:1], PITCH, qpf))

    assert torch.autograd.gradcheck(render, leaves, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
def test_gradients_match_direct_evaluation(qpf):
    width, height = 20, 16
    prims = concat(random_prims(30, width, height, seed=21),
                   random_prims(3, width, height, seed=22, scale_range=(7.0, 12.0)))
    assert footprint_margin(prims, width, height) > 1e-6
    g = torch.Generator().manual_seed(23)
    weights = torch.complex(torch.randn(2, height, width, generator=g, dtype=F64),
                            torch.randn(2, height, width, generator=g, dtype=F64))

    def grads(render):
        leaves = [getattr(prims, name).detach().clone().requires_grad_(True) for name in FIELDS]
        hologram = render(Primitives(*leaves))
        loss = (hologram * weights.conj()).real.sum() + (hologram.abs() ** 2).sum()
        return torch.autograd.grad(loss, leaves)

    ours = grads(lambda p: rasterize(p, width, height, WAVELENGTHS, PITCH, qpf))
    reference = grads(lambda p: direct_hologram(p, width, height, WAVELENGTHS, PITCH, qpf))
    for name, a, b in zip(FIELDS, ours, reference):
        scale = max(1.0, float(b.abs().max()))
        assert max_abs(a, b) <= 1e-10 * scale, name
        assert torch.isfinite(a).all()


# --------------------------------------------------------------------------- flat ≡ CVQPG at γ = 0


@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
def test_cvqpg_with_zero_curvature_renders_exactly_as_flat(qpf):
    base = FitConfig.create(width=20, height=16, num_gaussians=40, qpf=qpf)
    raw = init_gaussians(40, 3, 20, 16, seed=7)
    assert torch.all(raw.curvature == 0)
    cvqpg = render_hologram(raw, base.replace(primitive="cvqpg"))
    flat = render_hologram(raw, base.replace(primitive="flat"))
    assert torch.equal(cvqpg, flat)
    assert cvqpg.abs().max() > 0
    activated = activate(raw, base.replace(primitive="cvqpg"))
    assert torch.all(activated.curvature_per_m == 0)
    # and curvature does change the hologram once it is non-zero
    bent = Gaussians.from_tensors({**raw.tensors(), "curvature": torch.full((40,), 0.5)})
    assert not torch.allclose(render_hologram(bent, base.replace(primitive="cvqpg")), flat)


# --------------------------------------------------------------------------- Nyquist bound


def measured_frequency(scale_px: float, curvature: float, qpf: str, radius_px: float,
                       wavelengths=WAVELENGTHS, step_px: float = 0.004) -> np.ndarray:
    """Local fringe frequency (cycles/px) along +x at distance `radius_px` from an isotropic primitive's
    centre, read off the rendered phase: the primitive is moved by ±step/2 px so that one pixel samples the
    phase at r ± step/2 (sub-pixel sampling, so frequencies above 0.5 do not alias)."""
    pixel = int(math.ceil(radius_px)) + 2
    width, height = pixel + 1, 1
    phases = []
    for r in (radius_px - step_px / 2, radius_px + step_px / 2):
        prims = make_prims([[pixel - r, 0.0]], [[scale_px, scale_px]], [0.0],
                           [[1.0] * len(wavelengths)], [[0.0] * len(wavelengths)], [1.0], [curvature])
        field = rasterize(prims, width, height, wavelengths, PITCH, qpf)[:, 0, pixel]
        assert torch.all(field.abs() > 0), "the sample must lie inside the footprint"
        phases.append(torch.angle(field).numpy())
    difference = np.angle(np.exp(1j * (phases[1] - phases[0])))  # step small: no wrapping ambiguity
    return np.abs(difference) / (2 * math.pi * step_px)


def isotropic_bound(scale_px: float, bound: str) -> float:
    config = FitConfig.create(color="rgb", bound=bound)  # λ_min = 473 nm
    return float(curvature_bound(torch.tensor([[scale_px, scale_px]], dtype=F64), config)[0])


@pytest.mark.parametrize("scale_px", [0.8, 2.0, 5.0, 12.0])
def test_adaptive_bound_keeps_edge_frequency_below_nyquist(scale_px):
    gamma_max = isotropic_bound(scale_px, "adaptive")
    expected_gamma = 0.9 * 473e-9 / (6 * scale_px * PITCH**2)
    assert gamma_max == pytest.approx(expected_gamma, rel=1e-12)
    radius = 3 * scale_px  # the paper's 3σ edge, σ = max scale
    wavelengths = (639e-9, 532e-9, 473e-9)
    # standard QPF: frequency γ·r·Δx²/λ, = η/2 · λ_min/λ at the bound
    standard = measured_frequency(scale_px, gamma_max, "standard", radius, wavelengths)
    np.testing.assert_allclose(standard, [0.45 * 473e-9 / w for w in wavelengths], rtol=1e-6)
    assert np.all(standard <= 0.5)
    # Mahalanobis QPF (isotropic): γ s² Δx² r / ((s² + 0.1) λ) ≤ the same bound
    mahalanobis = measured_frequency(scale_px, gamma_max, "mahalanobis", radius, wavelengths)
    factor = scale_px**2 / (scale_px**2 + 0.1)
    np.testing.assert_allclose(mahalanobis, [0.45 * factor * 473e-9 / w for w in wavelengths], rtol=1e-6)
    assert np.all(mahalanobis <= 0.5)
    # a primitive whose raw curvature saturates tanh reaches the bound
    config = FitConfig.create(color="rgb")
    raw = Gaussians(position=torch.zeros(1, 2, dtype=F64),
                    scale=torch.tensor([[math.log(scale_px - 0.1)] * 2], dtype=F64),
                    rotation=torch.zeros(1, dtype=F64), amplitude=torch.ones(1, 3, dtype=F64),
                    phase=torch.zeros(1, 3, dtype=F64), opacity=torch.zeros(1, dtype=F64),
                    curvature=torch.tensor([40.0], dtype=F64))
    assert float(activate(raw, config).curvature_per_m[0]) == pytest.approx(gamma_max, rel=1e-12)


@pytest.mark.parametrize("curvature", ["per-channel", "channel-bound"])
def test_per_channel_bounds_put_every_channel_at_the_same_edge_frequency(curvature):
    """Each channel bounded by its own λ_c: every colour's 3σ fringe reaches η/2, not only blue's."""
    scale_px, wavelengths = 3.0, (639e-9, 532e-9, 473e-9)
    config = FitConfig.create(color="rgb", curvature=curvature)
    bound = curvature_bound(torch.tensor([[scale_px, scale_px]], dtype=F64), config)[0]
    np.testing.assert_allclose(bound.numpy(), [0.9 * w / (6 * scale_px * PITCH**2) for w in wavelengths],
                               rtol=1e-12)
    standard = measured_frequency(scale_px, bound.tolist(), "standard", 3 * scale_px, wavelengths)
    np.testing.assert_allclose(standard, [0.45] * 3, rtol=1e-6)
    shared = measured_frequency(scale_px, isotropic_bound(scale_px, "adaptive"), "standard", 3 * scale_px,
                                wavelengths)
    assert shared[0] < 0.75 * 0.45  # the shared bound leaves red at λ_min/λ_red of Nyquist's share
    saturated = torch.full((1, 3) if curvature == "per-channel" else (1,), 40.0, dtype=F64)
    raw = Gaussians(position=torch.zeros(1, 2, dtype=F64),
                    scale=torch.tensor([[math.log(scale_px - 0.1)] * 2], dtype=F64),
                    rotation=torch.zeros(1, dtype=F64), amplitude=torch.ones(1, 3, dtype=F64),
                    phase=torch.zeros(1, 3, dtype=F64), opacity=torch.zeros(1, dtype=F64), curvature=saturated)
    np.testing.assert_allclose(activate(raw, config).curvature_per_m[0].numpy(), bound.numpy(), rtol=1e-12)


def test_channel_bound_curvature_gives_every_channel_the_same_phase():
    """One raw curvature times each channel's λ_c-proportional bound: k_c γ_c is the same for all c."""
    config = FitConfig.create(width=24, height=18, color="rgb", curvature="channel-bound")
    raw = init_gaussians(30, 3, 24, 18, seed=3)
    raw.curvature = torch.linspace(-2.0, 2.0, 30)
    raw.phase = torch.zeros(30, 3)
    raw.amplitude = torch.ones(30, 3)
    hologram = render_hologram(raw, config)
    np.testing.assert_allclose(hologram[0].numpy(), hologram[2].numpy(), rtol=1e-5, atol=1e-6)
    shared = render_hologram(raw, config.replace(curvature="shared"))
    assert not torch.allclose(shared[0], shared[2], atol=1e-3)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_equal_per_channel_curvatures_render_as_one_shared_curvature(backend):
    prims = random_prims(25, 20, 14, seed=8)
    per_channel = with_curvature(prims, prims.curvature_per_m[:, None].expand(-1, 2).contiguous())
    shared = rasterize(prims, 20, 14, WAVELENGTHS, PITCH, "mahalanobis", backend=backend)
    separate = rasterize(per_channel, 20, 14, WAVELENGTHS, PITCH, "mahalanobis", backend=backend)
    torch.testing.assert_close(separate, shared, rtol=0, atol=0)
    different = with_curvature(prims, torch.stack([prims.curvature_per_m, -prims.curvature_per_m], dim=1))
    bent = rasterize(different, 20, 14, WAVELENGTHS, PITCH, "mahalanobis", backend=backend)
    torch.testing.assert_close(bent[0], shared[0], rtol=0, atol=0)
    assert not torch.allclose(bent[1], shared[1], atol=1e-3)


def test_neighbour_pixel_phase_difference_at_edge_below_half_cycle():
    """The brief's measurement: unwrapped phase difference of neighbouring pixels near 3σ, at γ_max."""
    scale = 4.0
    gamma_max = isotropic_bound(scale, "adaptive")
    width, height = 32, 5
    prims = make_prims([[8.0, 2.0]], [[scale, scale]], [0.0], [[1.0]], [[0.0]], [1.0], [gamma_max])
    for qpf in ("standard", "mahalanobis"):
        field = rasterize(prims, width, height, (473e-9,), PITCH, qpf)[0, 2]
        phase = np.unwrap(torch.angle(field[8:8 + 13]).numpy())  # centre → r = 12 = 3σ
        cycles_per_px = np.diff(phase) / (2 * math.pi)
        assert np.all(np.abs(cycles_per_px) <= 0.5)
        # the last difference straddles r ∈ [11, 12]: ≈ 0.45 · 11.5/12 (standard)
        if qpf == "standard":
            assert abs(cycles_per_px[-1]) == pytest.approx(0.45 * 11.5 / 12, rel=1e-6)


def test_global_bound_exceeds_nyquist_only_for_large_primitives():
    """γ = 200 1/m: edge frequency 200·3σ·Δx²/λ crosses 0.5 at σ ≈ 28 px (473 nm). It is *large*
    primitives, not small ones, whose 3σ edge the global bound lets exceed Nyquist; for small ones the
    global bound is far stricter than the adaptive one."""
    crossing = 0.5 * 473e-9 / (3 * 200.0 * PITCH**2)
    assert 27 < crossing < 29
    small, large = 1.0, 40.0
    assert isotropic_bound(small, "global") == 200.0
    assert isotropic_bound(small, "adaptive") > 20 * 200.0  # ≈ 5073 1/m
    assert isotropic_bound(large, "adaptive") < 200.0
    for qpf in ("standard", "mahalanobis"):
        f_small = measured_frequency(small, 200.0, qpf, 3 * small, (473e-9,))[0]
        f_large = measured_frequency(large, 200.0, qpf, 3 * large, (473e-9,))[0]
        assert f_small < 0.05
        assert f_large > 0.5
        shrink = 1 if qpf == "standard" else large**2 / (large**2 + 0.1)
        assert f_large == pytest.approx(200.0 * 3 * large * PITCH**2 / 473e-9 * shrink, rel=1e-5)
        # the adaptive bound keeps the large primitive under Nyquist
        assert measured_frequency(large, isotropic_bound(large, "adaptive"), qpf, 3 * large, (473e-9,))[0] < 0.5


# --------------------------------------------------------------------------- the CPU kernels' kept buffers


def kept_buffers_after_a_step(prims: Primitives, sizes: Sequence[tuple[int, int]]) -> list[weakref.ref]:
    """Rasterize (forward and backward, Numba) at each W×H in turn; weak references to the lane images the
    calling thread keeps afterwards."""
    for width, height in sizes:
        leaves = [t.clone().requires_grad_() for t in (prims.position_px, prims.amplitude)]
        moved = Primitives(**{**{name: getattr(prims, name) for name in FIELDS}, "position_px": leaves[0],
                              "amplitude": leaves[1]})
        _rasterize(moved, width, height, WAVELENGTHS, PITCH, backend="numba").abs().sum().backward()
    return [weakref.ref(array) for array in vars(rasterize_module._kept).values()]


def test_a_thread_keeps_one_buffer_per_pass_and_frees_them_when_it_ends():
    prims = random_prims(20, 20, 14, seed=3)
    kept: list[list[weakref.ref]] = []
    worker = threading.Thread(target=lambda: kept.append(kept_buffers_after_a_step(prims, [(20, 14), (24, 16)])))
    worker.start()
    worker.join()
    assert len(kept[0]) == 2  # the forward pass's partial images and the backward pass's lanes, of the last size
    gc.collect()
    assert all(ref() is None for ref in kept[0])


def test_release_buffers_frees_the_calling_threads_buffers():
    refs = kept_buffers_after_a_step(random_prims(20, 20, 14, seed=4), [(20, 14)])
    assert [ref() is not None for ref in refs] == [True, True]
    rasterize_module.release_buffers()
    gc.collect()
    assert all(ref() is None for ref in refs)
