"""The display model (method.md §8): its definition and record, the encodings' and the quantiser's gradients, the
4f aperture folded into the transfer functions, and the whole display path against a plain PyTorch reference."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from cvqpg.config import CONFIG_SCHEMA, FitConfig, padded_size
from cvqpg.defaults import DISPLAY_ENCODINGS, ENCODINGS
from cvqpg.display import DPAC_SLOPE_AMPLITUDE, PHASE_ENCODINGS, Display, read_lut
from cvqpg.patterns import (checkerboard, displayed_field, double_phase, dpac_offset, level_phases, phase_pattern,
                            quantise, shown_phase)
from cvqpg.display import ENCODINGS as MODEL_ENCODINGS
from cvqpg.errors import ConfigError, InputError
from cvqpg.ops.field import Grid, slm_field
from cvqpg.ops.propagation import TransferBank, propagate, propagate_content
from cvqpg.ops.propagation import reference as propagation_reference
from cvqpg.ops.display import _tables as display_tables
from cvqpg.ops.display import cpu as display_cpu
from cvqpg.ops.display import shown_field
from cvqpg.ops.display.reference import shown_field as shown_reference
from cvqpg.optics import display_grid, reconstruct

CPU = torch.device("cpu")
PITCH = 3.74e-6


def random_hologram(channels: int, height: int, width: int, seed: int, top: float = 1.3,
                    dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A complex hologram whose amplitudes reach `top` (above 1: some saturate on the SLM)."""
    g = torch.Generator().manual_seed(seed)
    amplitude = (0.05 + (top - 0.05) * torch.rand(channels, height, width, generator=g)).to(dtype)
    phase = ((2 * torch.rand(channels, height, width, generator=g) - 1) * math.pi).to(dtype)
    return torch.polar(amplitude, phase)


def small_config(**settings) -> FitConfig:
    return FitConfig.create(**{"width": 40, "height": 32, "color": "gray", "guard_band_px": 16,
                               "pad_multiple_px": 16, **settings}).validate()


# The definition and its record.

def test_the_encodings_are_one_list():
    assert MODEL_ENCODINGS == DISPLAY_ENCODINGS and PHASE_ENCODINGS == ENCODINGS


def test_the_default_display_is_the_complex_one_and_dpac_takes_the_measured_aperture():
    assert Display().ideal and FitConfig().display == Display() and Display.create() == Display()
    dpac = Display.create("dpac")
    assert dpac.aperture is not None and dpac.levels == 256 and dpac.phase_only and not dpac.ideal
    assert Display.create("phase").aperture is None
    assert Display.create("dpac", lut=(0.0, 1.0, 2.0)).levels == 3
    assert not Display(canvas=(32, 40)).ideal  # the complex field on a dark canvas


@pytest.mark.parametrize("settings, message", [
    ({"encoding": "amplitude"}, "is not one of"),
    ({"encoding": "dpac", "levels": 1}, "phase levels"),
    ({"encoding": "dpac", "levels": 2**17}, "phase levels"),
    ({"encoding": "dpac", "levels": 3.5}, "phase levels"),
    ({"encoding": "dpac", "levels": 4, "lut": (0.0, 1.0)}, "2 phases for 4"),
    ({"encoding": "dpac", "levels": 2, "lut": (0.0, math.nan)}, "finite"),
    ({"encoding": "dpac", "aperture": 0.0}, "radius in"),
    ({"encoding": "dpac", "aperture": 1.5}, "radius in"),
    ({"encoding": "dpac", "aperture": math.inf}, "radius in"),
    ({"encoding": "dpac", "canvas": (0, 10)}, "canvas"),
    ({"encoding": "complex", "levels": 16}, "phase-only"),
])
def test_a_display_is_checked_where_it_is_made(settings, message):
    with pytest.raises(ConfigError, match=message):
        Display(**settings)


def test_a_canvas_smaller_than_the_hologram_is_refused_by_the_configuration():
    with pytest.raises(ConfigError, match="smaller than the 40×32 hologram"):
        small_config(display=Display.create("dpac", canvas=(30, 40)))


