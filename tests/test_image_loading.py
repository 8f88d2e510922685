"""Images and depth maps read as a viewer shows them: 16-bit and float pictures scaled from their range, camera
pictures turned by their EXIF orientation, each with a note."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from PIL import Image

from cvqpg.errors import InputError
from cvqpg.targets import load_picture, prepare_depth, prepare_image

RAMP = np.tile(np.linspace(0.0, 1.0, 32), (24, 1))  # 0 on the left, 1 on the right, 32×24 px


class Collected(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@pytest.fixture
def notes():
    """The notes of the `cvqpg` logger (which the command line may have kept from the root logger)."""
    collected = Collected()
    logger = logging.getLogger("cvqpg")
    logger.addHandler(collected)
    yield collected.messages
    logger.removeHandler(collected)


def test_a_16_bit_image_is_scaled_from_its_range_not_saturated(tmp_path, notes):
    path = tmp_path / "ramp16.png"
    Image.fromarray((RAMP * 65535).round().astype(np.uint16)).save(path)
    picture = load_picture(path)
    assert picture.mode.startswith("I")
    image = prepare_image(picture, 32, 24, "rgb")
    assert image.shape == (3, 24, 32)
    assert torch.allclose(image[0], torch.from_numpy(RAMP).float(), atol=0.02)
    assert torch.equal(image[0], image[2])
    assert any("16-bit" in note and "65535" in note for note in notes)


@pytest.mark.parametrize("low, high", [(0.0, 1.0), (-3.0, 250.0)])
def test_a_float_tiff_is_read_from_its_range(tmp_path, notes, low, high):
    path = tmp_path / "ramp.tiff"
    Image.fromarray((low + RAMP * (high - low)).astype(np.float32), "F").save(path)
    image = prepare_image(load_picture(path), 32, 24, "gray")
    assert torch.allclose(image[0], torch.from_numpy(RAMP).float(), atol=0.02)
    assert any("ramp.tiff" in note and f"{low:g}" in note for note in notes)


def test_a_float_image_with_nan_is_refused_in_one_line(tmp_path):
    values = RAMP.astype(np.float32)
    values[3, 4] = np.nan
    Image.fromarray(values, "F").save(tmp_path / "holes.tiff")
    with pytest.raises(InputError, match="image .*holes.tiff has 1 of 768 pixels that are not finite"):
        prepare_image(load_picture(tmp_path / "holes.tiff"), 32, 24, "rgb")


def test_a_16_bit_depth_map_is_scaled_as_always_and_a_float_one_with_a_note(tmp_path, notes):
    Image.fromarray((RAMP * 65535).round().astype(np.uint16)).save(tmp_path / "depth16.png")
    depth = prepare_depth(load_picture(tmp_path / "depth16.png", "depth map"), 32, 24)
    assert torch.allclose(depth, torch.from_numpy(RAMP).float(), atol=0.02)
    assert notes == []  # `--depth auto` saves a 16-bit depth.png in the run: no note on every command
    Image.fromarray((2 + RAMP * 5).astype(np.float32), "F").save(tmp_path / "metres.tiff")
    depth = prepare_depth(load_picture(tmp_path / "metres.tiff", "depth map"), 32, 24)
    assert torch.allclose(depth, torch.from_numpy(RAMP).float(), atol=0.02)
    assert any(note.startswith("depth map") and "normalised" in note for note in notes)


@pytest.mark.parametrize("role", ["image", "depth map"])
def test_an_exif_turned_picture_is_used_as_it_is_shown(tmp_path, notes, role):
    stored = np.zeros((24, 32, 3), np.uint8)
    stored[:, :16] = 255  # white left half as stored; orientation 6: shown turned 90° clockwise, white on top
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(stored).save(tmp_path / "camera.jpg", exif=exif, quality=95)
    picture = load_picture(tmp_path / "camera.jpg", role)
    assert picture.size == (24, 32)
    shown = np.asarray(picture.convert("L"), np.float64)
    assert shown[:16].mean() > 200 and shown[16:].mean() < 50
    assert any(note.startswith(role) and "EXIF orientation 6" in note for note in notes)


def test_an_upright_8_bit_picture_is_read_as_before_without_a_note(tmp_path, notes):
    pixels = (np.random.default_rng(1).random((24, 32, 3)) * 255).astype(np.uint8)
    Image.fromarray(pixels).save(tmp_path / "plain.png")
    image = prepare_image(load_picture(tmp_path / "plain.png"), 32, 24, "rgb")
    assert torch.equal(image, torch.from_numpy(pixels.transpose(2, 0, 1).astype(np.float32) / 255.0))
    assert notes == []
