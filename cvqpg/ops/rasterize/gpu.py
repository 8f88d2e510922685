"""GPU kernels (Triton) for the splatting sum and its gradient.

They take the reference's per-primitive quantities (`reference.splats`), with two products formed
beforehand in PyTorch: the weight `w_c = amplitude_c · opacity` and the phase rate `κ_c = k_c · chirp`
(rad per unit of the squared distance the QPF uses). Per pixel p and channel c a primitive adds

    G_c(p) = w_c · exp(max(−½D², EXPONENT_FLOOR)) · e^{i(φ_c + κ_c·P)},   P = D² (Mahalanobis) or |p − x|²,

inside its circle |p − x| ≤ reach (method.md §2), as the reference does. With the phase terms beyond the
curvature (`HAS_FORM`), the angle also carries k_c·(P_a dx² + 2P_b dx dy + P_c dy² + L_x dx + L_y dy), the
terms' form [N, 5] (`reference.Splats.form`) times the wavenumbers [C]; without them the kernels compile as before.

One program per primitive walks the pixels of its footprint's bounding box (clipped to the image)
in blocks of BLOCK pixels, all channels at once. The forward pass adds its values to the complex
hologram with atomic adds; the backward pass reduces the chain rule over the same pixels in
registers and writes its primitive's gradients alone (no atomics). Both take their loop bounds from
the primitive's data on the device: the host launches N programs and never reads a value back.

Complex arrays travel as float32 pairs (real, imaginary) in the last axis: `torch.view_as_real`.
"""

from __future__ import annotations

import triton
import triton.language as tl
from torch import Tensor

from . import reference

EXPONENT_FLOOR = tl.constexpr(reference.EXPONENT_FLOOR)
BLOCK = 256  # pixels a program handles at once


@triton.jit
def _box(position, reach, n, height, width):
    """Centre (px), squared reach (px²) and the clipped bounding box of primitive n: its first column
    and row, its width and its pixel count (0 when it misses the image)."""
    cx = tl.load(position + 2 * n)
    cy = tl.load(position + 2 * n + 1)
    r = tl.load(reach + n)
    # False for NaN centres and for boxes wholly outside the image: an empty box.
    hits = (cx + r >= 0.0) & (cx - r <= width - 1.0) & (cy + r >= 0.0) & (cy - r <= height - 1.0)
    left = tl.where(hits, tl.maximum(tl.ceil(cx - r), 0.0), 0.0).to(tl.int32)
    right = tl.where(hits, tl.minimum(tl.floor(cx + r), width - 1.0), -1.0).to(tl.int32)
    top = tl.where(hits, tl.maximum(tl.ceil(cy - r), 0.0), 0.0).to(tl.int32)
    bottom = tl.where(hits, tl.minimum(tl.floor(cy + r), height - 1.0), -1.0).to(tl.int32)
    columns = tl.maximum(right - left + 1, 0)
    rows = tl.maximum(bottom - top + 1, 0)
    return cx, cy, r * r, left, top, columns, columns * rows


@triton.jit
def _channel_values(values, n, CHANNELS: tl.constexpr, CHANNEL_BLOCK: tl.constexpr):
    """Primitive n's row of an [N, C] array as a [CHANNEL_BLOCK, 1] column (zero past C)."""
    channel = tl.arange(0, CHANNEL_BLOCK)
    return tl.load(values + n * CHANNELS + channel, mask=channel < CHANNELS, other=0.0)[:, None]


@triton.jit
def _parameters(conic, weight, phase, rate, n, CHANNELS: tl.constexpr, CHANNEL_BLOCK: tl.constexpr):
    """Primitive n's Σ⁻¹ entries a, b, c (1/px²) and its weights, phases and phase rates (columns)."""
    a = tl.load(conic + 3 * n)
    b = tl.load(conic + 3 * n + 1)
    c = tl.load(conic + 3 * n + 2)
    return (a, b, c, _channel_values(weight, n, CHANNELS, CHANNEL_BLOCK),
            _channel_values(phase, n, CHANNELS, CHANNEL_BLOCK), _channel_values(rate, n, CHANNELS, CHANNEL_BLOCK))


@triton.jit
def _block_pixels(start, left, top, columns, pixels, cx, cy, a, b, c, phi, kappa, reach2, height, width,
                  CHANNELS: tl.constexpr, CHANNEL_BLOCK: tl.constexpr, MAHALANOBIS: tl.constexpr, BLOCK: tl.constexpr):
    """One block of a primitive's box: offsets dx, dy [BLOCK] (px), the squared distance P the QPF
    uses (px²), the clamped envelope (0 outside the circle), whether the floor leaves its exponent
    alone, the phases [CHANNEL_BLOCK, BLOCK] (rad), and the flat index of each pixel's real part in
    a [C, H, W, 2] array with its mask."""
    index = start + tl.arange(0, BLOCK)
    in_box = index < pixels
    x = left + index % columns
    y = top + index // columns
    dx = x.to(tl.float32) - cx
    dy = y.to(tl.float32) - cy
    mahalanobis2 = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
    radius2 = dx * dx + dy * dy
    exponent = -0.5 * mahalanobis2
    inside = in_box & (radius2 <= reach2)
    envelope = tl.where(inside, tl.exp(tl.maximum(exponent, EXPONENT_FLOOR)), 0.0)
    channel = tl.arange(0, CHANNEL_BLOCK)[:, None]
    at = 2 * ((channel * height + y[None, :]) * width + x[None, :])
    mask = (channel < CHANNELS) & inside[None, :]
    path = mahalanobis2 if MAHALANOBIS else radius2
    angle = phi + kappa * path[None, :]
    return dx, dy, path, envelope, exponent >= EXPONENT_FLOOR, angle, at, mask


