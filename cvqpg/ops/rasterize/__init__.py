"""The rasterizer: `rasterize` and its backends."""

from .reference import BACKENDS, cpu_array, rasterize, resolve_backend, wavenumbers_for

__all__ = ["BACKENDS", "cpu_array", "rasterize", "resolve_backend", "wavenumbers_for"]
