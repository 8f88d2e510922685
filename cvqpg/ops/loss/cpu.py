"""Fused CPU kernels (Numba) for the training loss (method.md §6).

PyTorch evaluates the loss's three MSE terms and the SSIM formula as some forty full-size
element-wise passes, forward and backward, and runs SSIM's 11-tap depthwise blurs at well under
1 GMAC/s on the CPU. Here:

- `standard_normals` draws the targets' noise as a pure function of a seed and each value's index,
  vectorised and threaded (PyTorch's `randn` on the CPU draws from one sequential generator);
- `pixel_terms` makes one pass for the three MSE terms and their gradient;
- `ssim_forward` blurs the five moments of SSIM (formed on the fly from the two images) and turns
  them into the map and its partial derivatives in one pass over the output rows, each thread
  owning whole rows with one row of column sums per moment, so nothing larger than a row is stored
  between the blur's passes; `ssim_backward` scatters the derivatives back through the adjoint blur
  and combines them with the images in one pass over the input rows.

Each thread owns whole rows and rows are summed in a fixed order, so results do not depend on
scheduling.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..cpu import CALLED_BY_KERNELS_ONLY, cosines_and_sines


def gaussian_taps(size_px: int, sigma_px: float) -> np.ndarray:
    """The normalised 1D Gaussian window [size_px] centred on its middle tap (σ in px)."""
    offsets = np.arange(size_px, dtype=np.float64) - size_px // 2
    taps = np.exp(-offsets**2 / (2 * sigma_px**2))
    return taps / taps.sum()


GOLDEN_GAMMA = np.uint64(0x9E3779B97F4A7C15)  # SplitMix64's increment: 2⁶⁴ over the golden ratio
# SplitMix64's output function: x ^= x >> s, x *= m for each (shift, multiplier), then x ^= x >> last shift
MIX_SHIFTS = (np.uint64(30), np.uint64(27), np.uint64(31))
MIX_MULTIPLIERS = (np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB))
NORMAL_PAIRS_PER_TASK = 4096
UNIFORM_BITS = 23  # a float32 holds k + ½ exactly for k < 2²³: no uniform rounds to 0 or 1


@nb.njit(cache=True, nogil=True, inline="always")
def _mixed(state):
    """SplitMix64's output function: 64 well-mixed bits from a counter state."""
    state = (state ^ (state >> MIX_SHIFTS[0])) * MIX_MULTIPLIERS[0]
    state = (state ^ (state >> MIX_SHIFTS[1])) * MIX_MULTIPLIERS[1]
    return state ^ (state >> MIX_SHIFTS[2])


@nb.njit(cache=True, nogil=True, fastmath=True, error_model="numpy", inline="always")
def _logarithm(x):
    """ln x of a positive normal float32 to float32 precision, branch-free so that loops over it
    vectorise (libm's logf is a call per value): x = m·2ᵉ with m in [√½, √2), and
    ln m = 2 atanh s = 2(s + s³/3 + ... + s⁹/9), s = (m − 1)/(m + 1), |s| ≤ 0.172."""
    bits = np.float32(x).view(np.int32)
    exponent = np.float32((bits >> 23) - 127)
    mantissa = np.int32((bits & 0x7FFFFF) | 0x3F800000).view(np.float32)  # in [1, 2)
    high = np.float32(mantissa > np.float32(1.4142135))
    mantissa *= np.float32(1.0) - np.float32(0.5) * high
    s = (mantissa - np.float32(1.0)) / (mantissa + np.float32(1.0))
    z = s * s
    series = np.float32(1.0) + z * (np.float32(1 / 3) + z * (np.float32(1 / 5) + z * (np.float32(1 / 7)
                                                                                      + z * np.float32(1 / 9))))
    return (exponent + high) * np.float32(math.log(2.0)) + np.float32(2.0) * s * series


@nb.njit(cache=True, nogil=True, fastmath=True, error_model="numpy", **CALLED_BY_KERNELS_ONLY)
def _normal_pairs(seed, first, count, out):
    """Pairs first..first + count − 1 of `standard_normals` into out [2·count] (its slice). The steps
    are separate loops, each of which LLVM vectorises (no division checks: NumPy's error model)."""
    scale = np.float32(2.0**-UNIFORM_BITS)
    radii, angles, cosines, sines = np.empty(count, np.float32), np.empty(count), np.empty(count), np.empty(count)
    for p in range(count):
        bits = _mixed(np.uint64(seed) + np.uint64(first + p + 1) * GOLDEN_GAMMA)
        radii[p] = (np.float32(np.int32(bits >> np.uint64(64 - UNIFORM_BITS))) + np.float32(0.5)) * scale
        angles[p] = np.float64(np.int32(bits & np.uint64(2**UNIFORM_BITS - 1))) * (2.0 * math.pi * scale)
    for p in range(count):
        radii[p] = math.sqrt(np.float32(-2.0) * _logarithm(radii[p]))
    cosines_and_sines(angles, cosines, sines)
    for p in range(count):
        out[2 * p] = radii[p] * cosines[p]
        out[2 * p + 1] = radii[p] * sines[p]


