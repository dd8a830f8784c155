"""Mechanism Attribution Compiler (MAC): (λ_t, z̄_t, u_t; R) -> α_t (B, E, M) on the simplex over M.

Paper: eq:rule_based_routing, eq:mechanism_attribution, [supp_mac] (eq:supp_mac_prototype_scores ...
eq:supp_mac_final_attribution):

  d_e = Norm(h_desc(φ_e)),  p̄_m = Norm(p_m),  ℓ_{e,m} = d_eᵀ p̄_m        eq:supp_mac_prototype_scores
  β_e = sparsemax(ℓ_e)                                                  eq:supp_mac_prototype_compatibility
  α^anc_{e,m} = β_{e,m} α⁰_{e,m} / Σ_j β_{e,j} α⁰_{e,j}                 eq:supp_mac_static_anchor
  r_i = log(1 + max(λ_i, 0)),  μ = sg(mean_i r_i)                       eq:supp_mac_bounded_scale
  I_e = tanh(r_e / (μ + ε))                                             eq:supp_mac_bounded_operator
  b^rule_{e,m} = c_m I_e r^mech_{e,m}                                   eq:supp_mac_rule_components
  b^ctx_e = h_ctx([r̄_e, z̄, u])   (last layer zero-initialized)          eq:supp_mac_context_correction
  δ = tanh(b^rule + κ b^ctx),  κ = 0.25                                 eq:supp_mac_dynamic_correction
  ρ = ρ_max σ(ρ_raw),  ρ_max = 1,  ρ_raw init −1                        eq:supp_mac_dynamic_strength
  α = Normalize_m(α^anc ⊙ exp(ρ δ))                                     eq:supp_mac_final_attribution
  T_{e,m} = λ_e α_{e,m}                                                 eq:supp_event_mechanism_driver

Choices where the paper is silent: h_desc and h_ctx are two-layer SiLU MLPs of width 24, the prototype space
has 16 dimensions; prototypes start as the first M unit vectors and h_desc's last layer as (0.01 × default
weights, bias on the prototypes' diagonal), so β ≈ uniform and α^anc ≈ α⁰ at initialization (random
prototypes would override the prior); c_m is initialized to 1; ε = 1e-6. r̄_e is the first 18 entries of
φ_e (the normalized event-parameter vector, eq:supp_event_descriptor).
With ``enabled=False`` (w/o MAC ablation) events are not routed: α = 1/M for every event.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.model.layers import mlp


@dataclass(frozen=True)
class MACConfig:
    n_families: int = 3  # M (physical, chemical, coupled)
    n_controls: int = 14  # U
    context_dim: int = 24  # size of z̄
    desc_dim: int = 35  # size of φ_e
    param_dim: int = 18  # size of r̄_e (leading block of φ_e)
    proto_dim: int = 16  # prototype space
    hidden: int = 24  # hidden width of h_desc and h_ctx
    kappa: float = 0.25  # κ, context-correction scale
    rho_max: float = 1.0  # ρ_max
    rho_raw_init: float = -1.0  # initial ρ_raw
    c_init: float = 1.0  # initial rule-correction strengths c_m
    eps: float = 1e-6


def sparsemax(logits: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Sparsemax (Martins & Astudillo 2016): Euclidean projection of ``logits`` onto the simplex."""
    z = logits.transpose(dim, -1)
    z_sorted, _ = torch.sort(z, dim=-1, descending=True)
    k = torch.arange(1, z.shape[-1] + 1, device=z.device, dtype=z.dtype)
    cumsum = z_sorted.cumsum(dim=-1)
    support = (1 + k * z_sorted) > cumsum  # prefix of True
    k_z = support.sum(dim=-1, keepdim=True)  # support size, >= 1
    tau = (cumsum.gather(-1, k_z - 1) - 1) / k_z.to(z.dtype)
    return torch.clamp(z - tau, min=0).transpose(dim, -1)


