"""The fused Numba kernels against the PyTorch reference (float32 kernel vs float64 reference)."""

import math

import numba
import numpy as np
import pytest
import torch
from numba.core.errors import TypingError

from cvqpg import ConfigError, FitConfig, builtin_pictures, fit
from cvqpg.config import RunOptions
from cvqpg.control import SILENT
from cvqpg.ops.cpu import cosines_and_sines
from cvqpg.ops.rasterize import cpu as kernels, vectors
from cvqpg.ops.rasterize import rasterize, resolve_backend, splat_fused, wavenumbers_for
from cvqpg.ops.rasterize.reference import FOOTPRINT_SIGMAS, splat_reference, splats
from cvqpg.primitives import COVARIANCE_REGULARISER_PX2, Gaussians, Primitives, activate, init_gaussians

WIDTH, HEIGHT = 56, 40
PITCH = FitConfig().optics.pixel_pitch


def random_gaussians(count: int, channels: int, seed: int, per_channel: bool = False) -> Gaussians:
    """Random primitives with tiny, huge, elongated, edge and strongly curved members."""
    g = init_gaussians(count, channels, WIDTH, HEIGHT, seed, per_channel_curvature=per_channel)
    gen = torch.Generator().manual_seed(seed)
    g.scale = g.scale + 0.8 * torch.randn(count, 2, generator=gen)
    g.scale[:3] = torch.tensor([[-4.0, -4.0], [3.6, 3.2], [2.5, -3.0]])  # tiny, huge, needle
    g.position[3:5] = torch.tensor([[2.5, 0.0], [-1.2, -3.0]])  # centres at the image edge
    g.curvature = 2.0 * torch.randn(g.curvature.shape, generator=gen)
    g.amplitude = g.amplitude - 0.2
    g.phase = 3.0 * torch.randn(count, channels, generator=gen)
    return Gaussians.from_tensors({k: v.double() for k, v in g.tensors().items()})


def weighted_sum(hologram: torch.Tensor) -> torch.Tensor:
    """A real loss of the hologram with random complex weights: its gradient reaches every parameter."""
    weights = torch.randn(hologram.shape, generator=torch.Generator().manual_seed(9), dtype=torch.complex128)
    return (hologram.to(torch.complex128) * weights.conj()).real.sum()


def outputs_and_gradients(backend, prims: Primitives, wavenumbers, qpf: str = "mahalanobis", width: int = WIDTH,
                          height: int = HEIGHT):
    """A backend's hologram and the gradients of `weighted_sum` for every field of the primitives."""
    leaves = {name: t.clone().requires_grad_() for name, t in prims.tensors().items()}
    hologram = backend(Primitives.from_tensors(leaves), width, height, wavenumbers, PITCH, qpf)
    return hologram.detach().to(torch.complex128), torch.autograd.grad(weighted_sum(hologram), list(leaves.values()))


def ways(prims: Primitives, qpf: str = "mahalanobis", width: int = WIDTH, height: int = HEIGHT) -> torch.Tensor:
    """How each primitive goes through the kernels (kernels.TABULATED, WALKED, ...)."""
    s = splats(prims, PITCH, qpf)
    arrays = (t.detach().float().contiguous().numpy() for t in (s.position_px, s.conic, s.reach_px))
    return torch.from_numpy(kernels.ways(*arrays, height, width))


def relative(a, b):
    return float((a - b).abs().norm() / b.abs().norm().clamp(min=1e-30))


def assert_fused_matches_reference(prims: Primitives, wavenumbers, qpf: str = "mahalanobis", width: int = WIDTH,
                                   height: int = HEIGHT):
    """The fused kernels' hologram and every parameter's gradient against the reference's, to 1e-4 relative."""
    expected, expected_grads = outputs_and_gradients(splat_reference, prims, wavenumbers, qpf, width, height)
    actual, actual_grads = outputs_and_gradients(splat_fused, prims, wavenumbers, qpf, width, height)
    assert relative(actual, expected) < 1e-4
    for name, got, want in zip(prims.tensors(), actual_grads, expected_grads):
        assert relative(got, want) < 1e-4, name


# Every primitive, colour and QPF is in the fast subset; the other combinations of them are slow.
FAST_COMBINATIONS = {("cvqpg", "rgb", "mahalanobis"), ("per-channel", "gray", "standard"), ("flat", "rgb", "standard")}


