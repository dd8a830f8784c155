"""NEMSim model: State Encoder, EIC, MAC, MRC, residual decoder.

Paper: Method section (eq:se ... eq:decoder) and [supp_eic], [supp_mac], [supp_mrc], [supp_training].

Shape letters (declared once for the whole package; every reshape is commented with them):
  B  batch
  T  time steps (rollouts)
  C  channels (state: C = 2, mask and Si; latent: C = 18)
  D, H, W  depth (z), height (y), width (x) voxels of the padded, transposed state; lower-case d, h, w
     are the same axes of the coarse latent grid (1/4 resolution)
  E  events of the compiled rule library (37)
  S  product / projectile species of the rule vocabulary (8)
  M  mechanism families (3: physical, chemical, coupled)
  R  response modes per family (R_b = 4)
  U  controls (14, normalized to [-1, 1])
  K  feature width of a small MLP (context, hidden)

Modules: ``encoder`` (State Encoder), ``eic`` (Event Intensity Compiler), ``mac`` (Mechanism Attribution
Compiler), ``mrc`` (Mechanism Response Compiler), ``decoder`` (State Increment Decoder), ``surrogate``
(``NEMSim`` composition and ``NEMSimConfig``). Models are built by name through ``nemsim.registry``.
"""

from nemsim.model.surrogate import NEMSim, NEMSimConfig

__all__ = ["NEMSim", "NEMSimConfig"]
