"""Fused CPU kernels (Numba) for the splatting sum and its gradient.

The primitives come in as centres, scales, rotations and curvatures: `splat_geometry` turns them
into Σ⁻¹, footprint radii and chirps, and `geometry_gradients` takes the gradients of those back.

Both passes visit only the pixels inside each primitive's 3σ_major circle and store nothing of size
N × pixels. Per channel a primitive is `G = α c e^{iφ} exp(E)` with a complex exponent E that is
quadratic in the pixel offset (dx, dy) from its centre, E = A dx² + 2B dx dy + C dy² (the envelope
−½D² and the quadratic phase). The kernels leave out the pixels where method.md §2's floor of −50 on the
envelope exponent applies (D² > 100: values below e⁻⁵⁰ ≈ 2e-22 of the amplitude, invisible in
float32), so each row's span is the 3σ circle cut to the band where D² ≤ 100.

**Lane tables (most primitives).** Down a column the value moves one row by the ratio
H = exp(2B dx + C(2dy + 1)), which itself changes by the constant Q = exp(2C) per row. The kernels
keep G and H for every column of the footprint's bounding box and every channel in float32 "lanes"
(lane = column · C + channel, the layout of the image arrays too). Eight lanes make one vector
(`vectors.Float32x8`), and a strip of them walks down the box's rows with G and H in registers: add
G masked to the row's span, then G ← G·H and H ← H + H·(Q − 1) (`_stepped_down`). Per row only the
image is read and written (in loops over lane arrays LLVM cannot prove that G and H do not
overlap the image and stores them back on every row, which takes longer; docs/performance.md). The
forward pass walks two vectors at once, so that their chains of complex products overlap. The lanes
start on the box's first row from six exponentials per channel, walked along the row in float64, four
channels at a time as vectors (`_walk_along_row`); the channels share their magnitudes, and their
angles go through one vectorised cos/sin (`cosines_and_sines`).
Lanes hold primitives whose values stay inside float32's range over the box, ½D² ≤
`TABLE_EXPONENT_LIMIT` at its top corners: at initialisation all of them, and 98% of a fitted
model's.

**Real lanes (primitives without curvature).** Where χ = 0 in every channel (the flat baseline, and
CVQPG during its warm-up) exp(E) is the real envelope, the same in every channel: the lanes hold it
and its real ratios, walked along the first row once for all channels, and the phase e^{iφ} moves
out of the rows, into the amplitude the forward pass scales by and into one rotation of each
strip's sums in the backward pass. A row then costs half the multiplications.

**Walks (the others: needles).** Along a row each pixel's value is its neighbour's times a ratio
that itself changes by a constant factor, and the same holds from row to row down the centre
column; such primitives are walked outwards from that column in float64 with complex
multiplications only. Needles so elongated that a walk down the centre column could leave float64's
range (D² > 600 inside the footprint) start each row instead at its own envelope maximum from exact
values, and walk outwards from there, where values only decrease.

The hologram and its gradient travel as float32 lane images [2, H, (W + STRIP)·C] (real and
imaginary planes; `STRIP` zero columns on the right that a row's last strip of lanes may run into).
The forward pass gives each thread its own slice of primitives and its own image, summed in a fixed
order, so results do not depend on scheduling; the backward pass gives each thread the same slice,
and each primitive's gradients are written by that thread alone. Both compile with fast-math, and
their loops over the primitives without Numba's reference counting (`WITHOUT_REFERENCE_COUNTS`).
The small helpers that run once per primitive are inlined into those loops (`inline="always"`): a
call hands over every array argument field by field, through memory. The table builders and the
walks stay calls: inlining them too lengthens the kernels' first compilation by more than a first
fit would save (docs/performance.md, "Tried and not kept").
"""

from __future__ import annotations

import cmath
import math

import numba as nb
import numpy as np

from ..cpu import CALLED_BY_KERNELS_ONLY, cosines_and_sines
from . import vectors

FLOOR_MAHALANOBIS2 = 100.0  # D² where the envelope exponent −½D² reaches method.md §2's floor of −50
MAX_WALKED_MAHALANOBIS2 = 600.0
TABLE_EXPONENT_LIMIT = 80.0  # |Re log| of a lane value or ratio on the first row: e^±80 is inside float32
LANES = vectors.WIDTH  # float32 values in one AVX2 register
STRIP = 2 * LANES  # lanes the forward pass walks down the rows together; lane images have STRIP padding columns

OFF_IMAGE, TABULATED, WALKED, WALKED_FROM_RIDGE = 0, 1, 2, 3  # the ways through the kernels


@nb.njit(cache=True, nogil=True)
def lane_image_width(width, channels):
    """Values per row of a lane image for a W×H, C-channel hologram: (W + STRIP)·C."""
    return (width + STRIP) * channels


@nb.njit(cache=True, nogil=True, inline="always")
def _image_width(row_length, channels):
    """W of the hologram whose lane image has rows of `row_length` values (`lane_image_width`)."""
    return row_length // channels - STRIP


@nb.njit(cache=True, nogil=True, inline="always")
def _row_span(center_y, reach, a, b, c, height):
    """Rows of the footprint: the 3σ circle's, within the band |dy| ≤ 10·√Σ_yy where D² ≤ 100 can hold."""
    determinant = a * c - b * b
    half = reach if determinant <= 0.0 else min(reach, math.sqrt(FLOOR_MAHALANOBIS2 * a / determinant))
    return max(0, math.ceil(center_y - half)), min(height - 1, math.floor(center_y + half))


@nb.njit(cache=True, nogil=True, inline="always")
def _walkable(a, b, c, reach):
    """Whether every exponent in the footprint circle stays in the range the walk down the centre
    column needs: reach² · λ_max(Σ⁻¹), a bound on D² there, is at most 600."""
    return reach * reach * (0.5 * (a + c) + math.sqrt(0.25 * (a - c) ** 2 + b * b)) <= MAX_WALKED_MAHALANOBIS2


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _footprint(n, position, conic, reach, height, width, lefts, rights):
    """Primitive n's geometry: centre (px), Σ⁻¹ (a, b, c), reach (px), its rows, each row's columns
    into lefts/rights [row − low] (float64 column indices; empty rows have left > right), and the
    columns of its bounding box (first > last when it misses the image).

    A row dy (px from the centre) covers the 3σ circle where D² ≤ 100: around the row's envelope
    maximum −b·dy/a, ±√(100a − dy²·det Σ⁻¹)/a. The box is the circle's and the band's extent along
    x, ±min(reach, 10·√Σ_xx), which holds every row. The loop over rows has no branch and no
    reduction, so LLVM vectorises its square roots."""
    x0, y0, r = np.float64(position[n, 0]), np.float64(position[n, 1]), np.float64(reach[n])
    a, b, c = np.float64(conic[n, 0]), np.float64(conic[n, 1]), np.float64(conic[n, 2])
    low, high = _row_span(y0, r, a, b, c, height)
    determinant = a * c - b * b
    extent = r if determinant <= 0.0 else min(r, math.sqrt(FLOOR_MAHALANOBIS2 * c / determinant))
    first, last = max(0, math.ceil(x0 - extent)), min(width - 1, math.floor(x0 + extent))
    if low > high or first > last:
        return x0, y0, a, b, c, r, low, high, width, -1
    slope, dy = -b / a, low - y0
    for k in range(high + 1 - low):
        row = dy + k
        circle = math.sqrt(max(r * r - row * row, 0.0))
        band = math.sqrt(max(FLOOR_MAHALANOBIS2 * a - row * row * determinant, 0.0)) / a
        lefts[k] = max(0.0, np.ceil(x0 + max(-circle, slope * row - band)))
        rights[k] = min(width - 1.0, np.floor(x0 + min(circle, slope * row + band)))
    return x0, y0, a, b, c, r, low, high, first, last