@pytest.mark.parametrize("primitive, color, qpf", [
    pytest.param(primitive, color, qpf, id=f"{primitive}-{color}-{qpf}",
                 marks=[] if (primitive, color, qpf) in FAST_COMBINATIONS else pytest.mark.slow)
    for primitive in ("flat", "cvqpg", "per-channel") for color in ("rgb", "gray")
    for qpf in ("mahalanobis", "standard")])
def test_fused_kernel_matches_reference_values_and_gradients(qpf, color, primitive):
    per_channel = primitive == "per-channel"
    config = FitConfig.create(width=WIDTH, height=HEIGHT, color=color, qpf=qpf,
                              primitive="cvqpg" if per_channel else primitive,
                              curvature="per-channel" if per_channel else "shared")
    raw = random_gaussians(300, config.channels, seed=5, per_channel=per_channel)
    if primitive == "flat":
        raw.curvature = torch.zeros_like(raw.curvature)
    else:
        raw.curvature[::3] = 0.0  # flat and curved primitives in one set: the kernels take each its own way
    prims = activate(raw, config)
    offsets = torch.tensor([[-9.0, 3.0], [WIDTH + 4.0, 0.0], [0.0, -HEIGHT - 1.0], [0.0, 30.0]])
    prims.position_px = torch.cat([prims.position_px[:5], prims.position_px[5:9] + offsets,
                                   prims.position_px[9:]])  # partly and fully off the image
    taken = set(ways(prims, qpf).tolist())  # every way through the kernels: lane tables, centre-column walk, row maxima
    assert {kernels.OFF_IMAGE, kernels.TABULATED, kernels.WALKED, kernels.WALKED_FROM_RIDGE} <= taken, taken
    assert_fused_matches_reference(prims, wavenumbers_for(config.wavelengths), qpf)


def test_any_number_of_channels_matches_reference():
    """Six channels: the lane tables walk the channels four at a time, in two groups."""
    config = FitConfig.create(width=WIDTH, height=HEIGHT)
    raw = random_gaussians(120, 3, seed=6)
    raw.curvature[::4] = 0.0
    six = activate(raw, config)
    six.amplitude = torch.cat([six.amplitude, 0.5 * six.amplitude], dim=1)
    six.phase_rad = torch.cat([six.phase_rad, six.phase_rad.flip(1)], dim=1)
    assert_fused_matches_reference(six, wavenumbers_for(config.wavelengths + (600e-9, 560e-9, 500e-9)))


@pytest.mark.parametrize("curved", [True, pytest.param(False, marks=pytest.mark.slow)],
                         ids=["complex lanes", "real lanes"])
def test_large_primitives_keep_the_agreement_down_hundreds_of_rows(curved):
    """Primitives of 20 to 90 px on a 240×180 image: the lanes step down up to 180 rows in float32.
    Stepping H by Q directly let float32(Q)'s rounding compound (1.3–1.7e-4 here, curved); H + H·(Q − 1)
    keeps it to 3e-5. Without curvature the lanes are real (`kernels._real_lane_tables`)."""
    width, height, count = 240, 180, 40
    config = FitConfig.create(width=width, height=height)
    g = init_gaussians(count, 3, width, height, seed=3)
    gen = torch.Generator().manual_seed(3)
    g.scale = torch.log(torch.empty(count, 2).uniform_(20.0, 90.0, generator=gen))
    g.curvature = (3.0 * torch.rand(count, generator=gen) - 1.5) * curved
    g.phase = 3.0 * torch.randn(count, 3, generator=gen)
    g.opacity = torch.zeros(count)
    prims = activate(Gaussians.from_tensors({k: v.double() for k, v in g.tensors().items()}), config)
    assert (ways(prims, width=width, height=height) == kernels.TABULATED).all()
    assert_fused_matches_reference(prims, wavenumbers_for(config.wavelengths), width=width, height=height)


