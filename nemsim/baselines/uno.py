"""U-NO baseline in 3-D ([supp_baselines], tab:supp_baseline_impl; Rahman et al. 2022).

"The seven-layer U-shaped neural-operator topology is extended to 3D using dense 3D Fourier operators and
multiresolution skip connections. A projected control field is broadcast and concatenated with the state and
spatial coordinates before lifting. Widths (8, 16, 32) and 4 x 4 x 4 Fourier modes." 2.432 M.

Configured from neuraloperator's ``neuralop.models.UNO`` when the optional extra is installed, otherwise
``nemsim.baselines.spectral.NativeUNO`` (same layout and count, different state-dict keys). Settings:
in_channels = 2 + 8 (control field Linear(14 -> 8)) + 3 coordinates (neuralop's grid embedding); lifting to
hidden 8; seven layers with output widths (8, 16, 32, 32, 32, 16, 8) and resolution scalings
(1, 1/2, 1/2, 1, 2, 2, 1); horizontal skips {6: 0, 5: 1, 4: 2} (neuralop's default for seven layers,
concatenated); dense (unfactorized) weights with n_modes = (8, 8, 7) per layer, i.e. Li et al.'s four 4x4x4
corner blocks; linear operator and channel-MLP skips (neuralop's soft-gating skip cannot change width);
lifting and projection hidden width 16.
Count: 2,440,378 (+0.34 % of the paper's 2.432 M; the paper does not list the layer widths, this is the
symmetric U over (8, 16, 32) closest to it).

Known neuralop 2.0 issue (checked): a resolution-changing ``SpectralConv`` calls irfftn(s=new size) on the
full-size spectrum, which drops the negative frequencies along D and H when downsampling (a pure sin along D
comes out at half amplitude) and misplaces them when upsampling. The native backend writes the kept modes into
the output grid's spectrum instead. The default is therefore ``backend="native"`` (also so that a checkpoint
loads whether or not the optional extra is installed); ``"neuralop"``/``"auto"`` select the library.

Odd grid sizes: each layer rounds size * scaling (paper 127 -> 64 -> 32 -> 32 -> 64 -> 128 -> 127); skips
are resampled to the receiving layer's grid and the last layer returns the input grid. Modes beyond a
coarse grid are dropped at that layer.
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass

import torch
from torch import nn

from nemsim.baselines.common import ControlField, check_inputs
from nemsim.baselines.fno import Backend, resolve_backend


@dataclass(frozen=True)
class UNOConfig:
    hidden: int = 8  # lifting width
    out_channels: tuple[int, ...] = (8, 16, 32, 32, 32, 16, 8)  # output width of each of the seven layers
    scalings: tuple[float, ...] = (1.0, 0.5, 0.5, 1.0, 2.0, 2.0, 1.0)  # resolution factor of each layer
    n_modes: tuple[int, int, int] = (8, 8, 7)  # neuralop convention: 4x4x4 corner blocks
    lifting_channels: int = 16
    projection_channels: int = 16
    control_channels: int = 8
    backend: Backend = "native"
    residual: bool = True


class UNO3d(nn.Module):
    def __init__(self, cfg: UNOConfig = UNOConfig()) -> None:
        super().__init__()
        n = len(cfg.out_channels)
        if len(cfg.scalings) != n:
            raise ValueError(f"scalings has {len(cfg.scalings)} entries for {n} layers: {cfg.scalings}")
        self.cfg = cfg
        self.backend = resolve_backend(cfg.backend)
        self.control = ControlField(cfg.control_channels)
        c_in = 2 + cfg.control_channels
        skips = {n - i - 1: i for i in range(n // 2)}
        if self.backend == "neuralop":
            from neuralop.models import UNO

            # neuralop 2.0's UNO.__init__ prints its skip settings; keep library output on logging only.
            with contextlib.redirect_stdout(io.StringIO()):
                self.op = UNO(
                    in_channels=c_in, out_channels=2, hidden_channels=cfg.hidden,
                    lifting_channels=cfg.lifting_channels, projection_channels=cfg.projection_channels,
                    n_layers=n, uno_out_channels=list(cfg.out_channels),
                    uno_n_modes=[list(cfg.n_modes)] * n, uno_scalings=[[s, s, s] for s in cfg.scalings],
                    horizontal_skips_map=skips, fno_skip="linear", horizontal_skip="linear",
                    channel_mlp_skip="linear",
                )
        else:
            from nemsim.baselines.spectral import NativeUNO

            self.op = NativeUNO(c_in, 2, cfg.hidden, tuple(cfg.out_channels), (*cfg.n_modes,),
                                tuple(cfg.scalings), skips, cfg.lifting_channels, cfg.projection_channels)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        check_inputs(x, u)
        D, H, W = x.shape[-3:]
        out = self.op(torch.cat([x, self.control(u.to(x.dtype), (D, H, W))], dim=1))  # (B, 2, D, H, W)
        return x + out if self.cfg.residual else out
