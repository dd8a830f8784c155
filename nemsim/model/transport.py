"""Line-of-sight transport input (not in the paper; ``NEMSimConfig.transport_input``, default off).

Why: how much of a species' directed flux reaches a point of the feature depends on what the point sees of
the plasma through the opening, under that species' angular distribution. The network sees only the
geometry and the controls, so it has to learn that non-local integral over directions, and models trained
without it miss the responses to the neutral flux and the angular exponents (``nemsim bench physics``;
docs/experiments.md). This module computes it and hands it to the encoder as input channels.

Per cell of the 1/2-resolution grid (the encoder's first level), for each species with an angular control
(neutral Cl, Cl+, Cl2+, Ar+, in the order of ``nemsim.controls``):

    Φ_c(cell) = Σ_d w_c,d · max(0, 1 - κ S_d(cell)),   w_c,d ∝ cos^{m_c}(θ_d) · Ω_d,   Σ_d w_c,d = 1

  * directions d: the polar angles ``polar_deg`` (0 = straight down) times ``azimuths`` evenly spaced
    azimuths (one direction at θ = 0); Ω_d is the solid angle of the direction's bin;
  * m_c: the species' cosine-power exponent in physical units (clamped >= 0), the simulator's source law;
  * S_d(cell): the solid material (mask or Si) a straight ray from the cell towards d crosses before it
    leaves the top of the box, in cells; transmittance max(0, 1 - κ S_d) (``kappa``; a clamp rather than
    exp(-κ S): direct flux through solid is nil either way). A voxel's material fraction is
    clamp(1/2 - ``sdf_scale`` · min(x), 0, 1), averaged over the 2x2x2 voxels of a cell;
  * rays run on the cell grid, i levels down shifted laterally by -round(i · tan θ) cells, periodic in x and
    y as the simulator's domain: a shear, a cumulative sum down each column and the inverse shear.

Limits: no reflection, re-emission or surface reaction (the simulator has all three): Φ is the direct flux,
the part of transport that is pure geometry. Only material above a cell shadows it, so a depth-windowed call
(``nemsim.model.window``) computes it exactly on its slab. The weights depend only on the controls
(``precompute``), the rays only on the state.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from nemsim.controls import ANGLE_CONTROLS
from nemsim.model.angle_features import angle_exponents


@dataclass(frozen=True)
class TransportConfig:
    polar_deg: tuple[float, ...] = (0.0, 3.0, 6.0, 10.0, 20.0, 35.0, 50.0, 65.0, 80.0)  # θ of the rays
    azimuths: int = 8  # rays per polar angle > 0
    kappa: float = 1.0  # a ray is blocked once it has crossed 1/kappa cells of solid material
    sdf_scale: float = 7.5  # SDF clipping distance in voxels (x = SDF / d_max): material fraction from x
    # NEMSim multiplies Φ by gain before its zero-initialized input convolution: with Adam a weight moves by
    # about the learning rate per step whatever its gradient's scale, so gain is that path's learning-rate
    # multiplier (at 1, a warm start's gentle rate left the new path nearly unused; docs/experiments.md)
    gain: float = 1.0

    def __post_init__(self) -> None:
        p = self.polar_deg
        if not p or p[0] != 0.0 or any(b <= a for a, b in zip(p[:-1], p[1:], strict=True)) or p[-1] >= 90.0:
            raise ValueError(f"polar_deg must start at 0 and increase below 90, got {p}")
        if self.azimuths < 1 or self.kappa <= 0 or self.sdf_scale <= 0 or self.gain <= 0:
            raise ValueError("azimuths must be >= 1, kappa, sdf_scale and gain > 0")


@functools.lru_cache(maxsize=16)
def directions(cfg: TransportConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(θ (K,) rad, lateral step per level (K, 2) as (dy, dx) cells, solid angle Ω (K,)) of the K rays
    (cached: every ``precompute`` asks for them; callers do not modify them)."""
    theta = [math.radians(t) for t in cfg.polar_deg]
    edges = [0.0] + [(a + b) / 2 for a, b in zip(theta[:-1], theta[1:], strict=True)] + [math.pi / 2]
    th, step, omega = [], [], []
    for j, t in enumerate(theta):
        ring = 2 * math.pi * (math.cos(edges[j]) - math.cos(edges[j + 1]))
        n = 1 if j == 0 else cfg.azimuths
        for k in range(n):
            phi = 2 * math.pi * k / n
            th.append(t)
            step.append((math.tan(t) * math.sin(phi), math.tan(t) * math.cos(phi)))
            omega.append(ring / n)
    return torch.tensor(th, dtype=torch.float64), torch.tensor(step, dtype=torch.float64), \
        torch.tensor(omega, dtype=torch.float64)


