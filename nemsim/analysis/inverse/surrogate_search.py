"""The surrogate search: recipes whose predicted profile meets an ``InverseSpec``.

In normalized control coordinates (eq:supp_control_normalization: log10 fluxes, the box [-1, 1] is the
training range), only over the free controls (``fixed`` ones are held), inside ``bounds`` (default the
training box):
  1. screening: ``screen`` scrambled-Sobol recipes, rolled out in batches without gradients (through the
     context's search runtime, ``InverseContext.final_states``), scored by the objective
     (``spec.objective``) on their exact metrics;
  2. refinement, ``method="adam"``: the ``starts`` best screened recipes (at least ``min_separation``
     apart) follow Adam on the soft metrics (``nemsim.geometry.soft_profile``) of a differentiable rollout,
     projected onto the bounds after every step, with a cosine learning-rate decay; every iterate's exact
     metrics join the candidate pool. ``method="cma"``: CMA-ES (the optional ``cma`` package) from the
     best screened recipe, one batched rollout per generation. ``"auto"`` picks CMA-ES when the package
     is installed (benchmarks/small/inverse compares the two), else Adam;
  3. the best distinct candidates get their integer controls rounded and are rolled out again; K are
     reported, ranked by (targets missed, objective plus the edge term: ``spec.search_score``, which
     every stage minimizes), with conformal intervals
     (``nemsim.analysis.intervals``) and a distance-to-training-data flag.

The reported metrics are always the exact ones (``nemsim.geometry.profile``) of a plain rollout. The spec is
``met`` when the best recipe's predicted metrics are all within tolerance, else ``unreachable`` (reported
with the closest recipe and its miss per target).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from nemsim.analysis.intervals import Calibration
from nemsim.analysis.inverse.context import InverseContext, rollout_to
from nemsim.analysis.inverse.spec import (
    InverseSpec,
    Progress,
    SearchCancelled,
    misses,
    objective,
    search_score,
    target_range,
)
from nemsim.controls import (
    CONTROL_NAMES,
    CONTROL_SPECS,
    INT_INDICES,
    N_CONTROLS,
    control_index,
    from_normalized,
    to_normalized,
)
from nemsim.geometry.profile import profile_metrics_batch
from nemsim.geometry.soft_profile import soft_profile_metrics


@dataclass
class _Pool:
    """Every evaluated recipe: normalized controls and exact metrics at the target step."""

    u: list[np.ndarray] = field(default_factory=list)
    metrics: list[dict[str, float]] = field(default_factory=list)

    def add(self, u: np.ndarray, metrics: dict[str, np.ndarray]) -> None:
        for i in range(u.shape[0]):
            self.u.append(np.array(u[i], dtype=np.float64))
            self.metrics.append({k: float(v[i]) for k, v in metrics.items()})

    def scores(self, spec: InverseSpec) -> np.ndarray:
        """The search score (``search_score``) of every recipe so far, (P,)."""
        return np.array([float(search_score(m, u, spec)) for m, u in zip(self.metrics, self.u, strict=True)])


@dataclass
class _Cost:
    forward_rollouts: int = 0
    gradient_rollouts: int = 0


def _box(spec: InverseSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi, free mask, fixed values) in normalized coordinates, (14,) each."""
    lo, hi = -np.ones(N_CONTROLS), np.ones(N_CONTROLS)
    for name, (a, b) in spec.bounds.items():
        j = control_index(name)
        row = np.asarray(from_normalized(np.zeros(N_CONTROLS)), dtype=np.float64)
        pair = np.stack([row, row])
        pair[:, j] = (a, b)
        lo[j], hi[j] = np.asarray(to_normalized(pair))[:, j]
    free = np.ones(N_CONTROLS, dtype=bool)
    fixed = np.zeros(N_CONTROLS)
    if spec.fixed:
        row = np.asarray(from_normalized(np.zeros(N_CONTROLS)), dtype=np.float64)
        for name, v in spec.fixed.items():
            row[control_index(name)] = v
        norm = np.asarray(to_normalized(row))
        for name in spec.fixed:
            j = control_index(name)
            free[j] = False
            fixed[j] = norm[j]
            lo[j] = hi[j] = norm[j]
    return lo, hi, free, fixed


