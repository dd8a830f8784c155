"""Event Intensity Compiler (EIC): (z̄_t, u_t; R) -> λ_t (B, E) ≥ 0.

Paper: eq:base_rate, eq:primary_intensity, [supp_eic] (eq:supp_eic_base_intensity ...
eq:supp_final_intensity). All rule kinetics come from ``nemsim.rules.kinetics`` (one shared module):

  λᵇ = f p Y                                   eq:supp_eic_base_intensity  (kinetics.primary_terms)
  λ^{p,b} = (1 - d_e) λᵇ                        eq:supp_eic_primary_base    (d_e = not is_primary)
  a^z = h_z(z̄)                                 eq:supp_eic_state_context
  s = γ tanh(h_s(u)),  d = γ h_d(u)             eq:supp_eic_control_modulation
  g = σ(h_g([z̄, u]))                           eq:supp_eic_selection_gate
  a = tanh(a^z ⊙ (1 + s) + d) ⊙ g               eq:supp_eic_fused_context
  q_e = [h_c(a), ψ_e]                           eq:supp_eic_event_context   (ψ: compiled (E, 7) buffer)
  Δℓ = δ_max tanh(h_rate(q_e))                  eq:supp_log_rate_modulation (h_rate last layer zero-init)
  λᵖ = λ^{p,b} exp(Δℓ)                          eq:supp_primary_intensity
  pool = η Σ_e λᵖ ξ,  η = 1                     eq:supp_product_pool        (kinetics.product_pool)
  λ^{d,b} = d_e p_stick pool_{q(e)}             eq:supp_dependency_base     (kinetics.dependency_base)
  λᵈ = λ^{d,b} exp(Δℓ)                          eq:supp_dependency_intensity
  λ = λᵖ + λᵈ                                   eq:supp_final_intensity

At initialization Δℓ = 0, so λ equals ``kinetics.formula_intensities(u, R, kinetics)`` exactly.

``kinetics`` (``NEMSimConfig.kinetics``): "paper" (default) or "physical" (``nemsim.rules.kinetics``). Only
λ^{p,b} and Y change, so a checkpoint's state dict loads under either.

Choices where the paper is silent: h_z, h_s, h_d, h_c are single linear layers, h_g and h_rate two-layer
SiLU MLPs; fused-context width 24, h_c output width 16; γ = 0.5; δ_max = 1.0 (a factor in [e⁻¹, e]).
The (1 - d_e) mask and the event-drop ``event_mask`` are applied inside ``kinetics.primary_terms`` (before the
Product Pool, as [supp_rule_robustness] describes).

``UnstructuredIntensity`` is the w/o-EIC ablation: λ = softplus(MLP([z̄, u])), no rule kinetics, no pool.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.controls import N_CONTROLS
from nemsim.model.layers import mlp
from nemsim.rules.kinetics import Kinetics, check_kinetics, dependency_base, primary_terms, product_pool


@dataclass(frozen=True)
class EICConfig:
    n_controls: int = 14  # U
    context_dim: int = 24  # size of z̄ (set by the encoder)
    fused_dim: int = 24  # width of a^z, s, d, g, a
    proj_dim: int = 16  # output width of h_c
    rate_hidden: int = 24  # hidden width of h_rate
    gamma: float = 0.5  # γ, strength of the control-modulation branches
    delta_max: float = 1.0  # δ_max, bound of the log-rate correction


class EventIntensityCompiler(nn.Module):
    def __init__(self, cfg: EICConfig, n_rate_desc: int = 7, kinetics: Kinetics = "paper") -> None:
        super().__init__()
        self.cfg = cfg
        self.kinetics = check_kinetics(kinetics)
        K, U = cfg.fused_dim, cfg.n_controls
        self.h_z = nn.Linear(cfg.context_dim, K)
        self.h_s = nn.Linear(U, K)
        self.h_d = nn.Linear(U, K)
        self.h_g = mlp(cfg.context_dim + U, K, K)
        self.h_c = nn.Linear(K, cfg.proj_dim)
        self.h_rate = mlp(cfg.proj_dim + n_rate_desc, cfg.rate_hidden, 1, zero_last=True)

    def _modulation(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Control-only branches s = γ tanh(h_s(u)), d = γ h_d(u), each (B, K)."""
        g = self.cfg.gamma
        return g * torch.tanh(self.h_s(u)), g * self.h_d(u)

    def _log_rate(
        self, z_bar: torch.Tensor, u: torch.Tensor, s: torch.Tensor, d: torch.Tensor, psi: torch.Tensor
    ) -> torch.Tensor:
        a_z = self.h_z(z_bar)  # (B, K)
        gate = torch.sigmoid(self.h_g(torch.cat([z_bar, u], dim=1)))  # (B, K)
        a = torch.tanh(a_z * (1.0 + s) + d) * gate  # (B, K)
        c = self.h_c(a)  # (B, K_c)
        B, E = c.shape[0], psi.shape[0]
        psi_b = psi[None].to(c.dtype).expand(B, E, -1)  # (B, E, 7)
        q = torch.cat([c[:, None, :].expand(B, E, -1), psi_b], dim=2)  # (B, E, K_c + 7)
        return self.cfg.delta_max * torch.tanh(self.h_rate(q).squeeze(-1))  # (B, E)

    def precompute(self, u: torch.Tensor, rules) -> dict[str, torch.Tensor]:
        """Everything that depends on the controls only, (B, ·) tensors in fp32: the rule kinetics
        (Y, λ^{p,b}), the control-modulation branches (s, d) and the fp32 rule buffers. Reused by
        ``forward(..., cache=...)`` across the steps of a rollout with constant controls."""
        with torch.autocast(device_type=u.device.type, enabled=False):
            u32 = u.float()
            # fp32 rule tensors on u's device, converted once (kinetics accepts the dict as ``rules``)
            bufs = {k: v.to(u32.device) for k, v in rules.torch_buffers(torch.float32).items()}
            # the rule kinetics read the 14 controls (u may carry the angle columns after them); f, p, Y
            # (B, E) each, zero where d_e = 1 or dropped
            f, p, Y = primary_terms(u32[:, :N_CONTROLS], bufs, self.kinetics)
            s, d = self._modulation(u32)  # (B, K) each
            return {"u": u32, "Y": Y, "lam_pb": f * p * Y, "s": s, "d": d, "rules": bufs}  # type: ignore[dict-item]

    def forward(
        self, z_bar: torch.Tensor, u: torch.Tensor, rules, cache: dict | None = None
    ) -> dict[str, torch.Tensor]:
        """Returns dict with ``lam`` (B, E) ≥ 0, ``lam_p``, ``lam_d``, ``pool`` (B, S), ``dl`` (B, E).

        ``cache``: ``precompute(u, rules)`` for these controls (same result, the control-only part skipped).
        """
        # Kinetics in fp32 (smooth gates and thresholds are not bf16-friendly).
        if cache is None:
            cache = self.precompute(u, rules)
        with torch.autocast(device_type=z_bar.device.type, enabled=False):
            bufs = cache["rules"]
            lam_pb = cache["lam_pb"]  # (B, E)  λ^{p,b} = (1 - d_e) λᵇ
            dl = self._log_rate(z_bar.float(), cache["u"], cache["s"], cache["d"], bufs["psi"])  # type: ignore[index]  # (B, E)
            scale = torch.exp(dl)  # (B, E)
            lam_p = lam_pb * scale  # (B, E)
            pool = product_pool(lam_p, cache["Y"], bufs)  # (B, S)
            lam_db = dependency_base(pool, bufs)  # (B, E), d_e p_stick pool_q(e)
            lam_d = lam_db * scale  # (B, E)
            lam = lam_p + lam_d  # (B, E)
        return {"lam": lam, "lam_p": lam_p, "lam_d": lam_d, "pool": pool, "dl": dl}


class UnstructuredIntensity(nn.Module):
    """w/o EIC ablation: λ = softplus(MLP([z̄, u])) (B, E); event activity not compiled from the rules."""

    def __init__(self, cfg: EICConfig, n_events: int) -> None:
        super().__init__()
        self.net = mlp(cfg.context_dim + cfg.n_controls, cfg.fused_dim, n_events)

    def precompute(self, u: torch.Tensor, rules) -> dict[str, torch.Tensor]:
        return {}

    def forward(
        self, z_bar: torch.Tensor, u: torch.Tensor, rules, cache: dict | None = None
    ) -> dict[str, torch.Tensor]:
        lam = F.softplus(self.net(torch.cat([z_bar, u], dim=1)).float())  # (B, E)
        zeros = torch.zeros_like(lam)
        return {"lam": lam, "lam_p": lam, "lam_d": zeros, "pool": lam.new_zeros(lam.shape[0], 0), "dl": zeros}