def bounded_intensity(lam: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Bnd(λ) (eq:supp_mac_bounded_operator): λ (B, E) ≥ 0 -> I (B, E) in [0, 1), stop-gradient mean scale."""
    r = torch.log1p(torch.clamp(lam, min=0))  # (B, E)
    mu = r.mean(dim=1, keepdim=True).detach()  # (B, 1)
    return torch.tanh(r / (mu + eps))


class MechanismAttributionCompiler(nn.Module):
    def __init__(self, cfg: MACConfig, enabled: bool = True) -> None:
        super().__init__()
        self.cfg = cfg
        self.enabled = enabled
        if not enabled:
            return
        M = cfg.n_families
        self.h_desc = mlp(cfg.desc_dim, cfg.hidden, cfg.proto_dim)
        # Initialization: prototypes are the first M unit vectors and every d_e starts near their common
        # diagonal, so β ≈ uniform and α^anc ≈ α⁰ at step 0 (the prior sets the initial preference).
        with torch.no_grad():
            last = self.h_desc[-1]
            last.weight.mul_(0.01)  # type: ignore[operator]
            last.bias.zero_()  # type: ignore[operator]
            last.bias[:M] = 1.0  # type: ignore[operator]
        self.prototypes = nn.Parameter(torch.eye(M, cfg.proto_dim))  # p_m
        self.c = nn.Parameter(torch.full((M,), cfg.c_init))  # c_phys, c_chem, c_coup
        self.rho_raw = nn.Parameter(torch.tensor(cfg.rho_raw_init))
        # h_ctx([r̄_e, z̄, u]): first layer split into an event part and a batch part (same function,
        # avoids materializing the (B, E, 18 + K + U) concatenation).
        self.ctx_event = nn.Linear(cfg.param_dim, cfg.hidden)
        self.ctx_state = nn.Linear(cfg.context_dim + cfg.n_controls, cfg.hidden, bias=False)
        self.ctx_out = nn.Linear(cfg.hidden, M)
        nn.init.zeros_(self.ctx_out.weight)
        nn.init.zeros_(self.ctx_out.bias)

    @property
    def rho(self) -> torch.Tensor:
        return self.cfg.rho_max * torch.sigmoid(self.rho_raw)

    def anchor(self, rules) -> torch.Tensor:
        """α^anc (E, M), state-independent (eq:supp_mac_static_anchor)."""
        phi = rules.phi.float()  # (E, 35)
        d = F.normalize(self.h_desc(phi), dim=-1)  # (E, K_p)
        p_bar = F.normalize(self.prototypes, dim=-1)  # (M, K_p)
        beta = sparsemax(d @ p_bar.T, dim=-1)  # (E, M)
        num = beta * rules.alpha0.float()  # (E, M)
        return num / num.sum(dim=-1, keepdim=True)

    def precompute(self, rules) -> dict[str, torch.Tensor]:
        """The state- and control-independent parts, fp32: α^anc (E, M), c_m r^mech (1, E, M), the event
        half of h_ctx's first layer (E, hidden) and ρ. Reused across the steps of a rollout."""
        if not self.enabled:
            return {}
        with torch.autocast(device_type=rules.phi.device.type, enabled=False):
            r_bar = rules.phi.float()[:, : self.cfg.param_dim]  # (E, 18)
            return {
                "a_anc": self.anchor(rules),  # (E, M)
                "role": self.c[None, None, :] * rules.r_mech.float()[None],  # (1, E, M) c_m r^mech_{e,m}
                "ctx_event": self.ctx_event(r_bar)[None],  # (1, E, hidden)
                "rho": self.rho,
            }

    def forward(
        self, lam: torch.Tensor, z_bar: torch.Tensor, u: torch.Tensor, rules, cache: dict | None = None
    ) -> torch.Tensor:
        """α (B, E, M) from λ (B, E), z̄ (B, K), u (B, U); ``cache``: ``precompute(rules)`` (same result)."""
        B, E = lam.shape
        M = self.cfg.n_families
        if not self.enabled:
            return lam.new_full((B, E, M), 1.0 / M)
        if cache is None:
            cache = self.precompute(rules)
        with torch.autocast(device_type=lam.device.type, enabled=False):
            lam = lam.float()
            intensity = bounded_intensity(lam, self.cfg.eps)  # (B, E)
            b_rule = intensity[:, :, None] * cache["role"]  # (B, E, M)
            zu = torch.cat([z_bar, u], 1).float()  # (B, K + U)
            hidden = cache["ctx_event"] + self.ctx_state(zu)[:, None]  # (B, E, hidden)
            b_ctx = self.ctx_out(F.silu(hidden))  # (B, E, M)
            delta = torch.tanh(b_rule + self.cfg.kappa * b_ctx)  # (B, E, M)
            v = cache["a_anc"][None] * torch.exp(cache["rho"] * delta)  # (B, E, M)
            return v / v.sum(dim=-1, keepdim=True)
