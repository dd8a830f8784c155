"""Saturated controls for the learned parts of NEMSim (``NEMSimConfig.control_saturation``).

A network fitted inside the training box [-1, 1]^14 (normalized controls) has no reason to be right far
outside it, and nothing keeps its extrapolation small: a zero Ar+ or Cl+ flux lies many box half-widths
below the box on the log-flux axis, and an unbounded input that far out moves every learned response by
whatever the fitted slopes give. With saturation on, the learned parts (EIC's control branches and gate,
MAC's context correction, MRC's gate and amplitudes, the rule-side kinetic inputs of EIC) read

  s(u_j) = u_j                                                    |u_j| <= 1 + knee
  s(u_j) = sign(u_j) (1 + knee + w tanh((|u_j| - 1 - knee) / w))   beyond,  w = limit - knee

per control: the identity up to ``knee`` half-widths past the box edge, then a smooth (C^1), strictly
increasing approach to ``limit`` (w = 0: a hard clamp at the knee). So the network answers a far request
as it answers near the box, where it was fitted. In-box predictions are bit for bit those without
saturation, so training and every in-box result are unchanged by construction.

The ion-flux gate (``nemsim.model.gate``), exact physics, keeps the true controls: a zero Ar+ flux with Cl+
present is answered as the lowest Ar+ flux the network knows, gated by the true ion flux.

``CONTROL_SATURATION`` was chosen on the extrapolation benchmark (``nemsim bench extrapolation``) over
knees 0..1 and limits knee..knee + 1: a lower knee worsened the predictions where the simulator keeps
changing past the box (high ion flux), and a limit beyond the knee gave back part of the gain far out
(zero fluxes, needle-like ion angles), where the simulator's answer is close to the box edge's.
"""

from __future__ import annotations

import math

import torch

# (knee, limit) in box half-widths past the edge of [-1, 1]: a hard clamp at |u| = 2, twice the box's
# half-width from its centre (the farthest the extrapolation benchmark measures along each control; how it
# was chosen: the module docstring)
CONTROL_SATURATION: tuple[float, float] = (1.0, 1.0)


def check_saturation(sat: tuple[float, float] | None) -> tuple[float, float] | None:
    """``sat`` as a (knee, limit) pair of floats with 0 <= knee <= limit, or None; ValueError otherwise."""
    if sat is None:
        return None
    if len(sat) != 2:
        raise ValueError(f"control_saturation must be (knee, limit) or None, got {sat!r}")
    knee, limit = float(sat[0]), float(sat[1])
    if not 0.0 <= knee <= limit < float("inf"):
        raise ValueError(f"control_saturation (knee, limit) needs 0 <= knee <= limit < inf, got {sat!r}")
    return knee, limit


def saturate_controls(u: torch.Tensor, knee: float, limit: float) -> torch.Tensor:
    """s(u) of the module docstring, element-wise on normalized controls u (..., 14); same dtype."""
    edge = 1.0 + knee
    if limit == knee:
        return u.clamp(-edge, edge)
    w = limit - knee
    excess = (u.abs() - edge).clamp_min(0.0)  # 0 inside: tanh(0) keeps gradients finite there
    out = torch.sign(u) * (edge + w * torch.tanh(excess / w))
    return torch.where(u.abs() <= edge, u, out)


def saturation_point(distance: float, knee: float, limit: float) -> float:
    """Where the network sees a control that lies ``distance`` half-widths past the box edge (>= 0): its
    distance past the edge after saturation (the service reports it beside the true distance)."""
    d = max(float(distance), 0.0)
    if d <= knee:
        return d
    if limit == knee:
        return knee
    w = limit - knee
    return knee + w * math.tanh((d - knee) / w)