def test_the_display_is_recorded_in_config_json_and_older_records_load_as_complex():
    display = Display.create("dpac", lut=(0.0, 2.0, 4.0), aperture=0.7, canvas=(40, 48))
    config = small_config(display=display)
    record = json.loads(json.dumps(config.to_dict()))
    assert record["config_schema"] == CONFIG_SCHEMA == 3 and record["display"]["encoding"] == "dpac"
    assert FitConfig.from_dict(record) == config and FitConfig.from_dict(record).display == display
    older = {k: v for k, v in record.items() if k != "display"}
    assert FitConfig.from_dict({**older, "config_schema": 2}).display == Display()
    assert FitConfig.from_dict({"width": 64, "height": 48}).display == Display()  # the flat layout


def test_a_lookup_table_reads_from_one_or_two_columns(tmp_path):
    (tmp_path / "one.txt").write_text("# measured at 633 nm\n0.0\n1.5\n\n3.0 # saturating\n")
    assert read_lut(tmp_path / "one.txt") == (0.0, 1.5, 3.0)
    (tmp_path / "two.csv").write_text("gray,phase_rad\n0,0.1\n1,0.2\n2,0.4\n")
    assert read_lut(tmp_path / "two.csv") == (0.1, 0.2, 0.4)
    (tmp_path / "gap.csv").write_text("0,0.1\n2,0.2\n")
    (tmp_path / "word.txt").write_text("0.1\nhalf\n")
    (tmp_path / "short.txt").write_text("0.1\n")
    for name, message in (("gap.csv", "row 2"), ("word.txt", "row 2.*not a number"), ("short.txt", "1 gray levels"),
                          ("missing.txt", "cannot read")):
        with pytest.raises(InputError, match=message):
            read_lut(tmp_path / name)


# The encodings, the quantiser and their gradients.

