"""Angular-spread inputs of the learned parts (not in the paper; ``NEMSimConfig.angle_features``, off).

Why: the paper normalizes the cosine-power exponents m of the four angular species linearly over their design
ranges (Cl 0..20, the ions 50..3000). The profile follows the angular spread of a species, s(m) below, which
falls as 1/sqrt(m), so the simulated top width responds mostly at small m. In the paper's coordinate half of
the fall of s lies in the lowest 4 % of the axis (m = 50..162), which a smooth control network fitted on a
Latin hypercube hardly resolves: models trained without these columns under-predict the top width's
response to the ion exponents (``docs/experiments.md``).

What the learned parts read with the option on: the 14 normalized controls u (unchanged, so the rule kinetics
and everything else still see the paper's representation) followed by four columns, one per angular species
in the order of ``nemsim.controls.ANGLE_CONTROLS``:

    s(m)  = sqrt(2 / (m + 3))                          the RMS sine of the polar angle of the launch
                                                       distribution, cos θ = U^(1/(m+1)) (nemsim.sim.kernels)
    a     = 2 (s(m) - s(m_high)) / (s(m_low) - s(m_high)) - 1      +1 the broadest recipe of the design,
                                                                    -1 the most collimated

with m the physical exponent of the (saturated) normalized control, clamped at >= 0, and a saturated like a
control (``nemsim.model.saturation``), so the columns stay in [-1, 1] in the box and bounded outside it. In
the new coordinate m = 1,525 sits at a = -0.88 for the ions, and m = 50..200 spans a = 1..-0.13.

Warm start: ``widen_control_inputs`` turns the weights of a model without the columns into those of a model
with them, the new input columns zero, so the widened model predicts exactly what the old one did and training
decides what the columns are worth.
"""

from __future__ import annotations

import torch

from nemsim.controls import ANGLE_CONTROLS, CONTROL_SPECS, N_CONTROLS, control_index, denormalize

N_ANGLE_FEATURES = len(ANGLE_CONTROLS)  # 4
ANGLE_INDEX = [control_index(n) for n in ANGLE_CONTROLS]  # their columns among the 14 controls


def angle_exponents(u: torch.Tensor) -> torch.Tensor:
    """The physical cosine-power exponents m (B, 4) of ``ANGLE_CONTROLS`` from normalized controls u (B, 14),
    float64, clamped at >= 0 (the law the simulator samples its launch directions from)."""
    return denormalize(u.double())[:, ANGLE_INDEX].clamp_min(0.0)


def angular_spread(m: torch.Tensor) -> torch.Tensor:
    """s(m) = sqrt(2 / (m + 3)), the RMS sine of the polar angle under cos θ = U^(1/(m+1)); m >= 0."""
    return torch.sqrt(2.0 / (m + 3.0))


def angle_features(u: torch.Tensor) -> torch.Tensor:
    """The four columns a (B, 4) of the module docstring from normalized controls u (B, 14), float64 inside,
    u's dtype out (not yet saturated)."""
    m = angle_exponents(u)  # (B, 4)
    lo = torch.tensor([CONTROL_SPECS[i].low for i in ANGLE_INDEX], dtype=torch.float64, device=u.device)
    hi = torch.tensor([CONTROL_SPECS[i].high for i in ANGLE_INDEX], dtype=torch.float64, device=u.device)
    s, s_broad, s_narrow = angular_spread(m), angular_spread(lo), angular_spread(hi)
    return (2.0 * (s - s_narrow) / (s_broad - s_narrow) - 1.0).to(u.dtype)  # (B, 4)


def widen_control_inputs(old: dict[str, torch.Tensor], new: dict[str, torch.Tensor],
                         context_dim: int) -> dict[str, torch.Tensor]:
    """``old`` (a state dict without the angle columns) with zero columns inserted where ``new`` (the state
    dict of a model with them) reads them: every 2-D weight whose input width grew by ``N_ANGLE_FEATURES``
    reads either the controls alone (then the columns follow the 14 controls) or [z̄, u, ...] (then they
    follow z̄ and the 14 controls). Other tensors are returned unchanged; a grown weight of another layout
    is refused (ValueError)."""
    out = dict(old)
    for name, w_old in old.items():
        w_new = new.get(name)
        if w_new is None or w_old.shape == w_new.shape:
            continue
        grown = (w_old.dim() == 2 and w_new.dim() == 2 and w_old.shape[0] == w_new.shape[0]
                 and w_new.shape[1] - w_old.shape[1] == N_ANGLE_FEATURES)  # fmt: skip
        if not grown or w_old.shape[1] < N_CONTROLS:
            raise ValueError(f"{name}: shape {tuple(w_old.shape)} does not widen to {tuple(w_new.shape)}")
        at = N_CONTROLS if w_old.shape[1] == N_CONTROLS else context_dim + N_CONTROLS
        zeros = w_old.new_zeros(w_old.shape[0], N_ANGLE_FEATURES)
        out[name] = torch.cat([w_old[:, :at], zeros, w_old[:, at:]], dim=1)
    return out