def _round_ints(u: np.ndarray) -> np.ndarray:
    """Normalized controls (B, 14) with the integer controls rounded in physical units."""
    raw = np.asarray(from_normalized(np.asarray(u, dtype=np.float64)))
    for j in INT_INDICES:
        raw[:, j] = np.clip(np.round(raw[:, j]), CONTROL_SPECS[j].phys_min, None)
    return np.asarray(to_normalized(raw))


class _Evaluator:
    """No-gradient batched rollouts to the target step, with exact metrics, counted."""

    def __init__(self, ctx: InverseContext, step: int, batch: int, cost: _Cost, check: Callable[[], None]):
        self.ctx, self.step, self.batch, self.cost, self.check = ctx, step, batch, cost, check

    def __call__(self, u: np.ndarray, done: Callable[[int], None] | None = None) -> dict[str, np.ndarray]:
        """Exact metrics {name: (B,)} of u (B, 14); done(recipes rolled out so far) after every batch."""
        out: dict[str, list[np.ndarray]] = {}
        for s in range(0, len(u), self.batch):
            self.check()
            ub = torch.as_tensor(u[s : s + self.batch], dtype=torch.float32)
            x = self.ctx.final_states(ub, self.step)
            self.cost.forward_rollouts += len(ub)
            for k, v in profile_metrics_batch(x.numpy(), self.ctx.scene).items():
                out.setdefault(k, []).append(v)
            if done is not None:
                done(s + len(ub))
        return {k: np.concatenate(v) for k, v in out.items()}


def _pick_distinct(order: Sequence[int], points: Sequence[np.ndarray], n: int, sep: float) -> list[int]:
    chosen: list[int] = []
    for i in order:
        if all(np.linalg.norm(points[i] - points[j]) >= sep for j in chosen):
            chosen.append(i)
        if len(chosen) == n:
            break
    return chosen


@dataclass(frozen=True)
class LocalRegion:
    """Restricts a search to a trust region: the box of half-width ``radius`` (normalized units) around
    ``anchor`` (14,), intersected with the spec's bounds; the ``warm`` recipes (W, 14) are evaluated
    (clipped into the region) beside the quasi-random screening. Used by the simulator-corrected rounds
    (``nemsim.analysis.inverse.refine``), where a metric offset measured at the anchor is only trusted
    nearby."""

    anchor: np.ndarray  # (14,) normalized
    radius: float
    warm: np.ndarray  # (W, 14) normalized