@triton.jit
def _form(form, wavenumber, n, CHANNELS: tl.constexpr, CHANNEL_BLOCK: tl.constexpr):
    """Primitive n's form (P_a, P_b, P_c in m/px², L_x, L_y in m/px) and the wavenumbers (1/m) as a column."""
    return (tl.load(form + 5 * n), tl.load(form + 5 * n + 1), tl.load(form + 5 * n + 2), tl.load(form + 5 * n + 3),
            tl.load(form + 5 * n + 4), _channel_values(wavenumber, 0, CHANNELS, CHANNEL_BLOCK))


@triton.jit
def splat_forward(position, conic, reach, weight, phase, rate, form, wavenumber, out, height, width,
                  CHANNELS: tl.constexpr, CHANNEL_BLOCK: tl.constexpr, MAHALANOBIS: tl.constexpr,
                  HAS_FORM: tl.constexpr, BLOCK: tl.constexpr):
    """Add primitive `program_id`'s values to `out` [C, H, W, 2] (zeroed by the caller)."""
    n = tl.program_id(0)
    cx, cy, reach2, left, top, columns, pixels = _box(position, reach, n, height, width)
    a, b, c, w, phi, kappa = _parameters(conic, weight, phase, rate, n, CHANNELS, CHANNEL_BLOCK)
    if HAS_FORM:
        pa, pb, pc, lx, ly, k = _form(form, wavenumber, n, CHANNELS, CHANNEL_BLOCK)
    for start in range(0, pixels, BLOCK):
        dx, dy, _, envelope, _, angle, at, mask = _block_pixels(
            start, left, top, columns, pixels, cx, cy, a, b, c, phi, kappa, reach2, height, width, CHANNELS,
            CHANNEL_BLOCK, MAHALANOBIS, BLOCK)
        if HAS_FORM:
            angle += k * (pa * dx * dx + 2.0 * pb * dx * dy + pc * dy * dy + lx * dx + ly * dy)[None, :]
        magnitude = w * envelope[None, :]
        tl.atomic_add(out + at, magnitude * tl.cos(angle), mask=mask)
        tl.atomic_add(out + at + 1, magnitude * tl.sin(angle), mask=mask)


