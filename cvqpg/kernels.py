"""Fused CPU kernels (Numba) for the splatting sum and its gradient.

Both passes visit only the pixels inside each primitive's 3σ_major circle and store nothing of size
N × pixels. Per channel a primitive is `G = α c exp(E)` with a complex exponent E that is quadratic
in the pixel offset (the envelope −½D² and the quadratic phase), so along a row each pixel's value
is its neighbour's times a ratio that itself changes by a constant factor, and the same holds from
row to row along the primitive's centre column. The kernels walk the footprint outwards from that
column with complex multiplications only, a few exact exponentials per primitive and channel.

The kernels leave out the pixels where SPEC's floor of −50 on the envelope exponent applies
(D² > 100: values below e⁻⁵⁰ ≈ 2e-22 of the amplitude, invisible in float32), so each row's span is
the 3σ circle cut to the band where D² ≤ 100; for elongated primitives that is most of the circle.
Primitives so elongated that a walk down the centre column could leave float64's range (D² > 600
inside the footprint) start each row instead at its own envelope maximum with exact values, three
exponentials per row, and walk outwards from there, where values only decrease.

Two special cases take most of the work. A primitive without curvature (the flat baseline, CVQPG's
warm-up) has the same real envelope in every channel, so the forward pass walks it once, as a real
number, for all channels. In the backward pass a walk is a chain of dependent multiplications that
LLVM cannot vectorise; most primitives (D² ≤ 300 across the footprint) instead split exp(E) into a
row factor and a table over the footprint's columns that moves down one row by an elementwise
product, and each row's sums become independent products over contiguous arrays.

The forward pass
gives each thread its own slice of primitives and its own output buffer, summed in a fixed order, so
results do not depend on scheduling; the backward pass gives each thread the same slice, and each
primitive's gradients are written by that thread alone. Arithmetic is float64 inside, float32 in the
arrays.

Both kernels compile with fast-math, which lets LLVM drop the infinity and NaN recovery of complex
products (a fifth of the backward pass). That is safe here: a walk state that overflows belongs to
a primitive whose rows start from exact values, and is never read.
"""

from __future__ import annotations

import cmath
import math

import numba as nb
import numpy as np

FLOOR_MAHALANOBIS2 = 100.0  # D² where the envelope exponent −½D² reaches SPEC's floor of −50
MAX_WALKED_MAHALANOBIS2 = 600.0
MAX_TABULATED_MAHALANOBIS2 = 300.0


@nb.njit(cache=True, nogil=True)
def _row_span(center_y, reach, a, b, c, height):
    """Rows of the footprint: the 3σ circle's, within the band |dy| ≤ 10·√Σ_yy where D² ≤ 100 can hold."""
    determinant = a * c - b * b
    half = reach if determinant <= 0.0 else min(reach, math.sqrt(FLOOR_MAHALANOBIS2 * a / determinant))
    return max(0, math.ceil(center_y - half)), min(height - 1, math.floor(center_y + half))


@nb.njit(cache=True, nogil=True)
def _column_span(center_x, reach, dy, a, b, c, width):
    """Columns of row dy (px from the centre) inside the 3σ circle where D² ≤ 100 (empty: left > right)."""
    circle = math.sqrt(max(reach * reach - dy * dy, 0.0))
    ridge = -b * dy / a  # the row's envelope maximum, relative to the centre
    band = math.sqrt(max(FLOOR_MAHALANOBIS2 * a - dy * dy * (a * c - b * b), 0.0)) / a
    return (max(0, math.ceil(center_x + max(-circle, ridge - band))),
            min(width - 1, math.floor(center_x + min(circle, ridge + band))))


@nb.njit(cache=True, nogil=True)
def _exponent_coefficients(a, b, c, k_chirp, mahalanobis):
    """(A, B, C) of the complex exponent E = A dx² + 2B dx dy + C dy² (without the constant iφ)."""
    if mahalanobis:
        factor = complex(-0.5, k_chirp)
        return factor * a, factor * b, factor * c
    return complex(-0.5 * a, k_chirp), complex(-0.5 * b, 0.0), complex(-0.5 * c, k_chirp)