def search(
    ctx: InverseContext,
    spec: InverseSpec,
    *,
    seed: int = 0,
    on_progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
    local: LocalRegion | None = None,
) -> dict[str, Any]:
    """Find recipes for ``spec`` (module docstring). Returns the JSON-ready result (see ``run_inverse``).

    With ``local`` the search stays inside that trust region and starts from its warm recipes.
    """
    from scipy.stats import qmc

    t0, c0 = time.perf_counter(), time.process_time()
    cfg = spec.search
    step = spec.step or ctx.scene.n_transitions
    if step > ctx.scene.n_transitions:
        raise ValueError(
            f"step = {step} is beyond the model's horizon of {ctx.scene.n_transitions} transitions"
        )
    progress = on_progress or (lambda f, m: None)

    def check() -> None:
        if should_stop is not None and should_stop():
            raise SearchCancelled

    if cfg.method == "auto":
        cfg = replace(cfg, method="cma" if _has_cma() else "adam")
        spec = replace(spec, search=cfg)
    lo, hi, free, fixed = _box(spec)
    if local is not None:
        if not local.radius > 0:
            raise ValueError(f"the trust-region radius must be > 0, got {local.radius:g}")
        a = np.asarray(local.anchor, dtype=np.float64)
        lo = np.where(free, np.maximum(lo, a - local.radius), lo)
        hi = np.where(free, np.maximum(np.minimum(hi, a + local.radius), lo), hi)
    cost = _Cost()
    evaluate = _Evaluator(ctx, step, cfg.batch, cost, check)
    pool = _Pool()
    n_free = int(free.sum())

    # 1. screening
    if n_free:
        with warnings.catch_warnings():  # any screen size, not only powers of 2
            warnings.simplefilter("ignore", UserWarning)
            sob = qmc.Sobol(d=n_free, scramble=True, seed=seed).random(cfg.screen)  # (N, F) in [0, 1)
    else:
        sob = np.zeros((1, 0))
    u_screen = np.tile(fixed, (len(sob), 1))
    u_screen[:, free] = lo[free] + sob * (hi[free] - lo[free])
    if local is not None and len(local.warm):
        warm = np.clip(np.asarray(local.warm, dtype=np.float64).reshape(-1, N_CONTROLS), lo, hi)
        warm[:, ~free] = fixed[~free]
        u_screen = np.concatenate([warm, u_screen])  # (W + N, 14)
    n = len(u_screen)
    progress(0.0, f"screening: 0/{n} recipes rolled out")
    m_screen = evaluate(u_screen, lambda k: progress(0.25 * k / n, f"screening: {k}/{n} recipes rolled out"))
    pool.add(u_screen, m_screen)
    trace = [round(float(np.min(objective(m_screen, spec))), 4)]  # best objective per stage/iteration
    progress(0.25, "screened")

    # 2. refinement
    if n_free and cfg.method == "adam" and cfg.iterations > 0:
        _adam(ctx, spec, step, pool, cost, lo, hi, free, check, progress, trace)
    elif n_free and cfg.method == "cma":
        _cma(evaluate, spec, pool, lo, hi, free, fixed, seed, check, progress, trace)

    # 3. candidates: round integer controls, roll out again, rank
    scores = pool.scores(spec)
    order = list(np.argsort(scores))
    picks = _pick_distinct(order, pool.u, max(spec.k + 2, 2 * spec.k), cfg.min_separation / 4)
    u_final = _round_ints(np.stack([pool.u[i] for i in picks]))
    u_final[:, ~free] = fixed[~free]  # rounding must not move a fixed control
    progress(0.9, "re-evaluating the best recipes")
    recipes = _final_recipes(ctx, spec, step, u_final, cost, check)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    best = recipes[0]
    status = "met" if all(v["met"] for v in best["targets"].values()) else "unreachable"
    return {
        "status": status,
        "message": _status_message(status, best),
        "step": step,
        "time_s": round(step * float(ctx.scene.snapshot_dt_s), 6),
        "recipes": recipes,
        "cost": {
            "method": cfg.method,
            "forward_rollouts": cost.forward_rollouts,
            "gradient_rollouts": cost.gradient_rollouts,
            "rollouts": cost.forward_rollouts + cost.gradient_rollouts,
            "wall_s": round(wall, 3),
            "cpu_s": round(cpu, 3),
            "objective_trace": trace,
        },
        "model_id": ctx.model_id,
        "intervals": _interval_note(ctx),
    }


