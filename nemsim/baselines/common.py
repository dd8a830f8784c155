"""Pieces shared by the baselines: control embedding, coordinate channels, parameter counting.

Every baseline keeps the NEMSim contract ``forward(x (B, 2, D, H, W), u (B, 14) normalized) -> x_next``
([supp_baselines]: "All baselines receive the same two-channel 3D state representation and the same normalized
14-dimensional control vector"). Choices where the paper is silent, applied to all baselines alike:
  * Output: ``residual=True`` predicts the increment, x_next = x + net(x, u) (NEMSim's decoder is residual
    too); ``residual=False`` predicts x_next directly. No clipping of the output.
  * Coordinate channels are (z, y, x) in [0, 1) on the padded grid, the convention of neuralop's grid
    embedding, so baselines that use neuralop and those that do not see the same coordinates.
"""

from __future__ import annotations

import torch
from torch import nn

from nemsim.controls import N_CONTROLS  # U


def coordinate_grid(shape: tuple[int, int, int], device=None, dtype=torch.float32) -> torch.Tensor:
    """(3, D, H, W) coordinates (z, y, x), each linspace(0, 1, n + 1)[:-1] along its axis."""
    axes = [torch.linspace(0.0, 1.0, n + 1, device=device, dtype=dtype)[:-1] for n in shape]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=0)  # (3, D, H, W)


class ControlField(nn.Module):
    """Project u (B, U) to ``channels`` features and broadcast them over the grid: (B, channels, D, H, W).

    ``hidden=0`` is a single Linear(U, channels); ``hidden>0`` is Linear(U, hidden) -> GELU -> Linear(hidden,
    channels).
    """

    def __init__(self, channels: int, hidden: int = 0, n_in: int = N_CONTROLS) -> None:
        super().__init__()
        if hidden > 0:
            self.net: nn.Module = nn.Sequential(
                nn.Linear(n_in, hidden), nn.GELU(), nn.Linear(hidden, channels)
            )
        else:
            self.net = nn.Linear(n_in, channels)

    def forward(self, u: torch.Tensor, spatial: tuple[int, int, int]) -> torch.Tensor:
        e = self.net(u)  # (B, K)
        return e[:, :, None, None, None].expand(*e.shape, *spatial)  # (B, K, D, H, W)


def check_inputs(x: torch.Tensor, u: torch.Tensor, n_channels: int = 2) -> None:
    """Raise ValueError for a state that is not (B, 2, D, H, W) or controls that are not (B, 14)."""
    if x.ndim != 5 or x.shape[1] != n_channels:
        raise ValueError(f"state must be (B, {n_channels}, D, H, W), got {tuple(x.shape)}")
    if u.ndim != 2 or u.shape[1] != N_CONTROLS or u.shape[0] != x.shape[0]:
        raise ValueError(f"controls must be (B={x.shape[0]}, {N_CONTROLS}), got {tuple(u.shape)}")