@nb.njit(cache=True, nogil=True)
def _largest_mahalanobis2(a, b, c, reach):
    """reach² · λ_max(Σ⁻¹): a bound on D² over the footprint circle, which picks the kernels' way."""
    return reach * reach * (0.5 * (a + c) + math.sqrt(0.25 * (a - c) ** 2 + b * b))


@nb.njit(cache=True, nogil=True)
def _walkable(a, b, c, reach):
    """Whether every exponent in the footprint stays in the range the multiplicative walk needs."""
    return _largest_mahalanobis2(a, b, c, reach) <= MAX_WALKED_MAHALANOBIS2


@nb.njit(cache=True, nogil=True)
def _footprint(n, position, conic, reach, height, width):
    """Primitive n's geometry: whether it can touch the image, centre (px), reach (px), Σ⁻¹ (a, b, c),
    its rows, whether it is walked down its centre column, that column, and the walk's start offset."""
    x0, y0, r = np.float64(position[n, 0]), np.float64(position[n, 1]), np.float64(reach[n])
    a, b, c = np.float64(conic[n, 0]), np.float64(conic[n, 1]), np.float64(conic[n, 2])
    low, high = _row_span(y0, r, a, b, c, height)
    cx = round(x0)
    visible = not (x0 + r < 0 or x0 - r > width - 1)
    return visible, x0, y0, r, a, b, c, low, high, _walkable(a, b, c, r), cx, cx - x0, low - y0


@nb.njit(cache=True, nogil=True)
def _is_flat(n, chirp):
    """Whether primitive n has no curvature in any channel: then its exponent is the real −½D²."""
    for slot in range(chirp.shape[1]):
        if chirp[n, slot] != 0.0:
            return False
    return True


@nb.njit(cache=True, nogil=True)
def _exact_at(A, B, C, dx, dy):
    """exp(E) at offset (dx, dy), and the ratios to its right and left neighbours."""
    return (cmath.exp(A * dx * dx + 2.0 * B * dx * dy + C * dy * dy),
            cmath.exp(A * (2.0 * dx + 1.0) + 2.0 * B * dy), cmath.exp(A * (1.0 - 2.0 * dx) - 2.0 * B * dy))


@nb.njit(cache=True, nogil=True)
def _walk_start(A, B, C, dx0, dy0):
    """Exact values at the walk's start (column dx0, first row dy0): exp(E), the vertical ratio and
    its change, the rightward and leftward ratios, their changes per row (right, left) and per step."""
    z0, s_right, s_left = _exact_at(A, B, C, dx0, dy0)
    return (z0, cmath.exp(2.0 * B * dx0 + C * (2.0 * dy0 + 1.0)), cmath.exp(2.0 * C), s_right, s_left,
            cmath.exp(2.0 * B), cmath.exp(-2.0 * B), cmath.exp(2.0 * A))


@nb.njit(cache=True, nogil=True)
def _row_walks(walk, A, B, C, scale, z_row, s_right, s_left, s_step, x0, dy, cx, ridge_slope, left, right):
    """Both walks of a row, stepped together so that their two multiplication chains overlap.

    Returns the start column, the rightward walk's value and ratio there, the leftward walk's one
    column to the left, and the step count that covers [left, right]. A walked primitive starts at
    its centre column with the state carried down from the row above; any other starts at the row's
    envelope maximum (clamped to the span) from exact values, times `scale`.
    """
    if walk:
        start = cx
    else:
        start = min(max(round(x0 + ridge_slope * dy), left), right)
        z_row, s_right, s_left = _exact_at(A, B, C, start - x0, dy)
        z_row *= scale
    steps = max(right + 1 - start, start - left) if left <= right else 0
    return start, z_row, s_right, z_row * s_left, s_left * s_step, steps


@nb.njit(cache=True, nogil=True)
def _next_row(z_row, v, v_step, s_right, s_left, s_row, s_row_left):
    """The walk's state one row down (no division: off the walk's range these values overflow to
    unused infinities, and a division by an underflowed zero would raise)."""
    return z_row * v, v * v_step, s_right * s_row, s_left * s_row_left


