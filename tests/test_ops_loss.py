"""The training loss and the targets' noise (method.md §6): the reference by hand and against pytorch-msssim, the
fused CPU kernels against the reference."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from pytorch_msssim import ssim as msssim_ssim

from cvqpg.ops.loss import multiplane_loss, noisy_targets, ssim_per_plane, standard_normal
from cvqpg.ops.loss.cpu import gaussian_taps, ssim_forward
from cvqpg.targets import plane_masks


# --------------------------------------------------------------------------- loss


def independent_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """SSIM of [C, H, W] images: 11-tap Gaussian (σ 1.5) separable window, valid region, data range 1,
    C1 = 0.01², C2 = 0.03², mean over the map and then over channels (as pytorch-msssim)."""
    taps = np.arange(11) - 5
    g = np.exp(-(taps**2) / (2 * 1.5**2))
    g /= g.sum()
    window = np.outer(g, g)

    def filt(a: np.ndarray) -> np.ndarray:
        h, w = a.shape
        out = np.empty((h - 10, w - 10))
        for i in range(h - 10):
            for j in range(w - 10):
                out[i, j] = (window * a[i:i + 11, j:j + 11]).sum()
        return out

    c1, c2 = 0.01**2, 0.03**2
    per_channel = []
    for a, b in zip(x.astype(np.float64), y.astype(np.float64)):
        mu_a, mu_b = filt(a), filt(b)
        var_a = filt(a * a) - mu_a**2
        var_b = filt(b * b) - mu_b**2
        cov = filt(a * b) - mu_a * mu_b
        ssim_map = ((2 * mu_a * mu_b + c1) / (mu_a**2 + mu_b**2 + c1)) * ((2 * cov + c2) / (var_a + var_b + c2))
        per_channel.append(ssim_map.mean())
    return float(np.mean(per_channel))


def loss_inputs(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    planes, channels, height, width = 2, 3, 16, 19
    targets = torch.rand(planes, channels, height, width, generator=g)
    recon = torch.clamp(targets + 0.2 * torch.randn(planes, channels, height, width, generator=g), 0, 1)
    depth = torch.rand(height, width, generator=g)
    masks = plane_masks(depth, planes)
    normal = torch.randn(planes, channels, height, width, generator=g)
    return recon, targets, masks, normal


def test_noisy_targets_by_hand():
    _, targets, _, normal = loss_inputs()
    targets = targets.clone()
    targets[1] *= 0.5  # different per-plane ranges
    noisy = noisy_targets(targets, normal, 1e-3)
    for m in range(targets.shape[0]):
        spread = float(targets[m].max() - targets[m].min())
        expected = targets[m].double() + 1e-3 * spread * normal[m].double()
        np.testing.assert_allclose(noisy[m].numpy(), expected.numpy(), rtol=0, atol=1e-7)
    assert float(targets[0].max() - targets[0].min()) != pytest.approx(float(targets[1].max() - targets[1].min()))


def test_standard_normal_draws_are_normal_and_reproducible():
    """The targets' noise on the CPU: N(0,1) by moments and Kolmogorov–Smirnov, a pure function of the
    generator's state (whatever the thread count), advancing it, odd sizes included."""
    draws = standard_normal((2, 3, 241, 321), torch.Generator().manual_seed(5))
    values, count = draws.double().flatten().sort().values, draws.numel()
    assert draws.dtype == torch.float32 and draws.shape == (2, 3, 241, 321)
    assert abs(float(values.mean())) < 5 / math.sqrt(count) and abs(float(values.var()) - 1) < 5e-3
    assert float((values**4).mean() / values.var() ** 2) == pytest.approx(3.0, abs=0.02)
    normal_cdf = 0.5 * (1 + torch.erf(values / math.sqrt(2)))
    below, above = torch.arange(count) / count, torch.arange(1, count + 1) / count
    distance = float(torch.maximum(above - normal_cdf, normal_cdf - below).max())  # Kolmogorov–Smirnov
    assert distance < 1.95 / math.sqrt(count)  # its 0.1% critical value
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        again = standard_normal((2, 3, 241, 321), torch.Generator().manual_seed(5))
    finally:
        numba.set_num_threads(threads)
    assert torch.equal(draws, again)
    odd = standard_normal((7,), torch.Generator().manual_seed(5))
    assert torch.equal(odd, standard_normal((8,), torch.Generator().manual_seed(5))[:7])
    generator = torch.Generator().manual_seed(5)
    assert not torch.equal(standard_normal((8,), generator), standard_normal((8,), generator))


