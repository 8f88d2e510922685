"""Initialisation from the targets: where the implied SLM field carries energy or at the targets' edges, the
paper's other draws kept, from the targets only in short runs under `auto`, and safe on black or damaged
targets."""

import math

import pytest
import torch

from cvqpg import FitConfig, builtin_scene
from cvqpg.errors import ConfigError
from cvqpg.initialisation import (EDGES_UNIFORM_SHARE, edge_density, implied_slm_field, initial_gaussians,
                                  positions_from_energy)
from cvqpg.ops.propagation.reference import propagate
from cvqpg.primitives import init_gaussians, positions_px
from cvqpg.targets import Scene

CONFIG = FitConfig.create(width=48, height=36, num_gaussians=400, steps=20, guard_band_px=16, color="gray",
                          init="targets")


def test_positions_follow_the_energy():
    energy = torch.zeros(36, 48)
    energy[10:14, 30:34] = 1.0
    position = positions_from_energy(energy, 500, torch.Generator().manual_seed(0))
    assert ((position[:, 0] >= 29.5) & (position[:, 0] < 33.5) & (position[:, 1] >= 9.5)
            & (position[:, 1] < 13.5)).all()


@pytest.mark.parametrize("energy", [torch.zeros(36, 48), torch.full((36, 48), float("nan"))])
def test_black_or_damaged_targets_fall_back_to_every_pixel_alike(energy):
    position = positions_from_energy(energy, 2000, torch.Generator().manual_seed(0))
    assert torch.isfinite(position).all()
    assert position[:, 0].min() < 5 and position[:, 0].max() > 42


def test_a_plane_s_target_propagates_back_to_a_field_that_reproduces_it():
    """One plane: the implied field, propagated forward by the same distance, gives the target amplitude back."""
    config = CONFIG.replace(num_planes=1, width=64, height=64)
    target = torch.zeros(1, 1, 64, 64)
    target[..., 24:40, 24:40] = 1.0
    scene = Scene(target[0], torch.ones(1, 64, 64), target)
    field = implied_slm_field(scene, config)
    back = propagate(field, [config.plane_distances[0]], config.wavelengths, config.optics.pixel_pitch)[0].abs()
    assert torch.allclose(back[0, 28:36, 28:36], torch.ones(8, 8), atol=0.15)
    assert math.isclose(field.abs().square().sum().item(), target.sum().item(), rel_tol=0.2)


def test_edges_draw_most_positions_at_the_targets_edges_and_the_rest_evenly():
    targets = torch.zeros(2, 3, 36, 48)
    targets[..., 24:] = 0.8  # one vertical edge, between columns 23 and 24
    density = edge_density(targets)
    assert math.isclose(density.sum().item(), 1.0, rel_tol=1e-9)
    flat = EDGES_UNIFORM_SHARE / density.numel()
    assert torch.allclose(density[:, 23], torch.full((36,), (1 - EDGES_UNIFORM_SHARE) / 36 + flat, dtype=torch.float64))
    others = torch.cat((density[:, :23], density[:, 24:]), dim=1)
    assert torch.allclose(others, torch.full_like(others, flat))
    position = positions_from_energy(density, 4000, torch.Generator().manual_seed(0))
    at_edge = ((position[:, 0] >= 22.5) & (position[:, 0] < 23.5)).float().mean().item()
    assert abs(at_edge - (1 - EDGES_UNIFORM_SHARE + EDGES_UNIFORM_SHARE / 48)) < 0.03


@pytest.mark.parametrize("targets", [torch.zeros(2, 1, 36, 48), torch.full((2, 1, 36, 48), 0.5),
                                     torch.full((2, 1, 36, 48), float("nan"))])
def test_edges_of_flat_black_or_damaged_targets_are_every_pixel_alike(targets):
    density = edge_density(targets)
    assert torch.allclose(density, torch.full_like(density, 1 / density.numel()))


@pytest.mark.parametrize("init", ["targets", "edges"])
def test_only_positions_move_and_the_paper_s_draws_stay(init):
    config = CONFIG.replace(init=init)
    scene = builtin_scene("demo", config)
    ours, paper = initial_gaussians(config, scene), init_gaussians(400, 1, 48, 36, config.optimisation.seed)
    for name, tensor in paper.tensors().items():
        if name != "position":
            assert torch.equal(ours.tensors()[name], tensor), name
    assert not torch.equal(ours.position, paper.position)
    assert torch.equal(initial_gaussians(config.replace(init="uniform")).position, paper.position)
    assert torch.isfinite(positions_px(ours.position, 48, 36)).all()


@pytest.mark.parametrize("init", ["targets", "edges"])
def test_the_targets_are_needed_to_start_from_them(init):
    with pytest.raises(ConfigError, match=f"`init` {init} .* needs the scene"):
        initial_gaussians(CONFIG.replace(init=init))


def test_positions_draw_from_maps_beyond_multinomial_s_limit():
    """More than 2^24 pixels (an 8K hologram): drawn all the same, and only where the energy is."""
    energy = torch.zeros(4100, 4100)
    energy[-1, -2] = 1.0
    position = positions_from_energy(energy, 10, torch.Generator().manual_seed(0))
    assert (position.round() == torch.tensor([4098.0, 4099.0])).all()
