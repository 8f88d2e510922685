"""Inputs and defocus-aware multi-plane targets (method.md §5, Kavaklı et al. 2023)."""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageOps, UnidentifiedImageError
from PIL.Image import DecompressionBombError, DecompressionBombWarning
from torch import Tensor

from .config import FitConfig
from .errors import InputError
from .files import input_file

BLUR_KERNEL_PX = 21
BLUR_SAMPLE_EXTENT = 10.5
IDENTITY_SIGMA = 1e-5


@dataclass
class Scene:
    """What a fit reproduces: the image, its plane masks and one target per plane."""

    image: Tensor  # [C, H, W] in [0, 1]
    masks: Tensor  # [M, H, W] in {0, 1}
    targets: Tensor  # [M, C, H, W]

    def to(self, device: torch.device | str) -> "Scene":
        """The same scene with its tensors on `device`."""
        return Scene(*(t.to(device) for t in (self.image, self.masks, self.targets)))


log = logging.getLogger("cvqpg")

ALPHA_MODES = ("RGBA", "LA", "PA", "RGBa", "La")
HIGH_DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I;16N", "I", "F")
ASPECT_TOLERANCE = 0.01
EXIF_ORIENTATION = 0x0112  # the EXIF tag of how a camera's picture is turned; 1 is upright


def to_tensor(picture: Image.Image) -> Tensor:
    """8-bit PIL image → float32 [C, H, W] in [0, 1]."""
    array = np.asarray(picture, dtype=np.float32) / 255.0
    if array.ndim == 2:
        array = array[:, :, None]
    return torch.from_numpy(np.ascontiguousarray(array.transpose(2, 0, 1)))


def prepare_image(picture: Image.Image, width: int, height: int, color: str) -> Tensor:
    """RGB (or L for grayscale), Lanczos-resized to W×H px, /255 → [C, H, W]. Alpha is dropped. A 16-bit or
    float picture (one channel) is scaled from its range as `unit_values` says, with a note, and resized in float."""
    if picture.mode in ALPHA_MODES or "transparency" in picture.info:
        log.warning("the image has an alpha channel; it is ignored (only colour is fitted)")
    note_upscaled(picture, "image", width, height)
    if picture.mode in HIGH_DEPTH_MODES:
        gray = unit_values(picture, "image", width, height)[None]
        return gray.expand(3 if color == "rgb" else 1, -1, -1).contiguous()
    mode = "RGB" if color == "rgb" else "L"
    return to_tensor(picture.convert(mode).resize((width, height), Image.LANCZOS))


def prepare_depth(picture: Image.Image, width: int, height: int) -> Tensor:
    """Depth map → [H, W] in [0, 1], 0 near, Lanczos-resized to W×H px.

    8-bit maps follow method.md §5 (L, /255); 16-bit and float maps are scaled as `unit_values` says. An alpha
    channel is dropped, with a note.
    """
    if picture.mode in ALPHA_MODES or "transparency" in picture.info:
        log.warning("the depth map has an alpha channel; it is ignored (only its gray levels are depths)")
    if picture.mode not in HIGH_DEPTH_MODES:
        return to_tensor(picture.convert("L").resize((width, height), Image.LANCZOS))[0]
    return unit_values(picture, "depth map", width, height)


def note_upscaled(picture: Image.Image, role: str, width: int, height: int) -> None:
    """A note where `picture` is smaller than the fit's W×H px on either side: it is upscaled, and holds no detail
    finer than its own pixels (a 1×1 image fits a constant)."""
    if picture.size[0] < width or picture.size[1] < height:
        log.warning(f"the {role} is {picture.size[0]}×{picture.size[1]} px, upscaled to {width}×{height} px: it "
                    "holds no detail finer than its own pixels")


