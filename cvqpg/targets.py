"""Inputs and defocus-aware multi-plane targets (SPEC §5, Kavaklı et al. 2023)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from .config import FitConfig

BLUR_KERNEL_PX = 21
BLUR_SAMPLE_EXTENT = 10.5
IDENTITY_SIGMA = 1e-5


@dataclass
class Scene:
    """What a fit reproduces: the image, its plane masks and one target per plane."""

    image: Tensor  # [C, H, W] in [0, 1]
    masks: Tensor  # [M, H, W] in {0, 1}
    targets: Tensor  # [M, C, H, W]


def to_tensor(picture: Image.Image) -> Tensor:
    """8-bit PIL image → float32 [C, H, W] in [0, 1]."""
    array = np.asarray(picture, dtype=np.float32) / 255.0
    if array.ndim == 2:
        array = array[:, :, None]
    return torch.from_numpy(np.ascontiguousarray(array.transpose(2, 0, 1)))


def prepare_image(picture: Image.Image, width: int, height: int, color: str) -> Tensor:
    """RGB (or L for grayscale), Lanczos-resized to W×H px, /255 → [C, H, W]."""
    mode = "RGB" if color == "rgb" else "L"
    return to_tensor(picture.convert(mode).resize((width, height), Image.LANCZOS))


def prepare_depth(picture: Image.Image, width: int, height: int) -> Tensor:
    """Depth map in L, Lanczos-resized to W×H px, /255 → [H, W]; 0 is near."""
    return to_tensor(picture.convert("L").resize((width, height), Image.LANCZOS))[0]


def load_picture(path: str | Path) -> Image.Image:
    with Image.open(path) as picture:
        picture.load()
        return picture


def plane_masks(depth: Tensor | None, num_planes: int, exponent: float = 1.0,
                shape: tuple[int, int] | None = None) -> Tensor:
    """One-hot plane membership [M, H, W]: plane `round(depth^ρ · (M−1))` (all plane 0 without depth)."""
    if depth is None:
        if shape is None:
            raise ValueError("plane_masks needs a depth map or a shape")
        index = torch.zeros(shape, dtype=torch.long)
    else:
        index = torch.round(depth**exponent * (num_planes - 1)).long()
    planes = torch.arange(num_planes, device=index.device)[:, None, None]
    return (index[None] == planes).to(torch.float32)


def gaussian_kernel(sigma_px: float, size: int = BLUR_KERNEL_PX) -> Tensor:
    """2D Gaussian [size, size] sampled on linspace(−10.5, 10.5, 21), normalised to sum 1."""
    sigma = sigma_px if sigma_px > 0 else IDENTITY_SIGMA
    samples = torch.linspace(-BLUR_SAMPLE_EXTENT, BLUR_SAMPLE_EXTENT, size, dtype=torch.float64)
    yy, xx = torch.meshgrid(samples, samples, indexing="ij")
    kernel = torch.exp(-(xx**2 + yy**2) / (2 * sigma**2))
    return (kernel / kernel.sum()).to(torch.float32)


def blur(image: Tensor, sigma_px: float) -> Tensor:
    """Same-size, zero-padded Gaussian blur of [C, H, W], channels independent."""
    kernel = gaussian_kernel(sigma_px).to(image.device)
    channels = image.shape[0]
    weight = kernel.expand(channels, 1, *kernel.shape)
    return F.conv2d(image[None], weight, padding="same", groups=channels)[0]


def defocus_targets(image: Tensor, masks: Tensor, sigma_per_plane_px: float = 8.0) -> Tensor:
    """`T_m = Σ_j blur_{σ=8|m−j|}(I) · Mask_j` → [M, C, H, W]."""
    num_planes = masks.shape[0]
    blurred = {gap: blur(image, sigma_per_plane_px * gap) for gap in range(num_planes)}
    return torch.stack([sum(blurred[abs(m - j)] * masks[j] for j in range(num_planes))
                        for m in range(num_planes)])


def build_scene(image: Tensor, depth: Tensor | None, config: FitConfig) -> Scene:
    """Scene from a prepared image [C, H, W] and optional depth [H, W] (needed for M > 1)."""
    if depth is None and config.num_planes > 1:
        raise ValueError(f"{config.num_planes} planes need a depth map; give one, or use a single plane")
    masks = plane_masks(depth, config.num_planes, config.depth_exponent, tuple(image.shape[1:]))
    targets = defocus_targets(image, masks, config.defocus_sigma_px)
    return Scene(image=image, masks=masks, targets=targets)


def _as_picture(source: str | Path | Image.Image) -> Image.Image:
    return source if isinstance(source, Image.Image) else load_picture(source)


def load_scene(image: str | Path | Image.Image | Tensor, depth: str | Path | Image.Image | Tensor | None,
               config: FitConfig) -> Scene:
    """Scene from files, PIL images or tensors ([C, H, W] / [H, W] in [0, 1], already W×H px)."""
    if not isinstance(image, Tensor):
        image = prepare_image(_as_picture(image), config.width, config.height, config.color)
    if depth is not None and not isinstance(depth, Tensor):
        depth = prepare_depth(_as_picture(depth), config.width, config.height)
    return build_scene(image.float(), None if depth is None else depth.float(), config)
