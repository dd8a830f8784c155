"""FNO baseline in 3-D ([supp_baselines], tab:supp_baseline_impl; Li et al. 2021).

"3D Fourier layers operate along all three spatial dimensions, with a pointwise residual path in each
operator block. A projected control field is broadcast and concatenated with the input state before lifting.
Width 14, four Fourier blocks, and 6 x 6 x 6 retained modes." 1.358 M.

Configured from neuraloperator's ``neuralop.models.FNO`` when the optional extra is installed
(``pip install nemsim[neuralop]``); otherwise ``nemsim.baselines.spectral.NativeFNO``, our re-implementation
of the same layout (same parameter count, different state-dict keys). Settings: in_channels = 2 (state) + 8
(control field Linear(14 -> 8)), neuralop's grid embedding adds the 3 coordinates; hidden 14; 4 layers;
n_modes = (12, 12, 11), i.e. frequencies -6..5 along D and H and 0..5 along W (rfft), Li et al.'s four 6x6x6
corner blocks; linear operator skip ("pointwise residual path"); neuralop defaults otherwise (lifting and
projection channel MLPs of ratio 2, channel MLP of expansion 0.5 with soft-gating skip, GELU, no padding).
Count: 1,357,912 (+120 control projection included), the paper's 1.358 M.

Choice where the paper is silent: no domain padding, although z is not periodic (x/y are, in the
simulator); the paper does not mention padding and padding does not change the count.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

from nemsim.baselines.common import ControlField, check_inputs

Backend = Literal["auto", "neuralop", "native"]


def resolve_backend(backend: str) -> str:
    """'auto' -> 'neuralop' if importable else 'native'. ValueError for an unknown or unavailable choice."""
    if backend not in ("auto", "neuralop", "native"):
        raise ValueError(f"backend must be one of ['auto', 'neuralop', 'native'], got {backend!r}")
    has = importlib.util.find_spec("neuralop") is not None
    if backend == "neuralop" and not has:
        raise ValueError(
            "backend='neuralop' but neuraloperator is not installed; pip install 'nemsim[neuralop]'"
        )
    if backend == "auto":
        return "neuralop" if has else "native"
    return backend


@dataclass(frozen=True)
class FNOConfig:
    width: int = 14  # hidden channels of the Fourier blocks
    n_layers: int = 4  # Fourier blocks
    n_modes: tuple[int, int, int] = (12, 12, 11)  # neuralop convention (see module docstring)
    control_channels: int = 8  # broadcast control field width
    backend: Backend = "native"  # "neuralop" (optional extra), "native", or "auto"
    residual: bool = True


class FNO3d(nn.Module):
    def __init__(self, cfg: FNOConfig = FNOConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.backend = resolve_backend(cfg.backend)
        self.control = ControlField(cfg.control_channels)
        c_in = 2 + cfg.control_channels
        if self.backend == "neuralop":
            from neuralop.models import FNO

            self.op = FNO(n_modes=tuple(cfg.n_modes), in_channels=c_in, out_channels=2,
                          hidden_channels=cfg.width, n_layers=cfg.n_layers, fno_skip="linear")
        else:
            from nemsim.baselines.spectral import NativeFNO

            self.op = NativeFNO(c_in, 2, cfg.width, (*cfg.n_modes,), cfg.n_layers)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        check_inputs(x, u)
        D, H, W = x.shape[-3:]
        out = self.op(torch.cat([x, self.control(u.to(x.dtype), (D, H, W))], dim=1))  # (B, 2, D, H, W)
        return x + out if self.cfg.residual else out