@triton.jit
def splat_backward(position, conic, reach, weight, phase, rate, form, wavenumber, grad, g_position, g_conic, g_weight,
                   g_phase, g_rate, g_form, height, width, CHANNELS: tl.constexpr, CHANNEL_BLOCK: tl.constexpr,
                   MAHALANOBIS: tl.constexpr, HAS_FORM: tl.constexpr, BLOCK: tl.constexpr):
    """Primitive `program_id`'s gradients from the incoming gradient `grad` [C, H, W, 2]: position [N, 2],
    conic [N, 3], weight, phase and rate [N, C], and the form [N, 5] with `HAS_FORM`. With
    g = ∂L/∂Re G + i ∂L/∂Im G (PyTorch's convention), a real parameter θ gets Σ Re(ḡ · ∂G/∂θ)."""
    n = tl.program_id(0)
    cx, cy, reach2, left, top, columns, pixels = _box(position, reach, n, height, width)
    a, b, c, w, phi, kappa = _parameters(conic, weight, phase, rate, n, CHANNELS, CHANNEL_BLOCK)
    if HAS_FORM:
        pa, pb, pc, lx, ly, k = _form(form, wavenumber, n, CHANNELS, CHANNEL_BLOCK)
        sum_pa = tl.zeros((BLOCK,), tl.float32)
        sum_pb = tl.zeros((BLOCK,), tl.float32)
        sum_pc = tl.zeros((BLOCK,), tl.float32)
        sum_lx = tl.zeros((BLOCK,), tl.float32)
        sum_ly = tl.zeros((BLOCK,), tl.float32)
    # Per-pixel partial sums, reduced once after the loop.
    sum_weight = tl.zeros((CHANNEL_BLOCK, BLOCK), tl.float32)
    sum_phase = tl.zeros((CHANNEL_BLOCK, BLOCK), tl.float32)
    sum_rate = tl.zeros((CHANNEL_BLOCK, BLOCK), tl.float32)
    sum_a = tl.zeros((BLOCK,), tl.float32)
    sum_b = tl.zeros((BLOCK,), tl.float32)
    sum_c = tl.zeros((BLOCK,), tl.float32)
    sum_x = tl.zeros((BLOCK,), tl.float32)
    sum_y = tl.zeros((BLOCK,), tl.float32)
    for start in range(0, pixels, BLOCK):
        dx, dy, path, envelope, unclamped, angle, at, mask = _block_pixels(
            start, left, top, columns, pixels, cx, cy, a, b, c, phi, kappa, reach2, height, width, CHANNELS,
            CHANNEL_BLOCK, MAHALANOBIS, BLOCK)
        if HAS_FORM:
            angle += k * (pa * dx * dx + 2.0 * pb * dx * dy + pc * dy * dy + lx * dx + ly * dy)[None, :]
        g_re = tl.load(grad + at, mask=mask, other=0.0)
        g_im = tl.load(grad + at + 1, mask=mask, other=0.0)
        cosine = tl.cos(angle)
        sine = tl.sin(angle)
        # Re(ḡ·G)/w and Re(ḡ·iG)/w: G's derivatives in its weight and in its phase, per unit weight.
        along = envelope[None, :] * (g_re * cosine + g_im * sine)
        across = envelope[None, :] * (g_im * cosine - g_re * sine)
        turned = w * across
        sum_weight += along
        sum_phase += turned
        sum_rate += turned * path[None, :]
        # ∂L/∂D² and ∂L/∂|p − x|²: the envelope's −½ (where its exponent is above the floor) and the
        # phase's κ.
        by_path = tl.sum(kappa * turned, axis=0)
        by_mahalanobis2 = -0.5 * tl.where(unclamped, tl.sum(w * along, axis=0), 0.0)
        if MAHALANOBIS:
            by_mahalanobis2 += by_path
            by_radius2 = 0.0
        else:
            by_radius2 = by_path
        sum_a += by_mahalanobis2 * dx * dx
        sum_b += 2.0 * by_mahalanobis2 * dx * dy
        sum_c += by_mahalanobis2 * dy * dy
        # dx = p_x − x_n: the centre moves against the offsets.
        sum_x -= by_mahalanobis2 * (2.0 * a * dx + 2.0 * b * dy) + 2.0 * by_radius2 * dx
        sum_y -= by_mahalanobis2 * (2.0 * b * dx + 2.0 * c * dy) + 2.0 * by_radius2 * dy
        if HAS_FORM:  # ∂L/∂(form's path): k_c times the phase's
            by_form = tl.sum(k * turned, axis=0)
            sum_pa += by_form * dx * dx
            sum_pb += 2.0 * by_form * dx * dy
            sum_pc += by_form * dy * dy
            sum_lx += by_form * dx
            sum_ly += by_form * dy
            sum_x -= by_form * (2.0 * pa * dx + 2.0 * pb * dy + lx)
            sum_y -= by_form * (2.0 * pb * dx + 2.0 * pc * dy + ly)
    if HAS_FORM:
        tl.store(g_form + 5 * n, tl.sum(sum_pa, axis=0))
        tl.store(g_form + 5 * n + 1, tl.sum(sum_pb, axis=0))
        tl.store(g_form + 5 * n + 2, tl.sum(sum_pc, axis=0))
        tl.store(g_form + 5 * n + 3, tl.sum(sum_lx, axis=0))
        tl.store(g_form + 5 * n + 4, tl.sum(sum_ly, axis=0))
    tl.store(g_position + 2 * n, tl.sum(sum_x, axis=0))
    tl.store(g_position + 2 * n + 1, tl.sum(sum_y, axis=0))
    tl.store(g_conic + 3 * n, tl.sum(sum_a, axis=0))
    tl.store(g_conic + 3 * n + 1, tl.sum(sum_b, axis=0))
    tl.store(g_conic + 3 * n + 2, tl.sum(sum_c, axis=0))
    channel = tl.arange(0, CHANNEL_BLOCK)
    has_channel = channel < CHANNELS
    tl.store(g_weight + n * CHANNELS + channel, tl.sum(sum_weight, axis=1), mask=has_channel)
    tl.store(g_phase + n * CHANNELS + channel, tl.sum(sum_phase, axis=1), mask=has_channel)
    tl.store(g_rate + n * CHANNELS + channel, tl.sum(sum_rate, axis=1), mask=has_channel)


def launch(kernel: triton.JITFunction, position: Tensor, *arrays: Tensor, height: int, width: int,
           mahalanobis: bool, has_form: bool) -> None:
    """Run `splat_forward` or `splat_backward` over the N primitives, one program each; the grid
    comes from the shapes alone. Without the form (`has_form` false) its arrays are placeholders."""
    count, channels = arrays[2].shape  # the weights [N, C]
    if count:
        kernel[(count,)](position, *arrays, height, width, CHANNELS=channels,
                         CHANNEL_BLOCK=triton.next_power_of_2(channels), MAHALANOBIS=mahalanobis, HAS_FORM=has_form,
                         BLOCK=BLOCK)
