"""The pruned propagation's CPU kernels (Numba): copies, transposes and transfer products (method.md §3).

`propagate_content` calls them with `fused` on (the `numba` backend), and PyTorch's operations
otherwise. The transpose moves the propagation's arrays between row and column layout (in less time
than PyTorch's strided copies: docs/performance.md, "Measured choices"), and the products apply
transfer functions kept as half of their rows.
"""

from __future__ import annotations

import numba as nb

# The longest tuple of arrays that a parallel loop takes (Numba unpacks tuples up to this size); the products
# and sums take their planes' transfer functions as such a tuple.
MAX_FUSED_PLANES = nb.config.PARFOR_MAX_TUPLE_SIZE

@nb.njit(parallel=True, cache=True)
def copy_rows(source, out, conjugate):
    """out = source, or its complex conjugate, for [R, N] arrays either of which may be a view into a
    wider array; threads take whole rows."""
    for r in nb.prange(source.shape[0]):
        row, target = source[r], out[r]
        if conjugate:
            for j in range(row.shape[0]):
                target[j] = row[j].conjugate()
        else:
            for j in range(row.shape[0]):
                target[j] = row[j]


TRANSPOSE_TILE = 16  # a 16×16 tile of complex64 is 2 KiB: source and target tiles stay in L1


@nb.njit(parallel=True, cache=True)
def transpose(source, out):
    """out[j, i] = source[i, j] for a source [R, N] and out [N, R], either of them a view into a wider
    array. Each task takes a band of 16 target rows and moves it tile by tile; the tiles are
    zero-based slices, so no index needs a wrap-around check."""
    rows, columns = source.shape
    for band in nb.prange((columns + TRANSPOSE_TILE - 1) // TRANSPOSE_TILE):
        first = band * TRANSPOSE_TILE
        stop = min(columns, first + TRANSPOSE_TILE)
        for top in range(0, rows, TRANSPOSE_TILE):
            bottom = min(rows, top + TRANSPOSE_TILE)
            tile, target = source[top:bottom, first:stop], out[first:stop, top:bottom]
            for j in range(stop - first):
                target_row = target[j]
                for i in range(bottom - top):
                    target_row[i] = tile[i, j]


@nb.njit(inline="always")
def _mirrored_row(row, length):
    """The row of a first half [length / 2, N] that holds row `row` of a function [length, N] even
    about the middle of its first axis."""
    return min(row, length - 1 - row)


@nb.njit(parallel=True, cache=True, fastmath=True)
def mirrored_products(spectrum, halves, first_row, out):
    """out[p, r] = spectrum[r] · T_p[first_row + r] for every plane p, for transfer functions T_p [2K, N]
    even about the middle of their first axis (T[k] = T[2K − 1 − k]), given as their first halves
    (a tuple of [K, N]). Each spectrum row is read once for all planes."""
    length = 2 * halves[0].shape[0]
    for r in nb.prange(spectrum.shape[0]):
        mirrored, source = _mirrored_row(first_row + r, length), spectrum[r]
        for plane in range(len(halves)):
            transfer, target = halves[plane][mirrored], out[plane, r]
            for j in range(source.shape[0]):
                target[j] = source[j] * transfer[j]


@nb.njit(parallel=True, cache=True, fastmath=True)
def mirrored_sum(spectra, halves, first_row):
    """spectra[0][r] = Σ_p spectra[p][r] · T_p[first_row + r], in place, for transfer functions given as
    in `mirrored_products`; one pass over the planes' rows."""
    length = 2 * halves[0].shape[0]
    for r in nb.prange(spectra[0].shape[0]):
        mirrored = _mirrored_row(first_row + r, length)
        target, transfer = spectra[0][r], halves[0][mirrored]
        for j in range(target.shape[0]):
            target[j] = target[j] * transfer[j]
        for plane in range(1, len(spectra)):
            source, transfer = spectra[plane][r], halves[plane][mirrored]
            for j in range(target.shape[0]):
                target[j] += source[j] * transfer[j]