@nb.njit(cache=True, nogil=True, fastmath=True)
def _with_row(moments, m0, m1, m2, dy):
    """A primitive's moments (Σm, Σm·dx, Σm·dx², Σm·dy, Σm·dx·dy, Σm·dy²) with one row's sums
    (Σm, Σm·dx, Σm·dx² over the row, at offset dy) added."""
    s00, s10, s20, s01, s11, s02 = moments
    return s00 + m0, s10 + m1, s20 + m2, s01 + m0 * dy, s11 + m1 * dy, s02 + m0 * dy * dy


@nb.njit(cache=True, nogil=True)
def _chirp_slot(channel, chirp):
    """Column of `chirp` [N, 1 or C] that channel uses: one shared curvature, or its own."""
    return min(channel, chirp.shape[1] - 1)


@nb.njit(cache=True, nogil=True, fastmath=True)
def _splat_one(n, position, conic, reach, chirp, color, phase, opacity, wavenumbers, mahalanobis, out, lefts, rights):
    channels, height, width = out.shape
    visible, x0, y0, r, a, b, c, low, high, walk, cx, dx0, dy0 = _footprint(n, position, conic, reach, height, width)
    if not visible:
        return
    first, last = _row_spans(x0, y0, r, a, b, c, low, high, width, lefts, rights)
    if first > last:
        return
    for ch in range(channels):
        k_chirp = wavenumbers[ch] * chirp[n, _chirp_slot(ch, chirp)]
        A, B, C = _exponent_coefficients(a, b, c, k_chirp, mahalanobis)
        amplitude = opacity[n] * color[n, ch] * cmath.exp(complex(0.0, phase[n, ch]))
        z_row, v, v_step, s_right, s_left, s_row, s_row_left, s_step = _walk_start(A, B, C, dx0, dy0)
        z_row *= amplitude
        for py in range(low, high + 1):
            dy = py - y0
            left, right = lefts[py - low], rights[py - low]
            row = out[ch, py]
            start, z_r, s_r, z_l, s_l, steps = _row_walks(walk, A, B, C, amplitude, z_row, s_right, s_left,
                                                          s_step, x0, dy, cx, -b / a, left, right)
            for i in range(steps):
                for px, z in ((start + i, z_r), (start - 1 - i, z_l)):
                    if left <= px <= right:
                        row[px] += z
                z_r, s_r = z_r * s_r, s_r * s_step
                z_l, s_l = z_l * s_l, s_l * s_step
            z_row, v, s_right, s_left = _next_row(z_row, v, v_step, s_right, s_left, s_row, s_row_left)


@nb.njit(cache=True, nogil=True, fastmath=True)
def _splat_flat_one(n, position, conic, reach, color, phase, opacity, mahalanobis, amplitudes, out):
    """A primitive without curvature: exp(E) is the real envelope exp(−½D²) in every channel, so one
    real walk serves all channels, each adding its own α c e^{iφ} times the envelope."""
    channels, height, width = out.shape
    visible, x0, y0, r, a, b, c, low, high, walk, cx, dx0, dy0 = _footprint(n, position, conic, reach, height, width)
    if not visible:
        return
    for ch in range(channels):
        amplitudes[ch] = opacity[n] * color[n, ch] * cmath.exp(complex(0.0, phase[n, ch]))
    A, B, C = _exponent_coefficients(a, b, c, 0.0, mahalanobis)
    z_row, v, v_step, s_right, s_left, s_row, s_row_left, s_step = _walk_start(A, B, C, dx0, dy0)
    for py in range(low, high + 1):
        dy = py - y0
        left, right = _column_span(x0, r, dy, a, b, c, width)
        start, z_r, s_r, z_l, s_l, steps = _row_walks(walk, A, B, C, complex(1.0, 0.0), z_row, s_right, s_left,
                                                      s_step, x0, dy, cx, -b / a, left, right)
        e_r, q_r, e_l, q_l, q_step = z_r.real, s_r.real, z_l.real, s_l.real, s_step.real
        for i in range(steps):
            for px, e in ((start + i, e_r), (start - 1 - i, e_l)):
                if left <= px <= right:
                    for ch in range(channels):
                        out[ch, py, px] += amplitudes[ch] * e
            e_r, q_r = e_r * q_r, q_r * q_step
            e_l, q_l = e_l * q_l, q_l * q_step
        z_row, v, s_right, s_left = _next_row(z_row, v, v_step, s_right, s_left, s_row, s_row_left)