@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
def test_needles_walked_from_each_rows_maximum_match_reference(qpf):
    """Primitives too elongated for the centre-column walk (aspect 10 to 60, every orientation,
    curved) start each row from exact values at its envelope maximum, unless they are aligned with
    the axes and fit the lane tables; alone, they must still agree."""
    config = FitConfig.create(width=WIDTH, height=HEIGHT, qpf=qpf)
    raw = random_gaussians(24, 3, seed=4)
    aspect = torch.linspace(math.log(10.0), math.log(60.0), 24, dtype=torch.float64)
    raw.scale = torch.stack([torch.full_like(aspect, 2.5), 2.5 - aspect], dim=1)
    raw.rotation = torch.linspace(0.0, math.pi, 24, dtype=torch.float64)
    prims = activate(raw, config)
    taken = ways(prims, qpf)  # axis-aligned needles fit the lane tables (the D² ≤ 100 band keeps their box narrow)
    assert (taken != kernels.WALKED).all() and (taken == kernels.WALKED_FROM_RIDGE).sum() >= 18, taken
    assert_fused_matches_reference(prims, wavenumbers_for(config.wavelengths), qpf)


@pytest.mark.slow
@pytest.mark.parametrize("curvature", ["shared", "per-channel", "channel-bound"])
def test_parameter_gradients_through_activations_match(curvature):
    config = FitConfig.create(width=WIDTH, height=HEIGHT, curvature=curvature)
    raw = random_gaussians(200, 3, seed=11, per_channel=curvature == "per-channel")
    results = []
    for backend in ("torch", "numba"):
        leaves = {k: v.clone().requires_grad_() for k, v in raw.tensors().items()}
        prims = activate(Gaussians.from_tensors(leaves), config)
        hologram = rasterize(prims, WIDTH, HEIGHT, config.wavelengths, config.optics.pixel_pitch, backend=backend)
        loss = (hologram.abs() ** 2).sum()
        results.append(torch.autograd.grad(loss, list(leaves.values())))
    for name, got, want in zip(raw.tensors(), results[1], results[0]):
        assert relative(got, want) < 1e-4, name


@pytest.mark.slow
@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
@pytest.mark.parametrize("curvature", ["shared", "per-channel", "zero"])
def test_fused_gradient_matches_finite_differences(curvature, qpf):
    """Every field of the primitives, including the curvature's gradient at zero, where the kernels take
    real lanes: what CVQPG's curvature starts from when the warm-up ends."""
    config = FitConfig.create(width=WIDTH, height=HEIGHT, curvature="shared" if curvature == "zero" else curvature)
    raw = random_gaussians(40, 3, seed=2, per_channel=curvature == "per-channel")
    if curvature == "zero":
        raw.curvature = torch.zeros_like(raw.curvature)
    prims = activate(raw, config)
    k = wavenumbers_for(config.wavelengths)
    _, grads = outputs_and_gradients(splat_fused, prims, k, qpf)

    def loss(tensors: dict[str, torch.Tensor]) -> float:
        return float(weighted_sum(splat_reference(Primitives.from_tensors(tensors), WIDTH, HEIGHT, k, PITCH, qpf)))

    base = prims.tensors()
    curvature_index = (7, 1) if curvature == "per-channel" else (7,)
    for (name, index), grad in zip((("position_px", (7, 0)), ("scale_px", (7, 1)), ("rotation_rad", (7,)),
                                    ("amplitude", (7, 2)), ("phase_rad", (7, 0)), ("opacity", (7,)),
                                    ("curvature_per_m", curvature_index)), grads):
        eps = 1e-6 * max(1.0, abs(float(base[name][index])))
        plus, minus = ({n: t.clone() for n, t in base.items()} for _ in range(2))
        plus[name][index] += eps
        minus[name][index] -= eps
        numeric = (loss(plus) - loss(minus)) / (2 * eps)
        assert math.isclose(float(grad[index]), numeric, rel_tol=1e-3, abs_tol=1e-6), name


