"""Kinetic laws of the Event Rules Library, with two entry points ([supp_kinetic_models], [supp_eic]).

* torch (model side): differentiable, smooth gates, normalized energy coordinates
  [eq:supp_energy_normalization]; ``primary_terms``, ``base_intensity``, ``product_pool``,
  ``dependency_base``, ``formula_intensities`` (RuleFeat's lambda^RF [eq:rulefeat] and EIC's value at init).
* numba (simulator side): ``prob_physical`` and ``yield_physical`` with physical eV, the real incidence
  cosine and hard thresholds, ``@njit(cache=True)`` so the Monte Carlo particle loop can call them.

Constants are defined once, here: TAU_E, TAU_C [eq:supp_smooth_gate], EPS (the paper's epsilon),
the P-law constants c_P = cos 60 deg, R_P = 1.0/0.2 [eq:supp_physical_angle_constants] and the C-law
angle theta_C = 45 deg [eq:supp_chemical_angle_constants].

Torch formulas (B batch, E events, S species):
  f = softplus(u[iota_f]), E = softplus(u[iota_E]), k = softplus(u[iota_theta]), c = (k+1)/(k+2+eps)
      [eq:supp_kinetic_inputs, eq:supp_effective_cosine]
  const:     p = clip(p_const, 0, 1)
  probModel: x = clip((E - E_th)/(E_ref - E_th + eps), 0, 1);
             p = clip(p0 x^n F^a(c) G_tauE(E; E_th) G0, 0, 1), G0 = sigmoid(p0/tau_E)
  F^P(c) = c_eps^-q_P exp(-s_P (1/c_eps - 1)) G_tauc(c; eps); F^C(c) = [w + (1-w) c/c_C] G_tauc(c; eps),
      w = sigmoid((theta_C - arccos c)/tau_C) (angles in radians); F^None = 1
  const Y = max(Y_const, 0); yamamura Y = c_eps^-q exp(-s(1/c_eps - 1)) G_tauE(E; E_th^Y) G_tauc(c; eps),
      q = -log(Y_max/max(Y0,eps)) / (log c_max + 1 - c_max + eps), s = q c_max
  lambda^b = f p Y [eq:supp_kinetic_base_intensity]; pool_q = sum_e lambda^p_e xi_eq (eta_q = 1)
  [eq:supp_product_pool]; lambda^{d,b}_e = d_e p_stick_e pool_q(e) [eq:supp_dependency_base].
E_th, E_ref and E_th^Y are taken from ``RuleTensors.prob_params_norm`` / ``yield_params_norm`` (mapped with
the fixed bounds of each event's energy control). Events without an energy control get E = 0; events
without an angle control get c = 1 (neither is used by their laws).

Choices where the paper is silent:
  * EPS = 1e-6.
  * x^n is evaluated as 0 where x = 0 (no infinite gradient at the clip boundary).
  * The physical (numba) side uses the hard limits of every smooth gate: [E > E_th], [cos > 0], and
    [p0 > 0] for G0 (so the torch probability equals the physical one times sigmoid(p0/tau_E) away from
    thresholds); the C law switches at theta_C with the hard indicator. F^P, F^C and the Yamamura factor
    use the real incidence cosine.
  * Dropped events (``event_mask`` = 0, [supp_rule_robustness]) are zeroed before the Product Pool.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numba
import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "C_C",
    "C_P",
    "EPS",
    "R_P",
    "TAU_C",
    "TAU_E",
    "THETA_C",
    "angle_factor",
    "base_intensity",
    "dependency_base",
    "effective_cosine",
    "formula_intensities",
    "kinetic_inputs",
    "primary_terms",
    "prob_physical",
    "probability",
    "product_pool",
    "smooth_gate",
    "yield_factor",
    "yield_physical",
]

TAU_E = 0.5  # energy-gate temperature
TAU_C = 0.05  # angular-gate temperature
EPS = 1e-6  # the paper's epsilon (denominators, c_eps, angular validity gate threshold)
C_P = math.cos(math.radians(60.0))  # physical angular law: cosine of the maximum-yield angle
R_P = 1.0 / 0.2  # physical angular law: peak-to-normal ratio
THETA_C = math.radians(45.0)  # chemical angular law: transition angle
C_C = math.cos(THETA_C)


def _shape(c_max: float, ratio: float) -> tuple[float, float]:
    """Yamamura-style shape (q, s) [eq:supp_physical_angle_shape, eq:supp_yield_shape_parameters]."""
    q = -math.log(ratio) / (math.log(c_max) + 1.0 - c_max + EPS)
    return q, q * c_max


Q_P, S_P = _shape(C_P, R_P)


# ================================================================================================
# torch side (differentiable, normalized coordinates)
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
    energy: torch.Tensor, c: torch.Tensor, yield_model: torch.Tensor, yield_params: torch.Tensor
) -> torch.Tensor:
    """Yield multiplier Y (B, E) [eq:supp_constant_yield, eq:supp_yamamura_yield].

    Args: energy (B, E) in the coordinates of yield_params' E_th; c (B, E); yield_model (E,) int
      (-1 none -> 0, 0 const, 1 yamamura); yield_params (E, 4) (Y_const | E_th, theta_max_deg, Y_max, Y0).
    """
    is_ya = yield_model == 1
    y_const = yield_params[:, 0].clamp_min(0.0).expand_as(energy)
    theta_max = torch.where(is_ya, yield_params[:, 1], torch.full_like(yield_params[:, 1], 60.0))
    c_max = torch.cos(torch.deg2rad(theta_max))
    y_max = torch.where(is_ya, yield_params[:, 2], torch.ones_like(c_max))
    ratio = y_max / torch.where(is_ya, yield_params[:, 3], torch.ones_like(c_max)).clamp_min(EPS)
    q = -torch.log(ratio) / (torch.log(c_max) + 1.0 - c_max + EPS)
    s = q * c_max
    y_ya = (
        _yamamura_shape_t(c, q, s)
        * smooth_gate(energy, yield_params[:, 0], TAU_E)
        * smooth_gate(c, EPS, TAU_C)
    )
    zero = torch.zeros_like(energy)
    return torch.where(yield_model == 0, y_const, torch.where(is_ya, y_ya, zero))


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
    """Event supply f, energy E and effective cosine c, each (B, E), from normalized controls (B, 14)."""
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


def primary_terms(u_norm: torch.Tensor, rules: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(f, p, Y), each (B, E), zero for product-mediated (and dropped) events [supp_kinetic_models].

    Args: u_norm (B, 14) controls normalized to [-1, 1]; rules: RuleTensors or its torch_buffers().
    """
    b = _buffers(rules, u_norm)
    f, energy, c = kinetic_inputs(u_norm, b)
    p = probability(energy, c, b["prob_model"], b["prob_params_norm"], b["angle_kind"])
    y = yield_factor(energy, c, b["yield_model"], b["yield_params_norm"])
    active = b["is_primary"].to(u_norm.dtype) * b["event_mask"]  # (E,)
    return f * active, p * active, y * active