@nb.njit(parallel=True, cache=True, fastmath=True)
def splat_forward(position, conic, reach, chirp, color, phase, opacity, wavenumbers, mahalanobis, partial):
    """partial[t] = the sum over primitives t, t+T, t+2T, ... (T = partial.shape[0]).

    `partial` [T, C, H, W] (complex64) starts at zero; the caller sums it over t in order.
    """
    threads = partial.shape[0]
    for t in nb.prange(threads):
        amplitudes = np.empty(color.shape[1], np.complex128)
        lefts, rights = np.empty(partial.shape[2], np.int64), np.empty(partial.shape[2], np.int64)
        for n in range(t, position.shape[0], threads):
            if _is_flat(n, chirp):
                _splat_flat_one(n, position, conic, reach, color, phase, opacity, mahalanobis, amplitudes, partial[t])
            else:
                _splat_one(n, position, conic, reach, chirp, color, phase, opacity, wavenumbers, mahalanobis,
                           partial[t], lefts, rights)


@nb.njit(cache=True, nogil=True, fastmath=True)
def _walked_moments(grad, A, B, C, rotation, walk, x0, y0, ridge_slope, low, high, lefts, rights, cx, dx0, dy0):
    """One channel's moments of t and u (see `splat_backward`) over the footprint, walking each row
    outwards from its start by complex multiplication."""
    z_row, v, v_step, s_right, s_left, s_row, s_row_left, s_step = _walk_start(A, B, C, dx0, dy0)
    z_row *= rotation
    t_moments = u_moments = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for py in range(low, high + 1):
        dy = py - y0
        left, right = lefts[py - low], rights[py - low]
        grad_row = grad[py]
        t0 = t1 = t2 = u0 = u1 = u2 = 0.0
        start, z_r, s_r, z_l, s_l, steps = _row_walks(walk, A, B, C, rotation, z_row, s_right, s_left,
                                                      s_step, x0, dy, cx, ridge_slope, left, right)
        for i in range(steps):
            for px, z in ((start + i, z_r), (start - 1 - i, z_l)):
                if left <= px <= right:
                    dx = px - x0
                    g = grad_row[px]
                    t = g.real * z.real + g.imag * z.imag
                    u = g.imag * z.real - g.real * z.imag
                    t0 += t
                    t1 += t * dx
                    t2 += t * dx * dx
                    u0 += u
                    u1 += u * dx
                    u2 += u * dx * dx
            z_r, s_r = z_r * s_r, s_r * s_step
            z_l, s_l = z_l * s_l, s_l * s_step
        z_row, v, s_right, s_left = _next_row(z_row, v, v_step, s_right, s_left, s_row, s_row_left)
        t_moments = _with_row(t_moments, t0, t1, t2, dy)
        u_moments = _with_row(u_moments, u0, u1, u2, dy)
    return t_moments, u_moments


@nb.njit(cache=True, nogil=True)
def _tabulated(a, b, c, reach):
    """Whether the column tables of `_tabulated_moments` stay well inside float64's range: every
    partial exponent A dx² + 2B dx dy in the footprint is below 450 in magnitude."""
    return _largest_mahalanobis2(a, b, c, reach) <= MAX_TABULATED_MAHALANOBIS2


@nb.njit(cache=True, nogil=True)
def _row_spans(x0, y0, r, a, b, c, low, high, width, lefts, rights):
    """Each footprint row's columns into lefts/rights [row − low]; returns the columns they cover
    (first > last when none)."""
    first, last = width, -1
    for py in range(low, high + 1):
        left, right = _column_span(x0, r, py - y0, a, b, c, width)
        lefts[py - low], rights[py - low] = left, right
        if left <= right:
            first, last = min(first, left), max(last, right)
    return first, last


