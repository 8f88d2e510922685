"""Built-in scenes generated in code, deterministic at any size: `demo` and `star`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from PIL import Image

from .config import FitConfig
from .defaults import SCENE_NAMES
from .errors import InputError
from .targets import Scene, load_scene

SUPERSAMPLING = 2


@dataclass(frozen=True)
class BuiltinScene:
    """An 8-bit image and an optional 8-bit depth map (0 = near), as files would give them."""

    image: Image.Image
    depth: Image.Image | None


@dataclass(frozen=True)
class SceneRecipe:
    """How to generate a built-in scene, and the colour mode and plane count it is meant for."""

    generate: Callable[[int, int], BuiltinScene]
    color: str
    planes: int


def _coordinates(width: int, height: int, supersampling: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates normalised by the height, origin at the image centre."""
    step = 1.0 / supersampling
    offsets = (np.arange(supersampling) + 0.5) * step - 0.5
    xs = (np.arange(width)[:, None] + offsets[None, :]).reshape(-1)
    ys = (np.arange(height)[:, None] + offsets[None, :]).reshape(-1)
    x, y = np.meshgrid((xs - (width - 1) / 2) / height, (ys - (height - 1) / 2) / height)
    return x.astype(np.float32), y.astype(np.float32)


def _downsample(values: np.ndarray, supersampling: int) -> np.ndarray:
    h, w = values.shape[0] // supersampling, values.shape[1] // supersampling
    return values.reshape(h, supersampling, w, supersampling, *values.shape[2:]).mean(axis=(1, 3))


def _to_8bit(values: np.ndarray) -> np.ndarray:
    return np.clip(np.round(values * 255), 0, 255).astype(np.uint8)


def demo_scene(width: int, height: int) -> BuiltinScene:
    """A far tiled wall, a mid-depth striped card and a near ringed disc, with their exact depth."""
    x, y = _coordinates(width, height, SUPERSAMPLING)
    tiles = (np.floor(x * 8) + np.floor(y * 8)) % 2
    hue = 0.5 + 0.5 * np.stack([np.cos(2 * math.pi * (x + 0.00)), np.cos(2 * math.pi * (y + 0.33)),
                                np.cos(2 * math.pi * (x + y + 0.66))], axis=-1)
    image = (0.25 + 0.5 * tiles)[..., None] * hue
    depth = np.ones_like(x)

    card = (np.abs(x - 0.35) < 0.22) & (np.abs(y - 0.12) < 0.3)
    stripes = 0.5 + 0.5 * np.sign(np.sin(2 * math.pi * 12 * x))
    image[card] = (np.array([0.95, 0.85, 0.2]) * (0.3 + 0.7 * stripes[card, None]))
    depth[card] = 0.5

    radius = np.hypot(x + 0.3, y + 0.02)
    disc = radius < 0.3
    rings = 0.5 + 0.5 * np.cos(2 * math.pi * 10 * radius)
    image[disc] = np.stack([0.9 * rings, 0.2 + 0.3 * (1 - rings), 0.9 * (1 - rings)], axis=-1)[disc]
    depth[disc] = 0.0

    rgb = _to_8bit(_downsample(image, SUPERSAMPLING))
    depth_map = _to_8bit(np.round(_downsample(depth, SUPERSAMPLING) * 2) / 2)
    return BuiltinScene(Image.fromarray(rgb, "RGB"), Image.fromarray(depth_map, "L"))


def siemens_star(width: int, height: int, spokes: int = 36) -> BuiltinScene:
    """A grayscale Siemens star: `spokes` black/white sectors whose frequency rises to the centre."""
    x, y = _coordinates(width, height, SUPERSAMPLING)
    angle = np.arctan2(y, x)
    sectors = 0.5 + 0.5 * np.sign(np.sin(spokes / 2 * angle))
    inside = np.hypot(x, y) < 0.45
    values = np.where(inside, sectors, 0.5)
    gray = _to_8bit(_downsample(values, SUPERSAMPLING))
    return BuiltinScene(Image.fromarray(gray, "L"), None)


SCENES = dict(zip(SCENE_NAMES, (SceneRecipe(demo_scene, "rgb", 2), SceneRecipe(siemens_star, "gray", 1)), strict=True))


def builtin_pictures(name: str, width: int, height: int) -> BuiltinScene:
    """The named built-in scene's image and depth map at W×H px, as files would give them."""
    if name not in SCENES:
        raise InputError(f"unknown scene {name!r}; built-in scenes are {', '.join(sorted(SCENES))}")
    return SCENES[name].generate(width, height)


def builtin_scene(name: str, config: FitConfig) -> Scene:
    """The named built-in scene with its targets for `config` (size, colour, planes): what `fit_scene` takes."""
    pictures = builtin_pictures(name, config.targets.width, config.targets.height)
    return load_scene(pictures.image, pictures.depth, config)
