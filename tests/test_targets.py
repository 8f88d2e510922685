"""Defocus-aware multi-plane targets (method.md §5) against hand computation, and the inputs they are built from."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from PIL import Image

from cvqpg.config import FitConfig
from cvqpg.errors import InputError
from cvqpg.targets import build_scene, defocus_targets, gaussian_kernel, load_picture, load_scene, plane_masks


# --------------------------------------------------------------------------- hand references


def hand_kernel(sigma: float) -> np.ndarray:
    sigma = sigma if sigma > 0 else 1e-5
    samples = np.linspace(-10.5, 10.5, 21)
    kernel = np.empty((21, 21))
    for i, y in enumerate(samples):
        for j, x in enumerate(samples):
            kernel[i, j] = math.exp(-(x * x + y * y) / (2 * sigma * sigma))
    return kernel / kernel.sum()


def hand_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """Same-size zero-padded convolution of [C, H, W] with the 21×21 kernel, explicit loops."""
    kernel = hand_kernel(sigma)
    channels, height, width = image.shape
    out = np.zeros_like(image, dtype=np.float64)
    for c in range(channels):
        for y in range(height):
            for x in range(width):
                total = 0.0
                for i in range(21):
                    yy = y + i - 10
                    if not 0 <= yy < height:
                        continue
                    for j in range(21):
                        xx = x + j - 10
                        if 0 <= xx < width:
                            total += kernel[i, j] * image[c, yy, xx]
                out[c, y, x] = total
    return out


def hand_masks(depth: np.ndarray, planes: int, exponent: float = 1.0) -> np.ndarray:
    masks = np.zeros((planes,) + depth.shape)
    for y in range(depth.shape[0]):
        for x in range(depth.shape[1]):
            index = int(np.round(depth[y, x] ** exponent * (planes - 1)))  # numpy rounds half to even too
            masks[index, y, x] = 1
    return masks


def hand_targets(image: np.ndarray, masks: np.ndarray, sigma: float = 8.0) -> np.ndarray:
    planes = masks.shape[0]
    blurred = {gap: hand_blur(image, sigma * gap) for gap in range(planes)}
    return np.stack([sum(blurred[abs(m - j)] * masks[j][None] for j in range(planes)) for m in range(planes)])


def small_image(channels: int, height: int, width: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.random((channels, height, width)).astype(np.float32)


# --------------------------------------------------------------------------- targets


def test_kernel_samples_linspace_and_normalises():
    for sigma in (8.0, 16.0, 0.0):
        np.testing.assert_allclose(gaussian_kernel(sigma).numpy(), hand_kernel(sigma), rtol=0, atol=1e-7)
    identity = gaussian_kernel(0.0).numpy()
    assert identity[10, 10] == pytest.approx(1.0) and identity.sum() == pytest.approx(1.0)


def test_plane_masks_round_half_to_even():
    depth = torch.tensor([[0.0, 0.25, 0.5, 0.5000001], [0.75, 1.0, 0.49, 0.51]], dtype=torch.float32)
    masks = plane_masks(depth, 2)
    assert masks.shape == (2, 2, 4)
    expected_index = torch.tensor([[0, 0, 0, 1], [1, 1, 0, 1]])  # round(0.5) = 0 (half to even)
    assert torch.equal(masks[1].long(), expected_index)
    assert torch.equal(masks.sum(0), torch.ones(2, 4))
    # three planes: depth·2 → 0.25·2 = 0.5 → 0; 0.75·2 = 1.5 → 2 (half to even)
    masks3 = plane_masks(torch.tensor([[0.25, 0.75, 0.5, 1.0, 0.2]]), 3)
    assert torch.equal(masks3.argmax(0), torch.tensor([[0, 2, 1, 2, 0]]))
    # exponent ρ: 0.5^2 · 1 = 0.25 → 0 ; 0.8^2 = 0.64 → 1
    masks_rho = plane_masks(torch.tensor([[0.5, 0.8]]), 2, exponent=2.0)
    assert torch.equal(masks_rho.argmax(0), torch.tensor([[0, 1]]))


def test_single_plane_without_depth_all_plane_zero():
    masks = plane_masks(None, 1, shape=(3, 5))
    assert masks.shape == (1, 3, 5) and torch.all(masks == 1)


def test_two_plane_targets_match_hand_computation():
    image = small_image(2, 16, 17, seed=0)
    rng = np.random.default_rng(1)
    depth = rng.random((16, 17)).astype(np.float32)
    depth[0, :3] = 0.5  # exactly half: plane 0
    depth[4, 4] = 1.0
    masks = hand_masks(depth, 2)
    assert masks[0, 0, :3].tolist() == [1, 1, 1]
    expected = hand_targets(image.astype(np.float64), masks)
    ours = defocus_targets(torch.from_numpy(image), torch.from_numpy(masks).float())
    assert ours.shape == (2, 2, 16, 17)
    np.testing.assert_allclose(ours.numpy(), expected, rtol=0, atol=1e-6)
    # plane m is sharp where Mask_m is set
    sharp = masks[0].astype(bool)
    np.testing.assert_allclose(ours[0].numpy()[:, sharp], image[:, sharp], atol=1e-6)

    config = FitConfig.create(width=17, height=16, color="gray", num_planes=2)
    scene = build_scene(torch.from_numpy(image), torch.from_numpy(depth), config)
    np.testing.assert_array_equal(scene.masks.numpy(), masks)
    np.testing.assert_allclose(scene.targets.numpy(), expected, rtol=0, atol=1e-6)
    assert torch.equal(scene.image, torch.from_numpy(image))


def test_three_plane_targets_match_hand_computation():
    image = small_image(1, 16, 18, seed=2)
    depth = np.random.default_rng(3).random((16, 18)).astype(np.float32)
    depth[2, 2] = 0.25  # 0.5 → plane 0
    depth[3, 3] = 0.75  # 1.5 → plane 2
    masks = hand_masks(depth, 3)
    assert masks[0, 2, 2] == 1 and masks[2, 3, 3] == 1
    expected = hand_targets(image.astype(np.float64), masks)  # σ = 0, 8, 16
    config = FitConfig.create(width=18, height=16, color="gray", num_planes=3)
    scene = build_scene(torch.from_numpy(image), torch.from_numpy(depth), config)
    np.testing.assert_array_equal(scene.masks.numpy(), masks)
    np.testing.assert_allclose(scene.targets.numpy(), expected, rtol=0, atol=1e-6)


def test_build_scene_needs_depth_for_several_planes():
    image = torch.rand(1, 16, 17)
    with pytest.raises(ValueError):
        build_scene(image, None, FitConfig.create(width=17, height=16, color="gray", num_planes=2))
    scene = build_scene(image, None, FitConfig.create(width=17, height=16, color="gray", num_planes=1))
    assert torch.allclose(scene.targets[0], image, atol=1e-7)


# --------------------------------------------------------------------------- inputs checked where they enter


@pytest.mark.parametrize("size", [(40, 30), (64, 48)])  # over Pillow's limit (a warning), over twice it (an error)
def test_an_image_over_pillows_pixel_limit_is_refused_with_its_size(tmp_path, monkeypatch, size):
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)
    path = tmp_path / "huge.png"
    Image.new("RGB", size).save(path)
    with pytest.raises(InputError, match="resize it first") as refused:
        load_picture(path)
    message = str(refused.value)
    assert str(path) in message and f"{size[0] * size[1]} pixels" in message and "\n" not in message


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_float_depth_map_with_pixels_that_are_not_finite_is_refused(tmp_path, bad):
    depth = np.tile(np.linspace(0.0, 1.0, 24, dtype=np.float32), (16, 1))
    depth[3, 4:7] = bad
    path = tmp_path / "depth.tiff"
    Image.fromarray(depth, "F").save(path)
    config = FitConfig.create(width=24, height=16, color="gray", num_planes=2)
    with pytest.raises(InputError, match="has 3 of 384 pixels that are not finite") as refused:
        load_scene(torch.rand(1, 16, 24), path, config)
    assert str(path) in str(refused.value)


@pytest.mark.parametrize(("image_shape", "depth_shape", "name"), [((3, 24, 32), (24, 32), None),
                                                                  ((1, 24, 32), (24, 32), "image"),
                                                                  ((3, 32, 24), (24, 32), "image"),
                                                                  ((3, 24, 32), (32, 24), "depth")])
def test_load_scene_checks_tensors_against_the_configuration(image_shape, depth_shape, name):
    config = FitConfig.create(width=32, height=24, color="rgb", num_planes=2)
    depth = torch.linspace(0, 1, math.prod(depth_shape)).reshape(depth_shape)
    if name is None:
        assert load_scene(torch.rand(image_shape), depth, config).targets.shape == (2, 3, 24, 32)
        return
    with pytest.raises(InputError, match=f"`{name}` tensor has shape"):
        load_scene(torch.rand(image_shape), depth, config)
