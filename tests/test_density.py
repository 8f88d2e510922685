"""Density control at a fixed N: who moves and where, an unchanged hologram at the split, and a run with
it that resumes bit for bit."""

import pytest
import torch

from cvqpg import FitConfig, builtin_scene
from cvqpg.config import DensityControl
from cvqpg.density import Relocator, relocation
from cvqpg.fitting import (CheckpointPolicy, FitInterrupted, FitState, fit_scene, initial_state, render_hologram,
                           state_from_payload)
from cvqpg.primitives import Primitives, activate, field_energy

SMALL = FitConfig(width=48, height=36, num_gaussians=120, steps=30, guard_band_px=16, color="gray",
                  density=DensityControl(every=0.2, until=0.9, fraction=0.1))


def primitives_at(positions: torch.Tensor, amplitudes: torch.Tensor) -> Primitives:
    count = positions.shape[0]
    return Primitives(position_px=positions, scale_px=torch.full((count, 2), 2.0), rotation_rad=torch.zeros(count),
                      amplitude=amplitudes[:, None], phase_rad=torch.zeros(count, 1), opacity=torch.ones(count),
                      curvature_per_m=torch.zeros(count))


def test_the_weakest_primitives_move_onto_others_where_the_error_is():
    positions = torch.tensor([[5.0, 5.0], [30.0, 20.0], [10.0, 30.0], [40.0, 8.0], [20.0, 15.0], [2.0, 2.0]])
    amplitudes = torch.tensor([0.01, 1.0, 0.9, 0.8, 0.02, 0.7])
    error = torch.zeros(36, 48)
    error[20, 30] = 1.0  # only the primitive at (30, 20) sits where the error is
    moved, sources, destination = relocation(primitives_at(positions, amplitudes), error, 1 / 6,
                                             torch.Generator().manual_seed(0))
    assert moved.tolist() == [0] and sources.tolist() == [1]
    assert torch.linalg.vector_norm(destination[0] - positions[1]) < 4 * 2.0


def test_sources_are_distinct_and_never_the_moved_ones():
    generator = torch.Generator().manual_seed(3)
    positions = torch.rand(50, 2, generator=generator) * torch.tensor([48.0, 36.0])
    primitives = primitives_at(positions, torch.rand(50, generator=generator))
    moved, sources, _ = relocation(primitives, torch.rand(36, 48, generator=generator), 0.2, generator)
    assert len(set(sources.tolist())) == len(sources) == 10
    assert not set(sources.tolist()) & set(moved.tolist())
    weakest = field_energy(primitives).argsort()[:10]
    assert sorted(moved.tolist()) == sorted(weakest.tolist())


def test_a_split_without_jitter_leaves_the_hologram_as_it_was(monkeypatch):
    monkeypatch.setattr("cvqpg.density.JITTER_SCALES", 0.0)
    scene = builtin_scene("demo", SMALL)
    state = initial_state(SMALL, scene)
    with torch.no_grad():  # the primitives that move carry nothing, so only the split could change the field
        weakest = field_energy(activate(state.gaussians, SMALL)).argsort()[:12]
        state.gaussians.amplitude[weakest] = 0
    before = render_hologram(state.gaussians, SMALL).detach()
    state.relocator.relocate(state.gaussians, state.optimizer, scene, SMALL, before)
    after = render_hologram(state.gaussians, SMALL).detach()
    assert state.relocator.moved_count == 12
    assert torch.allclose(after, before, atol=1e-5 * before.abs().max())


def test_moved_primitives_restart_their_optimiser_moments():
    scene = builtin_scene("demo", SMALL)
    state = initial_state(SMALL, scene)
    fit_scene(scene, SMALL.replace(steps=3, density=None), progress=False, state=state)
    field = render_hologram(state.gaussians, SMALL).detach()
    state.relocator.relocate(state.gaussians, state.optimizer, scene, SMALL, field)
    for name in ("position", "amplitude", "phase"):
        moments = state.optimizer.state[getattr(state.gaussians, name)]["exp_avg"]
        assert (moments.reshape(moments.shape[0], -1) == 0).all(dim=1).sum().item() >= 12, name


def test_relocation_events_scale_with_the_steps_and_stop_before_the_end():
    control = DensityControl(every=0.05, until=0.6, fraction=0.02)
    assert control.event_steps(2000) == tuple(range(100, 1200, 100))
    assert control.event_steps(8000) == tuple(range(400, 4800, 400))
    assert Relocator.for_config(FitConfig()) is None


@pytest.mark.parametrize("interrupt_at", [5, 12])
def test_a_fit_with_density_control_resumes_bit_for_bit(interrupt_at):
    scene = builtin_scene("demo", SMALL)
    straight = fit_scene(scene, SMALL, progress=False)

    saved: list[dict] = []

    def stop_requested() -> bool:
        return len(saved) == 0 and state.step == interrupt_at

    state = initial_state(SMALL, scene)
    with pytest.raises(FitInterrupted):
        fit_scene(scene, SMALL, progress=False, state=state,
                  checkpoint=CheckpointPolicy(save=lambda s: saved.append(s.to_payload()), every_seconds=None),
                  stop_requested=stop_requested)
    resumed_state: FitState = state_from_payload(saved[0], SMALL)
    resumed = fit_scene(scene, SMALL, progress=False, state=resumed_state)
    for name, tensor in straight.gaussians.tensors().items():
        assert torch.equal(tensor, resumed.gaussians.tensors()[name]), name
    assert resumed_state.relocator.moved_count == len(SMALL.density.event_steps(SMALL.steps)) * 12