@nb.njit(cache=True, nogil=True, inline="always")
def _fits_lanes(x0, y0, a, b, c, low, first, last):
    """Whether float32 lanes hold the primitive: its envelope exponent ½D² and its vertical ratio's
    |Re log H| = |b dx + c(dy + ½)| stay within TABLE_EXPONENT_LIMIT at the box's top corners. Both
    are extreme at a row's ends (D² is convex in dx, the other linear), and down the rows values only
    matter where D² ≤ 100, so the first row bounds them."""
    dy = low - y0
    worst = 0.0
    for dx in (first - x0, last - x0):
        worst = max(worst, 0.5 * (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy), abs(b * dx + c * (dy + 0.5)))
    return worst <= TABLE_EXPONENT_LIMIT


@nb.njit(cache=True, nogil=True, inline="always")
def _way(n, position, conic, reach, height, width, lefts, rights):
    """How primitive n goes through the kernels (OFF_IMAGE, TABULATED, WALKED or WALKED_FROM_RIDGE),
    with its geometry (`_footprint`)."""
    x0, y0, a, b, c, r, low, high, first, last = _footprint(n, position, conic, reach, height, width, lefts, rights)
    if first > last:
        way = OFF_IMAGE
    elif _fits_lanes(x0, y0, a, b, c, low, first, last):
        way = TABULATED
    else:
        way = WALKED if _walkable(a, b, c, r) else WALKED_FROM_RIDGE
    return way, x0, y0, a, b, c, r, low, high, first, last


@nb.njit(parallel=True, cache=True)
def ways(position, conic, reach, height, width):
    """The way each primitive goes through the kernels on an H×W image (for tests and diagnostics)."""
    result = np.empty(position.shape[0], np.int64)
    for n in nb.prange(position.shape[0]):
        lefts, rights = np.empty(height), np.empty(height)
        result[n] = _way(n, position, conic, reach, height, width, lefts, rights)[0]
    return result


LOCALITY_BAND_PX = 16


@nb.njit(cache=True)
def locality_order(position, height, width):
    """An order of the primitives by bands of LOCALITY_BAND_PX rows, then by column (a counting sort on
    the centre's band and nearest column, both clamped around the image): primitives that follow one
    another touch nearby memory, which shortens both kernels' time (docs/performance.md)."""
    bands, columns = height // LOCALITY_BAND_PX + 3, 3 * width + 1
    keys = np.empty(position.shape[0], np.int64)
    counts = np.zeros(bands * columns + 1, np.int64)
    for n in range(position.shape[0]):
        band = min(max(math.floor(position[n, 1] / LOCALITY_BAND_PX), -1), bands - 2) + 1
        column = min(max(round(position[n, 0]), -width), 2 * width) + width
        keys[n] = band * columns + column
        counts[keys[n] + 1] += 1
    for key in range(1, counts.shape[0]):
        counts[key] += counts[key - 1]
    order = np.empty(position.shape[0], np.int64)
    for n in range(position.shape[0]):
        order[counts[keys[n]]] = n
        counts[keys[n]] += 1
    return order


GEOMETRY_CHUNK = 4096  # primitives per task of the geometry's parallel loop


