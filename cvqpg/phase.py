"""A primitive's phase profile as a sum of named terms (method.md §2, "Phase terms"; the bound: §4).

Each primitive's field carries `exp(i k_c ψ(p))`, ψ (m) a sum of terms of the offset d = p − x (px) from its
centre, each one `PhaseTerm` here:

| term        | parameters                      | ψ                                     | physical tensor           |
|-------------|---------------------------------|---------------------------------------|---------------------------|
| `quadratic` | γ (1/m), the paper's curvature  | ½γ·s_x s_y·Δx²·D² (or ½γΔx²·|d|²)      | `curvature_per_m` [N(, C)]|
| `axes`      | γ_u, γ_v (1/m) along the axes   | ½Δx²·(γ_u u² + γ_v v²)                | `axes_curvature_per_m` [N, 2] |
| `tilt`      | t_x, t_y (rad), the slope ∂ψ/∂x | Δx·(t_x d_x + t_y d_y)                | `tilt_rad` [N, 2]         |

(u, v: d along the ellipse's axes, the directions of s_x and s_y rotated by θ.) A phase is a set of terms joined by
`+` (`PHASES`); `constant` has none. Every term starts at 0, where the primitive is today's flat one, and each takes
the share `weight / Σ weights` of the SLM's Nyquist limit (`nyquist_shares`), so that the largest local frequency
of their sum over the 3σ footprint never exceeds it (method.md §4). `quadratic` is the paper's and keeps its place in
`Gaussians.curvature`; the others live in `Gaussians.terms` by name, and the rasterizer sums them as one general
quadratic-plus-linear path (`phase_form`). A new term of at most second order is one `PhaseTerm` and its row in
`TERMS`; the kernels need nothing new. A `.cvq` file codes each extra term as a share of its bound (`limit`), which
the decoder knows from the decoded scale and the optics (docs/format.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from .errors import ConfigError, choices_error

if TYPE_CHECKING:  # the configuration imports this module, and the command line's parser it, without PyTorch
    from torch import Tensor

COVARIANCE_REGULARISER_PX2 = 0.1  # Σ = R S² Rᵀ + 0.1·I (method.md §2), as in `primitives`
NYQUIST_CYCLES_PER_PX = 0.5
FOOTPRINT_SIGMAS = 3.0  # the footprint the bound holds on: the 3σ ellipse D² ≤ 9
FORM_COLUMNS = 5  # (P_a, P_b, P_c) m/px² and (L_x, L_y) m/px of ψ = P_a d_x² + 2P_b d_x d_y + P_c d_y² + L·d


@dataclass(frozen=True)
class Bounds:
    """What a term's bound depends on: η, the shortest wavelength λ_min (m), the pixel pitch Δx (m), and the share
    of the Nyquist limit the term has."""

    eta: float
    shortest_wavelength_m: float
    pixel_pitch_m: float
    share: float

    @property
    def frequency(self) -> float:
        """The largest local frequency (cycles/px) the term may reach at λ_min: its share of η·Nyquist."""
        return self.share * self.eta * NYQUIST_CYCLES_PER_PX


@dataclass(frozen=True)
class PhaseTerm:
    """One term of ψ: its name (the raw tensor's in `Gaussians.terms`), how many raw parameters a primitive has,
    its physical tensor's name and unit, its weight in the Nyquist bound, its learning rate's name in
    `LearningRates`, whether its parameters follow the ellipse's axes (`per_axis`: a quarter turn of the ellipse
    with its axes swapped swaps them), and four functions:

    - `activate(raw [N, P], scale_px [N, 2], bounds) → physical [N, P]`, 0 at raw 0, within the term's bound;
    - `form(physical [N, P], rotation_rad [N], pixel_pitch_m) → [N, 5]`: its coefficients of ψ (`FORM_COLUMNS`);
    - `limit(scale_px [N, 2], bounds) → [N, P]`: the largest magnitude of each physical parameter `activate` reaches,
      the unit of the shares a `.cvq` file codes;
    - `within(shares [N, P]) → [N, P]`: shares (physical / `limit`) taken into the set `activate` reaches.
    """

    name: str
    parameters: int
    physical: str
    unit: str
    weight: float
    learning_rate: str
    summary: str
    activate: Callable[[Tensor, Tensor, Bounds], Tensor] | None = None
    form: Callable[[Tensor, Tensor, float], Tensor] | None = None
    limit: Callable[[Tensor, Bounds], Tensor] | None = None
    within: Callable[[Tensor], Tensor] | None = None
    per_axis: bool = False


def axis_sigmas_px(scale_px: Tensor) -> Tensor:
    """σ along the ellipse's two axes (px) [N, 2]: √(s² + 0.1), Σ's eigenvalues' roots."""
    return (scale_px * scale_px + COVARIANCE_REGULARISER_PX2).sqrt()