def test_the_dpac_offset_has_the_arccos_gradient_and_a_bounded_one_where_the_amplitude_reaches_1():
    smooth = torch.linspace(0.02, 0.98, 25, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(dpac_offset, (smooth,))
    saturated = torch.tensor([DPAC_SLOPE_AMPLITUDE, 0.9999, 1.0], dtype=torch.float64, requires_grad=True)
    value = dpac_offset(saturated)
    assert torch.allclose(value, torch.arccos(saturated.detach()))  # the value stays exact
    value.sum().backward()
    held = -1 / math.sqrt(1 - DPAC_SLOPE_AMPLITUDE**2)
    assert torch.allclose(saturated.grad, torch.full((3,), held, dtype=torch.float64))
    assert math.isfinite(held) and abs(held) < 30


@pytest.mark.parametrize("encoding", ["dpac", "phase"])
def test_the_shown_field_of_an_encoding_has_finite_difference_gradients_across_the_phase_wrap(encoding):
    # e^{iθ} is smooth where θ wraps at 2π: finite differences through it check the wrap's gradient of 1.
    hologram = random_hologram(1, 4, 6, seed=2, top=0.9, dtype=torch.float64).requires_grad_(True)
    wraps = torch.remainder(hologram.detach().angle(), 2 * math.pi)
    assert (wraps > 5).any() and (wraps < 1).any()
    encode = double_phase if encoding == "dpac" else (lambda f: torch.remainder(f.angle(), 2 * math.pi))
    assert torch.autograd.gradcheck(lambda h: torch.polar(torch.ones_like(h.real), encode(slm_field(h))),
                                    (hologram,))


def test_the_quantiser_shows_its_levels_and_passes_the_gradient_straight_through():
    display = Display.create("dpac", levels=16)
    phase = torch.linspace(-1.0, 7.5, 200, requires_grad=True)
    gray, shown = shown_phase(phase, display)
    assert torch.equal(shown.detach(), level_phases(display)[gray])
    assert gray.min() >= 0 and gray.max() < 16
    (shown * torch.arange(200.0)).sum().backward()
    assert torch.equal(phase.grad, torch.arange(200.0))  # the straight-through rule: the identity


def test_a_lookup_table_quantises_to_the_nearest_of_its_phases_on_the_circle():
    display = Display.create("phase", lut=(0.0, 3.0, 6.2, 7.0))  # 7.0 rad shows as 0.717 rad
    phase = torch.tensor([0.05, 6.22, 6.26, 0.7, 3.1, -0.1])  # 6.26 lies nearer 2π than 6.2, −0.1 nearer 6.2
    assert quantise(phase, display).tolist() == [0, 2, 0, 3, 1, 2]
    assert shown_phase(phase, display)[1].tolist() == pytest.approx([0.0, 6.2, 0.0, 7.0, 3.0, 6.2])


def test_uniform_levels_quantise_as_the_lookup_table_of_their_phases():
    uniform = Display.create("dpac", levels=64)
    table = Display.create("dpac", lut=tuple(level_phases(uniform).tolist()))
    phase = torch.rand(5000, generator=torch.Generator().manual_seed(3)) * 2 * math.pi
    differ = quantise(phase, uniform) != quantise(phase, table)
    assert differ.sum() <= 2  # only exact ties between two levels may round apart


def test_the_canvas_beyond_the_hologram_shows_gray_level_0():
    display = Display.create("dpac", lut=(0.5, 2.0, 4.0), canvas=(10, 12))
    pattern = phase_pattern(slm_field(random_hologram(1, 6, 8, seed=4)), display)
    assert pattern.gray.shape == (1, 10, 12)
    outside = torch.ones(10, 12, dtype=torch.bool)
    outside[2:8, 2:10] = False
    assert (pattern.gray[:, outside] == 0).all() and torch.allclose(pattern.shown_rad[:, outside], torch.tensor(0.5))


# The 4f aperture, folded into the transfer functions.

@pytest.mark.parametrize("transposed", [False, True])
def test_the_aperture_is_a_factor_of_the_transfer_functions(transposed):
    plain = TransferBank(64, 48, PITCH, (639e-9,), (2e-3,), CPU, transposed)
    filtered = TransferBank(64, 48, PITCH, (639e-9,), (2e-3,), CPU, transposed, aperture=0.5)
    _, rows, cols = propagation_reference.spectral_terms(64, 48, PITCH, 639e-9, CPU, centred=False)
    mask = (rows**2 + cols**2 <= (0.5 / (2 * PITCH)) ** 2).to(torch.complex64)
    whole = mask.T if transposed else mask
    assert torch.equal(filtered(0, 0), plain(0, 0) * whole)
    assert 0.15 < mask.real.mean() < 0.25  # π/4 · 0.5² of the spectrum


def test_the_aperture_passes_frequencies_inside_its_radius_and_stops_those_outside():
    # u = (1 + cos 2πfx)/2 at f = 0.8 × Nyquist: its DC (1/2) and its two orders (1/4 each). A micrometre after the
    # SLM an aperture of radius 1 passes all three (|u|²), one of radius 0.6 the DC alone (1/4).
    config = small_config(num_planes=1, plane_center=1e-6, plane_span=0.0)
    x = torch.arange(40, dtype=torch.float32)
    field = ((1 + torch.cos(math.pi * 0.8 * x)) / 2).expand(1, 32, 40).to(torch.complex64)
    centre = (..., slice(10, 22), slice(12, 28))
    wide = reconstruct(field, config.replace(display=Display(aperture=1.0)))
    narrow = reconstruct(field, config.replace(display=Display(aperture=0.6)))
    assert torch.allclose(wide[centre], (field.abs() ** 2)[centre], atol=0.03)
    assert torch.allclose(narrow[centre], torch.tensor(0.25), atol=0.04)  # the canvas' hard edge rings a little
    assert narrow[centre].std() < 0.15 * wide[centre].std()


def test_pruned_transforms_with_the_aperture_equal_the_full_grid_reference():
    field = random_hologram(2, 24, 20, seed=5, top=1.0)
    grid = Grid(16, 12, 24, 20)
    args = (field, grid, (1e-3, 3e-3), (639e-9, 473e-9), PITCH)
    fast = propagate_content(*args, fused=True, aperture=0.45)
    plain = grid.crop(propagate(field, *args[2:], aperture=0.45))
    assert torch.allclose(fast, plain, atol=2e-5)
    assert not torch.allclose(fast, grid.crop(propagate(field, *args[2:])), atol=1e-3)


# The whole display path against a plain reference.

def plain_display(hologram: torch.Tensor, config: FitConfig) -> torch.Tensor:
    """What `config.display` shows, written out in PyTorch: the clamped field, DPAC (arccos itself) or its phase,
    the uniform levels (straight-through), e^{iθ}, the dark padded array, and odak's propagation with the
    aperture multiplying its spectrum."""
    display = config.display
    _, height, width = hologram.shape
    field = hologram / torch.clamp(hologram.abs(), min=1.0)
    theta = field.angle()
    if display.encoding == "dpac":
        rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
        theta = torch.where((rows + cols) % 2 == 1, theta + torch.arccos(field.abs()), theta - torch.arccos(field.abs()))
    theta = torch.remainder(theta, 2 * math.pi)
    step = 2 * math.pi / display.levels
    shown = theta + (torch.remainder(torch.round(theta / step), display.levels) * step - theta).detach()
    canvas = torch.polar(torch.ones_like(shown), shown)
    rows = padded_size(height, config.optics.guard_band_px, config.optics.pad_multiple_px)
    cols = padded_size(width, config.optics.guard_band_px, config.optics.pad_multiple_px)
    top, left = (rows - height) // 2, (cols - width) // 2
    padded = torch.zeros(hologram.shape[0], 2 * rows, 2 * cols, dtype=hologram.dtype)
    padded[:, rows // 2 + top:rows // 2 + top + height, cols // 2 + left:cols // 2 + left + width] = canvas
    planes = []
    for distance in config.plane_distances:
        channels = []
        for channel, wavelength in enumerate(config.wavelengths):
            transfer = propagation_reference.transfer_function(2 * rows, 2 * cols, PITCH, wavelength, distance, CPU,
                                                               centred=False)
            _, f_rows, f_cols = propagation_reference.spectral_terms(2 * rows, 2 * cols, PITCH, wavelength, CPU,
                                                                     centred=False)
            if display.aperture is not None:
                transfer = transfer * (f_rows**2 + f_cols**2 <= (display.aperture / (2 * PITCH)) ** 2)
            out = torch.fft.ifft2(torch.fft.fft2(padded[channel]) * transfer)
            channels.append(out[rows // 2 + top:rows // 2 + top + height, cols // 2 + left:cols // 2 + left + width])
        planes.append(torch.stack(channels))
    return torch.clamp(torch.stack(planes).abs() ** 2, 0.0, 1.0)


@pytest.mark.parametrize("encoding, aperture", [("dpac", 0.5), ("phase", None)])
@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_the_display_path_is_held_to_a_plain_reference_values_and_gradients(encoding, aperture, backend):
    config = small_config(width=24, height=16, color="rgb", display=Display.create(encoding, aperture=aperture))
    hologram = random_hologram(3, 16, 24, seed=6, top=0.97)
    weights = torch.rand(2, 3, 16, 24, generator=torch.Generator().manual_seed(7))
    grads = []
    for shown_by in (lambda h: reconstruct(h, config, backend=backend), lambda h: plain_display(h, config)):
        leaf = hologram.clone().requires_grad_(True)
        shown = shown_by(leaf)
        (shown * weights).sum().backward()
        grads.append((shown.detach(), leaf.grad))
    (fast, fast_grad), (plain, plain_grad) = grads
    assert torch.allclose(fast, plain, atol=2e-5)
    assert torch.allclose(fast_grad, plain_grad, atol=1e-4 * plain_grad.abs().max())


def test_the_complex_display_on_a_canvas_is_the_field_itself_in_the_dark():
    config = small_config(display=Display(canvas=(36, 44)))
    hologram = random_hologram(1, 32, 40, seed=8)
    padded = shown_reference(hologram, display_grid(config), config.display)
    assert padded.shape[-2:] == (padded_size(36, 16, 16), padded_size(44, 16, 16))
    assert torch.equal(padded.abs().sum(), slm_field(hologram).abs().sum())


@pytest.mark.parametrize("display", [Display.create("dpac", levels=2**16), Display.create("phase", levels=2**16),
                                     Display.create("dpac", lut=tuple(0.3 + 2 * math.pi * k / 5000 for k in range(5000)),
                                                    canvas=(36, 46))])
def test_the_shown_field_kernels_match_the_reference_and_its_gradient(display):
    config = small_config(color="rgb", display=display)
    grid = display_grid(config)
    hologram = random_hologram(3, 32, 40, seed=9, top=1.2)
    incoming = torch.randn(3, grid.padded_height, grid.padded_width, dtype=torch.complex64,
                           generator=torch.Generator().manual_seed(10))
    shown = {}
    for backend in ("numba", "torch"):
        leaf = hologram.clone().requires_grad_(True)
        field = shown_field(leaf, grid, display, backend)
        torch.view_as_real(field).mul(torch.view_as_real(incoming)).sum().backward()
        shown[backend] = field.detach(), leaf.grad
    (fast, fast_grad), (plain, plain_grad) = shown["numba"], shown["torch"]
    assert torch.allclose(fast, plain, atol=2e-3)  # fine levels: a phase on a level's boundary may round either way
    assert torch.allclose(fast_grad, plain_grad, rtol=1e-3, atol=1e-3 * plain_grad.abs().max())


def test_the_shown_field_kernel_picks_the_reference_s_gray_levels():
    display = Display.create("dpac")
    config = small_config(display=display)
    grid = display_grid(config)
    hologram = random_hologram(1, 32, 40, seed=11)
    fast, plain = (shown_field(hologram, grid, display, backend) for backend in ("numba", "torch"))
    differ = (fast - plain).abs() > 1e-5
    assert differ.sum() <= 2  # a phase on a level's boundary may round either way in another float32 order


def test_the_kernel_s_arctangent_polynomial_stays_within_its_bound():
    t = np.linspace(0.0, 1.0, 200_001)
    polynomial = np.polynomial.Polynomial(display_cpu.ARCTANGENT_COEFFICIENTS)
    assert np.abs(t * polynomial(t * t) - np.arctan(t)).max() < 7e-9


def kernel_levels(hologram: np.ndarray, display: Display, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The shown field's kernel on a bare [C, H, W] hologram: its field and gray levels at this `margin`."""
    uniform, fields, ordered, order = display_tables(display)
    channels, height, width = hologram.shape
    out = np.empty((channels, height + 2, width + 2), dtype=np.complex64)
    grays = np.empty(hologram.shape, dtype=np.uint16)
    display_cpu.shown_field(hologram, display.encoding == "dpac", display.levels, uniform, margin, fields, ordered,
                            order, 1, 1, (1, 1, height, width), 0j, out, grays)
    return out, grays


@pytest.mark.parametrize("display", [Display.create("dpac"), Display.create("phase", levels=3),
                                     Display.create("dpac", levels=1000)])
def test_the_guessed_gray_levels_are_the_exact_path_s_even_on_the_levels_boundaries(display):
    levels, height, width = display.levels, 24, 32
    rng = np.random.default_rng(12)
    amplitude = rng.uniform(0.0, 1.2, (2, height, width))
    plus = (np.arange(height)[:, None] + np.arange(width)[None, :]) % 2 == 1
    offset = np.arccos(np.minimum(amplitude, 1.0)) if display.encoding == "dpac" else 0.0
    boundary = (rng.integers(0, levels, amplitude.shape) + 0.5) * 2 * math.pi / levels  # shown phases on boundaries
    boundary += rng.normal(0.0, 1e-6, amplitude.shape) * (rng.random(amplitude.shape) < 0.5)
    hologram = (amplitude * np.exp(1j * (boundary - np.where(plus, offset, -offset)))).astype(np.complex64)
    hologram[1] = (rng.normal(0.0, 0.6, (height, width)) + 1j * rng.normal(0.0, 0.6, (height, width)))
    hologram[1, 0, :9] = [0, np.inf, -np.inf, np.nan, 1j * np.inf, complex(np.inf, np.inf), 1, -1, -1j]
    guessed, exact = (kernel_levels(hologram, display, margin)
                      for margin in (display_cpu.LEVEL_MARGIN * levels, 1.0))  # margin 1: all on the libm path
    assert np.array_equal(guessed[1], exact[1])
    assert np.array_equal(guessed[0].view(np.uint64), exact[0].view(np.uint64))
    assert not np.array_equal(kernel_levels(hologram, display, 0.0)[1], exact[1])  # the boundaries needed the margin


# A fit through the display, and its export.

@pytest.fixture(scope="module")
def display_run(tmp_path_factory):
    from cvqpg.fitting import fit_scene
    from cvqpg.runs import write_run
    from cvqpg.scenes import builtin_scene

    config = FitConfig.create(recipe="beyond-short", width=32, height=24, color="gray", steps=3, guard_band_px=16,
                              display=Display.create("dpac", levels=64)).validate()
    scene = builtin_scene("demo", config)
    result = fit_scene(scene, config)
    return write_run(tmp_path_factory.mktemp("display") / "run", result, scene, {"scene": "demo"}), result


@pytest.mark.slow
def test_a_display_fit_measures_what_the_display_shows_and_records_the_complex_field(display_run):
    folder, result = display_run
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["mean"]["psnr"] == pytest.approx(result.metrics.to_dict()["mean"]["psnr"])
    assert metrics["complex_field"]["mean"]["psnr"] != metrics["mean"]["psnr"]
    assert json.loads((folder / "config.json").read_text())["display"]["levels"] == 64
    assert result.history["psnr"][-1] == pytest.approx(metrics["mean"]["psnr"], abs=1.0)


@pytest.mark.slow
def test_export_of_a_display_fit_writes_the_patterns_it_optimised_and_reproduces_its_metrics(display_run, tmp_path):
    from cvqpg.fitting import render
    from cvqpg.runs import export_run

    folder, result = display_run
    record = export_run(folder, out=tmp_path / "export")
    metrics = json.loads((folder / "metrics.json").read_text())
    assert record["display"] == result.config.display.to_dict()
    assert record["phase_only_display"]["mean"]["psnr"] == pytest.approx(metrics["mean"]["psnr"], abs=0.01)
    assert record["complex_field"]["mean"]["psnr"] == pytest.approx(metrics["complex_field"]["mean"]["psnr"], abs=1e-4)
    hologram, _ = render(result.primitives, result.config)
    gray = phase_pattern(slm_field(hologram), result.config.display).gray[0].numpy()
    assert np.array_equal(np.asarray(Image.open(tmp_path / "export" / "phase_gray_639nm.png")), gray)


def test_a_cvq_file_keeps_the_display_and_refuses_one_that_cannot_work():
    import zlib

    from cvqpg.codec import CHECKSUM, PREFIX, BitDepths, decode, deflated, encode, header_start, inflated
    from cvqpg.errors import ModelFileError
    from cvqpg.primitives import activate, init_gaussians

    config = FitConfig.create(width=32, height=24, color="gray", ratio=0.1,
                              display=Display.create("dpac", levels=64, canvas=(30, 40)))
    primitives = activate(init_gaussians(config.primitive_count, 1, 32, 24, 1), config)
    data = encode(primitives, config, BitDepths())
    assert decode(data).config.display == config.display
    assert decode(encode(primitives, config.replace(display=Display()), BitDepths())).config.display == Display()
    _, version, length = PREFIX.unpack_from(data)
    start = header_start(version)
    header = json.loads(inflated(data[start:start + length], version))
    header["display"]["levels"] = 1
    packed = deflated(header)
    body = PREFIX.pack(data[:8], version, len(packed)) + data[PREFIX.size:start] + packed + data[start + length:-4]
    with pytest.raises(ModelFileError, match="phase levels"):
        decode(body + CHECKSUM.pack(zlib.crc32(body)))


def test_the_command_line_s_options_make_the_display(tmp_path):
    (tmp_path / "lut.txt").write_text("0.0\n2.0\n4.0\n")
    assert Display.from_options() == Display()
    assert Display.from_options("dpac") == Display.create("dpac")
    made = Display.from_options("phase", lut=tmp_path / "lut.txt", aperture=0.0, slm=(48, 40))
    assert made == Display("phase", 3, (0.0, 2.0, 4.0), None, (40, 48))
    assert Display.from_options("dpac", levels=16, aperture=0.7).aperture == 0.7
