"""Kinetic laws of the Event Rules Library, model side: differentiable torch forms ([supp_kinetic_models],
[supp_eic]) of the laws whose simulator (numpy/numba) forms live in ``nemsim.rules.laws``, which defines
the constants (TAU_E, TAU_C, EPS, C_P, R_P, THETA_C, C_C, Q_P, S_P) once.

Two kinetics, chosen by ``kinetics=`` (``KINETICS``):

* "paper" (default): normalized energy coordinates [eq:supp_energy_normalization], smooth gates.
  f = softplus(u[iota_f]), E = softplus(u[iota_E]), k = softplus(u[iota_theta]), c = (k+1)/(k+2+eps)
      [eq:supp_kinetic_inputs, eq:supp_effective_cosine]
  const:     p = clip(p_const, 0, 1)
  probModel: x = clip((E - E_th)/(E_ref - E_th + eps), 0, 1);
             p = clip(p0 x^n F^a(c) G_tauE(E; E_th) G0, 0, 1), G0 = sigmoid(p0/tau_E)
  F^P(c) = c_eps^-q_P exp(-s_P (1/c_eps - 1)) G_tauc(c; eps); F^C(c) = [w + (1-w) c/c_C] G_tauc(c; eps),
      w = sigmoid((theta_C - arccos c)/tau_C) (angles in radians); F^None = 1
  const Y = max(Y_const, 0); yamamura Y = c_eps^-q exp(-s(1/c_eps - 1)) G_tauE(E; E_th^Y) G_tauc(c; eps),
      q = -log(Y_max/max(Y0,eps)) / (log c_max + 1 - c_max + eps), s = q c_max
  with E_th, E_ref, E_th^Y from ``RuleTensors.prob_params_norm`` / ``yield_params_norm``.
* "physical": the simulator's laws on physical units (eV, the mean incidence cosine of the cos^m source),
  their energy thresholds smoothed by the sampled energy spread (``probability_physical``). Why: with the
  design's energies every normalized energy gate of "paper" is saturated, so it carries no energy response.

Shared: lambda^b = f p Y [eq:supp_kinetic_base_intensity]; pool_q = sum_e lambda^p_e xi_eq (eta_q = 1)
[eq:supp_product_pool]; lambda^{d,b}_e = d_e p_stick_e pool_q(e) [eq:supp_dependency_base]. Events without
an energy control get E = 0, without an angle control c = 1 (their laws use neither).

Choices where the paper is silent: EPS = 1e-6; x^n = 0 where x = 0 (no infinite gradient at the clip);
the simulator uses the hard limits of every smooth gate (``laws``), so the paper's torch probability is the
physical one times sigmoid(p0/tau_E) away from thresholds; dropped events (``event_mask`` = 0,
[supp_rule_robustness]) are zeroed before the Product Pool.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal, cast

import torch
import torch.nn.functional as F

from nemsim.controls import denormalize
from nemsim.rules.laws import (
    C_C,
    C_P,
    EPS,
    Q_P,
    R_P,
    S_P,
    TAU_C,
    TAU_E,
    THETA_C,
    prob_physical,
    yield_physical,
)

__all__ = [
    "C_C",
    "C_P",
    "EPS",
    "KINETICS",
    "Q_P",
    "R_P",
    "S_P",
    "SIGMA_FLOOR_EV",
    "TAU_C",
    "TAU_E",
    "THETA_C",
    "Kinetics",
    "angle_factor",
    "base_intensity",
    "check_kinetics",
    "dependency_base",
    "effective_cosine",
    "expected_excess",
    "formula_intensities",
    "kinetic_inputs",
    "mean_cosine",
    "physical_inputs",
    "primary_terms",
    "prob_physical",
    "probability",
    "probability_physical",
    "product_pool",
    "smooth_gate",
    "yield_factor",
    "yield_physical",
]

Kinetics = Literal["paper", "physical"]
KINETICS: tuple[str, ...] = ("paper", "physical")
SIGMA_FLOOR_EV = 1.0  # "physical": floor of the energy-gate width, sigma_g = sqrt(sigma^2 + floor^2) (eV)


def check_kinetics(kinetics: str) -> Kinetics:
    """``kinetics`` if it names a kinetics, else ValueError listing the choices."""
    if kinetics not in KINETICS:
        raise ValueError(f"unknown kinetics {kinetics!r}; expected one of {list(KINETICS)}")
    return cast(Kinetics, kinetics)


# ================================================================================================
# torch side (differentiable)
# ================================================================================================


def smooth_gate(x: torch.Tensor, a: torch.Tensor | float, tau: float) -> torch.Tensor:
    """G_tau(x; a) = sigmoid((x - a)/tau) [eq:supp_smooth_gate]."""
    return torch.sigmoid((x - a) / tau)


def effective_cosine(u_angle: torch.Tensor) -> torch.Tensor:
    """c = (k + 1)/(k + 2 + eps), k = softplus(u) [eq:supp_angle_concentration, eq:supp_effective_cosine]."""
    k = F.softplus(u_angle)
    return (k + 1.0) / (k + 2.0 + EPS)


def _yamamura_shape_t(c: torch.Tensor, q: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    ce = c.clamp_min(EPS)
    return ce.pow(-q) * torch.exp(-s * (1.0 / ce - 1.0))


def angle_factor(c: torch.Tensor, angle_kind: torch.Tensor) -> torch.Tensor:
    """F^a(c) for a in {None, P, C} [eq:supp_physical_angle_factor, eq:supp_chemical_angle_factor].

    Args: c (B, E) effective cosine; angle_kind (E,) int (0 none, 1 P, 2 C). Returns (B, E).
    """
    valid = smooth_gate(c, EPS, TAU_C)
    f_p = _yamamura_shape_t(c, torch.as_tensor(Q_P), torch.as_tensor(S_P)) * valid
    theta = torch.arccos(c.clamp(-1.0 + 1e-7, 1.0 - 1e-7))
    w = torch.sigmoid((THETA_C - theta) / TAU_C)
    f_c = (w + (1.0 - w) * c / C_C) * valid
    one = torch.ones_like(c)
    return torch.where(angle_kind == 1, f_p, torch.where(angle_kind == 2, f_c, one))


def probability(
    energy: torch.Tensor, c: torch.Tensor, prob_model: torch.Tensor, prob_params: torch.Tensor,
    angle_kind: torch.Tensor,
) -> torch.Tensor:  # fmt: skip
    """Interaction probability p (B, E) [eq:supp_constant_probability, eq:supp_energy_angle_probability].

    Args:
      energy: (B, E) event energy in the same coordinates as prob_params' E_th, E_ref.
      c: (B, E) incidence cosine. prob_model: (E,) int (-1 none -> 0, 0 const, 1 probModel).
      prob_params: (E, 5) (p_const | E_th, E_ref, p0, n, angle). angle_kind: (E,) int.
    """
    p_const = prob_params[:, 0].clamp(0.0, 1.0).expand_as(energy)
    e_th, e_ref, p0, n = prob_params[:, 0], prob_params[:, 1], prob_params[:, 2], prob_params[:, 3]
    x = ((energy - e_th) / (e_ref - e_th + EPS)).clamp(0.0, 1.0)
    n_safe = torch.where(prob_model == 1, n, torch.ones_like(n))
    x_n = torch.where(x > 0, x.clamp_min(1e-12).pow(n_safe), torch.zeros_like(x))
    g0 = torch.sigmoid(p0 / TAU_E)
    p_model = (p0 * x_n * angle_factor(c, angle_kind) * smooth_gate(energy, e_th, TAU_E) * g0).clamp(0.0, 1.0)
    zero = torch.zeros_like(energy)
    return torch.where(prob_model == 0, p_const, torch.where(prob_model == 1, p_model, zero))


def yield_factor(
    energy: torch.Tensor, c: torch.Tensor, yield_model: torch.Tensor, yield_params: torch.Tensor,
    energy_gate: torch.Tensor | None = None,
) -> torch.Tensor:  # fmt: skip
    """Yield multiplier Y (B, E) [eq:supp_constant_yield, eq:supp_yamamura_yield].

    Args: energy (B, E) in the coordinates of yield_params' E_th; c (B, E); yield_model (E,) int
      (-1 none -> 0, 0 const, 1 yamamura); yield_params (E, 4) (Y_const | E_th, theta_max_deg, Y_max, Y0);
      energy_gate (B, E): the Yamamura energy gate, default the paper's G_tauE(energy; E_th).
    """
    is_ya = yield_model == 1
    y_const = yield_params[:, 0].clamp_min(0.0).expand_as(energy)
    theta_max = torch.where(is_ya, yield_params[:, 1], torch.full_like(yield_params[:, 1], 60.0))
    c_max = torch.cos(torch.deg2rad(theta_max))
    y_max = torch.where(is_ya, yield_params[:, 2], torch.ones_like(c_max))
    ratio = y_max / torch.where(is_ya, yield_params[:, 3], torch.ones_like(c_max)).clamp_min(EPS)
    q = -torch.log(ratio) / (torch.log(c_max) + 1.0 - c_max + EPS)
    s = q * c_max
    if energy_gate is None:
        energy_gate = smooth_gate(energy, yield_params[:, 0], TAU_E)
    y_ya = _yamamura_shape_t(c, q, s) * energy_gate * smooth_gate(c, EPS, TAU_C)
    zero = torch.zeros_like(energy)
    return torch.where(yield_model == 0, y_const, torch.where(is_ya, y_ya, zero))


def mean_cosine(m: torch.Tensor) -> torch.Tensor:
    """Mean incidence cosine (m+1)/(m+2) on a flat surface of the cos^m source distribution (m >= 0).

    p(Omega) ~ cos^m theta on the hemisphere gives cos theta = U^(1/(m+1)) (``kernels.cos_power_polar``),
    whose density is (m+1) c^m on [0, 1]."""
    return (m + 1.0) / (m + 2.0)


def expected_excess(mu: torch.Tensor, threshold: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """E[max(E' - threshold, 0)] for E' ~ N(mu, sigma^2): sigma (z Phi(z) + phi(z)),
    z = (mu - threshold)/sigma.

    Smooth, positive, increasing in mu, -> max(mu - threshold, 0) as sigma -> 0. Shapes broadcast."""
    z = (mu - threshold) / sigma
    pdf = torch.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    return (sigma * (z * torch.special.ndtr(z) + pdf)).clamp_min(0.0)


def probability_physical(
    energy_ev: torch.Tensor, sigma_ev: torch.Tensor, c: torch.Tensor, prob_model: torch.Tensor,
    prob_params: torch.Tensor, angle_kind: torch.Tensor,
) -> torch.Tensor:  # fmt: skip
    """Interaction probability p (B, E) of the "physical" kinetics: the simulator's laws ([supp_simulator],
    ``laws``) at E = mu (the event's energy-mean control, eV) and c = (m+1)/(m+2) (``mean_cosine``), their
    thresholds replaced by expectations over the sampled energy E' ~ N(mu, sigma^2)
    [eq:supp_particle_energy_sampling]:

        [E' > E_th] -> Phi(z),   max(E' - E_th, 0) -> sigma_g (z Phi(z) + phi(z)),   z = (mu - E_th)/sigma_g

    with sigma_g = sqrt(sigma^2 + SIGMA_FLOOR_EV^2) (the floor keeps sigma = 0 differentiable). probModel:
    xbar = expected excess / (E_ref - E_th + eps), p = clip(p0 min(xbar, 1)^n F^a(c), 0, 1) max(xbar, 1)^n,
    the simulator's ``prob_physical`` times its ``unsaturated_factor`` (above E_ref the law keeps growing as
    x^n). Yamamura Y: the same shape times Phi(z_Y). The supply f stays softplus(u[iota_f]) as in "paper".
    Far from thresholds (the whole design box) p and Y equal the simulator's laws at (mu, c) to 1e-5.

    Args:
      energy_ev, sigma_ev: (B, E) mean and spread (> 0) of the event's projectile energy, eV.
      c: (B, E) incidence cosine. prob_model: (E,) int (-1 none -> 0, 0 const, 1 probModel).
      prob_params: (E, 5) physical (p_const | E_th, E_ref, p0, n, angle) in eV. angle_kind: (E,) int.
    """
    p_const = prob_params[:, 0].clamp(0.0, 1.0).expand_as(energy_ev)
    e_th, e_ref, p0, n = prob_params[:, 0], prob_params[:, 1], prob_params[:, 2], prob_params[:, 3]
    x = expected_excess(energy_ev, e_th, sigma_ev) / (e_ref - e_th + EPS)  # (B, E) >= 0, not clipped
    n_safe = torch.where(prob_model == 1, n, torch.ones_like(n))
    x_lo = x.clamp(max=1.0)
    x_lo_n = torch.where(x_lo > 0, x_lo.clamp_min(1e-12).pow(n_safe), torch.zeros_like(x_lo))
    x_hi_n = x.clamp_min(1.0).pow(n_safe)  # the simulator's unsaturated factor above E_ref
    saturated = (p0 * x_lo_n * angle_factor(c, angle_kind)).clamp(0.0, 1.0)
    p_model = saturated * x_hi_n * (p0 > 0).to(x.dtype)
    zero = torch.zeros_like(energy_ev)
    return torch.where(prob_model == 0, p_const, torch.where(prob_model == 1, p_model, zero))


def _buffers(rules: Any, like: torch.Tensor) -> Mapping[str, torch.Tensor]:
    """RuleTensors or a dict of its ``torch_buffers()`` -> tensors on ``like``'s device/dtype."""
    bufs = rules.torch_buffers(like.dtype) if hasattr(rules, "torch_buffers") else rules
    out = {}
    for key, val in bufs.items():
        if val.dtype.is_floating_point:
            val = val.to(device=like.device, dtype=like.dtype)
        else:
            val = val.to(device=like.device)
        out[key] = val
    return out


def _gather(u: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """u (B, 14), idx (E,) with -1 = none -> (B, E) (zeros where none)."""
    vals = u[:, idx.clamp_min(0)]
    return torch.where(idx >= 0, vals, torch.zeros_like(vals))


def kinetic_inputs(u_norm: torch.Tensor, rules: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """"paper": event supply f, energy E and effective cosine c, each (B, E), from normalized controls
    (B, 14)."""
    b = _buffers(rules, u_norm)
    ctrl = b["ctrl_idx"]
    f = F.softplus(_gather(u_norm, ctrl[:, 0]))
    energy = F.softplus(_gather(u_norm, ctrl[:, 2]))
    c = effective_cosine(_gather(u_norm, ctrl[:, 1]))
    has = (ctrl >= 0).to(u_norm.dtype)
    f = f * has[:, 0]
    energy = energy * has[:, 2]
    c = torch.where(ctrl[:, 1] >= 0, c, torch.ones_like(c))
    return f, energy, c


def physical_inputs(
    u_norm: torch.Tensor, rules: Any
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """"physical": supply f (as "paper"), energy mean mu [eV], gate width sigma_g [eV] and mean incidence
    cosine c, each (B, E), from normalized controls (B, 14) (``probability_physical``)."""
    b = _buffers(rules, u_norm)
    ctrl = b["ctrl_idx"]
    # (B, 14) transformed controls: physical units for the angle and energy channels (their transform is
    # the identity; integers not rounded). The log-flux columns are not exponentiated (no overflow).
    raw = denormalize(u_norm)
    f = F.softplus(_gather(u_norm, ctrl[:, 0])) * (ctrl[:, 0] >= 0).to(u_norm.dtype)
    energy = _gather(raw, ctrl[:, 2]).clamp_min(0.0)
    sigma = torch.sqrt(_gather(raw, ctrl[:, 3]).clamp_min(0.0) ** 2 + SIGMA_FLOOR_EV**2)
    c = mean_cosine(_gather(raw, ctrl[:, 1]).clamp_min(0.0))
    c = torch.where(ctrl[:, 1] >= 0, c, torch.ones_like(c))
    return f, energy, sigma, c


def primary_terms(
    u_norm: torch.Tensor, rules: Any, kinetics: Kinetics = "paper"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(f, p, Y), each (B, E), zero for product-mediated (and dropped) events [supp_kinetic_models].

    Args: u_norm (B, 14) controls normalized to [-1, 1]; rules: RuleTensors or its torch_buffers();
      kinetics: "paper" or "physical" (module docstring).
    """
    b = _buffers(rules, u_norm)
    if check_kinetics(kinetics) == "paper":
        f, energy, c = kinetic_inputs(u_norm, b)
        p = probability(energy, c, b["prob_model"], b["prob_params_norm"], b["angle_kind"])
        y = yield_factor(energy, c, b["yield_model"], b["yield_params_norm"])
    else:
        f, energy, sigma, c = physical_inputs(u_norm, b)
        pp, yp = b["prob_params"], b["yield_params"]
        p = probability_physical(energy, sigma, c, b["prob_model"], pp, b["angle_kind"])
        y_gate = torch.special.ndtr((energy - yp[:, 0]) / sigma)  # E[[E' > E_th^Y]]
        y = yield_factor(energy, c, b["yield_model"], yp, energy_gate=y_gate)
    active = b["is_primary"].to(u_norm.dtype) * b["event_mask"]  # (E,)
    return f * active, p * active, y * active


def base_intensity(u_norm: torch.Tensor, rules: Any, kinetics: Kinetics = "paper") -> torch.Tensor:
    """lambda^{p,b} = (1 - d_e) f p Y, (B, E) [eq:supp_eic_primary_base]."""
    f, p, y = primary_terms(u_norm, rules, kinetics)
    return f * p * y


def product_pool(lambda_p: torch.Tensor, yield_: torch.Tensor, rules: Any) -> torch.Tensor:
    """Product Pool (B, S) = sum_e lambda^p_e xi_{e,q}, eta_q = 1 [eq:supp_product_pool].

    Args: lambda_p (B, E) primary intensities; yield_ (B, E) the event yields Y (used by yield-scaled
      sources, [eq:supp_eic_product_coefficient]).
    """
    b = _buffers(rules, lambda_p)
    w_src, is_y = b["w_src"], b["src_is_yield"]  # (E, S)
    xi = torch.where(is_y, w_src * yield_.unsqueeze(-1), w_src.expand(yield_.shape[0], *w_src.shape))
    return torch.einsum("be,bes->bs", lambda_p * b["event_mask"], xi)


def dependency_base(pool: torch.Tensor, rules: Any) -> torch.Tensor:
    """lambda^{d,b}_e = d_e p_stick_e pool_{q(e)}, (B, E) [eq:supp_dependency_base]."""
    b = _buffers(rules, pool)
    d = (~b["is_primary"]).to(pool.dtype) * b["event_mask"]
    return (pool @ b["w_sink"].T) * (b["s_dep"] * d)


def formula_intensities(u_norm: torch.Tensor, rules: Any, kinetics: Kinetics = "paper") -> torch.Tensor:
    """Formula-based event intensities lambda^RF (B, E): primary base intensity plus deposition driven by
    the Product Pool of the base intensities ([eq:rulefeat]; EIC's value at initialization)."""
    b = _buffers(rules, u_norm)
    f, p, y = primary_terms(u_norm, b, kinetics)
    lam_p = f * p * y
    return lam_p + dependency_base(product_pool(lam_p, y, b), b)
