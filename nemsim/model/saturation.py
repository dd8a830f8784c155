"""Saturated controls for the learned parts of NEMSim (``NEMSimConfig.control_saturation``).

A network fitted inside the training box [-1, 1]^14 (normalized controls) has no reason to be right far
outside it, and nothing keeps its extrapolation small: a zero Ar+ or Cl+ flux is 8.7 box half-widths below
the box on the log-flux axis, and an unbounded input that far out moves every learned response by whatever
the fitted slopes give. With saturation on, the learned parts (EIC's control branches and selection gate,
MAC's context correction, MRC's gate and amplitudes, the rule-side kinetic inputs of EIC) read

  s(u_j) = u_j                                                    |u_j| <= 1 + knee
  s(u_j) = sign(u_j) (1 + knee + w tanh((|u_j| - 1 - knee) / w))   beyond,  w = limit - knee

per control: the identity inside the box and up to ``knee`` half-widths past its edge, then a smooth (C^1,
slope 1 at the knee), strictly increasing approach to ``limit`` half-widths past the edge (w = 0: a hard
clamp at the knee). So the network never sees a control further out than ``limit``, however far the request
lies, and what it answers there is its answer near the box, where it was fitted.

What keeps the true controls: the ion-flux gate (``nemsim.model.gate``, with ``flux_gate``), the one part
that is exact physics (zero total ion flux is exactly no change, and below the box the update falls
linearly with the ion flux). So a zero Ar+ flux with Cl+ present is answered as the lowest Ar+ flux the
network knows, gated by the true ion flux; zero ion flux is still exactly no change.

In-box predictions are bit for bit those without saturation (the clamp and ``torch.where`` keep the input
itself wherever |u_j| <= 1 + knee, and knee >= 0), so training on in-box data and every in-box result
(control-id) are unchanged by construction.

How ``CONTROL_SATURATION`` was chosen: on the extrapolation benchmark (``nemsim bench extrapolation``,
figures in the model card), over knees 0..1 and limits knee..knee + 1. A knee below 1 moves the
predictions at 1.5 and 2 half-widths, and made them worse where the simulator keeps changing past the box
(high ion flux etches ever more; the network already under-predicts it there); a limit beyond the knee
gave back part of the gain far out (zero fluxes, needle-like ion angles), where the simulator's answer is
close to the box edge's. A hard clamp at knee = limit = 1 changes nothing up to 2 half-widths and is the
best of the settings tried far out.
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