def unit_values(picture: Image.Image, role: str, width: int, height: int) -> Tensor:
    """A one-channel 16-bit or float picture → [H, W] in [0, 1], Lanczos-resized to W×H px in float so that no
    precision is lost, with a note of the scaling (but for a 16-bit depth map): 16-bit values (0..65535) divided
    by 65535; float values in [0, 1] as they are; others normalised from their own range. `InputError` where a
    value is not finite."""
    values = np.asarray(picture, dtype=np.float64)
    name = f"{role} {picture.filename}" if getattr(picture, "filename", "") else f"the {role}"
    unknown = int(np.count_nonzero(~np.isfinite(values)))
    if unknown:
        # a NaN would spread through the normalisation and the resize to every target
        raise InputError(f"{name} has {unknown} of {values.size} pixels that are not finite (NaN or ±inf); give "
                         "every pixel a value and save it again")
    low, high = float(values.min()), float(values.max())
    if picture.mode.startswith("I;16") or (picture.mode == "I" and 0 <= low and high <= 65535):
        if role != "depth map":  # as depth maps always were: `--depth auto` saves one, read by every command
            log.warning(f"{name} has 16-bit values ({low:g}..{high:g}); scaled from 0..65535 to 0..1")
        values = values / 65535.0
    elif low < 0 or high > 1:
        log.warning(f"{name} has values spanning {low:g}..{high:g}; normalised to 0..1")
        values = (values - low) / max(high - low, 1e-12)
    else:
        log.warning(f"{name} has float values ({low:g}..{high:g}); used as they are, in 0..1")
    resized = Image.fromarray(values.astype(np.float32), "F").resize((width, height), Image.LANCZOS)
    return torch.from_numpy(np.clip(np.asarray(resized, dtype=np.float32), 0.0, 1.0).copy())


def upright(picture: Image.Image, role: str, path: Path) -> Image.Image:
    """`picture` turned as its EXIF orientation says a viewer shows it (a camera's portrait photo), with a note;
    as it is where it has none."""
    orientation = picture.getexif().get(EXIF_ORIENTATION, 1)
    if orientation == 1 or not isinstance(orientation, int) or not 1 <= orientation <= 8:
        return picture
    turned = ImageOps.exif_transpose(picture)
    turned.filename = picture.filename  # messages name the file
    log.warning(f"{role} {path} is stored turned (EXIF orientation {orientation}); it is used as it is shown, "
                f"{turned.size[0]}×{turned.size[1]} px")
    return turned


def check_file(path: str | Path, role: str = "image") -> Path:
    """The path of an existing image file, or an `InputError` naming it (`files.input_file`)."""
    return input_file(path, role, "an image file")


def load_picture(path: str | Path, role: str = "image", remedy: str = "re-export the file") -> Image.Image:
    """Open and decode an image file fully; any problem becomes an `InputError` naming the file, with
    `remedy` for a corrupt one."""
    path = check_file(path, role)
    try:
        # Pillow only warns up to twice its pixel limit; decoding such a file can take all the memory
        with warnings.catch_warnings():
            warnings.simplefilter("error", DecompressionBombWarning)
            with Image.open(path) as picture:
                picture.load()
                return upright(picture, role, path)
    except (DecompressionBombError, DecompressionBombWarning) as error:
        size = str(error).partition(", could be")[0]  # Pillow's "Image size (N pixels) exceeds limit of L pixels"
        raise InputError(f"{role} {path} is too large to decode safely ({size}); resize it first to a few "
                         "thousand px per side (the fit resizes it to its own size in any case)") from None
    except PermissionError:
        raise InputError(f"{role} {path} cannot be read (permission denied)") from None
    except UnidentifiedImageError:
        raise InputError(f"{role} {path} is not an image file Pillow can read; give a PNG, JPEG, TIFF, ...") \
            from None
    except (OSError, SyntaxError, ValueError) as error:
        raise InputError(f"{role} {path} is corrupt or truncated ({error}); {remedy}") from None


def check_depth_geometry(image: Image.Image, depth: Image.Image, resize_depth: bool) -> None:
    """A depth map of another size is resized (with a note); of another aspect ratio, refused unless
    `resize_depth` (then stretched, with a note)."""
    if depth.size == image.size:
        return
    if other_aspect(image.size, depth.size) and not resize_depth:
        raise InputError(f"depth map is {depth.size[0]}×{depth.size[1]} but the image is "
                         f"{image.size[0]}×{image.size[1]}: another aspect ratio, so the depth would be "
                         "distorted; set `resize_depth` to stretch it anyway")
    log.warning(depth_geometry_note(image.size, depth.size))


