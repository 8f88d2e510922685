"""Quantisation-aware fine-tuning (`cvqpg compress --finetune STEPS`): a few hundred steps of the fit's
loss on the run's own targets, rendered from the primitives as the `.cvq` codec would quantise them,
with a straight-through estimator (forward: the quantised value; backward: the identity)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .codec import BitDepths, outward_range
from .config import FitConfig
from .fitting import hologram
from .ops.loss import multiplane_loss, noisy_targets, standard_normal
from .optics import reconstruct
from .primitives import Primitives, curvature_bound
from .targets import Scene

# Adam's first steps move every value by about its learning rate whatever its gradient, and every value
# that crosses a bin edge changes the render: a quarter bin, reached over a short linear warm-up, then
# decayed by a cosine to 0. On the bento RGB 10% fit, one bit below the default budget, half a bin without
# warm-up lost 2.7 dB in its first 10 steps; this schedule gains 0.50 dB in 100 steps.
LEARNING_RATE_BINS = 0.25
WARMUP_STEPS = 10


def _straight_through(value: Tensor, step: float, low: float | None = None, high: float | None = None) -> Tensor:
    """`value` rounded to multiples of `step` from `low` in the forward pass, unchanged gradient."""
    origin = 0.0 if low is None else low
    rounded = origin + torch.round((value - origin) / step) * step
    if low is not None:
        rounded = rounded.clamp(low, high)
    return value + (rounded - value).detach()


def finetune(primitives: Primitives, config: FitConfig, scene: Scene, bits: BitDepths, steps: int,
             seed: int | None = None) -> Primitives:
    """`steps` Adam steps on the coded attributes (position px, log scale, rotation, signed
    amplitude·opacity, phase, curvature as a share of γ_max) through their quantisers at `bits`.

    Each attribute's learning rate is `LEARNING_RATE_BINS` of its quantisation step, so that a step
    moves a value by about a quarter of a bin at most. Returns float primitives (opacity 1) that the
    codec then quantises. The codec takes the ranges of log scale and |amplitude| from the model, so
    the entries at their extremes are held fixed and the others kept within them: the file's ranges,
    and its bins, are then those the loop trained against.
    """
    p = {name: t.detach().to(config.device, torch.float32, copy=True) for name, t in primitives.tensors().items()}
    weight = p["amplitude"] * p["opacity"][:, None]
    log_scale = torch.log(p["scale_px"])
    scale_range = tuple(outward_range(float(log_scale.min()), float(log_scale.max())))
    amplitude_max = outward_range(0.0, float(weight.abs().max()))[1]
    bound = curvature_bound(p["scale_px"], config)
    share = p["curvature_per_m"] / torch.where(bound > 0, bound, torch.ones_like(bound))
    half = 2 ** (bits.curvature - 1) - 1
    steps_of = {"position": 2.0**-bits.position,
                "scale": (scale_range[1] - scale_range[0]) / (2**bits.scale - 1) or 1.0,
                "rotation": math.pi / 2**bits.rotation, "amplitude": amplitude_max / (2**bits.amplitude - 1) or 1.0,
                "phase": 2 * math.pi / 2**bits.phase, "curvature": 1.0 / half}
    params = {"position": p["position_px"], "scale": log_scale, "rotation": p["rotation_rad"], "amplitude": weight,
              "phase": p["phase_rad"], "curvature": share}
    held = {"scale": _extremes(log_scale), "amplitude": _extremes(weight.abs())}
    held_values = {name: params[name].view(-1)[index].clone() for name, index in held.items()}
    trained = [name for name in params if name != "curvature" or config.primitive == "cvqpg"]
    for name in trained:
        params[name].requires_grad_(True)
    optimizer = torch.optim.Adam([{"params": [params[name]], "lr": LEARNING_RATE_BINS * steps_of[name]}
                                  for name in trained])
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda i: min(1.0, (i + 1) / (WARMUP_STEPS + 1))
                                                 * 0.5 * (1 + math.cos(math.pi * i / max(steps, 1))))
    generator = torch.Generator(device=config.device).manual_seed(config.seed if seed is None else seed)
    for _ in range(steps):
        quantised = _quantised(params, steps_of, scale_range, amplitude_max, config)
        recon = reconstruct(hologram(quantised, config), config)
        noise = standard_normal(scene.targets.shape, generator, config.backend)
        loss, _ = multiplane_loss(recon, scene.targets, scene.masks,
                                  noisy_targets(scene.targets, noise, config.target_noise),
                                  config.ssim_weight, config.backend)
        optimizer.zero_grad(set_to_none=True)
        if not torch.isfinite(loss):
            continue
        loss.backward()
        for name in trained:
            torch.nan_to_num_(params[name].grad, nan=0.0, posinf=0.0, neginf=0.0)
        optimizer.step()
        schedule.step()
        with torch.no_grad():
            params["scale"].clamp_(*held_values["scale"].aminmax())
            params["amplitude"].clamp_(-held_values["amplitude"].abs().max(), held_values["amplitude"].abs().max())
            params["curvature"].clamp_(-1.0, 1.0)
            for name, index in held.items():
                params[name].view(-1)[index] = held_values[name]
    with torch.no_grad():
        # γ from the share and the bound of the scale as decoded, as the codec will compute the share
        decoded_scale = _quantised(params, steps_of, scale_range, amplitude_max, config).scale_px
        return Primitives(position_px=params["position"].clone(), scale_px=torch.exp(params["scale"]),
                          rotation_rad=params["rotation"].clone(), amplitude=params["amplitude"].clone(),
                          phase_rad=params["phase"].clone(), opacity=torch.ones_like(p["opacity"]),
                          curvature_per_m=params["curvature"] * curvature_bound(decoded_scale, config)
                          ).detached().to("cpu")


def _extremes(values: Tensor) -> Tensor:
    """Flat indices of the smallest and the largest entry."""
    flat = values.reshape(-1)
    return torch.stack([flat.argmin(), flat.argmax()])


def _quantised(params: dict[str, Tensor], steps_of: dict[str, float], scale_range: tuple[float, float],
               amplitude_max: float, config: FitConfig) -> Primitives:
    """The primitives as the codec decodes them, with straight-through gradients."""
    scale_px = torch.exp(_straight_through(params["scale"], steps_of["scale"], *scale_range))
    weight = params["amplitude"]
    magnitude = _straight_through(weight.abs(), steps_of["amplitude"], 0.0, amplitude_max)
    share = _straight_through(params["curvature"], steps_of["curvature"], -1.0, 1.0)
    return Primitives(position_px=_straight_through(params["position"], steps_of["position"]), scale_px=scale_px,
                      rotation_rad=_straight_through(params["rotation"], steps_of["rotation"]),
                      amplitude=torch.sign(weight).detach() * magnitude,
                      phase_rad=_straight_through(params["phase"], steps_of["phase"]),
                      opacity=torch.ones_like(params["rotation"]),
                      curvature_per_m=share * curvature_bound(scale_px.detach(), config))