def species_weights(u: torch.Tensor, cfg: TransportConfig) -> torch.Tensor:
    """w (B, 4, K) float32 from normalized controls u (B, 14): cos^m(θ_d) Ω_d, normalized over d."""
    theta, _, omega = (t.to(u.device) for t in directions(cfg))
    m = angle_exponents(u)  # (B, 4) physical exponents (not log-transformed)
    logw = m[:, :, None] * torch.log(torch.cos(theta))[None, None] + torch.log(omega)[None, None]  # (B, 4, K)
    return torch.softmax(logw, dim=-1).float()


@functools.lru_cache(maxsize=16)
def shear_index(D: int, H: int, W: int, cfg: TransportConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(forward, inverse) gather indices (D, K*H*W) of the per-ray shear of a (D, H, W) cell grid whose
    levels are listed top first (row i is i levels below the top), for the layout (D, K, H*W) of K sheared
    copies: in copy k, column (y, x) is the ray of direction k that sits at (y - round(i dy), x - round(i dx))
    in row i (it moves by +(dy, dx) per level up). The rounding is counted from the top, so a slab that
    shares the top (a depth window) gets the same rays. ``forward`` gathers the copies from the grid
    (D, H*W); ``inverse`` puts each copy back on the grid within its own block of H*W. Cached per grid
    (computing them costs more than using them)."""
    _, step, _ = directions(cfg)
    K = step.shape[0]
    i = torch.arange(D, dtype=torch.float64)  # rows: levels below the top
    shift = -torch.round(i[None, :, None] * step[:, None, :]).long()  # (K, D, 2)
    y = torch.arange(H)[None, None, :, None]
    x = torch.arange(W)[None, None, None, :]
    sy, sx = shift[..., 0][:, :, None, None], shift[..., 1][:, :, None, None]
    fwd = ((y + sy) % H) * W + (x + sx) % W  # (K, D, H, W)
    block = (torch.arange(K) * H * W)[:, None, None, None]
    inv = ((y - sy) % H) * W + (x - sx) % W + block
    return fwd.reshape(K, D, H * W).transpose(0, 1).reshape(D, K * H * W).contiguous(), \
        inv.reshape(K, D, H * W).transpose(0, 1).reshape(D, K * H * W).contiguous()


def material_cells(x: torch.Tensor, cfg: TransportConfig) -> torch.Tensor:
    """Material fraction of the 1/2-resolution cells (B, D/2, H/2, W/2) from the padded state
    x (B, 2, D, H, W) (D, H, W even)."""
    solid = (0.5 - cfg.sdf_scale * x.float().amin(dim=1, keepdim=True)).clamp(0.0, 1.0)  # (B, 1, D, H, W)
    return F.avg_pool3d(solid, 2)[:, 0]


def transport_field(x: torch.Tensor, weights: torch.Tensor, cfg: TransportConfig) -> torch.Tensor:
    """Φ (B, 4, D/2, H/2, W/2) float32: the direct flux fraction of each species reaching each 1/2-resolution
    cell, from the padded state x (B, 2, D, H, W) and ``weights = species_weights(u)`` (B, 4, K)."""
    o = material_cells(x, cfg).flip(1)  # (B, d, h, w), top level first
    B, d, h, w = o.shape
    fwd, inv = (t.to(o.device) for t in shear_index(d, h, w, cfg))  # (d, K*h*w)
    K = fwd.shape[1] // (h * w)
    sheared = torch.gather(o.reshape(B, d, h * w), 2, fwd.expand(B, d, K * h * w))  # (B, d, K*h*w): rays
    above = sheared.cumsum(1).sub_(sheared)  # material strictly above each cell along its ray
    trans = torch.gather(above.mul_(-cfg.kappa).add_(1.0).clamp_(min=0.0), 2, inv.expand(B, d, K * h * w))
    phi = torch.matmul(weights.to(trans.dtype)[:, None], trans.view(B, d, K, h * w))  # (B, d, 4, h*w)
    return phi.transpose(1, 2).reshape(B, len(ANGLE_CONTROLS), d, h, w).flip(2)  # bottom level first again