def _axes_limit(scale_px: Tensor, bounds: Bounds) -> Tensor:
    """γ_max (1/m) = f·λ_min / (3σ Δx²) per axis [N, 2] (f: `Bounds.frequency`): the chirp Δx²γ·u/λ reaches f at the
    ellipse's edge u = 3σ_u."""
    limit = bounds.frequency * bounds.shortest_wavelength_m / (FOOTPRINT_SIGMAS * bounds.pixel_pitch_m**2)
    return limit / axis_sigmas_px(scale_px)


def _activate_axes(raw: Tensor, scale_px: Tensor, bounds: Bounds) -> Tensor:
    """γ_u, γ_v (1/m) = γ_max·tanh(raw), γ_max per axis (`_axes_limit`)."""
    return _axes_limit(scale_px, bounds) * raw.tanh()


def _within_box(shares: Tensor) -> Tensor:
    """Each share within [−1, 1]: tanh's range, one parameter at a time."""
    return shares.clamp(-1.0, 1.0)


def _axes_form(curvature_per_m: Tensor, rotation_rad: Tensor, pixel_pitch_m: float) -> Tensor:
    """½Δx²·R diag(γ_u, γ_v) Rᵀ as (P_a, P_b, P_c); no linear part."""
    import torch

    cos, sin = rotation_rad.cos(), rotation_rad.sin()
    half = 0.5 * pixel_pitch_m**2
    along, across = half * curvature_per_m[:, 0], half * curvature_per_m[:, 1]
    zero = torch.zeros_like(along)
    return torch.stack([cos * cos * along + sin * sin * across, cos * sin * (along - across),
                        sin * sin * along + cos * cos * across, zero, zero], dim=1)


def _largest_tilt_rad(bounds: Bounds) -> float:
    """t_max (rad) = f·λ_min/Δx (f: `Bounds.frequency`): the slope whose frequency tΔx/λ is f."""
    return bounds.frequency * bounds.shortest_wavelength_m / bounds.pixel_pitch_m


def _tilt_limit(scale_px: Tensor, bounds: Bounds) -> Tensor:
    """t_max (rad) for each primitive's t_x and t_y [N, 2]: the same for all."""
    return scale_px.new_full(scale_px.shape, _largest_tilt_rad(bounds))


def _activate_tilt(raw: Tensor, scale_px: Tensor, bounds: Bounds) -> Tensor:
    """t (rad) = t_max · r / √(1 + |r|²): its frequency tΔx/λ stays under f in every direction; the squash is smooth
    at 0, with slope 1 there as tanh's."""
    limit = _largest_tilt_rad(bounds)
    return limit * raw * (1 + (raw * raw).sum(dim=1, keepdim=True)).rsqrt()


def _within_disc(shares: Tensor) -> Tensor:
    """Each primitive's pair of shares within the unit disc, the squash's range: scaled onto it from beyond."""
    norm = shares.norm(dim=1, keepdim=True)
    return shares / norm.clamp(min=1.0)


def _tilt_form(tilt_rad: Tensor, rotation_rad: Tensor, pixel_pitch_m: float) -> Tensor:
    """Δx·t as (L_x, L_y): the path (m) per px of offset; no quadratic part."""
    import torch

    zero = torch.zeros_like(tilt_rad[:, :1])
    return torch.cat([zero, zero, zero, pixel_pitch_m * tilt_rad], dim=1)


QUADRATIC = PhaseTerm("quadratic", 1, "curvature_per_m", "1/m", 1.0, "curvature",
                      "the paper's curvature γ, along the ellipse (--qpf mahalanobis) or a circle (standard)")
AXES = PhaseTerm("axes", 2, "axes_curvature_per_m", "1/m", 1.0, "axes",
                 "two curvatures γ_u, γ_v along the ellipse's axes (astigmatic: two focal depths)",
                 _activate_axes, _axes_form, _axes_limit, _within_box, per_axis=True)
TILT = PhaseTerm("tilt", 2, "tilt_rad", "rad", 1.0, "tilt",
                 "a linear phase: the wavefront's slope (t_x, t_y), a carrier frequency t·Δx/λ that steers the light",
                 _activate_tilt, _tilt_form, _tilt_limit, _within_disc)
