"""What a command needs of the machine, checked before anything is written: a CUDA device that PyTorch sees, and
memory for the estimated peak of its fit or render (`fitting.estimated_peak_bytes`), one at a time or several at
once."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ..config import FitConfig
from ..errors import UsageError

if TYPE_CHECKING:
    from .executors import ExecutorOptions

DEFAULT_GUARD_BAND_PX = FitConfig().optics.guard_band_px


def available_memory_bytes() -> int | None:
    """MemAvailable from /proc/meminfo, or None where there is no such file."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def device_memory_bytes(device: str) -> int | None:
    """Memory a fit on `device` may take: the GPU's free memory (CUDA), else the host's MemAvailable."""
    import torch
    if torch.device(device).type == "cuda":
        return torch.cuda.mem_get_info(torch.device(device))[0]
    return available_memory_bytes()


def check_device(device: str) -> None:
    """A CUDA device needs a GPU that PyTorch sees; checked before anything is written."""
    import torch
    if torch.device(device).type == "cuda" and not torch.cuda.is_available():
        raise UsageError(f"device {device}: no CUDA GPU is visible to PyTorch; use --device cpu")


def check_memory(config: FitConfig, device: str, work: str = "fit", remedy: str = "reduce --size or --planes",
                 size: tuple[int, int] | None = None, planes: int | None = None) -> None:
    """Refuse a fit of `config`, or another `work` on its model at `size` (W, H) px and `planes` planes (default:
    the config's), whose estimated peak on `device` (`estimated_peak_bytes`) exceeds the memory there
    (`device_memory_bytes`; unknown: accepted), with the `remedy`."""
    import torch
    from ..fitting import estimated_peak_bytes
    needed, available = estimated_peak_bytes(config, device, size, planes), device_memory_bytes(device)
    if available is not None and needed > available:
        where = "free on the GPU" if torch.device(device).type == "cuda" else "available"
        width, height = size or (config.targets.width, config.targets.height)
        count = config.targets.num_planes if planes is None else planes
        guard = (f" and a {config.optics.guard_band_px} px guard band"
                 if config.optics.guard_band_px != DEFAULT_GUARD_BAND_PX else "")
        raise UsageError(f"a {width}×{height} {work} with {count} plane(s){guard} needs about "
                         f"{needed / 2**30:.1f} GiB but {available / 2**30:.1f} GiB are {where}; {remedy}")


def check_fits_at_once(peak: int, executor: ExecutorOptions, device: str) -> None:
    """Refuse to run as many fits at once on this machine as `executor` would (`fits_at_once`), each of `peak`
    bytes, where their memory exceeds what `device` offers (unknown: accepted)."""
    count = executor.fits_at_once(device)
    needed, available = count * peak, device_memory_bytes(device) if count else None
    if available is None or needed <= available:
        return
    given = (f"--jobs {executor.jobs}" if executor.kind == "local" else
             f"{count} fits at once on this machine's Ray instance")
    remedy = ("lower --jobs or --size" if executor.kind == "local" else
              "raise --gpus-per-fit or --threads, or lower --size")
    raise UsageError(f"{given} needs about {needed / 2**30:.1f} GiB but {available / 2**30:.1f} GiB are available "
                     f"on {device}; {remedy}")
