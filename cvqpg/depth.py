"""Depth from the photo (`--depth auto`): Depth Anything V2, the paper's choice, through transformers.

The model predicts relative inverse depth (disparity: larger = nearer) on its own grid. It is
resized to the image and mapped linearly onto this package's convention, 0 = nearest and 1 =
farthest, then stored as a 16-bit map: the plane masks only need the order and spacing of depths,
and a 16-bit `depth.png` in the run folder repeats the fit exactly with `--depth`. transformers (the
`depth` extra) fetches the weights from the Hugging Face Hub on first use and reads them from its
cache afterwards; nothing else is downloaded.
"""

from __future__ import annotations

import socket
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator
from urllib.parse import urlsplit

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from .defaults import DEPTH_MODEL
from .errors import InputError
from .targets import load_picture

DEPTH_LEVELS = 65535  # 16-bit map
HUB_TIMEOUT_SECONDS = 5.0  # how long a download waits for the Hugging Face Hub to answer


class DepthModelError(InputError):
    """The depth model cannot be loaded; the message says what to install or fetch."""


@dataclass(frozen=True)
class DepthModel:
    """A depth-estimation network and the image processor that prepares its input."""

    network: Any  # transformers' AutoModelForDepthEstimation
    processor: Any  # its (slow, PIL/NumPy) image processor: the fast one needs torchvision
    name: str


def hub_cache() -> str:
    """Where transformers keeps downloaded weights (HF_HOME/hub, by default ~/.cache/huggingface/hub)."""
    from huggingface_hub import constants

    return str(constants.HF_HUB_CACHE)


def load_depth_model(name: str = DEPTH_MODEL) -> DepthModel:
    """Depth Anything V2 (or another depth-estimation model of the Hub), from transformers' cache or
    downloaded into it; a `DepthModelError` naming the extra and the cache where that fails."""
    try:
        from transformers import AutoImageProcessor, AutoModelForDepthEstimation
    except ImportError:
        raise DepthModelError("depth estimation needs transformers: pip install 'cvqpg[depth]', or give "
                              "a `depth` map") from None
    missing = DepthModelError(f"depth estimation: the weights of {name} are not in the Hugging Face cache "
                              f"({hub_cache()}) and could not be downloaded; run once online with the depth "
                              "extra (pip install 'cvqpg[depth]'), or give a `depth` map")
    # The cache first, without a word on the network; a download only where the Hub answers, since offline the
    # Hub's client retries for minutes, warning as it goes
    for cached in (True, False):
        if not cached and not hub_reachable():
            raise missing
        try:
            with _hub_quiet():
                processor = AutoImageProcessor.from_pretrained(name, use_fast=False, local_files_only=cached)
                network = AutoModelForDepthEstimation.from_pretrained(name, local_files_only=cached)
        except OSError:
            continue
        return DepthModel(network.eval(), processor, name)
    raise missing


def hub_reachable(timeout: float = HUB_TIMEOUT_SECONDS) -> bool:
    """Whether the Hugging Face Hub (its endpoint, `HF_ENDPOINT`) answers within `timeout` seconds; never where
    the Hub is switched off (`HF_HUB_OFFLINE`)."""
    from huggingface_hub import constants

    if constants.HF_HUB_OFFLINE:
        return False
    address = urlsplit(constants.ENDPOINT)
    try:
        socket.create_connection((address.hostname, address.port or (443 if address.scheme == "https" else 80)),
                                 timeout=timeout).close()
    except (OSError, ValueError, TypeError):
        return False
    return True


@contextmanager
def _hub_quiet() -> Iterator[None]:
    """transformers' and the Hub client's warnings (each retry, each missing file) held back for the block: what
    fails is said once, by the caller."""
    from huggingface_hub.utils import logging as hub_logging
    from transformers.utils import logging as transformers_logging

    levels = transformers_logging.get_verbosity(), hub_logging.get_verbosity()
    transformers_logging.set_verbosity_error()
    hub_logging.set_verbosity_error()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        transformers_logging.set_verbosity(levels[0])
        hub_logging.set_verbosity(levels[1])


def depth_from_disparity(disparity: torch.Tensor) -> torch.Tensor:
    """Relative inverse depth (larger = nearer) → depth in [0, 1] with 0 = nearest (float32, same shape).
    A constant map gives zeros."""
    low, high = disparity.min(), disparity.max()
    if high <= low:
        return torch.zeros_like(disparity, dtype=torch.float32)
    return ((high - disparity) / (high - low)).float()


def estimate_depth(image: str | Path | Image.Image, model: DepthModel | None = None) -> Image.Image:
    """The depth map of an image (file or PIL image) at the image's size, as a 16-bit grayscale image
    (0 = near, 65535 = far), ready for `load_scene` or to save as `depth.png`."""
    picture = load_picture(image) if isinstance(image, (str, Path)) else image
    model = model or load_depth_model()
    inputs = model.processor(images=picture.convert("RGB"), return_tensors="pt")
    with torch.no_grad():
        disparity = model.network(**inputs).predicted_depth  # [1, h, w] on the model's grid
    width, height = picture.size
    resized = F.interpolate(disparity[:, None].float(), size=(height, width), mode="bilinear", align_corners=False)
    depth = depth_from_disparity(resized[0, 0])
    return Image.fromarray(np.round(depth.numpy() * DEPTH_LEVELS).astype(np.uint16))
