"""An exponential moving average of the trained weights (``TrainConfig.ema_decay``; not in the paper).

Why: a rolled-out surrogate is judged on 100 chained calls, and the weights of a single optimizer step carry
that step's noise into every call, and validation scores move from one round to the next at a constant
learning rate (docs/experiments.md). The average
of the recent weights is the usual remedy (Polyak averaging; the "EMA" of diffusion and neural-operator
training): it smooths that noise without changing the loss or the optimizer.

What the run does with it (``nemsim.training.loop``): after every optimizer step
``avg <- avg + (1 - d_n) (w - avg)``, with ``d_n = min(decay, (1 + n) / (10 + n))`` after n updates, so
the average follows the weights closely at first and forgets the starting point within a few hundred
steps. Validation rolls out the averaged weights, so ``best.pt`` holds the best average; ``last.pt``
holds the raw weights (what the optimizer continues from) and the average in its ``train_state``, and a
resumed run carries both on.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch
from torch import nn


class WeightAverage:
    """The moving average of ``model``'s trainable parameters (fp32 copies, in ``parameters()`` order)."""

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.params = [p for p in model.parameters() if p.requires_grad]
        self.shadow: list[torch.Tensor] = []
        self.updates = 0
        self.reset()

    def reset(self) -> None:
        """Start the average at the current weights (a fresh run, or a resumed run that kept none)."""
        self.shadow = [p.detach().float().clone() for p in self.params]
        self.updates = 0

    def rate(self) -> float:
        """The decay of the next update: ``min(decay, (1 + n) / (10 + n))`` after n updates."""
        n = self.updates
        return min(self.decay, (1.0 + n) / (10.0 + n))

    @torch.no_grad()
    def update(self) -> None:
        """Move the average towards the current weights (call after each optimizer step)."""
        weight = 1.0 - self.rate()
        for avg, p in zip(self.shadow, self.params, strict=True):
            avg.lerp_(p.detach().float(), weight)
        self.updates += 1

    @contextmanager
    @torch.no_grad()
    def applied(self) -> Iterator[None]:
        """Inside the block the model holds the averaged weights; the trained ones come back after it."""
        saved = [p.detach().clone() for p in self.params]
        for p, avg in zip(self.params, self.shadow, strict=True):
            p.copy_(avg)
        try:
            yield
        finally:
            for p, w in zip(self.params, saved, strict=True):
                p.copy_(w)

    def state_dict(self) -> dict[str, Any]:
        return {"decay": self.decay, "updates": self.updates, "shadow": [t.clone() for t in self.shadow]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        shadow = state["shadow"]
        if len(shadow) != len(self.params) or any(
                s.shape != p.shape for s, p in zip(shadow, self.params, strict=True)):
            raise ValueError("the stored weight average does not fit the model's parameters")
        self.shadow = [s.to(device=p.device, dtype=torch.float32).clone()
                       for s, p in zip(shadow, self.params, strict=True)]
        self.updates = int(state["updates"])
