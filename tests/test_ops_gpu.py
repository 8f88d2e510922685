"""The Triton rasterizer kernels against the PyTorch reference (float32 kernels vs float64 reference).

Without a GPU they run on the CPU through Triton's interpreter (conftest sets TRITON_INTERPRET=1);
with one, compiled on it. The interpreter runs each program in Python: sizes stay small.
"""

import math
import os
import subprocess
import sys

import pytest
import torch

from cvqpg import FitConfig
from cvqpg.config import ConfigError, RunOptions
from cvqpg import ops
from cvqpg.ops.rasterize import rasterize, resolve_backend, splat_triton, wavenumbers_for
from cvqpg.ops.rasterize.reference import splat_reference
from cvqpg.primitives import Gaussians, Primitives, activate, init_gaussians

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
WIDTH, HEIGHT, COUNT = 24, 16, 12
PITCH = FitConfig().optics.pixel_pitch
KINDS = ["flat", "shared", "per-channel", "channel-bound"]


def gaussians(channels: int, curvature: str, seed: int) -> Gaussians:
    """Random raw primitives (float64) with tiny, large-reach and needle members."""
    g = init_gaussians(COUNT, channels, WIDTH, HEIGHT, seed, per_channel_curvature=curvature == "per-channel")
    gen = torch.Generator().manual_seed(seed)
    g.scale = g.scale + 0.8 * torch.randn(COUNT, 2, generator=gen)
    g.scale[:3] = torch.tensor([[-3.0, -3.0], [3.4, 3.0], [2.2, -2.5]])  # tiny, reach ≫ image, needle
    g.curvature = 0.0 * g.curvature if curvature == "flat" else 2.0 * torch.randn(g.curvature.shape, generator=gen)
    g.amplitude = g.amplitude - 0.2
    g.phase = 3.0 * torch.randn(COUNT, channels, generator=gen)
    return Gaussians.from_tensors({k: v.double().to(DEVICE) for k, v in g.tensors().items()})


def config_for(color: str, qpf: str, curvature: str) -> FitConfig:
    return FitConfig.create(width=WIDTH, height=HEIGHT, color=color, qpf=qpf,
                            curvature="shared" if curvature == "flat" else curvature)


# Centres partly (up to 8 px) and one fully outside the image.
OFFSETS_PX = torch.zeros(COUNT, 2, dtype=torch.float64)
OFFSETS_PX[3:7] = torch.tensor([[-8.0, 2.0], [WIDTH - 2.0, 0.0], [0.0, -HEIGHT + 1.0], [5.0, 40.0]])


def hologram_and_gradients(backend: str, raw: Gaussians, config: FitConfig) -> tuple[torch.Tensor, tuple]:
    """A backend's hologram and the gradients of a random real loss of it for every raw parameter,
    through the activations (positions, scales, rotations, curvatures, colours, phases, opacities)."""
    leaves = {name: t.clone().requires_grad_() for name, t in raw.tensors().items()}
    prims = activate(Gaussians.from_tensors(leaves), config)
    prims.position_px = prims.position_px + OFFSETS_PX.to(DEVICE)
    hologram = rasterize(prims, WIDTH, HEIGHT, config.wavelengths, config.optics.pixel_pitch, config.primitives.qpf, backend)
    weights = torch.randn(hologram.shape, generator=torch.Generator().manual_seed(9), dtype=torch.complex128)
    loss = (hologram.to(torch.complex128) * weights.to(DEVICE).conj()).real.sum()
    return hologram.detach().to(torch.complex128), torch.autograd.grad(loss, list(leaves.values()))


def relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().norm() / b.abs().norm().clamp(min=1e-30))


@pytest.mark.slow
@pytest.mark.parametrize("qpf", ["mahalanobis", "standard"])
@pytest.mark.parametrize("color", ["rgb", "gray"])
@pytest.mark.parametrize("curvature", KINDS)
def test_triton_kernels_match_reference_values_and_gradients(curvature, color, qpf):
    config = config_for(color, qpf, curvature)
    raw = gaussians(config.channels, curvature, seed=5)
    expected, expected_grads = hologram_and_gradients("torch", raw, config)
    actual, actual_grads = hologram_and_gradients("triton", raw, config)
    assert expected.abs().max() > 0.1 and relative(actual, expected) < 1e-4
    for name, got, want in zip(raw.tensors(), actual_grads, expected_grads):
        assert want.abs().max() > 0 and relative(got, want) < 1e-4, name


