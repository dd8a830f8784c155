"""The compiled Event Rules Library held as fixed model buffers ([supp_rule_schema], "Validation and
Immutability": R, Φ, α⁰, R^mech, W^src, W^sink, s^dep are registered as fixed buffers, never parameters).

``RuleBuffers`` registers every tensor of ``RuleTensors.torch_buffers()`` as a persistent buffer, so the
library moves with ``.to(device)``, is saved in the state dict, and is never touched by the optimizer. It is
passed as the ``rules`` argument of ``nemsim.rules.kinetics`` (attribute access, item access and
``torch_buffers()`` all work), so the model evaluates the one shared kinetics module on its own buffers.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn


class RuleBuffers(nn.Module):
    """Fixed compiled-rule tensors (E events, S species) as buffers; non-tensor metadata as attributes."""

    def __init__(self, rules) -> None:
        super().__init__()
        for key, value in rules.torch_buffers().items():
            self.register_buffer(key, torch.as_tensor(value).clone())
        self.names = tuple(str(n) for n in getattr(rules, "names", ()))
        self.sha256 = str(getattr(rules, "sha256", ""))

    if TYPE_CHECKING:  # for the type checker: every registered attribute is a buffer

        def __getattr__(self, name: str) -> torch.Tensor: ...

    def __getitem__(self, key: str) -> torch.Tensor:
        return getattr(self, key)

    def __contains__(self, key: str) -> bool:
        return key in self._buffers

    def keys(self):
        return self._buffers.keys()

    def torch_buffers(self, dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
        """The buffers as a dict (floating ones cast to ``dtype`` if given), as RuleTensors.torch_buffers."""
        if dtype is None:
            return dict(self._buffers)  # type: ignore[arg-type]
        return {k: (v.to(dtype) if v.is_floating_point() else v) for k, v in self._buffers.items()}  # type: ignore[misc, union-attr]

    @property
    def n_events(self) -> int:
        return int(self.phi.shape[0])  # E