TERMS: dict[str, PhaseTerm] = {term.name: term for term in (QUADRATIC, AXES, TILT)}
CURVATURE_TERMS = ("quadratic", "axes")  # second-order terms: a phase takes at most one

CONSTANT = "constant"
PHASES: tuple[str, ...] = (CONSTANT, "quadratic", "tilt", "quadratic+tilt", "axes", "axes+tilt")


@dataclass(frozen=True)
class Phase:
    """A phase profile: its terms in `TERMS`' order."""

    terms: tuple[PhaseTerm, ...]

    @property
    def name(self) -> str:
        return "+".join(term.name for term in self.terms) or CONSTANT

    def has(self, name: str) -> bool:
        return any(term.name == name for term in self.terms)

    @property
    def extra_terms(self) -> tuple[PhaseTerm, ...]:
        """The terms beyond the paper's curvature: those in `Gaussians.terms`."""
        return tuple(term for term in self.terms if term is not QUADRATIC)

    def nyquist_shares(self) -> dict[str, float]:
        """Each term's share of the Nyquist bound: its weight over the terms' total (1 for a term alone)."""
        total = sum(term.weight for term in self.terms)
        return {term.name: term.weight / total for term in self.terms}


def parse_phase(name: str) -> Phase:
    """The `Phase` of a name (`PHASES`, or any terms of `TERMS` joined by `+`, at most one curvature);
    `ConfigError` naming the choices otherwise."""
    if name == CONSTANT:
        return Phase(())
    parts = name.split("+") if isinstance(name, str) else [name]
    if (not all(part in TERMS for part in parts) or len(set(parts)) != len(parts)
            or sum(part in CURVATURE_TERMS for part in parts) > 1):
        raise choices_error("phase", name, PHASES)
    return Phase(tuple(term for term in TERMS.values() if term.name in parts))


def activate_terms(raw_terms: dict[str, Tensor], phase: Phase, scale_px: Tensor, eta: float,
                   shortest_wavelength_m: float, pixel_pitch_m: float) -> dict[str, Tensor]:
    """The physical values of the extra terms' raw tensors, each within its share of the bound."""
    return {term.name: term.activate(raw_terms[term.name], scale_px, bounds)
            for term, bounds in _term_bounds(phase, eta, shortest_wavelength_m, pixel_pitch_m)}


def _term_bounds(phase: Phase, eta: float, shortest_wavelength_m: float, pixel_pitch_m: float
                 ) -> list[tuple[PhaseTerm, Bounds]]:
    """Each extra term with its bound: its share of the Nyquist limit beside the others."""
    shares = phase.nyquist_shares()
    return [(term, Bounds(eta, shortest_wavelength_m, pixel_pitch_m, shares[term.name])) for term in phase.extra_terms]


def term_limits(phase: Phase, scale_px: Tensor, eta: float, shortest_wavelength_m: float, pixel_pitch_m: float
                ) -> dict[str, Tensor]:
    """The largest magnitude (`PhaseTerm.limit`) of each extra term's parameters [N, P] at scale `scale_px`, each
    term within its share of the bound, as `activate_terms` bounds it."""
    return {term.name: term.limit(scale_px, bounds)
            for term, bounds in _term_bounds(phase, eta, shortest_wavelength_m, pixel_pitch_m)}


def phase_form(terms: dict[str, Tensor], rotation_rad: Tensor, pixel_pitch_m: float) -> Tensor | None:
    """The extra terms' ψ as one quadratic-plus-linear form [N, 5] (`FORM_COLUMNS`), or None without any: the
    rasterizer then runs the paper's path alone."""
    if not terms:
        return None
    forms = [TERMS[name].form(values, rotation_rad, pixel_pitch_m) for name, values in terms.items()]
    return sum(forms[1:], forms[0])


def check_phase_settings(phase: Phase, curvature: str, bound: str) -> None:
    """`ConfigError` where the other primitive settings cannot go with `phase`: `curvature` and the global `bound`
    shape the paper's quadratic term only."""
    if curvature != "shared" and not phase.has("quadratic"):
        raise ConfigError(f"`curvature` {curvature} shapes the quadratic term, which `phase` {phase.name} has not: "
                          "use `curvature` shared, or a phase with `quadratic`")
    if bound != "adaptive" and phase.extra_terms:
        raise ConfigError(f"`bound` {bound} is the paper's ablation of the quadratic term alone; `phase` "
                          f"{phase.name} needs `bound` adaptive")