def test_triton_gradient_matches_finite_differences():
    """Each field of the primitives at one primitive: the kernels' gradient against central differences
    of the float64 reference (per-channel curvature, RGB, Mahalanobis QPF)."""
    config = config_for("rgb", "mahalanobis", "per-channel")
    prims = activate(gaussians(3, "per-channel", seed=2), config)
    k = wavenumbers_for(config.wavelengths)
    weights = torch.randn(3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(4), dtype=torch.complex128)

    def loss(backend, tensors: dict[str, torch.Tensor]) -> torch.Tensor:
        hologram = backend(Primitives.from_tensors(tensors), WIDTH, HEIGHT, k, PITCH, config.primitives.qpf)
        return (hologram.to(torch.complex128) * weights.to(DEVICE).conj()).real.sum()

    base = prims.tensors()
    leaves = {name: t.clone().requires_grad_() for name, t in base.items()}
    grads = dict(zip(leaves, torch.autograd.grad(loss(splat_triton, leaves), list(leaves.values()))))
    for name, index in (("position_px", (7, 0)), ("scale_px", (7, 1)), ("rotation_rad", (7,)), ("amplitude", (7, 2)),
                        ("phase_rad", (7, 0)), ("opacity", (7,)), ("curvature_per_m", (7, 1))):
        eps = 1e-6 * max(1.0, abs(float(base[name][index])))
        plus, minus = ({n: t.clone() for n, t in base.items()} for _ in range(2))
        plus[name][index] += eps
        minus[name][index] -= eps
        numeric = float(loss(splat_reference, plus) - loss(splat_reference, minus)) / (2 * eps)
        assert math.isclose(float(grads[name][index]), numeric, rel_tol=1e-3, abs_tol=1e-6), name


def test_triton_kernels_take_empty_and_offscreen_sets():
    config = config_for("rgb", "mahalanobis", "shared")
    prims = activate(gaussians(3, "shared", seed=1), config)
    prims.position_px = prims.position_px + 500.0
    for count in (COUNT, 0):
        leaves = {name: t[:count].detach().clone().requires_grad_() for name, t in prims.tensors().items()}
        hologram = splat_triton(Primitives.from_tensors(leaves), WIDTH, HEIGHT, wavenumbers_for(config.wavelengths),
                                PITCH, config.primitives.qpf)
        assert hologram.shape == (3, HEIGHT, WIDTH) and torch.count_nonzero(hologram) == 0
        gradients = torch.autograd.grad(hologram.real.sum() + hologram.imag.sum(), list(leaves.values()))
        assert all(g.shape == t.shape and torch.count_nonzero(g) == 0 for g, t in zip(gradients, leaves.values()))


def test_auto_picks_triton_on_cuda_where_it_is_installed(monkeypatch):
    assert resolve_backend("auto", "cuda") == "triton"
    assert resolve_backend("auto", "cpu") == "numba"
    monkeypatch.setattr("cvqpg.config.triton_installed", lambda: False)
    assert resolve_backend("auto", "cuda") == "torch"
    with pytest.raises(ValueError, match="needs the triton package"):
        resolve_backend("triton", "cuda")


def test_triton_on_the_cpu_needs_the_interpreter(monkeypatch):
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    with pytest.raises(ValueError, match="runs on CUDA, not on cpu"):
        resolve_backend("triton", "cpu")
    with pytest.raises(ConfigError, match="`backend` triton runs on CUDA, not on cpu"):
        RunOptions(backend="triton").validate()


# Triton's compiler, run in a process without the interpreter: it rejects code the interpreter runs.
COMPILE_FOR_SM90 = """
import inspect
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource, compile
from cvqpg.ops.rasterize import gpu

for kernel, pointers in ((gpu.splat_forward, 9), (gpu.splat_backward, 15)):
    names = list(inspect.signature(kernel.fn).parameters)
    constants = {"CHANNELS": 3, "CHANNEL_BLOCK": 4, "MAHALANOBIS": True, "HAS_FORM": True, "BLOCK": gpu.BLOCK}
    signature = {name: "constexpr" if name in constants else "*fp32" if i < pointers else "i32"
                 for i, name in enumerate(names)}
    source = ASTSource(fn=kernel, signature=signature,
                       constexprs={(names.index(name),): value for name, value in constants.items()})
    assert compile(source, target=GPUTarget("cuda", 90, 32)).asm["cubin"]
"""


@pytest.mark.slow
def test_kernels_compile_for_a_gpu():
    """Both kernels compile to an sm_90 binary; no GPU needed."""
    environment = {name: value for name, value in os.environ.items() if name != "TRITON_INTERPRET"}
    run = subprocess.run([sys.executable, "-c", COMPILE_FOR_SM90], env=environment, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
