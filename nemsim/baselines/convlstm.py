"""ConvLSTM baseline adapted to 3-D ([supp_baselines], tab:supp_baseline_impl; Shi et al. 2015).

"Four stacked ConvLSTM3D layers followed by a 3D convolutional readout. The projected control vector is
spatially broadcast and concatenated with every input state. Hidden widths (28, 28, 28, 28)." 0.634 M.

Written here because no maintained library ships a 3-D ConvLSTM (neuraloperator has none; torch has no
ConvLSTM). Choices where the paper is silent:
  * Cell: one Conv3d(k=3, 'same' padding) over [input, h] to the four gates (i, f, o, g), with bias;
    c' = f c + i g, h' = o tanh(c').
  * Input per step: state (2) + control field Linear(14 -> 8) (8) + coordinates (3) = 13 channels, the same
    input set as CNO. With these the count is 634,098 at any scene (the paper: 0.634 M).
  * Readout: Conv3d(28 -> 2, k=3) on the last layer's hidden state.
  * The shared contract is Markov, forward(x_t, u_t) -> x_{t+1}, so the recurrence runs over
    ``recurrent_steps`` presentations of the same (x_t, u_t) starting from zero h, c. With the default 1
    (a single input state, as the one-step protocol gives) the hidden-to-gate half of each kernel and the
    forget gate act on zeros and receive no gradient; they are kept so the architecture and its parameter
    count are the paper's. No hidden state is carried between calls (rollouts stay stateless).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from nemsim.baselines.common import ControlField, check_inputs, coordinate_grid


@dataclass(frozen=True)
class ConvLSTMConfig:
    hidden: tuple[int, ...] = (28, 28, 28, 28)  # hidden width of each stacked ConvLSTM3D layer
    kernel: int = 3  # gate convolution kernel (cubic)
    control_channels: int = 8  # width of the broadcast control field
    use_coords: bool = True  # append the 3 coordinate channels to every input
    readout_kernel: int = 3  # kernel of the Conv3d readout
    recurrent_steps: int = 1  # presentations of (x_t, u_t) per forward (1 = the one-step protocol)
    residual: bool = True  # x_next = x + readout (see nemsim.baselines.common)


class ConvLSTMCell3d(nn.Module):
    """One ConvLSTM3D cell. x (B, C_in, D, H, W), state (h, c) each (B, C_h, D, H, W)."""

    def __init__(self, c_in: int, c_hidden: int, kernel: int) -> None:
        super().__init__()
        self.c_hidden = c_hidden
        self.gates = nn.Conv3d(c_in + c_hidden, 4 * c_hidden, kernel, padding=kernel // 2)

    def forward(
        self, x: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        h, c = state
        i, f, o, g = torch.chunk(self.gates(torch.cat([x, h], dim=1)), 4, dim=1)  # each (B, C_h, D, H, W)
        c_next = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h_next = torch.sigmoid(o) * torch.tanh(c_next)
        return h_next, c_next


class ConvLSTM3d(nn.Module):
    def __init__(self, cfg: ConvLSTMConfig = ConvLSTMConfig()) -> None:
        super().__init__()
        if cfg.recurrent_steps < 1:
            raise ValueError(f"recurrent_steps must be >= 1, got {cfg.recurrent_steps}")
        self.cfg = cfg
        self.control = ControlField(cfg.control_channels)
        c_in = 2 + cfg.control_channels + (3 if cfg.use_coords else 0)
        cells = []
        for width in cfg.hidden:
            cells.append(ConvLSTMCell3d(c_in, width, cfg.kernel))
            c_in = width
        self.cells = nn.ModuleList(cells)
        self.readout = nn.Conv3d(c_in, 2, cfg.readout_kernel, padding=cfg.readout_kernel // 2)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        check_inputs(x, u)
        B, _, D, H, W = x.shape
        parts = [x, self.control(u.to(x.dtype), (D, H, W))]
        if self.cfg.use_coords:
            parts.append(coordinate_grid((D, H, W), x.device, x.dtype).expand(B, 3, D, H, W))
        inp = torch.cat(parts, dim=1)  # (B, 13, D, H, W)
        hidden = [int(cell.c_hidden) for cell in self.cells]  # type: ignore[arg-type]
        states = [(x.new_zeros(B, c, D, H, W), x.new_zeros(B, c, D, H, W)) for c in hidden]
        for _ in range(self.cfg.recurrent_steps):
            h = inp
            for k, cell in enumerate(self.cells):
                states[k] = cell(h, states[k])
                h = states[k][0]  # (B, C_h, D, H, W)
        out = self.readout(h)  # (B, 2, D, H, W)
        return x + out if self.cfg.residual else out
