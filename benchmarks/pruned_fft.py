"""Are pruned transforms worth it? The propagation's zero-padded FFT2 against row-pruned ones.

    python benchmarks/pruned_fft.py

A 640×480 grid pads to 768×960 and propagates on 1536×1920. The forward transform's input is zero
outside the middle rows, so its x pass needs only those rows; the inverse's output is cropped to the
480×640 content, so its x pass needs only the content rows. Both are exact. One thread, medians of
7 runs, side by side in one process.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

PADDED_ROWS, PADDED_COLS = 768, 960
CONTENT_ROWS, CONTENT_COLS = 480, 640
REPEATS = 7


def median_ms(work: Callable[[], torch.Tensor]) -> float:
    work()
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return sorted(times)[REPEATS // 2] * 1e3


def main() -> None:
    torch.set_num_threads(1)
    rows, cols = PADDED_ROWS, PADDED_COLS
    field = torch.randn(rows, cols, dtype=torch.complex64, generator=torch.Generator().manual_seed(0))
    doubled = torch.zeros(2 * rows, 2 * cols, dtype=torch.complex64)
    middle_rows = torch.zeros(rows, 2 * cols, dtype=torch.complex64)

    def forward_full() -> torch.Tensor:
        doubled.zero_()
        doubled[rows // 2:rows // 2 + rows, cols // 2:cols // 2 + cols] = field
        return torch.fft.fft2(doubled)

    def forward_pruned() -> torch.Tensor:
        middle_rows.zero_()
        middle_rows[:, cols // 2:cols // 2 + cols] = field
        doubled.zero_()
        doubled[rows // 2:rows // 2 + rows] = torch.fft.fft(middle_rows, dim=-1)
        return torch.fft.fft(doubled, dim=-2)

    spectrum = forward_full()
    top, left = rows // 2 + (rows - CONTENT_ROWS) // 2, cols // 2 + (cols - CONTENT_COLS) // 2

    def inverse_full() -> torch.Tensor:
        return torch.fft.ifft2(spectrum)[top:top + CONTENT_ROWS, left:left + CONTENT_COLS]

    def inverse_pruned() -> torch.Tensor:
        content_rows = torch.fft.ifft(spectrum, dim=-2)[top:top + CONTENT_ROWS]
        return torch.fft.ifft(content_rows, dim=-1)[:, left:left + CONTENT_COLS]

    for name, full, pruned in (("forward", forward_full, forward_pruned), ("inverse", inverse_full, inverse_pruned)):
        expected, got = full(), pruned()
        error = float((got - expected).abs().max() / expected.abs().max())
        full_ms, pruned_ms = median_ms(full), median_ms(pruned)
        print(f"{name}: full {full_ms:6.1f} ms, pruned {pruned_ms:6.1f} ms, ratio {pruned_ms / full_ms:4.2f}, "
              f"max relative difference {error:.1e}")


if __name__ == "__main__":
    main()