def base_intensity(u_norm: torch.Tensor, rules: Any) -> torch.Tensor:
    """lambda^{p,b} = (1 - d_e) f p Y, (B, E) [eq:supp_eic_primary_base]."""
    f, p, y = primary_terms(u_norm, rules)
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


def formula_intensities(u_norm: torch.Tensor, rules: Any) -> torch.Tensor:
    """Formula-based event intensities lambda^RF (B, E): primary base intensity plus deposition driven by
    the Product Pool of the base intensities ([eq:rulefeat]; EIC's value at initialization)."""
    b = _buffers(rules, u_norm)
    f, p, y = primary_terms(u_norm, b)
    lam_p = f * p * y
    return lam_p + dependency_base(product_pool(lam_p, y, b), b)


# ================================================================================================
# numba side (simulator: physical eV, real incidence cosine, hard thresholds)
# ================================================================================================


@numba.njit(cache=True)
def _angle_physical(angle_kind: int, cos_theta: float) -> float:
    if angle_kind == 0:
        return 1.0
    if cos_theta <= 0.0:
        return 0.0
    c = min(cos_theta, 1.0)
    if angle_kind == 1:
        ce = max(c, EPS)
        return ce ** (-Q_P) * math.exp(-S_P * (1.0 / ce - 1.0))
    if angle_kind == 2:
        if math.acos(c) < THETA_C:
            return 1.0
        return c / C_C
    return 0.0


@numba.njit(cache=True)
def prob_physical(
    prob_model: int, prob_params: np.ndarray, angle_kind: int, energy_ev: float, cos_theta: float
) -> float:
    """Interaction probability with physical energy (eV) and real incidence cosine, hard thresholds.

    Args: prob_model (-1 none -> 0, 0 const, 1 probModel); prob_params (5,) physical (p_const | E_th,
      E_ref, p0, n, angle); angle_kind (0 none, 1 P, 2 C); energy_ev; cos_theta (cosine of the angle
      between the incoming direction reversed and the surface normal; <= 0 -> no interaction for
      angular laws).
    """
    if prob_model == 0:
        return min(max(prob_params[0], 0.0), 1.0)
    if prob_model != 1:
        return 0.0
    e_th = prob_params[0]
    e_ref = prob_params[1]
    p0 = prob_params[2]
    n = prob_params[3]
    if energy_ev <= e_th or p0 <= 0.0:
        return 0.0
    x = min(max((energy_ev - e_th) / (e_ref - e_th + EPS), 0.0), 1.0)
    p = p0 * x**n * _angle_physical(angle_kind, cos_theta)
    return min(max(p, 0.0), 1.0)


@numba.njit(cache=True)
def yield_physical(yield_model: int, yield_params: np.ndarray, energy_ev: float, cos_theta: float) -> float:
    """Yield multiplier with physical energy (eV), real incidence cosine and hard thresholds.

    Args: yield_model (-1 none -> 0, 0 const, 1 yamamura); yield_params (4,) (Y_const | E_th [eV],
      theta_max [deg], Y_max, Y0).
    """
    if yield_model == 0:
        return max(yield_params[0], 0.0)
    if yield_model != 1:
        return 0.0
    if energy_ev <= yield_params[0] or cos_theta <= 0.0:
        return 0.0
    c_max = math.cos(math.radians(yield_params[1]))
    ratio = yield_params[2] / max(yield_params[3], EPS)
    q = -math.log(ratio) / (math.log(c_max) + 1.0 - c_max + EPS)
    s = q * c_max
    ce = max(min(cos_theta, 1.0), EPS)
    return ce ** (-q) * math.exp(-s * (1.0 / ce - 1.0))