def test_ssim_term_matches_independent_ssim():
    recon, targets, _, _ = loss_inputs(1)
    ours = ssim_per_plane(recon, targets)
    for m in range(recon.shape[0]):
        reference = independent_ssim(recon[m].numpy(), targets[m].numpy())
        assert float(ours[m]) == pytest.approx(reference, abs=2e-5)
        library = msssim_ssim(recon[m:m + 1], targets[m:m + 1], data_range=1.0, win_size=11, win_sigma=1.5)
        assert float(ours[m]) == pytest.approx(float(library), abs=1e-6)
    assert float(ssim_per_plane(targets, targets).min()) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("focus_weight, product_weight", [(1.0, 1.0), (0.3, 2.0), (0.0, 0.0)])
def test_multiplane_loss_matches_spec_term_by_term(backend, focus_weight, product_weight):
    recon, targets, masks, normal = loss_inputs(2)
    noisy = noisy_targets(targets, normal, 1e-3)
    weight = 0.005
    loss, mse = multiplane_loss(recon, targets, masks, noisy, weight, backend, focus_weight, product_weight)
    r, t, n, k = (a.double().numpy() for a in (recon, targets, noisy, masks))
    total = 0.0
    expected_mse = []
    for m in range(r.shape[0]):
        mask = k[m][None]
        term_mse = np.mean((r[m] - t[m]) ** 2)
        term_masked = np.mean((r[m] * mask - n[m] * mask) ** 2)
        term_correlation = np.mean((r[m] * n[m] - n[m] * n[m]) ** 2)
        term_ssim = weight * (1 - independent_ssim(r[m], t[m]))
        expected_mse.append(term_mse)
        assert term_masked != pytest.approx(term_mse, rel=1e-3)  # the mask matters
        total += term_mse + focus_weight * term_masked + product_weight * term_correlation + term_ssim
    assert loss.ndim == 0
    assert float(loss) == pytest.approx(total, rel=1e-5, abs=1e-7)
    np.testing.assert_allclose(mse.numpy(), expected_mse, rtol=1e-5)
    assert not mse.requires_grad


def test_multiplane_loss_ssim_weight_enters_linearly():
    recon, targets, masks, normal = loss_inputs(3)
    noisy = noisy_targets(targets, normal, 1e-3)
    base, _ = multiplane_loss(recon, targets, masks, noisy, 0.0)
    weighted, _ = multiplane_loss(recon, targets, masks, noisy, 0.5)
    dissimilarity = sum(1 - independent_ssim(recon[m].numpy(), targets[m].numpy()) for m in range(2))
    assert float(weighted - base) == pytest.approx(0.5 * dissimilarity, rel=1e-4)


def test_multiplane_loss_gradient_flows_to_reconstruction():
    recon, targets, masks, normal = loss_inputs(4)
    recon = recon.clone().requires_grad_(True)
    loss, _ = multiplane_loss(recon, targets, masks, noisy_targets(targets, normal, 1e-3))
    loss.backward()
    assert torch.isfinite(recon.grad).all() and recon.grad.abs().sum() > 0


# --------------------------------------------------------------------------- fast SSIM (CPU kernels)


def test_fused_ssim_kernel_matches_the_formula_on_separably_blurred_moments():
    """`ssim_forward` (moments formed and blurred row by row) against SSIM written out from
    `conv2d` blurs of x, y, x², y², xy, in value and in its three derivative maps."""
    generator = torch.Generator().manual_seed(11)
    x, y = torch.rand(2, 3, 17, 23, dtype=torch.float64, generator=generator)
    taps = gaussian_taps(11, 1.5)
    kernel = torch.from_numpy(taps)

    def blur(images):
        return F.conv2d(F.conv2d(images[:, None], kernel.view(1, 1, 1, 11)), kernel.view(1, 1, 11, 1))[:, 0]

    mx, my, mxx, myy, mxy = (blur(m).requires_grad_(True) for m in (x, y, x * x, y * y, x * y))
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mx * my + c1) * (2 * (mxy - mx * my) + c2)
                / ((mx**2 + my**2 + c1) * (mxx - mx**2 + myy - my**2 + c2)))
    expected = ssim_map.sum(dim=(1, 2))
    partials = torch.autograd.grad(expected.sum(), (mx, mxx, mxy))
    maps = tuple(np.empty((3, 7, 13)) for _ in range(3))
    sums = ssim_forward(x.numpy(), y.numpy(), taps, c1, c2, *maps)
    np.testing.assert_allclose(sums, expected.detach().numpy(), rtol=1e-12)
    for got, want in zip(maps, partials):
        np.testing.assert_allclose(got, want.numpy(), rtol=1e-9, atol=1e-12)


