"""Kinetic laws of the Event Rules Library, simulator side: physical eV, real incidence cosine, hard
thresholds ([supp_kinetic_models]). numpy + numba only, so the simulator (and every data-generation
worker) runs without importing torch; the differentiable model side is ``nemsim.rules.kinetics``, which
takes its constants from here.

Constants are defined once, here: TAU_E, TAU_C [eq:supp_smooth_gate], EPS (the paper's epsilon),
the P-law constants c_P = cos 60 deg, R_P = 1.0/0.2 [eq:supp_physical_angle_constants] and the C-law
angle theta_C = 45 deg [eq:supp_chemical_angle_constants].

  probModel: p = p0 x^n F^a(cos) [E > E_th] [p0 > 0], x = clip((E - E_th)/(E_ref - E_th + eps), 0, 1)
  F^P(c) = c^-q_P exp(-s_P (1/c - 1)) [c > 0]; F^C(c) = 1 below theta_C, c / c_C above; F^None = 1
  yamamura:  Y = c^-q exp(-s (1/c - 1)) [E > E_th^Y] [c > 0],
             q = -log(Y_max / max(Y0, eps)) / (log c_max + 1 - c_max + eps), s = q c_max

These are the hard limits of the smooth torch gates: [E > E_th], [cos > 0], [p0 > 0] for
G0 = sigmoid(p0/tau_E), and the C law switches at theta_C with the hard indicator. (The simulator
multiplies the probability by ``nemsim.sim.kernels.unsaturated_factor`` above E_ref; see that module's
docstring.)
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "C_C",
    "C_P",
    "EPS",
    "Q_P",
    "R_P",
    "S_P",
    "TAU_C",
    "TAU_E",
    "THETA_C",
    "prob_physical",
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
