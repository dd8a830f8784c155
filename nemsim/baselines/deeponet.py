"""DeepONet baseline adapted to 3-D ([supp_baselines], tab:supp_baseline_impl; Lu et al. 2021), and the
DeepONet+Prior variant ([supp_rulefeat]).

"A 3D convolutional branch encoder is combined with a coordinate-based trunk network through a branch-trunk
basis contraction. The control vector is projected into a spatial feature map and concatenated with the
state inside the branch encoder. Branch widths (32, 64, 128), basis dimension 192, and a three-layer trunk
with width 160." 1.720 M; [supp_rulefeat] gives 1,720,162, and +15,712 for +Prior, which fixes the condition
encoder's first layer at 128 units (32 more inputs x 128 = 4,096, plus the 148 -> 64 -> 32 projection 11,616).

Written here because no maintained library has a convolutional-branch 3-D DeepONet (neuraloperator has
none; DeepXDE's are MLP-branch and not torch-first). Layout (choices where the paper is silent marked *):
  condition encoder   Linear(14 -> 128) -> GELU -> Linear(128 -> 16)*: 16 channels broadcast over the grid
                      (+Prior: input [u (14), RuleFeat projection (32)] = 46)
  branch encoder      [x (2), condition map (16)] -> three stages of two Conv3d(k3) + GELU, widths 32, 64,
                      128; the first conv of stages 2 and 3 has stride 2*
                      -> adaptive average pool to a fixed (4, 2, 2) grid* (keeps coarse position, makes the
                      count scene-independent) -> Linear(2048 -> 2 x 192): one coefficient vector per channel
  trunk               coordinates (z, y, x) in [0, 1) -> Linear(3, 160) -> GELU -> Linear(160, 160) -> GELU
                      -> Linear(160, 192): the shared basis t_k(z, y, x)
  contraction + head  y_c(z, y, x) = sum_k b_{c,k} t_k(z, y, x) / sqrt(192) + bias_c, then x + y
                      (residual, see nemsim.baselines.common)
Count: 1,721,202 at any scene (+0.06 % of the paper's 1,720,162; the paper does not give the layer list).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.baselines.common import check_inputs, coordinate_grid
from nemsim.baselines.rulefeat import RuleFeat, prior_projection


@dataclass(frozen=True)
class DeepONetConfig:
    branch_widths: tuple[int, ...] = (32, 64, 128)  # conv stage widths of the branch encoder
    convs_per_stage: int = 2
    pool_grid: tuple[int, int, int] = (4, 2, 2)  # (d, h, w) adaptive pooling grid before the branch head
    basis: int = 192  # basis dimension p of the branch-trunk contraction
    trunk_width: int = 160
    trunk_layers: int = 3  # Linear layers in the trunk (the last maps to the basis)
    cond_hidden: int = 128  # first layer of the condition encoder
    cond_channels: int = 16  # channels of the spatial condition map fed to the branch encoder
    rulefeat: bool = False  # DeepONet+Prior: RuleFeat projection joins u at the condition encoder
    rulefeat_hidden: int = 64  # RuleFeat projection 148 -> 64 -> rulefeat_dim
    rulefeat_dim: int = 32
    residual: bool = True


class DeepONet3d(nn.Module):
    """DeepONet (and DeepONet+Prior with ``cfg.rulefeat`` and the compiled ``rules``)."""

    def __init__(self, cfg: DeepONetConfig = DeepONetConfig(), rules=None) -> None:
        super().__init__()
        self.cfg = cfg
        n_cond_in = 14
        self.rulefeat: RuleFeat | None = None
        if cfg.rulefeat:
            self.rulefeat, self.rule_proj = prior_projection(rules, cfg.rulefeat_hidden, cfg.rulefeat_dim,
                                                             "DeepONet")
            n_cond_in += cfg.rulefeat_dim
        self.cond = nn.Sequential(
            nn.Linear(n_cond_in, cfg.cond_hidden), nn.GELU(), nn.Linear(cfg.cond_hidden, cfg.cond_channels)
        )
        layers: list[nn.Module] = []
        c_in = 2 + cfg.cond_channels
        for s, width in enumerate(cfg.branch_widths):
            for k in range(cfg.convs_per_stage):
                stride = 2 if (s > 0 and k == 0) else 1
                layers += [nn.Conv3d(c_in, width, 3, stride=stride, padding=1), nn.GELU()]
                c_in = width
        self.branch = nn.Sequential(*layers)
        self.branch_head = nn.Linear(c_in * math.prod(cfg.pool_grid), 2 * cfg.basis)
        trunk: list[nn.Module] = []
        d = 3
        for k in range(cfg.trunk_layers):
            last = k == cfg.trunk_layers - 1
            trunk.append(nn.Linear(d, cfg.basis if last else cfg.trunk_width))
            if not last:
                trunk.append(nn.GELU())
            d = cfg.trunk_width
        self.trunk = nn.Sequential(*trunk)
        self.bias = nn.Parameter(torch.zeros(2))

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        check_inputs(x, u)
        B, _, D, H, W = x.shape
        u = u.to(x.dtype)
        cond_in = u
        if self.rulefeat is not None:
            cond_in = torch.cat([u, self.rule_proj(self.rulefeat(u).to(x.dtype))], dim=1)  # (B, 46)
        c = self.cond(cond_in)  # (B, K)
        c_map = c[:, :, None, None, None].expand(B, c.shape[1], D, H, W)
        f = self.branch(torch.cat([x, c_map], dim=1))  # (B, 128, d, h, w)
        f = F.adaptive_avg_pool3d(f, self.cfg.pool_grid).flatten(1)  # (B, 128 * 16)
        b = self.branch_head(f).view(B, 2, self.cfg.basis)  # (B, 2, K)
        coords = coordinate_grid((D, H, W), x.device, x.dtype).flatten(1).T  # (D H W, 3)
        t = self.trunk(coords)  # (D H W, K)
        y = torch.einsum("bck,nk->bcn", b, t) / math.sqrt(self.cfg.basis)  # (B, 2, D H W)
        y = (y + self.bias[None, :, None]).view(B, 2, D, H, W)
        return x + y if self.cfg.residual else y
