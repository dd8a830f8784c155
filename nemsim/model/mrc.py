"""Mechanism Response Compiler (MRC): (z_t, z̄_t, u_t, T_t) -> Δz_t (B, C, d, h, w).

Paper: eq:event_basis_signature, eq:event_basis_drive, eq:response_weight, eq:latent_basis,
eq:latent_update, [supp_mrc] (eq:supp_mrc_signature_logits ... eq:supp_mrc_latent_increment):

  S_{e,m,:} = softmax_r(h_sig(φ_e)_{m,:})          eq:supp_mrc_signature     (h_sig: 2-layer SiLU MLP)
  P_{m,r} = Σ_e T_{e,m} S_{e,m,r} ≥ 0               eq:supp_mrc_mode_drive
  G = σ(h_gate([z̄, u]))                            eq:supp_mrc_state_control_gate (2-layer SiLU MLP)
  A = softplus(a_raw) + ε,  K = softplus(k_raw) + ε  eq:supp_mrc_saturation_parameters
  w = A P / (K + P + ε) G,  0 ≤ w < A               eq:supp_mrc_saturating_response
  H = SiLU(GN(Conv3x3x3(z)))                        eq:supp_mrc_shared_trunk  (readout width 24)
  B̃_m = Conv^m_1x1x1(H) -> R fields of C channels   eq:supp_mrc_spatial_modes
  B = B̃ / sqrt(mean_{c,i,j,k} B̃² + ε)              eq:supp_mrc_normalized_basis
  Δz = Σ_m Σ_r w_{m,r} B_{m,r}                       eq:supp_mrc_latent_increment

The M per-family 1x1x1 heads are stored as one Conv3d with M·R·C output channels: output rows
[m·R·C, (m+1)·R·C) are family m's head, mathematically M independent heads, but one kernel call.

Choices where the paper is silent: h_sig and h_gate hidden width 24; A initialized to 0.2 and K to 1.0
(P is O(1) because f = softplus(u) ∈ (0.3, 1.4) and p ≤ 1); ε = 1e-6. Modes live on the coarse latent grid.

With ``enabled=False`` (w/o MRC ablation) the signature, drive, gate and saturating law are removed:
w = h_direct([z̄, u, vec(T)]) (unbounded), while the mode fields, latent update and decoder are kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.model.layers import Conv3d, ConvGNAct, mlp


def _softplus_inv(y: float) -> float:
    return math.log(math.expm1(y))


@dataclass(frozen=True)
class MRCConfig:
    n_families: int = 3  # M
    n_modes: int = 4  # R_b
    latent_channels: int = 18  # C of z
    readout_width: int = 24  # trunk width
    context_dim: int = 24  # size of z̄
    n_controls: int = 14  # U
    desc_dim: int = 35  # size of φ_e
    hidden: int = 24  # hidden width of h_sig and h_gate
    amp_init: float = 0.2  # initial A_{m,r}
    sat_init: float = 1.0  # initial K_{m,r}
    eps: float = 1e-6


class MechanismResponseCompiler(nn.Module):
    def __init__(self, cfg: MRCConfig, n_events: int, enabled: bool = True) -> None:
        super().__init__()
        self.cfg = cfg
        self.enabled = enabled
        M, R, C = cfg.n_families, cfg.n_modes, cfg.latent_channels
        self.trunk = ConvGNAct(C, cfg.readout_width)
        self.heads = Conv3d(cfg.readout_width, M * R * C, 1)  # per-family heads, stacked
        if enabled:
            self.h_sig = mlp(cfg.desc_dim, cfg.hidden, M * R)
            self.h_gate = mlp(cfg.context_dim + cfg.n_controls, cfg.hidden, M * R)
            self.a_raw = nn.Parameter(torch.full((M, R), _softplus_inv(cfg.amp_init)))
            self.k_raw = nn.Parameter(torch.full((M, R), _softplus_inv(cfg.sat_init)))
        else:
            self.h_direct = mlp(cfg.context_dim + cfg.n_controls + n_events * M, cfg.hidden, M * R)

    def signature(self, rules) -> torch.Tensor:
        """S (E, M, R), rows on the simplex over R (eq:supp_mrc_signature)."""
        M, R = self.cfg.n_families, self.cfg.n_modes
        logits = self.h_sig(rules.phi.float()).view(-1, M, R)  # (E, M, R)
        return torch.softmax(logits, dim=-1)

    @property
    def capacity(self) -> torch.Tensor:
        return F.softplus(self.a_raw) + self.cfg.eps  # A (M, R)

    @property
    def saturation(self) -> torch.Tensor:
        return F.softplus(self.k_raw) + self.cfg.eps  # K (M, R)

    def amplitudes(
        self, z_bar: torch.Tensor, u: torch.Tensor, T: torch.Tensor, rules
    ) -> dict[str, torch.Tensor | None]:
        """w (B, M, R) and the intermediate S, P, G (None under the w/o-MRC ablation)."""
        B = T.shape[0]
        M, R = self.cfg.n_families, self.cfg.n_modes
        zu = torch.cat([z_bar, u], dim=1).float()  # (B, K + U)
        if not self.enabled:
            w = self.h_direct(torch.cat([zu, T.reshape(B, -1)], dim=1)).view(B, M, R)  # (B, M, R)
            return {"w": w, "S": None, "P": None, "G": None}
        S = self.signature(rules)  # (E, M, R)
        P = torch.einsum("bem,emr->bmr", T, S)  # (B, M, R)
        G = torch.sigmoid(self.h_gate(zu)).view(B, M, R)  # (B, M, R)
        eps = self.cfg.eps
        w = self.capacity * P / (self.saturation + P + eps) * G  # (B, M, R)
        return {"w": w, "S": S, "P": P, "G": G}

    def modes(self, z: torch.Tensor) -> torch.Tensor:
        """RMS-normalized mode fields B (B, M·R, C, d, h, w) from z (B, C, d, h, w)."""
        Bsz, C, d, h, w = z.shape
        MR = self.cfg.n_families * self.cfg.n_modes
        fields = self.heads(self.trunk(z)).reshape(Bsz, MR, C, d, h, w)  # (B, M·R, C, d, h, w)
        nu = torch.sqrt(fields.float().pow(2).mean(dim=(2, 3, 4, 5), keepdim=True) + self.cfg.eps)
        return fields / nu.to(fields.dtype)

    def forward(
        self, z: torch.Tensor, z_bar: torch.Tensor, u: torch.Tensor, T: torch.Tensor, rules
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor | None]]:
        with torch.autocast(device_type=z.device.type, enabled=False):
            amp = self.amplitudes(z_bar.float(), u.float(), T.float(), rules)
        basis = self.modes(z)  # (B, M·R, C, d, h, w)
        Bsz = z.shape[0]
        coef = amp["w"].reshape(Bsz, -1).to(basis.dtype)  # (B, M·R)
        dz = torch.einsum("bk,bkcdhw->bcdhw", coef, basis)  # (B, C, d, h, w)
        return dz, amp