def test_geometry_kernel_matches_the_reference_reduction():
    """`kernels.splat_geometry` against `splats` (Σ⁻¹, footprint radii, chirps), and its gradients against
    autograd's."""
    config = FitConfig.create(width=WIDTH, height=HEIGHT, curvature="per-channel")
    prims = activate(random_gaussians(200, 3, seed=12, per_channel=True), config)
    for qpf in ("mahalanobis", "standard"):
        leaves = {name: t.clone().requires_grad_() for name, t in prims.tensors().items()}
        s = splats(Primitives.from_tensors(leaves), PITCH, qpf)
        g_conic, g_chirp = torch.randn_like(s.conic), torch.randn_like(s.chirp)
        expected = torch.autograd.grad((s.conic * g_conic).sum() + (s.chirp * g_chirp).sum(),
                                       [leaves["scale_px"], leaves["rotation_rad"], leaves["curvature_per_m"]])
        scale, rotation, curvature = (t.detach().float().numpy() for t in (prims.scale_px, prims.rotation_rad,
                                                                            prims.curvature_per_m))
        terms, conic, reach = np.empty((4, 200)), np.empty((200, 3), np.float32), np.empty(200, np.float32)
        chirp = np.empty((200, 3), np.float32)
        kernels.splat_geometry(scale, rotation, curvature, COVARIANCE_REGULARISER_PX2, FOOTPRINT_SIGMAS,
                               0.5 * PITCH**2, qpf == "mahalanobis", terms, conic, reach, chirp)
        assert relative(torch.from_numpy(conic).double(), s.conic.detach()) < 1e-6
        assert relative(torch.from_numpy(reach).double(), s.reach_px) < 1e-6
        assert relative(torch.from_numpy(chirp).double(), s.chirp.detach()) < 1e-6
        actual = np.empty((200, 2)), np.empty(200), np.empty((200, 3))
        kernels.geometry_gradients(scale, curvature, 0.5 * PITCH**2, qpf == "mahalanobis", terms,
                                   g_conic.numpy(), g_chirp.numpy(), *actual)
        for got, want in zip(actual, expected):
            assert relative(torch.from_numpy(got), want) < 1e-6


def test_fused_kernel_handles_empty_and_fully_offscreen_sets():
    config = FitConfig.create(width=WIDTH, height=HEIGHT)
    prims = activate(random_gaussians(8, 3, seed=1), config)
    prims.position_px = prims.position_px + 500.0
    hologram = rasterize(prims, WIDTH, HEIGHT, config.wavelengths, config.optics.pixel_pitch, backend="numba")
    assert hologram.shape == (3, HEIGHT, WIDTH) and torch.count_nonzero(hologram) == 0
    for curvature in (torch.zeros(0), torch.zeros(0, 3)):  # no primitives, shared or per-channel curvature
        empty = Primitives.from_tensors({name: t[:0].clone().requires_grad_() for name, t in prims.tensors().items()})
        empty.curvature_per_m = curvature.requires_grad_()
        hologram = rasterize(empty, WIDTH, HEIGHT, config.wavelengths, config.optics.pixel_pitch, backend="numba")
        assert hologram.shape == (3, HEIGHT, WIDTH) and torch.count_nonzero(hologram) == 0
        gradients = torch.autograd.grad(weighted_sum(hologram), list(empty.tensors().values()))
        assert [g.shape for g in gradients] == [t.shape for t in empty.tensors().values()]


def test_auto_backend_picks_fused_kernels_on_cpu():
    assert resolve_backend("auto", "cpu") == "numba"
    with pytest.raises(ValueError, match="runs on the CPU"):
        resolve_backend("numba", "cuda")
    with pytest.raises(ConfigError, match="`backend`"):
        resolve_backend("opengl", "cpu")


@pytest.mark.slow
def test_fit_with_fused_kernels_matches_the_reference_fit():
    config = FitConfig.create(width=48, height=36, steps=100, curvature_warmup=30, guard_band_px=32)
    builtin = builtin_pictures("demo", config.targets.width, config.targets.height)
    psnr = {backend: fit(builtin.image, builtin.depth, config, RunOptions(backend=backend), SILENT)
            .metrics.mean["psnr"] for backend in ("numba", "torch")}
    assert abs(psnr["numba"] - psnr["torch"]) < 0.01, psnr


def test_cosines_and_sines_match_numpy_over_every_quadrant():
    """The kernels' vectorised cos/sin against libm's, from quadrant boundaries to 1e5 rad."""
    angles = np.concatenate([np.arange(-64, 65) * np.pi / 4, np.linspace(-1e5, 1e5, 20001),
                             np.random.default_rng(3).normal(0.0, 300.0, 20000), [0.0, 1e-300, -1e-12]])
    cosines, sines = np.empty_like(angles), np.empty_like(angles)
    cosines_and_sines(angles, cosines, sines)
    assert np.abs(cosines - np.cos(angles)).max() < 4e-16
    assert np.abs(sines - np.sin(angles)).max() < 4e-16