def _adam(
    ctx: InverseContext,
    spec: InverseSpec,
    step: int,
    pool: _Pool,
    cost: _Cost,
    lo: np.ndarray,
    hi: np.ndarray,
    free: np.ndarray,
    check: Callable[[], None],
    progress: Progress,
    trace: list[float],
) -> None:
    cfg = spec.search
    scores = pool.scores(spec)
    starts = _pick_distinct(list(np.argsort(scores)), pool.u, cfg.starts, cfg.min_separation)
    u0 = torch.as_tensor(np.stack([pool.u[i] for i in starts]), dtype=torch.float32)  # (S, 14)
    lo_t, hi_t = torch.as_tensor(lo, dtype=torch.float32), torch.as_tensor(hi, dtype=torch.float32)
    mask = torch.as_tensor(free)
    p = u0.clone().requires_grad_(True)
    opt = torch.optim.Adam([p], lr=cfg.lr)
    for it in range(cfg.iterations):
        check()
        for group in opt.param_groups:  # cosine decay to a tenth
            group["lr"] = cfg.lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * it / max(cfg.iterations, 1))))
        x = rollout_to(ctx.model, ctx.x0, p, step)  # (S, 2, D, H, W)
        cost.gradient_rollouts += p.shape[0]
        soft = soft_profile_metrics(x, ctx.scene)
        loss = search_score(soft, p, spec)
        exact = profile_metrics_batch(x.detach().numpy(), ctx.scene)
        pool.add(p.detach().numpy(), exact)
        trace.append(round(float(np.min(objective(exact, spec))), 4))
        # gradient with respect to the controls only: the model's parameters (shared with the service's
        # rollouts) never accumulate .grad
        (grad,) = torch.autograd.grad(loss.sum(), [p])
        p.grad = grad.masked_fill(~mask[None, :], 0.0)
        opt.step()
        with torch.no_grad():
            p.copy_(torch.maximum(torch.minimum(p, hi_t), lo_t))
        progress(0.25 + 0.65 * (it + 1) / cfg.iterations, f"gradient step {it + 1}/{cfg.iterations}")
    check()
    with torch.no_grad():  # the last iterate
        x = rollout_to(ctx.model, ctx.x0, p, step)
    cost.forward_rollouts += p.shape[0]
    pool.add(p.detach().numpy(), profile_metrics_batch(x.numpy(), ctx.scene))


def _has_cma() -> bool:
    import importlib.util

    return importlib.util.find_spec("cma") is not None


def _cma(
    evaluate: _Evaluator,
    spec: InverseSpec,
    pool: _Pool,
    lo: np.ndarray,
    hi: np.ndarray,
    free: np.ndarray,
    fixed: np.ndarray,
    seed: int,
    check: Callable[[], None],
    progress: Progress,
    trace: list[float],
) -> None:
    try:
        import cma
    except ImportError:
        raise ValueError(
            "search.method 'cma' needs the optional package cma (pip install 'nemsim[design]')"
        ) from None
    cfg = spec.search
    scores = pool.scores(spec)
    x0 = pool.u[int(np.argmin(scores))][free]
    es = cma.CMAEvolutionStrategy(
        x0,
        cfg.cma_sigma,
        {
            "bounds": [lo[free].tolist(), hi[free].tolist()],
            "seed": seed + 1,
            "verbose": -9,
            "popsize": cfg.batch,
            "maxfevals": cfg.cma_evals,
        },
    )
    used = 0
    while not es.stop() and used < cfg.cma_evals:
        check()
        xs = np.asarray(es.ask())  # (P, F)
        u = np.tile(fixed, (len(xs), 1))
        u[:, free] = np.clip(xs, lo[free], hi[free])
        m = evaluate(u)
        pool.add(u, m)
        scores = search_score(m, u, spec)  # (P,)
        es.tell(list(xs), [float(v) for v in scores])
        trace.append(round(float(np.min(objective(m, spec))), 4))
        used += len(xs)
        progress(0.25 + 0.65 * min(used / cfg.cma_evals, 1.0), f"CMA-ES {used}/{cfg.cma_evals} rollouts")