def test_fast_ssim_matches_pytorch_msssim_in_value_and_gradient():
    generator = torch.Generator().manual_seed(12)
    targets = torch.rand(2, 3, 40, 56, generator=generator)
    recon = (targets + 0.2 * torch.randn(targets.shape, generator=generator)).clamp(0, 1)
    grads = {}
    for backend in ("numba", "torch"):
        leaf = recon.clone().requires_grad_(True)
        value = ssim_per_plane(leaf, targets, backend)
        (grads[backend],) = torch.autograd.grad(value.sum(), leaf)
        grads[backend + " value"] = value.detach()
    np.testing.assert_allclose(grads["numba value"].numpy(), grads["torch value"].numpy(), rtol=1e-5)
    scale = float(grads["torch"].abs().max())
    assert float((grads["numba"] - grads["torch"]).abs().max()) <= 1e-4 * scale


@pytest.mark.slow
def test_fast_ssim_gradient_matches_finite_differences():
    generator = torch.Generator().manual_seed(13)
    recon = torch.rand(2, 1, 13, 15, dtype=torch.float64, generator=generator, requires_grad=True)
    targets = torch.rand(2, 1, 13, 15, dtype=torch.float64, generator=generator)
    assert torch.autograd.gradcheck(lambda x: ssim_per_plane(x, targets, "numba"), (recon,))


@pytest.mark.parametrize("seed, weights", [(15, (1.0, 1.0)), (16, (1.0, 1.0)), (16, (0.25, 0.0)), (15, (0.0, 3.0))])
def test_fused_loss_matches_reference_in_value_and_gradient(seed, weights):
    """The CPU kernels' loss against the plain PyTorch formula with pytorch-msssim (backend torch), at the
    paper's weights of the masked and correlation terms and at others."""
    recon, targets, masks, normal = loss_inputs(seed)
    noisy = noisy_targets(targets, normal, 1e-3)
    results = {}
    for backend in ("numba", "torch"):
        leaf = recon.clone().requires_grad_(True)
        loss, mse = multiplane_loss(leaf, targets, masks, noisy, 0.5, backend, *weights)
        (gradient,) = torch.autograd.grad(loss, leaf)
        results[backend] = (loss.detach(), mse, gradient)
    fused, reference = results["numba"], results["torch"]
    assert float(fused[0]) == pytest.approx(float(reference[0]), rel=1e-5)
    np.testing.assert_allclose(fused[1].numpy(), reference[1].numpy(), rtol=1e-5)
    scale = float(reference[2].abs().max())
    assert float((fused[2] - reference[2]).abs().max()) <= 1e-4 * scale


@pytest.mark.slow
def test_fused_loss_gradient_matches_finite_differences():
    recon, targets, masks, normal = (t.double() for t in loss_inputs(17))
    noisy = noisy_targets(targets, normal, 1e-3)
    leaf = recon[:, :, :13, :14].clone().requires_grad_(True)
    crop = (targets[:, :, :13, :14], masks[:, :13, :14], noisy[:, :, :13, :14])
    for weights in ((1.0, 1.0), (0.5, 2.0)):
        assert torch.autograd.gradcheck(lambda x: multiplane_loss(x, crop[0], crop[1], crop[2], 0.5, "numba",
                                                                  *weights)[0], (leaf,))


def test_ssim_of_images_narrower_than_the_window_uses_the_reference():
    generator = torch.Generator().manual_seed(14)
    recon, targets = torch.rand(2, 1, 1, 8, 30, generator=generator)
    with pytest.warns(UserWarning, match="Skipping Gaussian Smoothing"):
        fast = ssim_per_plane(recon, targets, "numba")
        reference = msssim_ssim(recon, targets, data_range=1.0, size_average=False, win_size=11,
                                win_sigma=1.5)
    np.testing.assert_allclose(fast.numpy(), reference.numpy(), rtol=1e-6)
