"""Ion-flux gate of the state update (``NEMSimConfig.flux_gate``): invariants by construction.

With the gate on, NEMSim's next state is clamp(x + g(u) Dec(...), -1, 1) with

  g(u) = 1 - exp(-(Gamma(Ar+) + Gamma(Cl+) + Gamma(Cl2+)) / GAMMA_REF),  (B,)

the ion fluxes Gamma (mol m^-2 s^-1) recovered from the normalized log-flux controls by the fixed control
ranges (``nemsim.controls.denormalize``, ``inverse_transform``). So zero flux is no change (g = 0; from a
float32 u the recovered flux is 0 or ~1e-18, so g <= ~1e-13), and so is a recipe without ions.

Why ions only: without ions the simulator changes the state by no more than its own seed-to-seed noise
(the slow spontaneous etch of SiCl3 by neutral Cl), so a neutral term would only scale an untrained
extrapolation of the network at ion-free controls; zero is closer to the simulator.

Properties: smooth; monotone non-decreasing in each ion flux; saturating (g < 1, g -> 1); no parameters (old
checkpoints load unchanged). GAMMA_REF = 1e-5 mol m^-2 s^-1, a tenth of the box's lowest Ar+ / Cl+ flux, so
inside the training box (total ion flux >= 2.01e-4) g >= 1 - exp(-20.1), exactly 1.0 in float32: a gated
model's in-box predictions are bit for bit the ungated model's. Below the box g falls linearly with the ion
flux (g ~ S/GAMMA_REF), as the simulator's change per step does (incident ions are proportional to it).

Not done here: monotone dependence on ion energy. With ``kinetics="physical"`` the rule side follows the
laws' energy dependence, but the learned parts see the raw normalized energies unconstrained.
"""

from __future__ import annotations

import torch

from nemsim.controls import CONTROL_INDEX, IS_LOG, denormalize, inverse_transform

ION_FLUXES: tuple[str, ...] = ("flux_ar_plus", "flux_cl_plus", "flux_cl2_plus")
ION_FLUX_INDICES: tuple[int, ...] = tuple(CONTROL_INDEX[n] for n in ION_FLUXES)
GAMMA_REF = 1e-5  # mol m^-2 s^-1, a tenth of the box's lowest Ar+ / Cl+ flux (1e-4)


def ion_flux_gate(u_norm: torch.Tensor) -> torch.Tensor:
    """g (B,) in [0, 1) from normalized controls u (B, 14) (module docstring). Computed in float64."""
    t = denormalize(u_norm.double())  # (B, 14) log10(flux + eps) for the fluxes
    # non-flux columns set to 0 before the inverse transform: 10^t of an energy overflows (NaN gradients)
    t = torch.where(torch.as_tensor(IS_LOG, device=t.device), t, torch.zeros_like(t))
    raw = inverse_transform(t)  # (B, 14) fluxes in mol m^-2 s^-1 (zeros elsewhere)
    total = raw[:, list(ION_FLUX_INDICES)].clamp_min(0.0).sum(dim=1)  # (B,) total ion flux
    return (-torch.expm1(-total / GAMMA_REF)).to(u_norm.dtype)