def other_aspect(image_size: tuple[int, int], depth_size: tuple[int, int]) -> bool:
    """Whether a depth map of `depth_size` (W, H px) has another aspect ratio than an image of `image_size`."""
    image_aspect, depth_aspect = image_size[0] / image_size[1], depth_size[0] / depth_size[1]
    return abs(image_aspect - depth_aspect) > ASPECT_TOLERANCE * image_aspect


def depth_geometry_note(image_size: tuple[int, int], depth_size: tuple[int, int]) -> str:
    """What resizing a depth map of `depth_size` to an image of `image_size` (W, H px) does to it: resized, or,
    of another aspect ratio, stretched."""
    what = "stretched to the image (another aspect ratio)" if other_aspect(image_size, depth_size) else \
        "resized to match"
    return (f"depth map is {depth_size[0]}×{depth_size[1]}, the image {image_size[0]}×{image_size[1]}; the depth "
            f"map is {what}")


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
    planes = config.targets.num_planes
    if depth is None and planes > 1:
        raise InputError(f"{planes} planes need a depth map (`depth`), or set `num_planes` to 1")
    if depth is not None and planes > 1 and float(depth.max() - depth.min()) < 1e-6:
        raise InputError(f"the depth map is constant ({float(depth.min()):.3g}), so it cannot separate "
                         f"{planes} planes; set `num_planes` to 1")
    masks = plane_masks(depth, planes, config.targets.depth_exponent, tuple(image.shape[1:]))
    empty = [m for m in range(planes) if not masks[m].any()]
    if empty:
        raise InputError(f"the depth map puts no pixel on plane(s) {', '.join(map(str, empty))} of {planes}: "
                         f"it separates only {planes - len(empty)}; lower `num_planes`")
    targets = defocus_targets(image, masks, config.targets.defocus_sigma_px)
    return Scene(image=image, masks=masks, targets=targets)


def check_tensor(values: Tensor, name: str, shape: tuple[int, ...]) -> None:
    """An image or depth given as a tensor must already have the fit's shape and finite values in [0, 1]."""
    if tuple(values.shape) != shape:
        raise InputError(f"`{name}` tensor has shape {tuple(values.shape)}, the configuration needs {shape} "
                         "(channels, height, width as `color`, `height` and `width` say); resize it, or give a "
                         "file or PIL image, which are resized")
    if not bool(torch.isfinite(values).all()) or float(values.min()) < 0 or float(values.max()) > 1:
        raise InputError(f"`{name}` tensor must hold finite values in [0, 1]")


def _as_picture(source: str | Path | Image.Image, role: str) -> Image.Image:
    return source if isinstance(source, Image.Image) else load_picture(source, role)


def load_scene(image: str | Path | Image.Image | Tensor, depth: str | Path | Image.Image | Tensor | None,
               config: FitConfig, resize_depth: bool = False) -> Scene:
    """Scene from files, PIL images or tensors ([C, H, W] / [H, W] in [0, 1], already W×H px).

    A depth map of another aspect ratio than the image is refused unless `resize_depth`.
    """
    picture = None if isinstance(image, Tensor) else _as_picture(image, "image")
    depth_picture = None if depth is None or isinstance(depth, Tensor) else _as_picture(depth, "depth map")
    if picture is not None and depth_picture is not None:
        check_depth_geometry(picture, depth_picture, resize_depth)
    if picture is not None:
        image = prepare_image(picture, config.targets.width, config.targets.height, config.targets.color)
    else:
        check_tensor(image, "image", (config.channels, config.targets.height, config.targets.width))
    if depth_picture is not None:
        depth = prepare_depth(depth_picture, config.targets.width, config.targets.height)
    elif depth is not None:
        check_tensor(depth, "depth", (config.targets.height, config.targets.width))
    return build_scene(image.float(), None if depth is None else depth.float(), config)
