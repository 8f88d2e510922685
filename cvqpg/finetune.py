"""Quantisation-aware fine-tuning (`cvqpg compress --finetune STEPS`): a few hundred steps of the fit's
loss on the run's own targets, rendered from the primitives as the `.cvq` codec decodes them. Every
attribute goes through the codec's own quantiser with a straight-through estimator (forward: the
decoded value; backward: the identity)."""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from .codec import (BitDepths, Quantiser, attribute_shapes, chained_quantisers, coding, folded, primitives_from,
                    quantisers)
from .config import FitConfig
from .control import SILENT, RunControl
from .fitting import FitInterrupted, hologram, hologram_loss, psnr_from_mse
from .primitives import Primitives
from .ratefit import RateObjective
from .targets import Scene

# Adam's first steps move every value by about its learning rate whatever its gradient, and every value
# that crosses a bin edge changes the render: the rate is reached over a short linear ramp, then decayed by a
# cosine to 0. A short tuning keeps to a quarter bin; a long one gains from values that hop between bins
# before the cosine settles them, up to 4 bins from 400 steps (docs/compression.md, "Fine-tuning's rate").
SHORT_RATE_BINS, SHORT_STEPS = 0.25, 100
LONG_RATE_BINS = 4.0
RAMP_STEPS = 10


def learning_rate_bins(steps: int) -> float:
    """Peak learning rate of a tuning of `steps` steps, in bins of each attribute's quantiser: a quarter bin up to
    100 steps, growing with the square of the length beyond, up to 4 bins (reached at 400)."""
    return min(LONG_RATE_BINS, SHORT_RATE_BINS * max(steps / SHORT_STEPS, 1.0) ** 2)


def straight_through(value: Tensor, quantiser: Quantiser) -> Tensor:
    """`value` (float64) as the codec decodes it in the forward pass, with an unchanged gradient."""
    return value + (quantiser.values(quantiser.codes(value.detach())) - value).detach()


def quantised(values: dict[str, Tensor], ranges: dict[str, list[float]], config: FitConfig, bits: BitDepths
              ) -> Primitives:
    """The primitives as the codec decodes `values` (the attributes of `codec.Coding`) at `bits` with the header's
    `ranges`, each value at the depth the values it decodes to derive (`codec.derived_depths`), with
    straight-through gradients."""
    values, decoded = folded(values), {}

    def read(name: str, chosen: Quantiser, _) -> Tensor:
        decoded[name] = straight_through(values[name], chosen.on(values[name].device))
        return decoded[name]

    chained_quantisers(ranges, bits, attribute_shapes(values["position"].shape[0], config), read)
    return primitives_from(decoded, torch.exp(decoded["scale"].float()), config)


def finetune(primitives: Primitives, config: FitConfig, scene: Scene, bits: BitDepths, steps: int,
             seed: int | None = None, control: RunControl = SILENT, objective: RateObjective | None = None
             ) -> Primitives:
    """`steps` Adam steps on the coded attributes (position px, log scale, rotation, signed
    amplitude·opacity, phase, curvature as a share of γ_max, the phase terms beyond it as shares of their bounds)
    through their quantisers at `bits`.

    The attributes are trained in float64, as the codec quantises them, so that the loop's bins are the
    file's. Each attribute's learning rate is `learning_rate_bins(steps)` of its quantisation step: a step
    moves a value by about that many bins at most. Returns float primitives (opacity 1) that the codec then
    quantises. The codec takes the ranges of log scale and |amplitude| from the model, so
    the entries at their extremes are held fixed and the others kept within them: the file's ranges,
    and its bins, are then those the loop trained against. `control.on_step(step, loss, psnr)` is told each
    step's loss and the PSNR (dB, mean over planes) of the quantised render it trains on; a stop request
    (`control`) raises `FitInterrupted` before the next step. An `objective` (`ratefit.RateObjective`, without
    noise: the quantisers already round) adds its rate term, the file's bits at `bits` weighed by its λ.
    """
    coded = coding(primitives, config, bits)
    device = primitives.position_px.device  # where the primitives were fitted or loaded
    params = {name: value.to(device, copy=True) for name, value in coded.values.items()}
    # scenes are built on the CPU; a run fitted on a GPU tunes there, as `fit_scene` fits there
    scene = scene.to(device)
    held = {"scale": _extremes(params["scale"]), "amplitude": _extremes(params["amplitude"].abs())}
    held_values = {name: params[name].view(-1)[index].clone() for name, index in held.items()}
    for value in params.values():
        value.requires_grad_(True)
    rate = learning_rate_bins(steps)
    # rotation's bins differ per primitive: its rate counts those of `bits.rotation` (`quantisers`' own)
    bins = {name: quantiser.step for name, quantiser in quantisers(coded.ranges, bits).items()}
    optimizer = torch.optim.Adam([{"params": [value], "lr": rate * bins[name]} for name, value in params.items()])
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda i: min(1.0, (i + 1) / (RAMP_STEPS + 1))
                                                 * 0.5 * (1 + math.cos(math.pi * i / max(steps, 1))))
    generator = torch.Generator(device=device).manual_seed(config.optimisation.seed if seed is None else seed)
    for step in range(steps):
        if control.should_stop():
            raise FitInterrupted(config.optimisation.steps + 1, during="fine-tuning")
        loss, mse = hologram_loss(hologram(quantised(params, coded.ranges, config, bits), config), scene,
                                  config, generator)
        if objective is not None:
            _, term = objective.step(primitives_from(params, torch.exp(params["scale"]).float(), config), steps,
                                     steps, generator)
            if term is not None:
                loss = loss + term
        if control.on_step is not None:  # reads the device back: only for a caller that shows progress
            control.report(step, float(loss.detach()), float(psnr_from_mse(mse.detach())))
        optimizer.zero_grad(set_to_none=True)
        if not torch.isfinite(loss):
            continue
        loss.backward()
        for value in params.values():
            torch.nan_to_num_(value.grad, nan=0.0, posinf=0.0, neginf=0.0)
        optimizer.step()
        schedule.step()
        with torch.no_grad():
            params["scale"].clamp_(*held_values["scale"].aminmax())
            params["amplitude"].clamp_(-held_values["amplitude"].abs().max(), held_values["amplitude"].abs().max())
            if "curvature" in params:
                params["curvature"].clamp_(-1.0, 1.0)
            for term in config.phase.extra_terms:  # shares of the bounds, within what the activation reaches
                params[term.name].copy_(term.within(params[term.name]))
            for name, index in held.items():
                params[name].view(-1)[index] = held_values[name]
    with torch.no_grad():
        # γ from the share and the bound at the scale as decoded, the bound the codec will divide by; the
        # scale itself through a float64 exp, which returns the held extremes exactly as they came
        tuned = primitives_from(params, quantised(params, coded.ranges, config, bits).scale_px, config)
        return replace(tuned, scale_px=torch.exp(params["scale"]).float()).to("cpu")


def _extremes(values: Tensor) -> Tensor:
    """Flat indices of the smallest and the largest entry."""
    flat = values.reshape(-1)
    return torch.stack([flat.argmin(), flat.argmax()])
