"""Data-driven baselines adapted to 3-D, and their RuleFeat (+Prior) variants ([supp_baselines],
tab:supp_baseline_impl; [supp_rulefeat], eq:rulefeat).

Every model keeps the shared contract ``forward(x (B, 2, D, H, W), u (B, 14) normalized) -> x_next`` and has a
frozen config dataclass whose defaults are the paper's configuration. Registered (by ``nemsim.registry``,
which sits above this package) under:

  name            class        config           trainable params at any scene (paper)
  convlstm        ConvLSTM3d   ConvLSTMConfig     634,098   (0.634 M)
  fno             FNO3d        FNOConfig        1,357,912   (1.358 M)
  uno             UNO3d        UNOConfig        2,440,378   (2.432 M)
  cno             CNO3d        CNOConfig        1,733,908   (1,733,908)
  deeponet        DeepONet3d   DeepONetConfig   1,721,202   (1,720,162)
  cno-prior       CNO3d        rulefeat=True    1,750,876   (1,750,876)
  deeponet-prior  DeepONet3d   rulefeat=True    1,736,914   (1,735,874; delta +15,712 as the paper)

Complex Fourier weights count as two reals (``nemsim.evaluation.metrics.count_params``). None of the counts
depends on the scene: every layer is convolutional, spectral with fixed modes, or follows an adaptive pooling.
"""

from __future__ import annotations

from nemsim.baselines.cno import CNO3d, CNOConfig
from nemsim.baselines.convlstm import ConvLSTM3d, ConvLSTMConfig
from nemsim.baselines.deeponet import DeepONet3d, DeepONetConfig
from nemsim.baselines.fno import FNO3d, FNOConfig
from nemsim.baselines.rulefeat import RuleFeat
from nemsim.baselines.uno import UNO3d, UNOConfig

__all__ = [
    "CNO3d", "CNOConfig", "ConvLSTM3d", "ConvLSTMConfig", "DeepONet3d", "DeepONetConfig",
    "FNO3d", "FNOConfig",
    "RuleFeat", "UNO3d", "UNOConfig",
]

