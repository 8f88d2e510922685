"""Hologram field, guard band and BLASM propagation (method.md §3)."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

from cvqpg.config import FitConfig
from cvqpg.ops import propagation
from cvqpg.ops.field import Grid, clamped_intensity, guard_window, guarded_field, pad_with_guard_band, slm_field
from cvqpg.ops.propagation import TransferBank, propagate, propagate_content, propagate_planes, transfer_function
from cvqpg.ops.propagation import cpu as propagation_kernels, reference as propagation_reference
from cvqpg.optics import reconstruct

CPU = torch.device("cpu")
PITCH = 3.74e-6
RED, BLUE = 639e-9, 473e-9


def odak_kernel(rows: int, cols: int, wavelength: float, distance: float) -> torch.Tensor:
    from odak.learn.wave import get_propagation_kernel

    logging.disable(logging.WARNING)  # odak logs one warning per kernel
    try:
        return get_propagation_kernel(nu=rows, nv=cols, dx=PITCH, wavelength=wavelength, distance=distance,
                                      device=CPU, propagation_type="Bandlimited Angular Spectrum")
    finally:
        logging.disable(logging.NOTSET)


def centred_pad(field: torch.Tensor) -> torch.Tensor:
    """[C, P_H, P_W] → [C, 2P_H, 2P_W], content at (P_H//2, P_W//2) as method.md §3 / odak place it."""
    channels, rows, cols = field.shape
    padded = field.new_zeros(channels, 2 * rows, 2 * cols)
    padded[:, rows // 2:rows // 2 + rows, cols // 2:cols // 2 + cols] = field
    return padded


def centre_crop(padded: torch.Tensor, rows: int, cols: int) -> torch.Tensor:
    return padded[..., rows // 2:rows // 2 + rows, cols // 2:cols // 2 + cols]


def spec_propagate(field: torch.Tensor, distance: float, wavelengths: list[float]) -> torch.Tensor:
    """method.md §3 written out literally with odak's kernel: pad, fftshift(fft2), ×H, ifft2(ifftshift), crop."""
    _, rows, cols = field.shape
    padded = centred_pad(field)
    out = []
    for c, wavelength in enumerate(wavelengths):
        kernel = odak_kernel(2 * rows, 2 * cols, wavelength, distance)
        spectrum = torch.fft.fftshift(torch.fft.fft2(padded[c]))
        out.append(torch.fft.ifft2(torch.fft.ifftshift(spectrum * kernel)))
    return centre_crop(torch.stack(out), rows, cols)


def band_limited(field: torch.Tensor, distance: float, wavelengths: list[float]) -> torch.Tensor:
    """The padded field with its (centred) spectrum multiplied by the BLASM passband, uncropped."""
    _, rows, cols = field.shape
    padded = centred_pad(field)
    out = []
    for c, wavelength in enumerate(wavelengths):
        passband = (transfer_function(2 * rows, 2 * cols, PITCH, wavelength, distance, CPU).abs() > 0)
        spectrum = torch.fft.fftshift(torch.fft.fft2(padded[c]))
        out.append(torch.fft.ifft2(torch.fft.ifftshift(spectrum * passband)))
    return torch.stack(out)


# --------------------------------------------------------------------------- transfer function


@pytest.mark.parametrize("rows, cols", [(48, 64), (64, 40)])
@pytest.mark.parametrize("distance", [1e-3, 5e-3])
@pytest.mark.parametrize("wavelength", [RED, BLUE])
def test_transfer_function_equals_odak_on_non_square_grids(rows, cols, distance, wavelength):
    ours = transfer_function(rows, cols, PITCH, wavelength, distance, CPU)
    reference = odak_kernel(rows, cols, wavelength, distance)
    assert ours.shape == reference.shape == (rows, cols)
    assert ours.dtype == torch.complex64
    assert (ours - reference).abs().max().item() < 1e-5


@pytest.mark.parametrize("rows, cols, distance, wavelength", [
    (64, 40, 1e-3, RED),    # the band limit cuts ~12% of this grid's frequencies, unequally per axis
    (48, 64, 5e-3, BLUE),   # most frequencies cut
    (40, 56, 2e-2, RED),    # larger distance, small grid
])
def test_transfer_function_equals_odak_where_band_limit_cuts(rows, cols, distance, wavelength):
    ours = transfer_function(rows, cols, PITCH, wavelength, distance, CPU)
    reference = odak_kernel(rows, cols, wavelength, distance)
    passband = ours.abs() > 0.5
    fraction = passband.double().mean().item()
    assert 0.0 < fraction < 1.0, "the band limit should cut some, but not all, frequencies"
    assert torch.equal(passband, reference.abs() > 0.5)
    assert (ours - reference).abs().max().item() < 1e-5
    # unit modulus in the passband, exactly zero outside it
    assert torch.allclose(ours.abs()[passband], torch.ones(()), atol=1e-6)
    assert torch.all(ours[~passband] == 0)


@pytest.mark.parametrize("rows, cols", [(64, 40), (33, 50)])
def test_uncentred_transfer_function_is_the_ifftshift_of_the_centred_one(rows, cols):
    centred = transfer_function(rows, cols, PITCH, BLUE, 2e-3, CPU)
    uncentred = transfer_function(rows, cols, PITCH, BLUE, 2e-3, CPU, centred=False)
    assert torch.equal(uncentred, torch.fft.ifftshift(centred))


def test_transfer_function_band_limit_uses_odak_axis_convention():
    """On a non-square grid each axis' band limit uses the *other* axis' length (odak 0.2.7)."""
    rows, cols, distance, wavelength = 64, 40, 1e-3, RED
    ours = transfer_function(rows, cols, PITCH, wavelength, distance, CPU)
    f_rows = np.linspace(-1 / (2 * PITCH) + 0.5 / (2 * rows * PITCH), 1 / (2 * PITCH) - 0.5 / (2 * rows * PITCH), rows)
    f_cols = np.linspace(-1 / (2 * PITCH) + 0.5 / (2 * cols * PITCH), 1 / (2 * PITCH) - 0.5 / (2 * cols * PITCH), cols)
    limit_for_cols = 1 / math.sqrt((2 * distance / (rows * PITCH)) ** 2 + 1) / wavelength
    limit_for_rows = 1 / math.sqrt((2 * distance / (cols * PITCH)) ** 2 + 1) / wavelength
    expected = (np.abs(f_rows)[:, None] < limit_for_rows) & (np.abs(f_cols)[None, :] < limit_for_cols)
    assert 0 < expected.mean() < 1
    np.testing.assert_array_equal((ours.abs() > 0.5).numpy(), expected)
    phase = 2 * np.pi * distance * np.sqrt(1 / wavelength**2 - f_rows[:, None] ** 2 - f_cols[None, :] ** 2)
    expected_kernel = expected * np.exp(1j * phase)
    # float32 phase of ~1e4 rad: agreement to float32 resolution of the phase
    assert np.abs(ours.numpy().astype(np.complex128) - expected_kernel).max() < 2e-2


@pytest.mark.parametrize("rows, cols", [(64, 40), (1536, 1920)])
@pytest.mark.parametrize("transposed", [False, True], ids=["rows-first", "transposed"])
def test_transfer_bank_halves_hold_the_whole_functions_exactly(rows, cols, transposed):
    """In FFT order a BLASM transfer function is even about the middle of its axes, exactly so in
    float32, so the bank keeps half of each: mirrored, the half is the whole function bit for bit
    (on a small grid and on the 640×480 fit's doubled grid)."""
    distances, wavelengths = (1e-3, 5e-3), (RED, BLUE)
    bank = TransferBank(rows, cols, PITCH, wavelengths, distances, CPU, transposed)
    for plane, distance in enumerate(distances):
        for channel, wavelength in enumerate(wavelengths):
            whole = transfer_function(rows, cols, PITCH, wavelength, distance, CPU, centred=False)
            whole = whole.T if transposed else whole
            assert bank.half(plane, channel).shape[0] == whole.shape[0] // 2
            assert torch.equal(bank(plane, channel), whole)


# --------------------------------------------------------------------------- propagation


def test_propagate_matches_spec_recipe_with_odak_kernel():
    generator = torch.Generator().manual_seed(0)
    field = torch.complex(torch.randn(2, 24, 20, generator=generator, dtype=torch.float64),
                          torch.randn(2, 24, 20, generator=generator, dtype=torch.float64))
    for distance in (1e-3, 5e-3):
        ours = propagate(field, [distance], [RED, BLUE], PITCH)
        assert ours.shape == (1, 2, 24, 20)
        reference = spec_propagate(field, distance, [RED, BLUE])
        assert (ours[0] - reference).abs().max().item() < 1e-6 * field.abs().max().item()
    both = propagate(field, [1e-3, 5e-3], [RED, BLUE], PITCH)
    assert torch.allclose(both[1], propagate(field, [5e-3], [RED, BLUE], PITCH)[0])


@pytest.mark.parametrize("dtype", [torch.complex64, torch.complex128])
def test_propagation_transpose_moves_exactly_the_values_it_names(dtype):
    """The CPU kernel behind the pruned propagation, between views into wider arrays as the
    propagation uses it (into columns of a zero-margined array, out of a window of columns): odd
    sizes, both precisions, nothing outside the target view touched."""
    generator = torch.Generator().manual_seed(8)
    source = torch.complex(torch.randn(13, 21, generator=generator), torch.randn(13, 21, generator=generator)).to(dtype)
    wide = torch.full((21, 40), 7.0 + 0j, dtype=dtype)
    propagation_kernels.transpose(source.numpy(), wide[:, 5:18].numpy())
    assert torch.equal(wide[:, 5:18], source.T)
    assert (wide[:, :5] == 7).all() and (wide[:, 18:] == 7).all()
    window = torch.full((9, 25), 3.0 + 0j, dtype=dtype)
    propagation_kernels.transpose(wide[:, 6:15].numpy(), window[:, 2:23].numpy())
    assert torch.equal(window[:, 2:23], wide[:, 6:15].T)
    assert (window[:, :2] == 3).all() and (window[:, 23:] == 3).all()


@pytest.mark.parametrize("kernels, cached", [
    (True, True), pytest.param(True, False, marks=pytest.mark.slow), pytest.param(False, True, marks=pytest.mark.slow),
    pytest.param(False, False, marks=pytest.mark.slow)],
    ids=["cpu-kernels-cached", "cpu-kernels-rebuilt", "torch-copies-cached", "torch-copies-rebuilt"])
def test_pruned_content_propagation_and_its_adjoint_match_the_full_transforms(kernels, cached, monkeypatch):
    """`propagate_content` (pruned transforms, hand-written adjoint) against autograd through the plain
    `propagate` in float64: at float32, on a wide grid like the paper's (content off-centre in its
    padded array, three channels, two planes, spectra in several blocks), the same numbers to float32
    noise, forward and adjoint; a second call reuses the zero-margined arrays and gives the same
    numbers. With the kernels switched off the transposes are the PyTorch copies that other devices
    (CUDA) run; transfer functions are kept in memory or rebuilt on demand (large grids), once per
    pass."""
    builds = []
    if not cached:
        monkeypatch.setattr(propagation_reference, "TRANSFER_CACHE_BYTES", 0)
        build_half = TransferBank.build_half
        monkeypatch.setattr(TransferBank, "build_half", lambda bank, *key: builds.append(key) or build_half(bank, *key))
    monkeypatch.setattr(propagation, "SPECTRUM_BLOCK_ROWS", 48)
    grid = Grid(height=30, width=44, padded_height=64, padded_width=80)
    generator = torch.Generator().manual_seed(12)
    field = torch.complex(torch.randn(3, 64, 80, generator=generator), torch.randn(3, 64, 80, generator=generator))
    upstream = torch.complex(torch.randn(2, 3, 30, 44, generator=generator),
                             torch.randn(2, 3, 30, 44, generator=generator))
    distances, wavelengths = [1e-3, 5e-3], [RED, 532e-9, BLUE]
    runs = []
    for _ in range(2):
        leaf = field.clone().requires_grad_(True)
        content = propagate_content(leaf, grid, distances, wavelengths, PITCH, fused=kernels)
        (content * upstream.conj()).real.sum().backward()
        runs.append((content.detach(), leaf.grad))
    built_in_runs = len(builds)
    reference_leaf = field.to(torch.complex128).requires_grad_(True)
    reference = grid.crop(propagate(reference_leaf, distances, wavelengths, PITCH))
    (reference * upstream.to(torch.complex128).conj()).real.sum().backward()
    reference = reference.detach()
    assert reference_leaf.grad.abs().max() > 0.1
    for content, gradient in runs:
        assert content.dtype == torch.complex64
        assert float((content - reference).abs().max() / reference.abs().max()) < 1e-5
        assert float((gradient - reference_leaf.grad).abs().max() / reference_leaf.grad.abs().max()) < 1e-5
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])
    # rebuilt functions are built once per pass, not once per block (a 3840×2160 build takes seconds)
    assert built_in_runs == (0 if cached else 2 * 2 * len(distances) * len(wavelengths))


def test_the_torch_and_numba_backends_give_the_same_reconstruction_and_gradient():
    """`reconstruct` through the full-grid transforms and the PyTorch formulas (`--backend torch`, the
    transforms of CUDA too) and through the pruned transforms and the CPU kernels (`numba`): the same
    intensities and hologram gradient to float32 noise."""
    config = FitConfig.create(width=40, height=28, guard_band_px=8, pad_multiple_px=8)
    generator = torch.Generator().manual_seed(4)
    hologram = 0.6 * torch.complex(torch.randn(3, 28, 40, generator=generator),
                                   torch.randn(3, 28, 40, generator=generator))
    upstream = torch.rand(2, 3, 28, 40, generator=generator)
    results = {}
    for backend in ("torch", "numba"):
        leaf = hologram.clone().requires_grad_(True)
        recon = reconstruct(leaf, config, backend=backend)
        (recon * upstream).sum().backward()
        results[backend] = recon.detach(), leaf.grad
    (full, full_grad), (pruned, pruned_grad) = results["torch"], results["numba"]
    assert full.shape == pruned.shape == (2, 3, 28, 40) and full.max() > 0.01
    assert float((full - pruned).abs().max()) < 1e-5 * float(full.abs().max()) + 1e-7
    assert float((full_grad - pruned_grad).abs().max()) < 1e-4 * float(full_grad.abs().max())


def test_the_backend_picks_the_pruned_transforms_with_the_cpu_kernels_and_else_the_full_grid_reference():
    grid = Grid(height=12, width=20, padded_height=32, padded_width=40)
    generator = torch.Generator().manual_seed(5)
    field = torch.complex(torch.randn(2, 32, 40, generator=generator), torch.randn(2, 32, 40, generator=generator))
    optics = ([1e-3, 5e-3], [RED, BLUE], PITCH)
    pruned = propagate_content(field, grid, *optics, fused=True)
    assert torch.equal(propagate_planes(field, grid, *optics, "numba"), pruned)
    assert torch.equal(propagate_planes(field, grid, *optics), pruned)  # auto, on the CPU
    assert torch.equal(propagate_planes(field, grid, *optics, "torch"), grid.crop(propagate(field, *optics)))


def test_a_recorded_config_with_the_former_propagation_setting_still_loads():
    assert FitConfig.from_dict({**FitConfig.create().to_dict(), "propagation": "pruned"}) == FitConfig.create()


def test_energy_conserved_equals_band_limited_input_energy():
    """Uncropped pipeline: ‖ifft2(fft2(pad U) · H)‖² = ‖band-limited pad U‖² (Parseval, |H| ∈ {0, 1})."""
    generator = torch.Generator().manual_seed(1)
    rows, cols, distance = 32, 20, 1e-3
    wavelengths = [RED, BLUE]
    field = torch.complex(torch.randn(2, rows, cols, generator=generator, dtype=torch.float64),
                          torch.randn(2, rows, cols, generator=generator, dtype=torch.float64))
    padded = centred_pad(field)
    input_energy = (padded.abs() ** 2).sum().item()
    band = band_limited(field, distance, wavelengths)
    band_energy = (band.abs() ** 2).sum().item()
    assert band_energy < 0.999 * input_energy, "choose a case where the band limit removes energy"
    outputs = []
    for c, wavelength in enumerate(wavelengths):
        transfer = torch.fft.ifftshift(transfer_function(2 * rows, 2 * cols, PITCH, wavelength, distance, CPU))
        outputs.append(torch.fft.ifft2(torch.fft.fft2(padded[c]) * transfer))
    output = torch.stack(outputs)
    output_energy = (output.abs() ** 2).sum().item()
    assert abs(output_energy - band_energy) <= 1e-4 * band_energy
    # per channel too
    for c in range(2):
        e_out = (output[c].abs() ** 2).sum().item()
        e_band = (band[c].abs() ** 2).sum().item()
        assert abs(e_out - e_band) <= 1e-4 * e_band
    # and `propagate` is the centre crop of this uncropped pipeline
    cropped = propagate(field, [distance], wavelengths, PITCH)[0]
    assert (cropped - centre_crop(output, rows, cols)).abs().max().item() < 1e-9


def gaussian_blob(n: int, width_px: float) -> torch.Tensor:
    y = torch.arange(n, dtype=torch.float64) - n // 2
    return torch.exp(-(y[:, None] ** 2 + y[None, :] ** 2) / width_px**2).to(torch.complex128)


@pytest.mark.parametrize("distance, wavelength", [(1e-3, RED), (1e-3, BLUE), (3e-3, RED), (3e-3, BLUE)])
def test_propagate_forward_then_back_returns_band_limited_field(distance, wavelength):
    n = 64
    field = torch.stack([gaussian_blob(n, 5.0), 0.5j * gaussian_blob(n, 4.0)])
    wavelengths = [wavelength, RED]
    away = propagate(field, [distance], wavelengths, PITCH)[0]
    assert (away - field).norm() > 0.1 * field.norm(), "propagation should change the field"
    back = propagate(away, [-distance], wavelengths, PITCH)[0]
    expected = centre_crop(band_limited(field, distance, wavelengths), n, n)
    relative = ((back - expected).norm() / expected.norm()).item()
    assert relative < 1e-3


def test_propagate_forward_then_back_where_passband_is_partial():
    n, distance = 64, 3e-3
    passband = transfer_function(2 * n, 2 * n, PITCH, RED, distance, CPU).abs() > 0
    assert 0 < passband.double().mean().item() < 1
    field = gaussian_blob(n, 5.0)[None]
    back = propagate(propagate(field, [distance], [RED], PITCH)[0], [-distance], [RED], PITCH)[0]
    expected = centre_crop(band_limited(field, distance, [RED]), n, n)
    assert ((back - expected).norm() / expected.norm()).item() < 1e-3


@pytest.mark.parametrize("wavelength", [RED, BLUE])
@pytest.mark.parametrize("waist_px", [3.0, 4.0])
def test_gaussian_beam_width_follows_fresnel_formula(wavelength, waist_px):
    """u0 = exp(−r²/w0²) → |u(z)|² ∝ exp(−2r²/w(z)²), w(z) = w0 √(1+(z/z_R)²), z_R = π w0²/λ."""
    n = 96
    field = gaussian_blob(n, waist_px)[None]
    distances = [1e-3, 2e-3, 5e-3]
    intensity = propagate(field, distances, [wavelength], PITCH)[:, 0].abs() ** 2
    coords = torch.arange(n, dtype=torch.float64) - n // 2
    w0 = waist_px * PITCH
    rayleigh = math.pi * w0**2 / wavelength
    for plane, distance in zip(intensity, distances):
        total = plane.sum()
        cx = (plane.sum(0) * coords).sum() / total
        cy = (plane.sum(1) * coords).sum() / total
        var_x = (plane.sum(0) * (coords - cx) ** 2).sum() / total
        var_y = (plane.sum(1) * (coords - cy) ** 2).sum() / total
        measured = 2 * math.sqrt(float(var_x + var_y) / 2) * PITCH  # <x²> = w²/4 per axis
        analytic = w0 * math.sqrt(1 + (distance / rayleigh) ** 2)
        assert analytic > 1.5 * w0 or distance < 2e-3  # spreading is measurable
        assert abs(measured / analytic - 1) < 0.02, (distance, measured / analytic)


# --------------------------------------------------------------------------- guard band


def test_grid_for_paper_config_is_768_by_960():
    grid = Grid.for_config(FitConfig.create())
    assert (grid.height, grid.width) == (480, 640)
    assert (grid.padded_height, grid.padded_width) == (768, 960)
    assert grid.top >= 144 and grid.left >= 144
    assert grid.padded_height - grid.height - grid.top >= 144
    assert grid.padded_width - grid.width - grid.left >= 144


def small_grid() -> Grid:
    return Grid.for_config(FitConfig.create(width=20, height=16, guard_band_px=10, pad_multiple_px=8))


def test_guard_band_sizes_for_small_grid():
    grid = small_grid()
    # 16 + 20 = 36 → 40; 20 + 20 = 40 → 40
    assert (grid.padded_height, grid.padded_width) == (40, 40)
    assert (grid.top, grid.left) == (12, 10)  # the content centred: (40 − 16) / 2


def test_pad_with_guard_band_content_edges_and_window():
    grid = small_grid()
    generator = torch.Generator().manual_seed(3)
    hologram = torch.complex(torch.randn(2, grid.height, grid.width, generator=generator, dtype=torch.float64),
                             torch.randn(2, grid.height, grid.width, generator=generator, dtype=torch.float64))
    padded = pad_with_guard_band(hologram, grid)
    assert padded.shape == (2, grid.padded_height, grid.padded_width)
    window = guard_window(grid, CPU).double()
    assert window.shape == (grid.padded_height, grid.padded_width)
    # content untouched, window 1 there
    assert torch.equal(grid.crop(padded), hologram)
    assert torch.all(grid.crop(window) == 1)
    # window in [0, 1], 0 along the whole outer edge
    assert window.min() >= 0 and window.max() <= 1
    for edge in (window[0], window[-1], window[:, 0], window[:, -1]):
        assert torch.all(edge == 0)
    # strictly inside the guard band the window is strictly between 0 and 1 (it tapers)
    assert 0 < window[grid.top - 1, grid.left + 3] < 1
    assert 0 < window[grid.top + 3, grid.left - 1] < 1
    # guard band = edge-replicated values × window
    bottom = grid.padded_height - grid.height - grid.top
    right = grid.padded_width - grid.width - grid.left
    replicated = np.pad(hologram.numpy(), ((0, 0), (grid.top, bottom), (grid.left, right)), mode="edge")
    expected = replicated * window.numpy()
    np.testing.assert_allclose(padded.numpy(), expected, rtol=0, atol=1e-12)
    # monotone taper: non-decreasing towards the content along a row through the content
    row = window[grid.top + 2]
    assert torch.all(row[1:grid.left + 1] - row[:grid.left] >= 0)


def test_guard_band_passes_no_gradient_through_replicated_values():
    grid = small_grid()
    generator = torch.Generator().manual_seed(4)
    hologram = torch.complex(torch.randn(1, grid.height, grid.width, generator=generator, dtype=torch.float64),
                             torch.randn(1, grid.height, grid.width, generator=generator, dtype=torch.float64))
    hologram.requires_grad_(True)
    padded = pad_with_guard_band(hologram, grid)
    (padded.abs() ** 2).sum().backward()
    # only the content (window 1) contributes: d/dH* Σ|H|² = 2H
    assert torch.allclose(hologram.grad, 2 * hologram.detach(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_guarded_field_matches_autograd_through_the_composition(backend):
    """The fused field (hand-written backward over the content; PyTorch formulas or the one-pass CPU
    kernels) against autograd through `slm_field(pad_with_guard_band(·))`, with amplitudes on both
    sides of the clamp at 1."""
    grid = small_grid()
    generator = torch.Generator().manual_seed(8)
    shape = (3, grid.height, grid.width)
    hologram = torch.complex(torch.randn(shape, generator=generator, dtype=torch.float64),
                             torch.randn(shape, generator=generator, dtype=torch.float64))
    hologram[0, :2] = 0
    magnitude = hologram.abs()
    assert (magnitude > 1).float().mean() > 0.2 and (magnitude < 1).float().mean() > 0.2
    weights = torch.complex(torch.randn(3, grid.padded_height, grid.padded_width, generator=generator,
                                        dtype=torch.float64),
                            torch.randn(3, grid.padded_height, grid.padded_width, generator=generator,
                                        dtype=torch.float64))

    def value_and_gradient(build):
        leaf = hologram.clone().requires_grad_(True)
        field = build(leaf)
        ((field * weights.conj()).real.sum() + (field.abs() ** 2).sum()).backward()
        return field.detach(), leaf.grad

    fused, fused_grad = value_and_gradient(lambda h: guarded_field(h, grid, backend))
    reference, reference_grad = value_and_gradient(lambda h: slm_field(pad_with_guard_band(h, grid)))
    assert torch.allclose(fused, reference, rtol=1e-13, atol=1e-15)
    assert torch.allclose(fused_grad, reference_grad, rtol=1e-12, atol=1e-12)
    assert torch.isfinite(fused_grad).all()
    # finite differences see the replicated guard band move too, which by method.md §3 carries no gradient:
    # they are taken on the content
    assert torch.autograd.gradcheck(lambda h: grid.crop(guarded_field(h, grid, backend)),
                                    (hologram[:1].clone().requires_grad_(True),), fast_mode=True)


def test_fused_clamped_intensity_matches_the_formula_and_its_gradient():
    """The one-pass intensity kernels against `clamp(|u|², 0, 1)` under autograd, with values on both
    sides of the clamp, and against finite differences."""
    generator = torch.Generator().manual_seed(3)
    field = torch.complex(torch.randn(2, 3, 9, 11, generator=generator, dtype=torch.float64),
                          torch.randn(2, 3, 9, 11, generator=generator, dtype=torch.float64))
    assert ((field.abs() > 1).float().mean() > 0.2) and ((field.abs() < 1).float().mean() > 0.2)
    weights = torch.rand(field.shape, generator=generator, dtype=torch.float64)
    results = []
    for backend in ("torch", "numba"):
        leaf = field.clone().requires_grad_(True)
        intensity = clamped_intensity(leaf, backend)
        (intensity * weights).sum().backward()
        results.append((intensity.detach(), leaf.grad))
    (fused, fused_grad), (reference, reference_grad) = results[1], results[0]
    assert torch.allclose(fused, reference, rtol=1e-14, atol=0)
    assert torch.allclose(fused_grad, reference_grad, rtol=1e-14, atol=0)
    assert torch.autograd.gradcheck(lambda u: clamped_intensity(u, "numba"), (field.clone().requires_grad_(True),),
                                    fast_mode=True)


# --------------------------------------------------------------------------- SLM field


def test_slm_field_is_clamped_amplitude_with_phase():
    generator = torch.Generator().manual_seed(5)
    real = 2 * torch.randn(3, 7, 9, generator=generator, dtype=torch.float64)
    imag = 2 * torch.randn(3, 7, 9, generator=generator, dtype=torch.float64)
    hologram = torch.complex(real, imag)
    hologram[0, 0, :4] = 0
    hologram[1, 2, 3] = 0
    hologram[2, 1, 1] = 1.0 + 0j
    hologram[2, 1, 2] = -1j
    magnitude = hologram.abs()
    assert (magnitude > 1).any() and (magnitude < 1).any() and (magnitude == 0).any()
    expected = torch.clamp(magnitude, 0, 1) * torch.exp(1j * torch.angle(hologram))
    ours = slm_field(hologram)
    assert (ours - expected).abs().max().item() < 1e-12
    assert torch.all(ours.abs() <= 1 + 1e-12)
    assert torch.all(ours[hologram == 0] == 0)


def test_slm_field_gradient_finite_at_zero():
    generator = torch.Generator().manual_seed(6)
    hologram = torch.complex(torch.randn(1, 4, 5, generator=generator, dtype=torch.float64),
                             torch.randn(1, 4, 5, generator=generator, dtype=torch.float64))
    hologram[0, 0, 0] = 0
    hologram[0, 3, 4] = 0
    hologram[0, 1, 1] = 3 + 4j
    hologram.requires_grad_(True)
    weights = torch.complex(torch.randn(1, 4, 5, generator=generator, dtype=torch.float64),
                            torch.randn(1, 4, 5, generator=generator, dtype=torch.float64))
    loss = (slm_field(hologram) * weights.conj()).real.sum() + (slm_field(hologram).abs() ** 2).sum()
    loss.backward()
    grad = hologram.grad
    assert torch.isfinite(torch.view_as_real(grad)).all()
    # below |H| = 1 the field is H itself: gradient of Re(H w*) + |H|² is w + 2H; at H = 0 that is w
    assert torch.allclose(grad[0, 0, 0], weights[0, 0, 0])
    assert torch.allclose(grad[0, 3, 4], weights[0, 3, 4])
    inside = hologram.detach().abs() < 1
    assert torch.allclose(grad[inside], (weights + 2 * hologram.detach())[inside])


@pytest.mark.parametrize("at_once", [1, 2])
def test_more_planes_than_the_fused_kernels_take_at_once_match_the_full_transforms(monkeypatch, at_once):
    """Planes in groups (`FUSED_PLANES_AT_ONCE`, shrunk here to 1 or 2 of 3, one fused call each): forward and
    adjoint, whose groups' sums add up, still match the full transforms in float64."""
    monkeypatch.setattr(propagation, "FUSED_PLANES_AT_ONCE", at_once)
    grid = Grid(height=12, width=20, padded_height=32, padded_width=40)
    generator = torch.Generator().manual_seed(7)
    field = torch.complex(torch.randn(2, 32, 40, generator=generator), torch.randn(2, 32, 40, generator=generator))
    upstream = torch.complex(torch.randn(3, 2, 12, 20, generator=generator),
                             torch.randn(3, 2, 12, 20, generator=generator))
    optics = ([1e-3, 3e-3, 5e-3], [RED, BLUE], PITCH)
    leaf = field.clone().requires_grad_(True)
    content = propagate_content(leaf, grid, *optics, fused=True)
    (content * upstream.conj()).real.sum().backward()
    reference_leaf = field.to(torch.complex128).requires_grad_(True)
    reference = grid.crop(propagate(reference_leaf, *optics))
    (reference * upstream.to(torch.complex128).conj()).real.sum().backward()
    reference = reference.detach()
    assert content.shape == (3, 2, 12, 20)
    assert float((content.detach() - reference).abs().max() / reference.abs().max()) < 1e-5
    assert float((leaf.grad - reference_leaf.grad).abs().max() / reference_leaf.grad.abs().max()) < 1e-5