@nb.njit(cache=True, nogil=True, fastmath=True)
def _tabulated_moments(grad, A, B, C, rotation, x0, y0, low, high, lefts, rights, first, last,
                       g_real, g_imag, h_real, h_imag):
    """One channel's moments of t and u over the footprint, from column tables.

    exp(E) = exp(C dy²)·G(dx) with G(dx) = exp(A dx² + 2B dx dy): a row factor times a table over
    the footprint's columns that moves one row down by the factor h(dx) = exp(2B dx). Neither needs
    a recurrence along the row, so each row is one loop of independent products that LLVM
    vectorises, and the row factor is applied once to the row's sums Σḡ·G·{1, dx, dx²}."""
    columns = last + 1 - first
    dx_first, dy0 = first - x0, low - y0
    g = cmath.exp(A * dx_first * dx_first + 2.0 * B * dx_first * dy0)
    ratio, ratio_step = cmath.exp(A * (2.0 * dx_first + 1.0) + 2.0 * B * dy0), cmath.exp(2.0 * A)
    h, h_step = cmath.exp(2.0 * B * dx_first), cmath.exp(2.0 * B)
    for i in range(columns):
        g_real[i], g_imag[i], h_real[i], h_imag[i] = g.real, g.imag, h.real, h.imag
        g, ratio, h = g * ratio, ratio * ratio_step, h * h_step
    row_factor = rotation * cmath.exp(C * dy0 * dy0)
    down, down_step = cmath.exp(C * (2.0 * dy0 + 1.0)), cmath.exp(2.0 * C)
    t_moments = u_moments = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for k in range(high + 1 - low):
        left, right = lefts[k], rights[k]
        if left <= right:
            count, offset = right + 1 - left, left - first
            grad_row = grad[low + k, left:right + 1]
            table_real, table_imag = g_real[offset:offset + count], g_imag[offset:offset + count]
            dx_left = left - x0
            s0r = s0i = s1r = s1i = s2r = s2i = 0.0
            for j in range(count):  # zero-based slices: LLVM proves the indices and vectorises
                gr, gi = grad_row[j].real, grad_row[j].imag
                wr = gr * table_real[j] + gi * table_imag[j]
                wi = gr * table_imag[j] - gi * table_real[j]
                dx = dx_left + j
                s0r += wr
                s0i += wi
                s1r += wr * dx
                s1i += wi * dx
                s2r += wr * dx * dx
                s2i += wi * dx * dx
            fr, fi = row_factor.real, row_factor.imag  # t + i·(−u) = row factor · Σḡ·G
            dy = low + k - y0
            t_moments = _with_row(t_moments, fr * s0r - fi * s0i, fr * s1r - fi * s1i, fr * s2r - fi * s2i, dy)
            u_moments = _with_row(u_moments, -(fr * s0i + fi * s0r), -(fr * s1i + fi * s1r),
                                  -(fr * s2i + fi * s2r), dy)
        for i in range(columns):
            gr = g_real[i] * h_real[i] - g_imag[i] * h_imag[i]
            g_imag[i] = g_real[i] * h_imag[i] + g_imag[i] * h_real[i]
            g_real[i] = gr
        row_factor, down = row_factor * down, down * down_step
    return t_moments, u_moments