@nb.njit(parallel=True, cache=True, fastmath=True)
def splat_geometry(scale, rotation, curvature, regulariser, sigmas, half_pitch2, mahalanobis, terms, conic, reach,
                   chirp):
    """Σ⁻¹ (a, b, c) in 1/px² into conic [N, 3], the footprint radius into reach [N] (px) and the chirp χ
    into chirp [N, S] (S = curvature's columns) from the scales s (px), rotations θ (rad) and curvatures γ
    (1/m): `reference.splats`, the reference's reduction, once per primitive. Σ⁻¹ = R diag(i) Rᵀ with
    i = 1/(s² + r) (r the covariance regulariser, px²); the reach is `sigmas`·σ_major, the root of Σ's
    largest eigenvalue max(s)² + r; χ = ½Δx²·γ (half_pitch2 = ½Δx²), times s_x·s_y for the Mahalanobis QPF.
    terms [4, N] (float64) receives cos θ, sin θ, i_x and i_y, which `geometry_gradients` takes."""
    count = scale.shape[0]
    for task in nb.prange((count + GEOMETRY_CHUNK - 1) // GEOMETRY_CHUNK):
        low, high = task * GEOMETRY_CHUNK, min(count, (task + 1) * GEOMETRY_CHUNK)
        cosines, sines = terms[0, low:high], terms[1, low:high]
        cosines_and_sines(rotation[low:high], cosines, sines)
        for n in range(low, high):
            sx, sy = np.float64(scale[n, 0]), np.float64(scale[n, 1])
            along, across = 1.0 / (sx * sx + regulariser), 1.0 / (sy * sy + regulariser)
            cos, sin = terms[0, n], terms[1, n]
            terms[2, n], terms[3, n] = along, across
            conic[n, 0] = cos * cos * along + sin * sin * across
            conic[n, 1] = cos * sin * (along - across)
            conic[n, 2] = sin * sin * along + cos * cos * across
            reach[n] = sigmas * math.sqrt(max(sx * sx, sy * sy) + regulariser)
            factor = half_pitch2 * (sx * sy if mahalanobis else 1.0)
            for slot in range(chirp.shape[1]):
                chirp[n, slot] = factor * curvature[n, slot]


@nb.njit(parallel=True, cache=True, fastmath=True)
def geometry_gradients(scale, curvature, half_pitch2, mahalanobis, terms, g_conic, g_chirp, g_scale, g_rotation,
                       g_curvature):
    """The gradients of the scales, rotations and curvatures (float64) from those of Σ⁻¹'s (a, b, c) and
    of the chirps, through `splat_geometry` (whose `terms` it takes): with C, S = cos θ, sin θ,
    a = C²iₓ + S²i_y, b = CS(iₓ − i_y), c = S²iₓ + C²i_y, and ∂i/∂s = −2s·i²."""
    for n in nb.prange(scale.shape[0]):
        cos, sin, along, across = terms[0, n], terms[1, n], terms[2, n], terms[3, n]
        ga, gb, gc = g_conic[n, 0], g_conic[n, 1], g_conic[n, 2]
        cos2, sin2, both = cos * cos, sin * sin, cos * sin
        g_rotation[n] = (along - across) * ((cos2 - sin2) * gb - 2.0 * both * (ga - gc))
        sx, sy = np.float64(scale[n, 0]), np.float64(scale[n, 1])
        g_sx = -2.0 * sx * along * along * (cos2 * ga + both * gb + sin2 * gc)
        g_sy = -2.0 * sy * across * across * (sin2 * ga - both * gb + cos2 * gc)
        factor = half_pitch2 * (sx * sy if mahalanobis else 1.0)
        for slot in range(g_chirp.shape[1]):
            g_curvature[n, slot] = factor * g_chirp[n, slot]
            if mahalanobis:  # χ carries s_x·s_y
                g_product = half_pitch2 * curvature[n, slot] * g_chirp[n, slot]
                g_sx += g_product * sy
                g_sy += g_product * sx
        g_scale[n, 0], g_scale[n, 1] = g_sx, g_sy


@nb.njit(cache=True, nogil=True, inline="always")
def _phase_coefficients(a, b, c, mahalanobis):
    """(α_A, α_B, α_C) of the quadratic form the phase follows: D² (Σ⁻¹'s a, b, c) for the
    Mahalanobis QPF, |p − x|² (1, 0, 1) for the standard one."""
    return (a, b, c) if mahalanobis else (1.0, 0.0, 1.0)


@nb.njit(cache=True, nogil=True, inline="always")
def _exponent_coefficients(a, b, c, k_chirp, mahalanobis):
    """(A, B, C) of the complex exponent E = A dx² + 2B dx dy + C dy² (without the constant iφ): the
    envelope −½D² as real parts, k·χ times the phase's quadratic form as imaginary parts."""
    pa, pb, pc = _phase_coefficients(a, b, c, mahalanobis)
    return complex(-0.5 * a, k_chirp * pa), complex(-0.5 * b, k_chirp * pb), complex(-0.5 * c, k_chirp * pc)


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _scratch(channels):
    """A thread's arrays for the lane tables: angles, their cosines and sines (six per channel), the
    six magnitudes, the per-channel lane patterns (`PATTERNS`), and the walks' start values
    (`_walk_along_row`; zero for the channels past the last, which must stay finite)."""
    return (np.empty(6 * channels), np.empty(6 * channels), np.empty(6 * channels), np.empty(6),
            np.empty((PATTERNS, LANES * channels), np.float32), np.zeros((10, _vector_channels(channels))))


WALKED_CHANNELS = vectors.WIDTH_FLOAT64  # channels that the first-row walk and the moments take together


@nb.njit(cache=True, nogil=True, inline="always")
def _vector_channels(channels):
    """`channels` rounded up to whole vectors of WALKED_CHANNELS: the columns of arrays that hold one
    value per channel for them."""
    return (channels + WALKED_CHANNELS - 1) // WALKED_CHANNELS * WALKED_CHANNELS


# Per lane of LANES columns: Q − 1 (real and imaginary parts); the amplitude αc, or for real lanes e^{iφ} (times αc
# in the forward pass; real and imaginary parts).
PATTERNS = 4


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _pattern_index(strip, channels):
    """Where the lanes from `strip` start in a pattern of LANES columns: values that depend on the
    channel only repeat every LANES · C lanes, a whole number of vectors."""
    return strip % (LANES * channels)


@nb.njit(cache=True, nogil=True, inline="always")
def _polar(magnitudes, cosines, sines, channel, j):
    """The j-th of a channel's six lane exponentials from its magnitude and its angle's cos and sin."""
    return complex(magnitudes[j] * cosines[6 * channel + j], magnitudes[j] * sines[6 * channel + j])


@nb.njit(cache=True, nogil=True, inline="always")
def _lane_exponentials(magnitudes, cosines, sines, channel):
    """A channel's six lane exponentials: G, its ratio along the row, the ratio's step, H, its step, Q."""
    return (_polar(magnitudes, cosines, sines, channel, 0), _polar(magnitudes, cosines, sines, channel, 1),
            _polar(magnitudes, cosines, sines, channel, 2), _polar(magnitudes, cosines, sines, channel, 3),
            _polar(magnitudes, cosines, sines, channel, 4), _polar(magnitudes, cosines, sines, channel, 5))


@nb.njit(cache=True, nogil=True, inline="always")
def _lane_exponents(dx, dy, a, b, c):
    """The six lane exponentials' exponents, up to their factor, in a quadratic form (a, b, c) at the
    box's top-left offset (dx, dy): G, its ratio along the row, the ratio's step, H, its step, Q."""
    return (a * dx * dx + 2.0 * b * dx * dy + c * dy * dy, a * (2.0 * dx + 1.0) + 2.0 * b * dy, 2.0 * a,
            2.0 * b * dx + c * (2.0 * dy + 1.0), 2.0 * b, 2.0 * c)


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _lane_tables(n, a, b, c, x0, y0, low, first, columns, chirp, form, phase, wavenumbers, mahalanobis, count, lanes,
                 scratch):
    """Every channel's lanes (lane = column · C + channel) on the box's first row, zero past them up to
    `count` (a whole number of strips): G = e^{iφ}·exp(E), without the amplitude αc (the forward pass
    scales each strip by it, the gradient's moments are per unit αc), walked along the row by its
    ratio exp(A(2dx + 1) + 2B dy), which changes by exp(2A) per column; H = exp(2B dx + C(2dy + 1)),
    which changes by exp(2B). Q = exp(2C) depends on the channel only: Q − 1 goes into the scratch's
    pattern (`_pattern_index`; see `_stepped_down`). Those six exponentials per channel share their
    real parts, −½ of the same expressions in (a, b, c); their imaginary parts are k_c χ times them
    in (α_A, α_B, α_C), plus k_c times the phase terms' form (`_form_exponents`) where the primitive has one."""
    channels = phase.shape[1]
    dx, dy = first - x0, low - y0
    angles, cosines, sines, magnitudes, patterns, starts = scratch
    _lane_magnitudes(dx, dy, a, b, c, magnitudes)
    pa, pb, pc = _phase_coefficients(a, b, c, mahalanobis)
    quadratic = _lane_exponents(dx, dy, pa, pb, pc)
    for ch in range(channels):
        k_chirp = wavenumbers[ch] * chirp[n, _chirp_slot(ch, chirp)]
        for j in range(6):
            angles[6 * ch + j] = k_chirp * quadratic[j]
        angles[6 * ch] += phase[n, ch]
    if _has_form(n, form):
        extra = _form_exponents(dx, dy, n, form)
        for ch in range(channels):
            for j in range(6):
                angles[6 * ch + j] += wavenumbers[ch] * extra[j]
    cosines_and_sines(angles[:6 * channels], cosines, sines)
    for ch in range(channels):
        g, ratio, step, h, h_step, q = _lane_exponentials(magnitudes, cosines, sines, ch)
        for j in range(ch, LANES * channels, channels):
            patterns[0, j], patterns[1, j] = q.real - 1.0, q.imag
        starts[0, ch], starts[1, ch], starts[2, ch], starts[3, ch] = g.real, g.imag, ratio.real, ratio.imag
        starts[4, ch], starts[5, ch], starts[6, ch], starts[7, ch] = step.real, step.imag, h.real, h.imag
        starts[8, ch], starts[9, ch] = h_step.real, h_step.imag
    _walk_along_row(starts, channels, columns, lanes)
    g_re, g_im, h_re, h_im = lanes
    for j in range(columns * channels, count):
        g_re[j] = g_im[j] = h_re[j] = h_im[j] = 0.0


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _walk_along_row(starts, channels, columns, lanes):
    """G and H of every column and channel into the lanes (G ← G·ratio, ratio ← ratio·step,
    H ← H·step_H per column), from `starts` [10, ·] (G, ratio, step, H, step_H, real and imaginary
    parts, one column per channel). The channels go WALKED_CHANNELS at a time as float64 vectors
    (`vectors.Float64x4`), whose chains of complex products are the row's critical path: one chain for
    three channels instead of three one after the other. Each column stores four lanes at once. Past
    a group's last channel those stores overwrite the lanes of the next column's first channels, so
    the groups go from the last: the first group, walked last, leaves every lane right. The last
    column's stores reach up to three lanes past the box's lanes, which the lane arrays, as long as
    an image row, always have."""
    g_re, g_im, h_re, h_im = lanes
    for group in range((channels - 1) // WALKED_CHANNELS, -1, -1):
        at = group * WALKED_CHANNELS
        gr, gi, rr, ri = (vectors.load(starts[0], at), vectors.load(starts[1], at), vectors.load(starts[2], at),
                          vectors.load(starts[3], at))
        sr, si, hr, hi = (vectors.load(starts[4], at), vectors.load(starts[5], at), vectors.load(starts[6], at),
                          vectors.load(starts[7], at))
        hsr, hsi = vectors.load(starts[8], at), vectors.load(starts[9], at)
        for column in range(columns):
            j = column * channels + at
            vectors.store_float32(g_re, j, gr)
            vectors.store_float32(g_im, j, gi)
            vectors.store_float32(h_re, j, hr)
            vectors.store_float32(h_im, j, hi)
            gr, gi, rr, ri = gr * rr - gi * ri, gr * ri + gi * rr, rr * sr - ri * si, rr * si + ri * sr
            hr, hi = hr * hsr - hi * hsi, hr * hsi + hi * hsr


@nb.njit(cache=True, nogil=True, inline="always")
def _lane_magnitudes(dx, dy, a, b, c, magnitudes):
    """The six lane exponentials' magnitudes (`_lane_exponents`), exp(−½·) of the envelope's exponents,
    which every channel shares."""
    envelope = _lane_exponents(dx, dy, a, b, c)
    for j in range(6):
        magnitudes[j] = math.exp(-0.5 * envelope[j])


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _real_lane_tables(a, b, c, x0, y0, low, first, columns, channels, count, lanes, magnitudes, patterns):
    """`_lane_tables` for a primitive without quadratic phase (χ = 0 in every channel): exp(E) is then
    the real envelope, the same in every channel, and its lanes hold it without the phase e^{iφ}
    (G and H into lanes[0] and lanes[2]; Q − 1 into the pattern). The walk along the row is a chain
    of real products, shared by the channels; each column's value goes into its lanes four at a time,
    past the column's last channel into lanes that the next column overwrites, or up to three lanes
    past the box's (as in `_walk_along_row`)."""
    _lane_magnitudes(first - x0, low - y0, a, b, c, magnitudes)
    g, ratio, step, h, h_step, q = magnitudes[0], magnitudes[1], magnitudes[2], magnitudes[3], magnitudes[4], \
        magnitudes[5]
    for j in range(LANES * channels):
        patterns[0, j] = q - 1.0
    g_lanes, h_lanes = lanes[0], lanes[2]
    for column in range(columns):
        gv, hv = vectors.splat_float64(g), vectors.splat_float64(h)
        for j in range(column * channels, (column + 1) * channels, WALKED_CHANNELS):
            vectors.store_float32(g_lanes, j, gv)
            vectors.store_float32(h_lanes, j, hv)
        g, ratio, h = g * ratio, ratio * step, h * h_step
    for j in range(columns * channels, count):
        g_lanes[j] = h_lanes[j] = 0.0


@nb.njit(cache=True, nogil=True, inline="always")
def _is_real(n, chirp):
    """Whether primitive n has no quadratic phase in any channel (χ = 0): its exp(E) is real."""
    for slot in range(chirp.shape[1]):
        if chirp[n, slot] != 0.0:
            return False
    return True


@nb.njit(cache=True, nogil=True, inline="always")
def _has_form(n, form):
    """Whether primitive n has a phase beyond the paper's chirp (`reference.Splats.form`, [N, 5] or [0, 5] for
    none): the path P_a dx² + 2P_b dx dy + P_c dy² + L_x dx + L_y dy (m) is not zero."""
    if form.shape[0] == 0:
        return False
    for j in range(form.shape[1]):
        if form[n, j] != 0.0:
            return True
    return False


@nb.njit(cache=True, nogil=True, inline="always")
def _form_exponents(dx, dy, n, form):
    """The form's path (m) in the six lane exponentials (`_lane_exponents`) at the box's top-left offset: its
    quadratic part as the envelope's, and its linear part L·d in G, L_x in the row's ratio, L_y in H."""
    pa, pb, pc, lx, ly = (np.float64(form[n, 0]), np.float64(form[n, 1]), np.float64(form[n, 2]),
                          np.float64(form[n, 3]), np.float64(form[n, 4]))
    g, ratio, step, h, h_step, q = _lane_exponents(dx, dy, pa, pb, pc)
    return g + lx * dx + ly * dy, ratio + lx, step, h + ly, h_step, q


@nb.njit(cache=True, nogil=True, inline="always")
def _with_form(A, B, C, k, n, form, tilted):
    """(A, B, C) of the complex exponent with k times the form's quadratic part added to their imaginary parts
    where `tilted`, and the linear coefficients (D, F) of E's D dx + F dy (zero otherwise)."""
    if not tilted:
        return A, B, C, 0j, 0j
    return (A + complex(0.0, k * form[n, 0]), B + complex(0.0, k * form[n, 1]), C + complex(0.0, k * form[n, 2]),
            complex(0.0, k * form[n, 3]), complex(0.0, k * form[n, 4]))


@nb.njit(cache=True, nogil=True, inline="always")
def _amplitude_pattern(n, color, opacity, patterns):
    """The amplitude αc of primitive n's channels into the scratch's pattern (`_pattern_index`)."""
    channels = color.shape[1]
    for ch in range(channels):
        amplitude = opacity[n] * color[n, ch]
        for j in range(ch, LANES * channels, channels):
            patterns[2, j] = amplitude


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _rotation_pattern(n, phase, color, opacity, with_amplitude, patterns):
    """e^{iφ} of primitive n's channels, times the amplitude αc if `with_amplitude`, into the lane
    patterns (real and imaginary parts, `_pattern_index`): what real lanes are multiplied by. libm's
    cos and sin, one pair per channel, cost less here than a call to `cosines_and_sines` for so few."""
    channels = phase.shape[1]
    for ch in range(channels):
        scale = opacity[n] * color[n, ch] if with_amplitude else 1.0
        angle = np.float64(phase[n, ch])
        cosine, sine = scale * math.cos(angle), scale * math.sin(angle)
        for j in range(ch, LANES * channels, channels):
            patterns[2, j], patterns[3, j] = cosine, sine


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _tabulate(n, a, b, c, x0, y0, low, first, columns, chirp, form, color, phase, opacity, wavenumbers,
              mahalanobis, count, lanes, scratch, with_amplitude):
    """The box's lane tables and the scratch's patterns, the amplitude αc among them if `with_amplitude`
    (the forward pass): real lanes (`_real_lane_tables`) for a primitive without curvature, else
    complex ones (`_lane_tables`). Returns whether the lanes are real."""
    patterns = scratch[4]
    if _is_real(n, chirp) and not _has_form(n, form):
        _real_lane_tables(a, b, c, x0, y0, low, first, columns, phase.shape[1], count, lanes, scratch[3], patterns)
        _rotation_pattern(n, phase, color, opacity, with_amplitude, patterns)
        return True
    _lane_tables(n, a, b, c, x0, y0, low, first, columns, chirp, form, phase, wavenumbers, mahalanobis, count, lanes,
                 scratch)
    if with_amplitude:
        _amplitude_pattern(n, color, opacity, patterns)
    return False


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _lane_spans(lefts, rights, first, channels, rows, spans):
    """Each row's span [left, right] (columns) as lane positions [low, high) in the box, into
    spans = (lows, highs) (float32; empty where low ≥ high)."""
    lows, highs = spans
    for k in range(rows):
        lows[k] = (lefts[k] - first) * channels
        highs[k] = (rights[k] + 1 - first) * channels


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _strip_rows(strip, lanes, spans, rows):
    """How many of the box's rows the `lanes` lanes from `strip` walk: down to the last row whose span
    meets them (the rows below need nothing from them)."""
    lows, highs = spans
    last = rows - 1
    while last >= 0 and max(lows[last], strip) >= min(highs[last], strip + lanes):
        last -= 1
    return last + 1


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _strip_state(lanes, patterns, strip, channels):
    """The G, H and Q (real and imaginary vectors) of the eight lanes from `strip`, on the box's first row."""
    at = _pattern_index(strip, channels)
    return (vectors.load(lanes[0], strip), vectors.load(lanes[1], strip), vectors.load(lanes[2], strip),
            vectors.load(lanes[3], strip), vectors.load(patterns[0], at), vectors.load(patterns[1], at))


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _stepped_down(gr, gi, hr, hi, qr, qi):
    """G and H one row down: G·H, and H·Q as H + H·q from q = Q − 1. Q is close to 1, and float32(Q)'s
    rounding would compound over the rows (H drifting by k times it after k rows, G by k²/2 times);
    float32(Q − 1) carries the same rounding relative to Q − 1, far smaller. For the same arithmetic,
    boxes of 180 rows agree with the float64 reference to 3e-5 instead of 1.7e-4."""
    return gr * hr - gi * hi, gr * hi + gi * hr, hr + (hr * qr - hi * qi), hi + (hr * qi + hi * qr)


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _add_masked(image, at, position, low, high, value):
    """image[at:at + 8] += value where low ≤ position < high."""
    vectors.store(image, at, vectors.load(image, at) + vectors.where_between(position, low, high, value))


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _add_strips(lanes, patterns, channels, count, spans, rows, row_length, start, out_re, out_im):
    """out += αc·G over the box's rows, each row masked to its span. The lanes go down the rows STRIP
    at a time, as two vectors with G and H in registers (G ← G·H, H ← H·Q): one vector's chain of
    complex products would leave the multipliers idle for its latency. `out_re`, `out_im` are flat
    lane images; the box's first lane is at `start`, a row is `row_length` further."""
    lows, highs = spans
    for strip in range(0, count, STRIP):
        second = strip + LANES
        gr, gi, hr, hi, qr, qi = _strip_state(lanes, patterns, strip, channels)
        gr2, gi2, hr2, hi2, qr2, qi2 = _strip_state(lanes, patterns, second, channels)
        amplitude = vectors.load(patterns[2], _pattern_index(strip, channels))
        amplitude2 = vectors.load(patterns[2], _pattern_index(second, channels))
        gr, gi, gr2, gi2 = gr * amplitude, gi * amplitude, gr2 * amplitude2, gi2 * amplitude2
        position, position2 = vectors.ramp(strip), vectors.ramp(second)
        at = start + strip
        for k in range(_strip_rows(strip, STRIP, spans, rows)):
            low, high = vectors.splat(lows[k]), vectors.splat(highs[k])
            _add_masked(out_re, at, position, low, high, gr)
            _add_masked(out_im, at, position, low, high, gi)
            _add_masked(out_re, at + LANES, position2, low, high, gr2)
            _add_masked(out_im, at + LANES, position2, low, high, gi2)
            gr, gi, hr, hi = _stepped_down(gr, gi, hr, hi, qr, qi)
            gr2, gi2, hr2, hi2 = _stepped_down(gr2, gi2, hr2, hi2, qr2, qi2)
            at += row_length


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _add_real_strips(lanes, patterns, channels, count, spans, rows, row_length, start, out_re, out_im):
    """`_add_strips` for real lanes (`_real_lane_tables`): out += αc·e^{iφ}·G, with G and H real, so a row
    costs a product and a multiply-add per vector for G and H, and one multiply-add per image plane."""
    lows, highs = spans
    for strip in range(0, count, STRIP):
        second = strip + LANES
        at, at2 = _pattern_index(strip, channels), _pattern_index(second, channels)
        g, h, q = vectors.load(lanes[0], strip), vectors.load(lanes[2], strip), vectors.load(patterns[0], at)
        g2, h2, q2 = vectors.load(lanes[0], second), vectors.load(lanes[2], second), vectors.load(patterns[0], at2)
        ar, ai = vectors.load(patterns[2], at), vectors.load(patterns[3], at)
        ar2, ai2 = vectors.load(patterns[2], at2), vectors.load(patterns[3], at2)
        position, position2 = vectors.ramp(strip), vectors.ramp(second)
        at = start + strip
        for k in range(_strip_rows(strip, STRIP, spans, rows)):
            low, high = vectors.splat(lows[k]), vectors.splat(highs[k])
            inside, inside2 = (vectors.where_between(position, low, high, g),
                               vectors.where_between(position2, low, high, g2))
            vectors.store(out_re, at, vectors.load(out_re, at) + ar * inside)
            vectors.store(out_im, at, vectors.load(out_im, at) + ai * inside)
            vectors.store(out_re, at + LANES, vectors.load(out_re, at + LANES) + ar2 * inside2)
            vectors.store(out_im, at + LANES, vectors.load(out_im, at + LANES) + ai2 * inside2)
            g, h, g2, h2 = g * h, h + h * q, g2 * h2, h2 + h2 * q2
            at += row_length


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _accumulate_strips(lanes, patterns, channels, count, spans, rows, row_length, start, dy_first, grad_re,
                       grad_im):
    """Per lane, with w = ḡ·G over each row's span: Σw, Σw·dy and Σw·dy² (real and imaginary parts)
    into lanes[4:10]. As in `_add_strips`, with eight lanes at a time: the sums live in registers
    too, which leaves no room for a second vector.

    The rows add w into running sums, T += w, U += T, V += U, additions only (the multipliers are
    the loop's bottleneck). After K rows, with m = K − k for row k, U = Σw·m and 2V − U = Σw·m², and
    dy = e − m with e = dy_first + K, so Σw·dy = eT − U and Σw·dy² = e²T − (2e + 1)U + 2V."""
    lows, highs = spans
    for strip in range(0, count, LANES):
        gr, gi, hr, hi, qr, qi = _strip_state(lanes, patterns, strip, channels)
        position = vectors.ramp(strip)
        tr = ti = ur = ui = vr = vi = vectors.splat(0.0)
        at, walked = start + strip, _strip_rows(strip, LANES, spans, rows)
        for k in range(walked):
            low, high = vectors.splat(lows[k]), vectors.splat(highs[k])
            er, ei = vectors.load(grad_re, at), vectors.load(grad_im, at)
            tr = tr + vectors.where_between(position, low, high, er * gr + ei * gi)
            ti = ti + vectors.where_between(position, low, high, er * gi - ei * gr)
            ur, ui = ur + tr, ui + ti
            vr, vi = vr + ur, vi + ui
            gr, gi, hr, hi = _stepped_down(gr, gi, hr, hi, qr, qi)
            at += row_length
        _store_moments(lanes, strip, dy_first + walked, tr, ti, ur, ui, vr, vi)


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _store_moments(lanes, strip, e, tr, ti, ur, ui, vr, vi):
    """Σw, Σw·dy and Σw·dy² of the lanes from `strip` into lanes[4:10] from their running sums T, U, V
    (`_accumulate_strips`), e being dy one row past the strip's last."""
    first, second, third = vectors.splat(e), vectors.splat(e * e), vectors.splat(2.0 * e + 1.0)
    two = vectors.splat(2.0)
    vectors.store(lanes[4], strip, tr)
    vectors.store(lanes[5], strip, ti)
    vectors.store(lanes[6], strip, first * tr - ur)
    vectors.store(lanes[7], strip, first * ti - ui)
    vectors.store(lanes[8], strip, second * tr - third * ur + two * vr)
    vectors.store(lanes[9], strip, second * ti - third * ui + two * vi)


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _accumulate_real_strips(lanes, patterns, channels, count, spans, rows, row_length, start, dy_first, grad_re,
                            grad_im):
    """`_accumulate_strips` for real lanes (`_real_lane_tables`): the rows sum ḡ·G with G real, and the
    sums are rotated by the pattern's e^{iφ} once at the strip's end (w = e^{iφ}·ḡ·G)."""
    lows, highs = spans
    for strip in range(0, count, LANES):
        at = _pattern_index(strip, channels)
        g, h, q = vectors.load(lanes[0], strip), vectors.load(lanes[2], strip), vectors.load(patterns[0], at)
        cosine, sine = vectors.load(patterns[2], at), vectors.load(patterns[3], at)
        position = vectors.ramp(strip)
        tr = ti = ur = ui = vr = vi = vectors.splat(0.0)
        at, walked = start + strip, _strip_rows(strip, LANES, spans, rows)
        for k in range(walked):
            inside = vectors.where_between(position, vectors.splat(lows[k]), vectors.splat(highs[k]), g)
            tr = tr + vectors.load(grad_re, at) * inside
            ti = ti + vectors.load(grad_im, at) * inside
            ur, ui = ur + tr, ui + ti
            vr, vi = vr + ur, vi + ui
            g, h = g * h, h + h * q
            at += row_length
        _store_moments(lanes, strip, dy_first + walked, cosine * tr + sine * ti, sine * tr - cosine * ti,
                       cosine * ur + sine * ui, sine * ur - cosine * ui, cosine * vr + sine * vi,
                       sine * vr - cosine * vi)


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _exact_at(A, B, C, dx, dy):
    """exp(E) at offset (dx, dy), and the ratios to its right and left neighbours."""
    return (cmath.exp(A * dx * dx + 2.0 * B * dx * dy + C * dy * dy),
            cmath.exp(A * (2.0 * dx + 1.0) + 2.0 * B * dy), cmath.exp(A * (1.0 - 2.0 * dx) - 2.0 * B * dy))


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _walk_start(A, B, C, D, F, tilted, dx0, dy0):
    """Exact values at the walk's start (column dx0, first row dy0): exp(E), the vertical ratio and
    its change, the rightward and leftward ratios, their changes per row (right, left) and per step.
    Where `tilted`, E's linear part D dx + F dy scales exp(E) and the ratios: it changes none of the steps."""
    z0, s_right, s_left = _exact_at(A, B, C, dx0, dy0)
    vertical = cmath.exp(2.0 * B * dx0 + C * (2.0 * dy0 + 1.0))
    if tilted:
        z0, s_right, s_left = _tilted(z0, s_right, s_left, D, F, dx0, dy0)
        vertical *= cmath.exp(F)
    return (z0, vertical, cmath.exp(2.0 * C), s_right, s_left, cmath.exp(2.0 * B), cmath.exp(-2.0 * B),
            cmath.exp(2.0 * A))


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _tilted(z, s_right, s_left, D, F, dx, dy):
    """exp(E) at (dx, dy) and its ratios to the right and left neighbours (`_exact_at`) with E's linear part
    D dx + F dy added."""
    return z * cmath.exp(D * dx + F * dy), s_right * cmath.exp(D), s_left * cmath.exp(-D)


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _row_walks(walk, A, B, C, D, F, tilted, scale, z_row, s_right, s_left, s_step, x0, dy, cx, ridge_slope, left,
               right):
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
        if tilted:
            z_row, s_right, s_left = _tilted(z_row, s_right, s_left, D, F, start - x0, dy)
        z_row *= scale
    steps = max(right + 1 - start, start - left) if left <= right else 0
    return start, z_row, s_right, z_row * s_left, s_left * s_step, steps


@nb.njit(cache=True, nogil=True, **CALLED_BY_KERNELS_ONLY)
def _next_row(z_row, v, v_step, s_right, s_left, s_row, s_row_left):
    """The walk's state one row down (no division: off the walk's range these values overflow to
    unused infinities, and a division by an underflowed zero would raise)."""
    return z_row * v, v * v_step, s_right * s_row, s_left * s_row_left


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _with_row(moments, m0, m1, m2, dy):
    """A primitive's moments (Σm, Σm·dx, Σm·dx², Σm·dy, Σm·dx·dy, Σm·dy²) with one row's sums
    (Σm, Σm·dx, Σm·dx² over the row, at offset dy) added."""
    s00, s10, s20, s01, s11, s02 = moments
    return s00 + m0, s10 + m1, s20 + m2, s01 + m0 * dy, s11 + m1 * dy, s02 + m0 * dy * dy


@nb.njit(cache=True, nogil=True, inline="always")
def _chirp_slot(channel, chirp):
    """Column of `chirp` [N, 1 or C] that channel uses: one shared curvature, or its own."""
    return min(channel, chirp.shape[1] - 1)


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _walked_rows(A, B, C, D, F, tilted, amplitude, way, x0, y0, low, high, lefts, rights, lane, channels, out_re,
                 out_im):
    """out += amplitude · exp(E) over the footprint, each row walked outwards (see the module notes); E has the
    linear part D dx + F dy where `tilted`."""
    cx = round(x0)
    z_row, v, v_step, s_right, s_left, s_row, s_row_left, s_step = _walk_start(A, B, C, D, F, tilted, cx - x0,
                                                                               low - y0)
    z_row *= amplitude
    for py in range(low, high + 1):
        dy = py - y0
        left, right = int(lefts[py - low]), int(rights[py - low])
        row_re, row_im = out_re[py], out_im[py]
        start, z_r, s_r, z_l, s_l, steps = _row_walks(way == WALKED, A, B, C, D, F, tilted, amplitude, z_row, s_right,
                                                      s_left, s_step, x0, dy, cx, -B.real / A.real, left, right)
        for i in range(steps):
            for px, z in ((start + i, z_r), (start - 1 - i, z_l)):
                if left <= px <= right:
                    row_re[px * channels + lane] += z.real
                    row_im[px * channels + lane] += z.imag
            z_r, s_r = z_r * s_r, s_r * s_step
            z_l, s_l = z_l * s_l, s_l * s_step
        z_row, v, s_right, s_left = _next_row(z_row, v, v_step, s_right, s_left, s_row, s_row_left)


@nb.njit(cache=True, nogil=True, inline="always")
def _block_lanes(columns, channels, block):
    """Lanes of `columns` box columns, rounded up to whole blocks of `block` lanes."""
    return (columns * channels + block - 1) // block * block


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _splat_one(n, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers, mahalanobis, out_re,
               out_im, image_re, image_im, lefts, rights, spans, lanes, scratch):
    channels = color.shape[1]
    height, width = out_re.shape[0], _image_width(out_re.shape[1], channels)
    way, x0, y0, a, b, c, r, low, high, first, last = _way(n, position, conic, reach, height, width, lefts, rights)
    if way == OFF_IMAGE:
        return
    if way != TABULATED:
        tilted = _has_form(n, form)
        for ch in range(channels):
            A, B, C = _exponent_coefficients(a, b, c, wavenumbers[ch] * chirp[n, _chirp_slot(ch, chirp)],
                                             mahalanobis)
            A, B, C, D, F = _with_form(A, B, C, wavenumbers[ch], n, form, tilted)
            amplitude = opacity[n] * color[n, ch] * cmath.exp(complex(0.0, phase[n, ch]))
            _walked_rows(A, B, C, D, F, tilted, amplitude, way, x0, y0, low, high, lefts, rights, ch, channels,
                         out_re, out_im)
        return
    columns, count = last + 1 - first, _block_lanes(last + 1 - first, channels, STRIP)
    box = (lanes[0][:count], lanes[1][:count], lanes[2][:count], lanes[3][:count])
    _lane_spans(lefts, rights, first, channels, high + 1 - low, spans)
    row_length, patterns = out_re.shape[1], scratch[4]
    start = low * row_length + first * channels
    if _tabulate(n, a, b, c, x0, y0, low, first, columns, chirp, form, color, phase, opacity, wavenumbers,
                 mahalanobis, count, box, scratch, True):
        _add_real_strips(box, patterns, channels, count, spans, high + 1 - low, row_length, start, image_re, image_im)
    else:
        _add_strips(box, patterns, channels, count, spans, high + 1 - low, row_length, start, image_re, image_im)


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _splat_share(t, threads, order, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers,
                 mahalanobis, out_re, out_im):
    """out += the sum over primitives order[t], order[t+T], order[t+2T], ... (T = threads): one thread's
    share. Its work arrays are made here, for `_splat_loop`, which cannot allocate."""
    height, width = out_re.shape[0], out_re.shape[1]
    lefts, rights, spans = np.empty(height), np.empty(height), (np.empty(height, np.float32),
                                                                np.empty(height, np.float32))
    lanes = (np.empty(width, np.float32), np.empty(width, np.float32), np.empty(width, np.float32),
             np.empty(width, np.float32))
    _splat_loop(t, threads, order, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers,
                mahalanobis, out_re, out_im, out_re.reshape(out_re.size), out_im.reshape(out_im.size), lefts, rights, spans, lanes,
                _scratch(color.shape[1]))


# Numba's runtime counts the references to every array that enters an inlined function, with an
# atomic increment and decrement per array and call: about 50 per primitive, which slow either kernel
# (docs/performance.md, "Around the kernels"). The loops over the primitives compile without it (Numba
# 0.68's `_nrt` option), which leaves those counts out; such a function cannot allocate, so its caller
# passes in its arrays.
WITHOUT_REFERENCE_COUNTS = {"_nrt": False}


@nb.njit(cache=True, nogil=True, fastmath=True, **WITHOUT_REFERENCE_COUNTS, **CALLED_BY_KERNELS_ONLY)
def _splat_loop(t, threads, order, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers,
                mahalanobis, out_re, out_im, image_re, image_im, lefts, rights, spans, lanes, scratch):
    """`_splat_share`'s loop: a plain loop into which each primitive's work is inlined (a call per
    primitive would hand over every array field by field, docs/performance.md, and Numba 0.68
    miscompiles that work inlined into the parallel loop). `image_re`, `image_im` are `out_re`,
    `out_im` as flat arrays, which the strips index: reshaped once here, not per primitive (a call
    into Numba's helper library each)."""
    for i in range(t, position.shape[0], threads):
        _splat_one(order[i], position, conic, reach, chirp, form, color, phase, opacity, wavenumbers, mahalanobis,
                   out_re, out_im, image_re, image_im, lefts, rights, spans, lanes, scratch)


# A prange index is int64 where Numba first types a parallel function and uint64 in the loop body it
# compiles from it: a function called with the bare index compiles twice (the rasterizer's loops did:
# docs/performance.md, "First run"). The parallel loops hand it on as np.int64.


@nb.njit(parallel=True, cache=True, fastmath=True)
def splat_forward(order, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers, mahalanobis,
                  partial):
    """partial[t] += the sum over primitives order[t], order[t+T], order[t+2T], ... (T = partial.shape[0]).

    `partial` [T, 2, H, (W + STRIP)·C] (float32 lane images) starts at zero; `gather_partials` sums it
    over t in order.
    """
    threads = partial.shape[0]
    for t in nb.prange(threads):
        _splat_share(np.int64(t), threads, order, position, conic, reach, chirp, form, color, phase, opacity,
                     wavenumbers, mahalanobis, partial[t, 0], partial[t, 1])


@nb.njit(parallel=True, cache=True)
def gather_partials(partial, out):
    """out [C, H, W] (complex64) = Σ_t partial[t] in order of t, from lane images; partial is left
    zero, ready for the next forward pass."""
    channels, height, width = out.shape
    for y in nb.prange(height):
        for ch in range(channels):
            target = out[ch, y]
            for x in range(width):
                target[x] = complex(partial[0, 0, y, x * channels + ch], partial[0, 1, y, x * channels + ch])
            for t in range(1, partial.shape[0]):
                for x in range(width):
                    target[x] += complex(partial[t, 0, y, x * channels + ch], partial[t, 1, y, x * channels + ch])
        for t in range(partial.shape[0]):
            partial[t, 0, y, :] = 0.0
            partial[t, 1, y, :] = 0.0


@nb.njit(parallel=True, cache=True)
def split_lanes(values, out):
    """out [2, H, (W + STRIP)·C] (float32 lane image) = values [C, H, W] (complex64); the padding
    columns are left as they are (zero in a zero-initialised array)."""
    channels, height, width = values.shape
    for y in nb.prange(height):
        real, imag = out[0, y], out[1, y]
        for ch in range(channels):
            source = values[ch, y]
            for x in range(width):
                real[x * channels + ch], imag[x * channels + ch] = source[x].real, source[x].imag


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _walked_moments(grad_re, grad_im, A, B, C, D, F, tilted, rotation, way, x0, y0, low, high, lefts, rights, lane,
                    channels):
    """One channel's moments of t and u (see `splat_backward`) over the footprint, walking each row
    outwards from its start by complex multiplication (E with D dx + F dy where `tilted`)."""
    cx = round(x0)
    z_row, v, v_step, s_right, s_left, s_row, s_row_left, s_step = _walk_start(A, B, C, D, F, tilted, cx - x0,
                                                                               low - y0)
    z_row *= rotation
    t_moments = u_moments = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for py in range(low, high + 1):
        dy = py - y0
        left, right = int(lefts[py - low]), int(rights[py - low])
        row_re, row_im = grad_re[py], grad_im[py]
        t0 = t1 = t2 = u0 = u1 = u2 = 0.0
        start, z_r, s_r, z_l, s_l, steps = _row_walks(way == WALKED, A, B, C, D, F, tilted, rotation, z_row, s_right,
                                                      s_left, s_step, x0, dy, cx, -B.real / A.real, left, right)
        for i in range(steps):
            for px, z in ((start + i, z_r), (start - 1 - i, z_l)):
                if left <= px <= right:
                    dx = px - x0
                    gr, gi = np.float64(row_re[px * channels + lane]), np.float64(row_im[px * channels + lane])
                    t = gr * z.real + gi * z.imag
                    u = gi * z.real - gr * z.imag
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


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _lane_moments(lanes, channels, columns, dx_first, moments):
    """Every channel's moments of t and u from its lanes' sums Σw, Σw·dy, Σw·dy² (w = t − i·u): each
    column adds them weighted by 1, dx, dx². Into moments [12, ·], one column per channel: t00, t10,
    t20, t01, t11, t02, then u00 to u02. The channels go WALKED_CHANNELS at a time as float64 vectors
    (their lanes are consecutive); past a group's last channel the vectors' lanes read the next
    column's first channels, or up to three lanes past the box's, and are discarded."""
    s0r, s0i, s1r, s1i, s2r, s2i = lanes[4:]
    zero = vectors.splat_float64(0.0)
    for at in range(0, channels, WALKED_CHANNELS):
        t00 = t10 = t20 = t01 = t11 = t02 = u00 = u10 = u20 = u01 = u11 = u02 = zero
        for i in range(columns):
            j = i * channels + at
            dx = vectors.splat_float64(dx_first + i)
            t0, t1, u0, u1 = (vectors.load_float64(s0r, j), vectors.load_float64(s1r, j), vectors.load_float64(s0i, j),
                              vectors.load_float64(s1i, j))
            t0x, u0x = t0 * dx, u0 * dx
            t00, t10, t20, t01, t11 = t00 + t0, t10 + t0x, t20 + t0x * dx, t01 + t1, t11 + t1 * dx
            u00, u10, u20, u01, u11 = u00 + u0, u10 + u0x, u20 + u0x * dx, u01 + u1, u11 + u1 * dx
            t02, u02 = t02 + vectors.load_float64(s2r, j), u02 + vectors.load_float64(s2i, j)
        for row, value in enumerate((t00, t10, t20, t01, t11, t02)):
            vectors.store(moments[row], at, value)
        for row, value in enumerate((u00, u10, u20, u01, u11, u02)):
            vectors.store(moments[6 + row], at, zero - value)  # u = −Im(w)


@nb.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _gradients_of_one(n, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers, mahalanobis,
                      grad_re, grad_im, image_re, image_im, g_position, g_conic, g_chirp, g_form, g_color, g_phase,
                      g_opacity, lefts, rights, spans, lanes, scratch, moments):
    channels = color.shape[1]
    height, width = grad_re.shape[0], _image_width(grad_re.shape[1], channels)
    way, x0, y0, a, b, c, r, low, high, first, last = _way(n, position, conic, reach, height, width, lefts, rights)
    if way == OFF_IMAGE:
        return
    columns = last + 1 - first
    count = _block_lanes(columns, channels, LANES) if way == TABULATED else 0
    box = (lanes[0][:count], lanes[1][:count], lanes[2][:count], lanes[3][:count], lanes[4][:count],
           lanes[5][:count], lanes[6][:count], lanes[7][:count], lanes[8][:count], lanes[9][:count])
    if way == TABULATED:
        _lane_spans(lefts, rights, first, channels, high + 1 - low, spans)
        row_length, patterns = grad_re.shape[1], scratch[4]
        start = low * row_length + first * channels
        if _tabulate(n, a, b, c, x0, y0, low, first, columns, chirp, form, color, phase, opacity, wavenumbers,
                     mahalanobis, count, box[:4], scratch, False):
            _accumulate_real_strips(box, patterns, channels, count, spans, high + 1 - low, row_length, start, low - y0,
                                    image_re, image_im)
        else:
            _accumulate_strips(box, patterns, channels, count, spans, high + 1 - low, row_length, start, low - y0,
                               image_re, image_im)
        _lane_moments(box, channels, columns, first - x0, moments)
    alpha = np.float64(opacity[n])
    g_alpha = ga = gb = gc = gx = gy = 0.0
    tilted = _has_form(n, form)
    for ch in range(channels):
        k, color_c = wavenumbers[ch], np.float64(color[n, ch])
        slot = _chirp_slot(ch, chirp)
        k_chirp = k * np.float64(chirp[n, slot])
        if way == TABULATED:
            t_moments = moments[0, ch], moments[1, ch], moments[2, ch], moments[3, ch], moments[4, ch], moments[5, ch]
            u_moments = moments[6, ch], moments[7, ch], moments[8, ch], moments[9, ch], moments[10, ch], moments[11, ch]
        else:
            A, B, C = _exponent_coefficients(a, b, c, k_chirp, mahalanobis)
            A, B, C, D, F = _with_form(A, B, C, k, n, form, tilted)
            t_moments, u_moments = _walked_moments(grad_re, grad_im, A, B, C, D, F, tilted,
                                                   cmath.exp(complex(0.0, phase[n, ch])), way, x0, y0, low, high, lefts,
                                                   rights, ch, channels)
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
        if form.shape[0]:  # the form's path k·(P_a dx² + 2P_b dx dy + P_c dy² + L·d), d = p − x, also where it is 0
            q = scale * k
            pa, pb, pc, lx, ly = (np.float64(form[n, 0]), np.float64(form[n, 1]), np.float64(form[n, 2]),
                                  np.float64(form[n, 3]), np.float64(form[n, 4]))
            g_form[n, 0] += q * u20
            g_form[n, 1] += 2.0 * q * u11
            g_form[n, 2] += q * u02
            g_form[n, 3] += q * u10
            g_form[n, 4] += q * u01
            gx -= q * (2.0 * (pa * u10 + pb * u01) + lx * u00)
            gy -= q * (2.0 * (pb * u10 + pc * u01) + ly * u00)
    g_opacity[n] = g_alpha
    g_conic[n, 0], g_conic[n, 1], g_conic[n, 2] = ga, gb, gc
    g_position[n, 0], g_position[n, 1] = gx, gy


@nb.njit(cache=True, nogil=True, fastmath=True, **CALLED_BY_KERNELS_ONLY)
def _gradients_share(t, threads, order, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers,
                     mahalanobis, grad_re, grad_im, g_position, g_conic, g_chirp, g_form, g_color, g_phase, g_opacity):
    """The gradients of primitives order[t], order[t+T], ... (T = threads): one thread's share, with its
    work arrays for `_gradients_loop` (as in `_splat_share`)."""
    height, width = grad_re.shape[0], grad_re.shape[1]
    lefts, rights, spans = np.empty(height), np.empty(height), (np.empty(height, np.float32),
                                                                np.empty(height, np.float32))
    lanes = (np.empty(width, np.float32), np.empty(width, np.float32), np.empty(width, np.float32),
             np.empty(width, np.float32), np.empty(width, np.float32), np.empty(width, np.float32),
             np.empty(width, np.float32), np.empty(width, np.float32), np.empty(width, np.float32),
             np.empty(width, np.float32))
    _gradients_loop(t, threads, order, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers,
                    mahalanobis, grad_re, grad_im, grad_re.reshape(grad_re.size), grad_im.reshape(grad_im.size),
                    g_position, g_conic, g_chirp, g_form, g_color, g_phase, g_opacity, lefts, rights, spans, lanes,
                    _scratch(color.shape[1]), np.empty((12, _vector_channels(color.shape[1]))))


@nb.njit(cache=True, nogil=True, fastmath=True, **WITHOUT_REFERENCE_COUNTS, **CALLED_BY_KERNELS_ONLY)
def _gradients_loop(t, threads, order, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers,
                    mahalanobis, grad_re, grad_im, image_re, image_im, g_position, g_conic, g_chirp, g_form, g_color,
                    g_phase, g_opacity, lefts, rights, spans, lanes, scratch, moments):
    """`_gradients_share`'s loop, with each primitive's work inlined and the gradient images also as
    flat arrays (as in `_splat_loop`)."""
    for i in range(t, position.shape[0], threads):
        _gradients_of_one(order[i], position, conic, reach, chirp, form, color, phase, opacity, wavenumbers,
                          mahalanobis, grad_re, grad_im, image_re, image_im, g_position, g_conic, g_chirp, g_form,
                          g_color, g_phase, g_opacity, lefts, rights, spans, lanes, scratch, moments)


@nb.njit(parallel=True, cache=True, fastmath=True)
def splat_backward(order, position, conic, reach, chirp, form, color, phase, opacity, wavenumbers, mahalanobis,
                   grad, g_position, g_conic, g_chirp, g_form, g_color, g_phase, g_opacity, threads):
    """Gradients (float64, each row written by its own primitive only) from grad [2, H, (W + STRIP)·C]
    (a float32 lane image, zero in the padding columns).

    Thread t of `threads` takes primitives order[t], order[t+T], ..., as in the forward pass.

    The gradient arrays start at zero: channels sharing a curvature add into the same `g_chirp` slot, and every
    channel into `g_form`'s row (the phase terms' form, [N, 5] or [0, 5] for none, as `form`).

    With z = exp(E) (phase φ included) and g the incoming gradient, a pixel contributes
    t = Re(ḡz) = dL/dRe(E)/(αc) and u = −Im(ḡz) = dL/dIm(E)/(αc). Every parameter's gradient is a
    sum of t or u times 1, dx, dy, dx², dx·dy or dy², so each pixel only adds to those moments,
    which become gradients once per primitive and channel. (The −50 floor's zero gradient is
    not reproduced: it concerns values below e⁻⁵⁰.)
    """
    for t in nb.prange(threads):
        _gradients_share(np.int64(t), threads, order, position, conic, reach, chirp, form, color, phase, opacity,
                         wavenumbers, mahalanobis, grad[0], grad[1], g_position, g_conic, g_chirp, g_form, g_color,
                         g_phase, g_opacity)
