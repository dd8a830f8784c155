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

Quarter-domain models (``model.config.domain == "quarter"``, ``nemsim.symmetry``): the rollout runs on the
lower quadrant of x_0 (every call, the monotone projection and the buffers a quarter of the size) and returns
the full fields rebuilt by reflection, exactly symmetric (the quadrant starts from the symmetric mean of x_0
and each call's states are averaged with their transpose, the diagonal mirror); ``on_step`` sees full
fields. A cross-section model (``domain == "section"``, a trench) the same on its cross-section (each call's
rows averaged), returning the full fields repeated along the line.

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

from nemsim.model.monotone import projection_of
from nemsim.model.unpack import Finish
from nemsim.symmetry import FieldFold, model_fold

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
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """Roll a one-step model forward from x0.

    Args:
        model: forward(x (B,2,D,H,W), u (B,14)) -> x_next (B,2,D,H,W); or a NEMSim-like model with
            precompute/step (and predict for steps_per_call > 1, see the module docstring).
        x0: (B, 2, D, H, W) initial states (ground truth at step 0).
        u: (B, T, 14) normalized controls per transition, or (B, 14) for a constant control
            (then ``steps`` is required).
        steps: number of transitions to run (default T); must be <= T when u is (B, T, 14).
        keep: return the whole trajectory; False: only the last state (memory of two calls' states).
        on_step: called as on_step(t, x̂_t) for t = 1..steps; x̂_t is a view of the rollout's buffer, valid
            (with keep=False) until on_step(t + 1) has returned.
        window: compute each call on the depth slab that can change (``nemsim.model.window``; NEMSim only;
            within a tolerance of the full rollout, off by default: see there).
        stats: if given, filled with {"calls", "full_calls", "fraction_computed", "start"} of the window
            (``fraction_computed`` = mean share of the voxels computed per call), or {"calls"} without one.
        monotone: project every predicted state onto x >= (running maximum) - eps (``nemsim.model.monotone``).
            None (default): the model's ``config.monotone_eps`` (NEMSim: on; baselines: off); True / False.
        out: optional (B, >= steps + 1, 2, D, H, W) buffer (x0's dtype and device) the trajectory is written
            into and returned from (its first steps + 1 states), so a caller running many rollouts reuses
            one allocation; only with keep=True.

    Returns:
        (B, steps + 1, 2, D, H, W) with x0 first, or (B, 2, D, H, W) (the last state) if keep=False.
        Same device and dtype as x0.

    How (speed, same values): the states are written in place into one preallocated trajectory buffer (or,
    with keep=False, into two alternating buffers of one call's states): a predictor with ``predict_into``
    (``nemsim.inference.runtime``) writes its output there directly, others are copied once; the monotone
    projection runs in place on the buffer; the next call reads its input state from the buffer.
    """
    if x0.ndim != 5:
        raise ValueError(f"x0 must be (B, 2, D, H, W), got shape {tuple(x0.shape)}")
    f = model_fold(model)
    if f is not None and f.is_full(x0):  # a quarter- or section-domain model: roll the folded field
        on_q = None if on_step is None else (lambda t, xq, g=f: on_step(t, g.unfold(xq)))
        return on_quadrant(x0, f, lambda xq: rollout(model, xq, u, steps, keep=keep, on_step=on_q,
                                                     window=window, stats=stats, monotone=monotone),
                           keep, out)
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
        if f is not None:
            raise ValueError(f"window=True is not available for a {f.kind}-domain model (its depth window "
                             "records full-width statistics); roll it out without the window")
        depth_window = DepthWindow(model)
    project = projection_of(model, x0, monotone)
    folded = f.kind if f is not None else None  # x0 is a folded model's quadrant or cross-section
    traj = _trajectory_buffer(x0, T, keep, out)  # (B, T+1, 2, D, H, W) or None
    # keep=False: two buffers of one call's states, alternating, so the previous call's states stay valid
    # while this call's are predicted (the next input, and on_step's contract)
    spare = None if keep else [x0.new_empty((B, k, *x0.shape[1:])) for _ in range(2)]
    into = getattr(model, "predict_into", None) if fast and depth_window is None else None
    # each call's states: the fold's mean (diagonal, rows) where ``predict`` has not taken it, then projected
    late = into is not None or not fast
    finish = Finish(folded == "quarter" and late, project, rows=folded == "section" and late)
    cache = None
    x = x0
    t = calls = 0
    while t < T:
        n = _chunk_length(changed, t, k, T) if fast else 1
        dst = traj[:, t + 1 : t + 1 + n] if traj is not None else spare[calls % 2][:, :n]  # type: ignore[index]
        calls += 1
        if not fast:
            dst[:, 0] = model(x, u[:, t])  # (B, 2, D, H, W)
            finish.apply_(dst)
        else:
            if changed[t]:
                cache = model.precompute(u[:, t])  # type: ignore[operator]
            if into is not None:  # (B, n, 2, D, H, W) written and finished in place, in one pass
                into(x, cache, dst, finish)
            elif depth_window is not None:
                finish.apply_(dst.copy_(depth_window.predict(x, cache)[:, :n]))  # type: ignore[arg-type]
            elif k == 1:
                dst[:, 0] = model.step(x, cache)  # type: ignore[operator]
                finish.apply_(dst)
            else:
                finish.apply_(dst.copy_(model.predict(x, cache)[:, :n]))  # type: ignore[operator]
        for j in range(n):
            x = dst[:, j]  # (B, 2, D, H, W)
            t += 1
            if on_step is not None:
                on_step(t, x)
    if stats is not None:
        stats.update(depth_window.stats() if depth_window is not None else {"calls": calls})
    if traj is not None:
        return traj
    return x


def on_quadrant(x0: torch.Tensor, f: FieldFold, roll: Callable[[torch.Tensor], torch.Tensor],
                keep: bool = True, out: torch.Tensor | None = None) -> torch.Tensor:
    """A folded rollout from full fields x0 (B, 2, D, n, n): ``roll`` runs on the folded part (``f``) of
    x0's symmetric mean and returns (B, T+1, 2, D, h, w) (or the last state with ``keep`` False); the result
    is unfolded to full fields (into ``out`` when given), x0 itself first (module docstring)."""
    res = roll(f.fold(f.symmetrize(x0)).contiguous())
    if not keep:
        return f.unfold(res)
    if out is not None and out.shape[1] < res.shape[1]:
        raise ValueError(f"out must hold {res.shape[1]} states, got {tuple(out.shape)}")
    full = f.unfold(res, None if out is None else out[:, : res.shape[1]])
    full[:, 0] = x0  # x̂_0 is the given x_0 (the quadrant holds its symmetric mean)
    return full


def _trajectory_buffer(x0: torch.Tensor, T: int, keep: bool, out: torch.Tensor | None) -> torch.Tensor | None:
    """The (B, T+1, 2, D, H, W) buffer a kept trajectory is written into, x0 first (``rollout``'s ``out``)."""
    if out is None:
        if not keep:
            return None
        traj = x0.new_empty((x0.shape[0], T + 1, *x0.shape[1:]))
    else:
        if not keep:
            raise ValueError("out= needs keep=True (keep=False returns only the last state)")
        want = (x0.shape[0], T + 1, *x0.shape[1:])
        if (out.dim() != 6 or out.shape[0] != want[0] or out.shape[1] < want[1]
                or tuple(out.shape[2:]) != want[2:]):
            raise ValueError(f"out must be (B, >= T+1, 2, D, H, W) = {want}, got {tuple(out.shape)}")
        if out.dtype != x0.dtype or out.device != x0.device:
            raise ValueError(f"out must be {x0.dtype} on {x0.device} like x0, "
                             f"got {out.dtype} on {out.device}")
        traj = out[:, : T + 1]
    traj[:, 0] = x0
    return traj


def steps_per_call(model: nn.Module) -> int:
    """k, the states one call of ``model`` predicts: ``model.config.steps_per_call`` if the model has
    ``predict``, else 1 (as ``runtime.model_predict`` calls it)."""
    if not callable(getattr(model, "predict", None)):
        return 1
    return int(getattr(getattr(model, "config", None), "steps_per_call", 1) or 1)


def _chunk_length(changed: list[bool], t: int, k: int, T: int) -> int:
    """Transitions covered by the call at step t: up to k, not past T, not past the next control change."""
    n = 1
    while n < k and t + n < T and not changed[t + n]:
        n += 1
    return n