@nb.njit(cache=True, nogil=True, fastmath=True)
def _gradients_of_one(n, position, conic, reach, chirp, color, phase, opacity, wavenumbers, mahalanobis,
                      grad, g_position, g_conic, g_chirp, g_color, g_phase, g_opacity, lefts, rights, tables):
    channels, height, width = grad.shape
    visible, x0, y0, r, a, b, c, low, high, walk, cx, dx0, dy0 = _footprint(n, position, conic, reach, height, width)
    if not visible:
        return
    first, last = _row_spans(x0, y0, r, a, b, c, low, high, width, lefts, rights)
    if first > last:
        return
    tabulated = _tabulated(a, b, c, r)
    alpha = np.float64(opacity[n])
    g_alpha = ga = gb = gc = gx = gy = 0.0
    for ch in range(channels):
        k, color_c = wavenumbers[ch], np.float64(color[n, ch])
        slot = _chirp_slot(ch, chirp)
        k_chirp = k * np.float64(chirp[n, slot])
        A, B, C = _exponent_coefficients(a, b, c, k_chirp, mahalanobis)
        rotation = cmath.exp(complex(0.0, phase[n, ch]))
        if tabulated:
            t_moments, u_moments = _tabulated_moments(grad[ch], A, B, C, rotation, x0, y0, low, high, lefts, rights,
                                                      first, last, tables[0], tables[1], tables[2], tables[3])
        else:
            t_moments, u_moments = _walked_moments(grad[ch], A, B, C, rotation, walk, x0, y0, -b / a, low, high,
                                                   lefts, rights, cx, dx0, dy0)
        t00, t10, t20, t01, t11, t02 = t_moments
        u00, u10, u20, u01, u11, u02 = u_moments
        scale = alpha * color_c
        g_color[n, ch] = alpha * t00
        g_phase[n, ch] = scale * u00
        g_alpha += color_c * t00
        if mahalanobis:  # D² carries both the envelope (−½) and the phase (k χ)
            w = -0.5 * scale
            q = scale * k_chirp
            m20, m11, m02 = w * t20 + q * u20, w * t11 + q * u11, w * t02 + q * u02
            m10, m01 = w * t10 + q * u10, w * t01 + q * u01
            g_chirp[n, slot] += scale * k * (a * u20 + 2.0 * b * u11 + c * u02)
            rx = ry = 0.0
        else:  # D² carries the envelope, |p − x|² the phase
            w = -0.5 * scale
            m20, m11, m02, m10, m01 = w * t20, w * t11, w * t02, w * t10, w * t01
            g_chirp[n, slot] += scale * k * (u20 + u02)
            rx, ry = scale * k_chirp * u10, scale * k_chirp * u01
        ga += m20
        gb += 2.0 * m11
        gc += m02
        gx -= 2.0 * (a * m10 + b * m01 + rx)
        gy -= 2.0 * (b * m10 + c * m01 + ry)
    g_opacity[n] = g_alpha
    g_conic[n, 0], g_conic[n, 1], g_conic[n, 2] = ga, gb, gc
    g_position[n, 0], g_position[n, 1] = gx, gy


@nb.njit(parallel=True, cache=True, fastmath=True)
def splat_backward(position, conic, reach, chirp, color, phase, opacity, wavenumbers, mahalanobis,
                   grad, g_position, g_conic, g_chirp, g_color, g_phase, g_opacity, threads):
    """Gradients (float64, each row written by its own primitive only) from grad [C, H, W] (complex64).

    Thread t of `threads` takes primitives t, t+T, t+2T, ..., as in the forward pass.

    The gradient arrays start at zero: channels sharing a curvature add into the same `g_chirp` slot.

    With z = exp(E) (phase φ included) and g the incoming gradient, a pixel contributes
    t = Re(ḡz) = dL/dRe(E)/(αc) and u = −Im(ḡz) = dL/dIm(E)/(αc). Every parameter's gradient is a
    sum of t or u times 1, dx, dy, dx², dx·dy or dy², so each pixel only adds to those moments,
    which become gradients once per primitive and channel. (The −50 floor's zero gradient is
    not reproduced: it concerns values below e⁻⁵⁰.)
    """
    height, width = grad.shape[1], grad.shape[2]
    for t in nb.prange(threads):
        lefts, rights = np.empty(height, np.int64), np.empty(height, np.int64)
        tables = (np.empty(width), np.empty(width), np.empty(width), np.empty(width))  # separate: no aliasing
        for n in range(t, position.shape[0], threads):
            _gradients_of_one(n, position, conic, reach, chirp, color, phase, opacity, wavenumbers, mahalanobis,
                              grad, g_position, g_conic, g_chirp, g_color, g_phase, g_opacity, lefts, rights, tables)