@nb.njit(parallel=True, cache=True)
def standard_normals(seed, out):
    """out [2P] (float32) = standard normal draws, values 2p and 2p + 1 from the counter p: SplitMix64's
    64 bits of seed + (p + 1)·γ give two 23-bit uniforms u (in (0, 1)) and v, and Box–Muller turns
    them into √(−2 ln u)·(cos 2πv, sin 2πv) (|values| ≤ 5.8). The same seed gives the same values
    whatever the thread count."""
    pairs = out.shape[0] // 2
    for task in nb.prange((pairs + NORMAL_PAIRS_PER_TASK - 1) // NORMAL_PAIRS_PER_TASK):
        first = task * NORMAL_PAIRS_PER_TASK
        stop = min(pairs, first + NORMAL_PAIRS_PER_TASK)
        _normal_pairs(seed, first, stop - first, out[2 * first:2 * stop])


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _run_sums(rows, runs):
    """Sums [runs, K] (float64) of rows [runs·n, K] over each run of n consecutive rows, each added in
    the order of its rows, as `rows.reshape(runs, n, K).sum(axis=1)` adds them. Without fastmath, so
    LLVM keeps that order. (NumPy's sum over an axis compiles many of Numba's library functions,
    most of them for the error messages of its axis check; docs/performance.md, "First run".)"""
    length = rows.shape[0] // runs
    sums = np.zeros((runs, rows.shape[1]))
    for run in range(runs):
        for row in range(run * length, (run + 1) * length):
            for k in range(rows.shape[1]):
                sums[run, k] += rows[row, k]
    return sums


@nb.njit(parallel=True, cache=True, fastmath=True)
def pixel_terms(recon, targets, noisy, focus, guide, gradient):
    """Per-plane sums over [C, H, W] of `(x − t)²` and of `(a² + b²)(x − ñ)²` ([M, 2], float64).

    With x the reconstruction, t the target, ñ the noisy target, a the focus weight [M, H, W] and b the
    guide [M, C, H, W], the second sum is the masked and the correlation MSE terms together:
    (x·a − ñ·a)² + (x·b − ñ·b)², the paper's with a the plane's mask and b = ñ. Writes the derivative
    of both sums with respect to x, `2(x − t) + 2(a² + b²)(x − ñ)`, into `gradient`.
    """
    planes, channels, height, width = recon.shape
    rows = np.zeros((planes * height, 2))
    for row in nb.prange(planes * height):
        m, i = row // height, row % height
        plain = weighted = 0.0
        for c in range(channels):
            for j in range(width):
                x, n, b = recon[m, c, i, j], noisy[m, c, i, j], guide[m, c, i, j]
                weight = focus[m, i, j] * focus[m, i, j] + b * b
                error, noisy_error = x - targets[m, c, i, j], x - n
                plain += error * error
                weighted += weight * noisy_error * noisy_error
                gradient[m, c, i, j] = 2.0 * (error + weight * noisy_error)
        rows[row, 0], rows[row, 1] = plain, weighted
    return _run_sums(rows, planes)


SSIM_TAPS = 11  # the window (px), a constant: the filters' loops over taps unroll, their loops over pixels vectorise
SSIM_TASKS = 64  # the SSIM kernels' rows go in consecutive runs to this many tasks (a few per thread)


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _task_rows(task, rows):
    """The run of rows that task `task` of SSIM_TASKS takes: consecutive rows share their input rows in
    cache. `task` comes as np.int64 (see `kernels.splat_forward`: one compilation, not two)."""
    return range(task * rows // SSIM_TASKS, (task + 1) * rows // SSIM_TASKS)


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _filtered(row, taps, out):
    """out[j] = Σ_k taps[k]·row[j + k] for every j of out (row holds SSIM_TAPS − 1 values more), each
    output summed in registers."""
    for j in range(out.shape[0]):
        total = taps[0] * row[j]
        for k in range(1, SSIM_TAPS):
            total += taps[k] * row[j + k]
        out[j] = total


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _column_moments(x, y, i, taps, s_x, s_y, s_xx, s_yy, s_xy):
    """Column sums of x, y, x², y² and xy [W] under the window whose top row is i, weighted by taps.

    Across whole rows, which LLVM vectorises, two taps per pass (the last pass's second with weight 0
    at a clamped row): the sums stay in memory, and pairs halve their loads and stores."""
    for sums in (s_x, s_y, s_xx, s_yy, s_xy):
        sums[:] = 0.0
    last = x.shape[0] - 1
    for k in range(0, SSIM_TAPS, 2):
        first_tap = taps[k]
        second_tap = taps[k + 1] if k + 1 < SSIM_TAPS else first_tap - first_tap
        x0, y0, x1, y1 = x[i + k], y[i + k], x[min(i + k + 1, last)], y[min(i + k + 1, last)]
        for j in range(x0.shape[0]):
            a0, b0, a1, b1 = x0[j], y0[j], x1[j], y1[j]
            p0, p1, q0, q1 = first_tap * a0, second_tap * a1, first_tap * b0, second_tap * b1
            s_x[j] += p0 + p1
            s_y[j] += q0 + q1
            s_xx[j] += p0 * a0 + p1 * a1
            s_yy[j] += q0 * b0 + q1 * b1
            s_xy[j] += p0 * b0 + p1 * b1


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _gathered_columns(d_x, d_xx, d_xy, i, taps, c_x, c_xx, c_xy):
    """The vertical blur's adjoint at input row i: c[j] = Σ_k taps[k]·d[i − k, j] over the output rows
    i − k that exist, for the three derivative maps [h, w] at once, two taps per pass as in
    `_column_moments` (a missing row enters with weight 0 at a clamped index)."""
    for sums in (c_x, c_xx, c_xy):
        sums[:] = 0.0
    first, stop = max(0, i - d_x.shape[0] + 1), min(SSIM_TAPS, i + 1)
    for k in range(first, stop, 2):
        first_tap = taps[k]
        second_tap = taps[k + 1] if k + 1 < stop else first_tap - first_tap
        row, other = i - k, max(i - k - 1, 0)
        x0, xx0, xy0, x1, xx1, xy1 = d_x[row], d_xx[row], d_xy[row], d_x[other], d_xx[other], d_xy[other]
        for j in range(x0.shape[0]):
            c_x[j] += first_tap * x0[j] + second_tap * x1[j]
            c_xx[j] += first_tap * xx0[j] + second_tap * xx1[j]
            c_xy[j] += first_tap * xy0[j] + second_tap * xy1[j]


@nb.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def ssim_forward(x, y, taps, c1, c2, d_mean_x, d_mean_xx, d_mean_xy):
    """Sum of the SSIM map per image ([B], float64) of x against y [B, H, W], over the valid window
    positions [h, w] = [H − K + 1, W − K + 1] of the K-tap separable blur (K = SSIM_TAPS).

    Each of SSIM_TASKS tasks takes a run of output rows (`_task_rows`), with its row buffers allocated
    once: allocations per row slowed the kernel (docs/performance.md). For one row it sums
    the K input rows under the window into one row of column sums per moment (x, y, x², y², xy,
    formed on the fly), filters those along x, and turns the five blurred moments into the map
    (`_ssim_row`): SSIM = a1·a2 / (b1·b2) with a1 = 2μxμy + c1, b1 = μx² + μy² + c1,
    a2 = 2σxy + c2, b2 = σx² + σy² + c2. It writes the map's partial derivatives with respect to μx,
    E[x²] and E[xy] into `d_mean_x`, `d_mean_xx`, `d_mean_xy` [B, h, w]; they are written without
    dividing by a1 or a2, which may vanish (b1, b2 ≥ c1, c2 > 0).
    """
    if taps.size != SSIM_TAPS:
        raise ValueError("the SSIM kernels take SSIM_TAPS taps")
    images, height, width = x.shape
    out_height, out_width = height - SSIM_TAPS + 1, width - SSIM_TAPS + 1
    rows = np.zeros((images * out_height, 1))
    for task in nb.prange(SSIM_TASKS):
        s_x, s_y, s_xx, s_yy, s_xy = (np.empty(width, x.dtype), np.empty(width, x.dtype), np.empty(width, x.dtype),
                                      np.empty(width, x.dtype), np.empty(width, x.dtype))  # apart: no aliasing
        m_x, m_y, m_xx, m_yy, m_xy = (np.empty(out_width, x.dtype), np.empty(out_width, x.dtype),
                                      np.empty(out_width, x.dtype), np.empty(out_width, x.dtype),
                                      np.empty(out_width, x.dtype))
        for row in _task_rows(np.int64(task), rows.shape[0]):
            rows[row, 0] = _ssim_row(x, y, taps, c1, c2, row // out_height, row % out_height,
                                     (s_x, s_y, s_xx, s_yy, s_xy), (m_x, m_y, m_xx, m_yy, m_xy), d_mean_x, d_mean_xx,
                                     d_mean_xy)
    return _run_sums(rows, images)[:, 0]


@nb.njit(cache=True, nogil=True, fastmath=True, error_model="numpy", **CALLED_BY_KERNELS_ONLY)
def _ssim_row(x, y, taps, c1, c2, b, i, sums, blurred, d_mean_x, d_mean_xx, d_mean_xy):
    """Output row i of image b (`ssim_forward`), through a thread's buffers for the five moments' column
    sums and blurs: its derivative maps, and the sum of its SSIM map."""
    s_x, s_y, s_xx, s_yy, s_xy = sums
    m_x, m_y, m_xx, m_yy, m_xy = blurred
    _column_moments(x[b], y[b], i, taps, s_x, s_y, s_xx, s_yy, s_xy)
    for moment, out in zip(sums, blurred):
        _filtered(moment, taps, out)
    total = 0.0
    for j in range(m_x.shape[0]):
        mx, my = np.float64(m_x[j]), np.float64(m_y[j])
        mxy = mx * my
        a1, b1 = 2.0 * mxy + c1, mx * mx + my * my + c1
        a2 = 2.0 * (m_xy[j] - mxy) + c2
        b2 = (m_xx[j] - mx * mx) + (m_yy[j] - my * my) + c2
        denominator = b1 * b2
        value = a1 * a2 / denominator
        total += value
        d_mean_x[b, i, j] = 2.0 * my * (a2 - a1) / denominator - 2.0 * mx * value * (1.0 / b1 - 1.0 / b2)
        d_mean_xx[b, i, j] = -value / b2
        d_mean_xy[b, i, j] = 2.0 * a1 / denominator
    return total


@nb.njit(parallel=True, cache=True, fastmath=True)
def ssim_backward(d_mean_x, d_mean_xx, d_mean_xy, weights, x, y, taps, out):
    """out [B, H, W] = w_b·(B*(∂μx) + 2x·B*(∂E[x²]) + y·B*(∂E[xy])): the gradient of Σ_b w_b·ΣSSIM_b
    with respect to x, from `ssim_forward`'s derivative maps [B, h, w], B* the adjoint of the blur.

    Each of SSIM_TASKS tasks takes a run of input rows, with its row buffers allocated once: for a row
    it gathers the output rows whose windows cover the row into column sums, spreads them back along x (the filter with
    reversed taps over the sums padded with zeros, whose margins stay zero), and combines the three
    maps with x and y in the same pass.
    """
    if taps.size != SSIM_TAPS:
        raise ValueError("the SSIM kernels take SSIM_TAPS taps")
    images, height, width = x.shape
    out_width, margin = d_mean_x.shape[2], SSIM_TAPS - 1
    reversed_taps = taps[::-1].copy()
    for task in nb.prange(SSIM_TASKS):
        c_x, c_xx, c_xy = (np.zeros(out_width + 2 * margin, x.dtype), np.zeros(out_width + 2 * margin, x.dtype),
                           np.zeros(out_width + 2 * margin, x.dtype))
        g_x, g_xx, g_xy = np.empty(width, x.dtype), np.empty(width, x.dtype), np.empty(width, x.dtype)
        for row in _task_rows(np.int64(task), images * height):
            b, i = row // height, row % height
            _gathered_columns(d_mean_x[b], d_mean_xx[b], d_mean_xy[b], i, taps, c_x[margin:margin + out_width],
                              c_xx[margin:margin + out_width], c_xy[margin:margin + out_width])
            for sums, spread in ((c_x, g_x), (c_xx, g_xx), (c_xy, g_xy)):
                _filtered(sums, reversed_taps, spread)
            weight, xs, ys, target = weights[b], x[b, i], y[b, i], out[b, i]
            for j in range(width):
                target[j] = weight * (g_x[j] + 2.0 * xs[j] * g_xx[j] + ys[j] * g_xy[j])
