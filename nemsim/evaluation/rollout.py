"""The autoregressive rollout protocol of [supp_protocols] (eq. supp_autoregressive_rollout).

x̂_0 = x_0 (ground truth), x̂_{t+1} = G_θ(x̂_t, u_t) for t = 0..T-1. Every prediction is fed back as it
is: no teacher forcing, no correction, no reinitialization, no clipping of states or controls -- except
the monotone projection of a model that asks for it (``monotone``; ``nemsim.model.monotone``): each
predicted state is lifted to at least its running maximum minus a per-channel slack, because etching only
removes material. It is part of the model's prediction (the next call reads the projected state).
Controls may vary per transition (a recipe); a constant control is the same vector repeated.

Fast path ("model only what a scene needs"): a model with ``precompute(u) -> cache`` and
``step(x, cache) -> x_next`` (NEMSim) gets its control-only part (rule kinetics, static anchor, MRC
signature) computed once per distinct control vector instead of once per step; the prediction is the same
as ``model(x, u_t)`` (same operations). Other models are called as ``model(x, u_t)``.

Multi-step models (``model.config.steps_per_call`` = k > 1, with ``predict(x, cache) -> (B, k, 2, D, H, W)``):
one call yields the next k states, and every state is still returned (and passed to ``on_step``). A call
("chunk") predicts its states under one control vector, so a chunk never spans a control change: it covers
min(k, transitions left, transitions until the controls next change) steps and keeps that many of its k
predictions. With constant controls that is ceil(T / k) calls; with a recipe, every state is predicted
under the controls of its own transition (at the cost of shorter chunks where the recipe changes). The
chunk boundaries are the same for every batch row (a change in any row splits all rows' chunks).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from nemsim.model.monotone import MonotoneProjection, projection_of

StepCallback = Callable[[int, torch.Tensor], None]


@torch.no_grad()
def rollout(
    model: nn.Module,
    x0: torch.Tensor,
    u: torch.Tensor,
    steps: int | None = None,
    *,
    keep: bool = True,
    on_step: StepCallback | None = None,
    window: bool = False,
    stats: dict[str, Any] | None = None,
    monotone: bool | None = None,
) -> torch.Tensor:
    """Roll a one-step model forward from x0.

    Args:
        model: forward(x (B,2,D,H,W), u (B,14)) -> x_next (B,2,D,H,W); or a NEMSim-like model with
            precompute/step (and predict for steps_per_call > 1, see the module docstring).
        x0: (B, 2, D, H, W) initial states (ground truth at step 0).
        u: (B, T, 14) normalized controls per transition, or (B, 14) for a constant control
            (then ``steps`` is required).
        steps: number of transitions to run (default T); must be <= T when u is (B, T, 14).
        keep: return the whole trajectory; with keep=False only the last state is returned
            (memory stays at one state -- use ``on_step`` to stream the others).
        on_step: called as on_step(t, x̂_t) for t = 1..steps with the freshly predicted state.
        window: compute each call on the depth slab that can change (``nemsim.model.window.DepthWindow``;
            NEMSim only); it agrees with the full rollout within a tolerance, not exactly, and measured no
            faster on ``small`` (see there): off by default.
        stats: if given, filled with {"calls", "full_calls", "fraction_computed", "start"} of the window
            (``fraction_computed`` = mean share of the voxels computed per call), or {"calls"} without one.
        monotone: project every predicted state onto x >= (running maximum) - eps
            (``nemsim.model.monotone.MonotoneProjection``). None (default) follows the model's
            ``config.monotone_eps`` (NEMSim: on; baselines: off); False: off; True: on (``MONOTONE_EPS``
            for a model without its own eps).

    Returns:
        (B, steps + 1, 2, D, H, W) with x0 first, or (B, 2, D, H, W) (the last state) if keep=False.
        Same device and dtype as x0.
    """
    if x0.ndim != 5:
        raise ValueError(f"x0 must be (B, 2, D, H, W), got shape {tuple(x0.shape)}")
    B = x0.shape[0]
    if u.ndim == 2:
        if steps is None:
            raise ValueError("a constant control u (B, 14) needs steps")
        u = u[:, None, :].expand(B, steps, u.shape[-1])  # (B, T, 14)
    if u.ndim != 3 or u.shape[0] != B:
        raise ValueError(f"u must be (B={B}, T, 14) or (B, 14), got shape {tuple(u.shape)}")
    T = u.shape[1] if steps is None else steps
    if T > u.shape[1]:
        raise ValueError(f"steps={T} exceeds the {u.shape[1]} control vectors supplied")
    u = u.to(device=x0.device, dtype=x0.dtype)
    traj = [x0] if keep else None
    x = x0
    fast = callable(getattr(model, "precompute", None)) and callable(getattr(model, "step", None))
    k = steps_per_call(model)
    # steps whose controls differ from the previous step's (recipes); one comparison up front
    changed = [True] + (u[:, 1:T] != u[:, : T - 1]).flatten(2).any(dim=2).any(dim=0).tolist() if fast else []
    depth_window = None
    if window:
        from nemsim.model.window import DepthWindow

        if not fast:
            raise ValueError(f"window=True needs a NEMSim model (precompute/predict); "
                             f"got {type(model).__name__}")
        depth_window = DepthWindow(model)
    project = _projection(model, x0, monotone)
    cache = None
    t = calls = 0
    while t < T:
        calls += 1
        if not fast:
            chunk = model(x, u[:, t])[:, None]  # (B, 1, 2, D, H, W)
        else:
            if changed[t]:
                cache = model.precompute(u[:, t])  # type: ignore[operator]
            if depth_window is not None:
                n = _chunk_length(changed, t, k, T)
                chunk = depth_window.predict(x, cache)[:, :n]  # type: ignore[arg-type]  # (B, n, 2, D, H, W)
            elif k == 1:
                chunk = model.step(x, cache)[:, None]  # type: ignore[operator]  # (B, 1, 2, D, H, W)
            else:
                n = _chunk_length(changed, t, k, T)
                chunk = model.predict(x, cache)[:, :n]  # type: ignore[operator]  # (B, n, 2, D, H, W)
        for j in range(chunk.shape[1]):
            x = chunk[:, j] if project is None else project(chunk[:, j])  # (B, 2, D, H, W)
            t += 1
            if keep:
                traj.append(x)  # type: ignore[union-attr]
            if on_step is not None:
                on_step(t, x)
    if stats is not None:
        stats.update(depth_window.stats() if depth_window is not None else {"calls": calls})
    if keep:
        return torch.stack(traj, dim=1)  # type: ignore[arg-type]  # (B, T+1, 2, D, H, W)
    return x


def _projection(model: nn.Module, x0: torch.Tensor, monotone: bool | None) -> MonotoneProjection | None:
    """The monotone projection of this rollout, or None (``rollout``'s ``monotone``)."""
    return projection_of(model, x0, monotone)


def steps_per_call(model: nn.Module) -> int:
    """k, the states one call of ``model`` predicts: ``model.config.steps_per_call`` if the model has
    ``predict``, else 1."""
    if not callable(getattr(model, "predict", None)):
        return 1
    return int(getattr(getattr(model, "config", None), "steps_per_call", 1))


def _chunk_length(changed: list[bool], t: int, k: int, T: int) -> int:
    """Transitions covered by the call at step t: up to k, not past T, not past the next control change."""
    n = 1
    while n < k and t + n < T and not changed[t + n]:
        n += 1
    return n