def _final_recipes(
    ctx: InverseContext, spec: InverseSpec, step: int, u: np.ndarray, cost: _Cost, check: Callable[[], None]
) -> list[dict[str, Any]]:
    """Roll the candidates out over the whole trajectory (exact metrics per step), rank and describe."""
    from nemsim.evaluation.rollout import rollout

    check()
    ub = torch.as_tensor(u, dtype=torch.float32)
    with torch.no_grad():
        traj = rollout(ctx.model, ctx.x0[None].expand(len(ub), *ctx.x0.shape).contiguous(), ub, step)
    cost.forward_rollouts += len(ub)
    out: list[tuple[tuple[int, float], dict[str, Any]]] = []  # (rank key, recipe)
    for i in range(len(ub)):
        mt = profile_metrics_batch(traj[i].numpy(), ctx.scene)  # {name: (step + 1,)}
        at = {k: float(v[step]) for k, v in mt.items()}
        raw = np.asarray(from_normalized(u[i].astype(np.float64)))
        for j in INT_INDICES:
            raw[j] = float(round(raw[j]))
        rec: dict[str, Any] = {
            "controls": {n: float(v) for n, v in zip(CONTROL_NAMES, raw, strict=True)},
            "controls_normalized": [round(float(v), 5) for v in u[i]],
            "predicted": {k: round(v, 3) for k, v in at.items()},
            "targets": misses(at, spec),
            "objective": round(float(objective(at, spec)), 5),
            "intervals": _intervals_at(ctx.calibration, at, step, ctx.scene),
            "training_data": ctx.support.describe(u[i]),
        }
        missed = sum(not v["met"] for v in rec["targets"].values())
        out.append(((missed, float(search_score(at, u[i], spec))), rec))
    out.sort(key=lambda kr: kr[0])
    keep: list[dict[str, Any]] = []
    for _, r in out:
        pts = np.asarray(r["controls_normalized"])
        if all(np.linalg.norm(pts - np.asarray(q["controls_normalized"])) > 1e-6 for q in keep):
            keep.append(r)
    for rank, r in enumerate(keep[: spec.k], 1):
        r["rank"] = rank
    return keep[: spec.k]


def _intervals_at(
    cal: Calibration | None, at: dict[str, float], step: int, scene: Any
) -> dict[str, Any] | None:
    """{level: {metric: [lo, hi]}} at the target step, None without a calibration. Each interval is cut to
    the metric's physical range in ``scene`` (``target_range``: no depth beyond the Si thickness, no
    negative width), an unbounded side included."""
    if cal is None:
        return None
    s = min(step, cal.steps)
    out: dict[str, Any] = {}
    for level in cal.levels:
        per: dict[str, list[float]] = {}
        for m in cal.metrics:
            if m not in at:
                continue
            lo, hi = cal.interval(m, s, at[m], level)
            low, high, _ = target_range(m, scene)
            lo = low if lo is None else min(max(lo, low), high)
            hi = high if hi is None else min(max(hi, low), high)
            per[m] = [round(lo, 3), round(hi, 3)]
        out[f"{level:g}"] = per
    return out


def _interval_note(ctx: InverseContext) -> dict[str, Any]:
    cal = ctx.calibration
    if cal is None:
        return {"available": False, "reason": "no calibration file for this checkpoint (nemsim calibrate)"}
    cov = (cal.test_coverage or {}).get("coverage") or {}
    return {
        "available": True,
        "levels": list(cal.levels),
        "method": cal.calibration.get("method"),
        "calibrated_on": f"{cal.calibration.get('cases')} {cal.calibration.get('split')} cases "
        f"({cal.calibration.get('setting')})",
        "test_coverage": {k: v.get("all") for k, v in cov.items()},
    }


def _status_message(status: str, best: dict[str, Any]) -> str:
    if status == "met":
        return "the top recipe's predicted metrics meet every target within its tolerance"
    missed = {k: v for k, v in best["targets"].items() if not v["met"]}
    parts = ", ".join(
        f"{k} {v['value']:.1f} nm (target {v['target']:g} +- {v['tol']:g}, miss {v['miss']:.1f} nm)"
        for k, v in missed.items()
    )
    return f"unreachable: no recipe found meets every target; the closest recipe gives {parts}"