def test_locality_order_is_a_permutation_by_band_then_column():
    rng = np.random.default_rng(8)
    position = np.concatenate([rng.uniform(-50, 150, (500, 2)), [[1e6, -1e6], [-1e6, 1e6]]]).astype(np.float32)
    order = kernels.locality_order(position, 100, 80)
    assert sorted(order.tolist()) == list(range(len(position)))
    inside = position[order]
    band = np.clip(np.floor(inside[:, 1] / kernels.LOCALITY_BAND_PX), -1, 100 // kernels.LOCALITY_BAND_PX + 1)
    column = np.clip(np.round(inside[:, 0]), -80, 160)
    keys = band * 1000 + column
    assert (np.diff(keys) >= 0).all()


def test_fused_kernel_gives_identical_results_on_reused_buffers():
    """The forward pass reuses its lane images between calls (cleared as they are gathered), the
    backward pass its gradient image: repeated and interleaved calls at two sizes agree bit for bit."""
    config = FitConfig.create(width=WIDTH, height=HEIGHT)
    prims = activate(random_gaussians(120, 3, seed=6), config)
    small = activate(random_gaussians(40, 3, seed=7), config)
    k = wavenumbers_for(config.wavelengths)
    first = outputs_and_gradients(splat_fused, prims, k)
    splat_fused(small, WIDTH // 2, HEIGHT // 2, k, PITCH, "mahalanobis")
    second = outputs_and_gradients(splat_fused, prims, k)
    assert torch.equal(first[0], second[0])
    assert all(torch.equal(a, b) for a, b in zip(first[1], second[1]))


@numba.njit
def _vector_expressions(a, b, low, high, out):
    """Every `vectors` operation once: out[0:8] = (a·b − a) + b where low ≤ position < high (positions
    8..15), out[8:16] = the positions, out[16:24] = low."""
    position = vectors.ramp(8)
    x, y = vectors.load(a, 0), vectors.load(b, 0)
    masked = vectors.where_between(position, vectors.splat(low), vectors.splat(high), x * y - x)
    vectors.store(out, 0, masked + y)
    vectors.store(out, 8, position)
    vectors.store(out, 16, vectors.splat(low))


def test_eight_lane_vectors_match_numpy():
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=8).astype(np.float32), rng.normal(size=8).astype(np.float32)
    out = np.zeros(24, np.float32)
    _vector_expressions(a, b, 10, 13.5, out)
    positions = np.arange(8, 16, dtype=np.float32)
    inside = (positions >= 10) & (positions < 13.5)
    np.testing.assert_allclose(out[:8], np.where(inside, a * b - a, 0.0) + b, rtol=1e-6)
    assert (out[8:16] == positions).all() and (out[16:] == 10).all()
    load = numba.njit(lambda array: vectors.load(array, 0))
    with pytest.raises(TypingError, match="contiguous 1D float32 or float64 array"):
        load(np.zeros(8, np.int64))
    with pytest.raises(TypingError, match="contiguous 1D float32 or float64 array"):
        load(np.zeros(16, np.float32)[::2])


@numba.njit
def _float64_expressions(a, b, c, out, narrow):
    """out[0:4] = a·b − a + b in float64, out[4:8] = c[1:5] widened, times 2.5; narrow[1:5] = out[0:4]
    rounded to float32."""
    x, y = vectors.load(a, 0), vectors.load(b, 0)
    vectors.store(out, 0, x * y - x + y)
    vectors.store(out, 4, vectors.load_float64(c, 1) * vectors.splat_float64(2.5))
    vectors.store_float32(narrow, 1, x * y - x + y)


def test_four_lane_float64_vectors_match_numpy():
    rng = np.random.default_rng(5)
    a, b, c = rng.normal(size=4), rng.normal(size=4), rng.normal(size=6).astype(np.float32)
    out, narrow = np.zeros(8), np.zeros(6, np.float32)
    _float64_expressions(a, b, c, out, narrow)
    np.testing.assert_allclose(out[:4], a * b - a + b, rtol=1e-15)
    assert (out[4:] == c[1:5].astype(np.float64) * 2.5).all()
    assert (narrow[1:5] == (a * b - a + b).astype(np.float32)).all() and narrow[0] == narrow[5] == 0
    with pytest.raises(TypingError, match="a Float32x8 stores into .*, not a Float64x4"):
        _float64_expressions(a, b, c, np.zeros(8, np.float32), narrow)
    with pytest.raises(TypingError, match="store_float32 rounds a Float64x4 into a float32 array"):
        _float64_expressions(a, b, c, out, np.zeros(6))
    with pytest.raises(TypingError, match="load_float64 widens four values of a float32 array"):
        _float64_expressions(a, b, c.astype(np.float64), out, narrow)
