"""Inverse design: recipes (constant controls) whose predicted profile meets target metrics.

Question answered: "which controls give a 100-nm-deep hole with a 30-nm bottom and the least mask loss?"
The surrogate is differentiable and a rollout costs a fraction of a second, so the search runs on it; the
reported metrics are always the exact ones (``nemsim.geometry.profile``) of a plain rollout, with the
conformal intervals of ``nemsim.analysis.intervals`` and a distance-to-training-data flag.

Search (``search``), in normalized control coordinates (eq:supp_control_normalization: log10 fluxes, the
box [-1, 1] is the training range), only over the free controls (``fixed`` ones are held), inside
``bounds`` (default the training box):
  1. screening: ``screen`` scrambled-Sobol recipes, rolled out in batches without gradients, scored by the
     objective on their exact metrics;
  2. gradient stage (``method="adam"``): the ``starts`` best screened recipes (kept apart by at least
     ``min_separation``) are refined together by Adam on the soft metrics (``nemsim.geometry.soft_profile``)
     of a differentiable rollout (``rollout_to``), projected onto the bounds after every step, with a cosine
     learning-rate decay; every iterate's exact metrics come for free from the same forward pass and join
     the candidate pool;
     derivative-free alternative (``method="cma"``): CMA-ES (the optional ``cma`` package, extra
     ``nemsim[design]``) from the best screened recipe, one batched rollout per generation, with a
     forward-rollout budget matched to the gradient stage's CPU time. On three held-out targets of `small`
     it reached a lower objective than Adam on all three at equal CPU (benchmarks/small/inverse), so
     ``method="auto"`` (the default) uses it when the package is installed, Adam otherwise;
     ``cost.objective_trace`` lists the best objective of the screening, then of each Adam iteration or
     CMA-ES generation (not a running minimum: it shows how the stage moves);
  3. the best distinct candidates get their integer controls (cosine-power exponents) rounded and are
     rolled out again; K are reported, ranked by (targets missed, objective).

Objective: sum over targets of ((metric - value) / tol)^2, plus ``secondary_weight`` * metric / 10 nm for a
secondary goal (e.g. least mask loss; negative for "max"). A spec is ``met`` when the best recipe's
predicted metrics are all within tolerance, else ``unreachable`` (reported with the closest recipe and its
miss per target, never as a met target).

Verification (``verify_recipes``) runs the simulator (a caller-supplied function: in-process for the CLI,
simulator jobs in the service) on the top recipes and reports achieved against target. The simulator can
also work inside the design loop (``nemsim.analysis.inverse_refine``: simulator-corrected rounds that
correct the surrogate's local bias), then the top recipe is the best simulated one.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

from nemsim.analysis.intervals import DEFAULT_LEVELS, Calibration, Support
from nemsim.controls import (
    CONTROL_NAMES,
    CONTROL_SPECS,
    INT_INDICES,
    N_CONTROLS,
    check_admissible,
    control_index,
    from_normalized,
    to_normalized,
)
from nemsim.geometry.profile import profile_metrics_batch
from nemsim.geometry.soft_profile import SOFT_METRICS, soft_profile_metrics

if TYPE_CHECKING:
    from nemsim.analysis.inverse_refine import RefineConfig

TARGET_METRICS = SOFT_METRICS  # etch_depth, top_width, bottom_width, bowing, mask_loss
DEFAULT_TOL = {"etch_depth": 5.0, "top_width": 3.0, "bottom_width": 3.0, "mask_loss": 2.0, "bowing": 2.0}
SECONDARY_SCALE_NM = 10.0
Method = Literal["auto", "adam", "cma"]
Progress = Callable[[float, str], None]


class DesignCancelled(Exception):
    """The caller asked the search to stop."""


@dataclass(frozen=True)
class Target:
    value: float  # nm
    tol: float  # nm, > 0


@dataclass(frozen=True)
class SearchConfig:
    method: Method = "auto"  # auto: cma when the package is installed (it measured better), else adam
    screen: int = 32  # quasi-random recipes rolled out before the refinement
    starts: int = 4  # Adam starts (the best screened recipes)
    iterations: int = 14  # Adam steps
    lr: float = 0.15  # Adam learning rate, normalized units (the box is 2 wide)
    min_separation: float = 0.25  # normalized distance between starts / between reported recipes
    batch: int = 8  # rollouts per no-gradient batch
    cma_evals: int = 200  # CMA-ES forward rollouts (about the gradient stage's cost)
    cma_sigma: float = 0.3
    secondary_weight: float = 0.1


@dataclass(frozen=True)
class DesignSpec:
    """What to design (see ``spec_from_dict`` for the JSON form)."""

    targets: dict[str, Target]
    step: int | None = None  # state index the targets refer to (None: the scene's horizon)
    fixed: dict[str, float] = field(default_factory=dict)  # raw values of held controls
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)  # raw [low, high] per control
    secondary: tuple[str, str] | None = None  # (metric, "min" | "max")
    k: int = 3  # recipes reported
    search: SearchConfig = field(default_factory=SearchConfig)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def _control(name: Any, where: str) -> int:
    if not isinstance(name, str):
        raise ValueError(f"{where}: control names are strings, got {name!r}")
    try:
        return control_index(name)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def spec_from_dict(d: Any) -> DesignSpec:
    """A ``DesignSpec`` from its JSON form; ValueError naming the bad key.

    {"targets": {metric: {"value": nm, "tol": nm} | nm}, "step": int, "fixed": {control: raw},
     "bounds": {control: [low, high]}, "secondary": {"metric": m, "goal": "min" | "max"}, "k": int,
     "search": {SearchConfig fields}}. A bare number as a target takes the default tolerance
     (depth 5 nm, widths 3 nm, mask loss 2 nm, bowing 2 nm).
    """
    if not isinstance(d, dict):
        raise ValueError(f"the design spec must be a JSON object, got {type(d).__name__}")
    known = {"targets", "step", "fixed", "bounds", "secondary", "k", "search"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"unknown spec keys {unknown}; expected some of {sorted(known)}")
    raw_targets = d.get("targets")
    if not isinstance(raw_targets, dict) or not raw_targets:
        raise ValueError(
            f"targets: give at least one of {list(TARGET_METRICS)}, e.g. "
            '{"etch_depth": {"value": 100, "tol": 5}}'
        )
    targets: dict[str, Target] = {}
    for name, t in raw_targets.items():
        if name not in TARGET_METRICS:
            raise ValueError(f"targets: unknown metric {name!r}; expected one of {list(TARGET_METRICS)}")
        if isinstance(t, dict):
            extra = sorted(set(t) - {"value", "tol"})
            if extra or "value" not in t:
                raise ValueError(f'targets.{name}: expected {{"value": nm, "tol": nm}}, got {t!r}')
            value = _number(t["value"], f"targets.{name}.value")
            tol = _number(t.get("tol", DEFAULT_TOL[name]), f"targets.{name}.tol")
        else:
            value, tol = _number(t, f"targets.{name}"), DEFAULT_TOL[name]
        if tol <= 0:
            raise ValueError(f"targets.{name}.tol must be > 0 nm, got {tol:g}")
        targets[name] = Target(value, tol)
    step = d.get("step")
    if step is not None and (isinstance(step, bool) or not isinstance(step, int) or step < 1):
        raise ValueError(f"step must be an integer >= 1 (a state index; default the horizon), got {step!r}")
    fixed: dict[str, float] = {}
    for name, v in (d.get("fixed") or {}).items():
        j = _control(name, "fixed")
        fixed[name] = _number(v, f"fixed.{name}")
        if CONTROL_SPECS[j].kind == "int" and fixed[name] != round(fixed[name]):
            raise ValueError(f"fixed.{name} = {fixed[name]:g} is not an integer (cosine-power exponent)")
    bounds: dict[str, tuple[float, float]] = {}
    for name, b in (d.get("bounds") or {}).items():
        _control(name, "bounds")
        if not isinstance(b, list | tuple) or len(b) != 2:
            raise ValueError(f"bounds.{name} must be [low, high] in physical units, got {b!r}")
        lo, hi = _number(b[0], f"bounds.{name}[0]"), _number(b[1], f"bounds.{name}[1]")
        if not lo < hi:
            raise ValueError(f"bounds.{name}: need low < high, got [{lo:g}, {hi:g}]")
        if name in fixed:
            raise ValueError(f"{name} is both fixed and bounded; give one")
        bounds[name] = (lo, hi)
    probe = np.asarray(from_normalized(np.zeros(N_CONTROLS)), dtype=np.float64)
    for name, v in fixed.items():
        probe[control_index(name)] = v
    bad = check_admissible(probe)
    for name, (lo, _) in bounds.items():
        if lo < CONTROL_SPECS[control_index(name)].phys_min:
            bad.append(f"bounds.{name} low {lo:g} is below the physical minimum")
    if bad:
        raise ValueError(f"physically impossible input: {bad[0]}")
    for name, (_, hi) in bounds.items():
        if not math.isfinite(hi):
            raise ValueError(f"bounds.{name} high must be finite")
    secondary = None
    sec = d.get("secondary")
    if sec is not None:
        if (
            not isinstance(sec, dict)
            or sec.get("metric") not in TARGET_METRICS
            or sec.get("goal", "min") not in ("min", "max")
        ):
            raise ValueError(
                f'secondary must be {{"metric": one of {list(TARGET_METRICS)}, "goal": '
                f'"min" | "max"}}, got {sec!r}'
            )
        secondary = (str(sec["metric"]), str(sec.get("goal", "min")))
    k = d.get("k", 3)
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= 10:
        raise ValueError(f"k (recipes to report) must be an integer in 1..10, got {k!r}")
    search = SearchConfig()
    if d.get("search") is not None:
        s = d["search"]
        fields_ = set(SearchConfig.__dataclass_fields__)
        if not isinstance(s, dict) or set(s) - fields_:
            raise ValueError(
                f"search: unknown keys {sorted(set(s) - fields_) if isinstance(s, dict) else s!r}; "
                f"expected some of {sorted(fields_)}"
            )
        search = replace(search, **s)
        if search.method not in ("auto", "adam", "cma"):
            raise ValueError(f"search.method must be 'auto', 'adam' or 'cma', got {search.method!r}")
        if search.screen < 1 or search.starts < 1 or search.iterations < 0 or search.batch < 1:
            raise ValueError("search: screen, starts and batch must be >= 1 and iterations >= 0")
    return DesignSpec(
        targets=targets, step=step, fixed=fixed, bounds=bounds, secondary=secondary, k=k, search=search
    )


# --- model side -----------------------------------------------------------------------------------


@dataclass
class DesignContext:
    """A loaded surrogate with what the design reports need."""

    model: torch.nn.Module
    scene: Any
    x0: torch.Tensor  # (2, D, H, W) float32 initial state
    calibration: Calibration | None
    support: Support
    model_id: str
    loaded: Any = None  # LoadedModel (rules and simulator configuration for verification)


def simulator_config(loaded: Any) -> Any:
    """The SimConfig of the checkpoint's training data (the recorded generator's ``config`` entry), else
    the simulator defaults."""
    from nemsim.sim import SimConfig

    return SimConfig.from_record((getattr(loaded, "raw", None) or {}).get("sim_config"))


def load_design_context(checkpoint: str | Path) -> DesignContext:
    """Load a checkpoint, its initial state (its simulator configuration) and its calibration file."""
    from nemsim.analysis.intervals import calibration_for, file_digest
    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.sim import initial_state

    path = Path(checkpoint)
    if not path.is_file():
        raise ValueError(f"checkpoint {path} does not exist")
    loaded = load_checkpoint(path)
    x0 = torch.from_numpy(np.asarray(initial_state(loaded.scene, simulator_config(loaded)), dtype=np.float32))
    cal = calibration_for(path)
    return DesignContext(
        model=loaded.model,
        scene=loaded.scene,
        x0=x0,
        calibration=cal,
        support=Support.from_record(cal.support if cal else None),
        model_id=f"{path.stem}@{file_digest(path)}",
        loaded=loaded,
    )


def rollout_to(model: torch.nn.Module, x0: torch.Tensor, u: torch.Tensor, step: int) -> torch.Tensor:
    """The state at ``step`` of constant-control rollouts, differentiable in u (and the weights).

    Same predictions as ``nemsim.evaluation.rollout.rollout`` (multi-step models: chunks of k states per
    call, the last chunk cut at ``step``); only the states the next call needs are kept.

    Args:
        x0: (2, D, H, W) initial state. u: (B, 14) normalized controls.
    Returns:
        (B, 2, D, H, W).
    """
    from nemsim.evaluation.rollout import steps_per_call
    from nemsim.model.monotone import axis_eps_of, eps_field, monotone_eps_of, project

    B = u.shape[0]
    x = x0[None].expand(B, *x0.shape).to(u.dtype)  # (B, 2, D, H, W)
    fast = callable(getattr(model, "precompute", None))
    k = steps_per_call(model)
    cache = model.precompute(u) if fast else None  # type: ignore[operator]
    eps_of = monotone_eps_of(model, None)  # the rollout's monotone projection, if the model has one
    eps = None if eps_of is None else eps_field(x.shape, eps_of, axis_eps_of(model), x.dtype, x.device)
    running_max = x
    t = 0
    while t < step:
        n = min(k, step - t)
        if k > 1:
            states = model.predict(x, cache)[:, :n]  # type: ignore[operator]  # (B, n, 2, D, H, W)
        elif fast:
            states = model.step(x, cache)[:, None]  # type: ignore[operator]
        else:
            states = model(x, u)[:, None]
        if eps is None:
            x = states[:, -1]
        else:  # every state of the chunk updates the running maximum, as in the rollout
            for j in range(n):
                x, running_max = project(states[:, j], running_max, eps)
        t += n
    return x


# --- objective --------------------------------------------------------------------------------------


def objective(metrics: dict[str, Any], spec: DesignSpec) -> Any:
    """Sum of squared tolerance-scaled misses plus the secondary term; works on numpy and torch (B,)."""
    total: Any = 0.0
    for name, t in spec.targets.items():
        total = total + ((metrics[name] - t.value) / t.tol) ** 2
    if spec.secondary is not None:
        m, goal = spec.secondary
        sign = 1.0 if goal == "min" else -1.0
        total = total + sign * spec.search.secondary_weight * metrics[m] / SECONDARY_SCALE_NM
    return total


def misses(metrics: dict[str, float], spec: DesignSpec) -> dict[str, dict[str, Any]]:
    """Per target: predicted value, error (value - target), miss beyond tolerance (0 when met), met."""
    out = {}
    for name, t in spec.targets.items():
        v = float(metrics[name])
        err = v - t.value
        out[name] = {
            "target": t.value,
            "tol": t.tol,
            "value": round(v, 3),
            "error": round(err, 3),
            "miss": round(max(abs(err) - t.tol, 0.0), 3),
            "met": bool(abs(err) <= t.tol),
        }
    return out


# --- search -------------------------------------------------------------------------------------------


@dataclass
class _Pool:
    """Every evaluated recipe: normalized controls and exact metrics at the target step."""

    u: list[np.ndarray] = field(default_factory=list)
    metrics: list[dict[str, float]] = field(default_factory=list)

    def add(self, u: np.ndarray, metrics: dict[str, np.ndarray]) -> None:
        for i in range(u.shape[0]):
            self.u.append(np.array(u[i], dtype=np.float64))
            self.metrics.append({k: float(v[i]) for k, v in metrics.items()})


@dataclass
class _Cost:
    forward_rollouts: int = 0
    gradient_rollouts: int = 0


def _box(spec: DesignSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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

    def __init__(self, ctx: DesignContext, step: int, batch: int, cost: _Cost, check: Callable[[], None]):
        self.ctx, self.step, self.batch, self.cost, self.check = ctx, step, batch, cost, check

    def __call__(self, u: np.ndarray) -> dict[str, np.ndarray]:
        out: dict[str, list[np.ndarray]] = {}
        for s in range(0, len(u), self.batch):
            self.check()
            ub = torch.as_tensor(u[s : s + self.batch], dtype=torch.float32)
            with torch.no_grad():
                x = rollout_to(self.ctx.model, self.ctx.x0, ub, self.step)
            self.cost.forward_rollouts += len(ub)
            for k, v in profile_metrics_batch(x.numpy(), self.ctx.scene).items():
                out.setdefault(k, []).append(v)
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
    (``nemsim.analysis.inverse_refine``), where a metric offset measured at the anchor is only trusted
    nearby."""

    anchor: np.ndarray  # (14,) normalized
    radius: float
    warm: np.ndarray  # (W, 14) normalized


def search(
    ctx: DesignContext,
    spec: DesignSpec,
    *,
    seed: int = 0,
    on_progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
    local: LocalRegion | None = None,
) -> dict[str, Any]:
    """Find recipes for ``spec`` (module docstring). Returns the JSON-ready result (see ``run_design``).

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
            raise DesignCancelled

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
    progress(0.0, "screening")
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
    m_screen = evaluate(u_screen)
    pool.add(u_screen, m_screen)
    trace = [round(float(np.min(objective(m_screen, spec))), 4)]  # best objective per stage/iteration
    progress(0.25, "screened")

    # 2. refinement
    if n_free and cfg.method == "adam" and cfg.iterations > 0:
        _adam(ctx, spec, step, pool, cost, lo, hi, free, check, progress, trace)
    elif n_free and cfg.method == "cma":
        _cma(evaluate, spec, pool, lo, hi, free, fixed, seed, check, progress, trace)

    # 3. candidates: round integer controls, roll out again, rank
    scores = np.array([float(objective(m, spec)) for m in pool.metrics])
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
    ctx: DesignContext,
    spec: DesignSpec,
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
    scores = np.array([float(objective(m, spec)) for m in pool.metrics])
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
        loss = objective(soft, spec)
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
    spec: DesignSpec,
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
    scores = np.array([float(objective(m, spec)) for m in pool.metrics])
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
        scores = objective(m, spec)  # (P,)
        es.tell(list(xs), [float(v) for v in scores])
        trace.append(round(float(np.min(scores)), 4))
        used += len(xs)
        progress(0.25 + 0.65 * min(used / cfg.cma_evals, 1.0), f"CMA-ES {used}/{cfg.cma_evals} rollouts")


def _final_recipes(
    ctx: DesignContext, spec: DesignSpec, step: int, u: np.ndarray, cost: _Cost, check: Callable[[], None]
) -> list[dict[str, Any]]:
    """Roll the candidates out over the whole trajectory (exact metrics per step), rank and describe."""
    from nemsim.evaluation.rollout import rollout

    check()
    ub = torch.as_tensor(u, dtype=torch.float32)
    with torch.no_grad():
        traj = rollout(ctx.model, ctx.x0[None].expand(len(ub), *ctx.x0.shape).contiguous(), ub, step)
    cost.forward_rollouts += len(ub)
    out: list[dict[str, Any]] = []
    for i in range(len(ub)):
        mt = profile_metrics_batch(traj[i].numpy(), ctx.scene)  # {name: (step + 1,)}
        at = {k: float(v[step]) for k, v in mt.items()}
        raw = np.asarray(from_normalized(u[i].astype(np.float64)))
        for j in INT_INDICES:
            raw[j] = float(round(raw[j]))
        rec = {
            "controls": {n: float(v) for n, v in zip(CONTROL_NAMES, raw, strict=True)},
            "controls_normalized": [round(float(v), 5) for v in u[i]],
            "predicted": {k: round(v, 3) for k, v in at.items()},
            "targets": misses(at, spec),
            "objective": round(float(objective(at, spec)), 5),
            "intervals": _intervals_at(ctx.calibration, at, step),
            "training_data": ctx.support.describe(u[i]),
        }
        out.append(rec)
    out.sort(key=lambda r: (sum(not v["met"] for v in r["targets"].values()), r["objective"]))
    keep: list[dict[str, Any]] = []
    for r in out:
        pts = np.asarray(r["controls_normalized"])
        if all(np.linalg.norm(pts - np.asarray(q["controls_normalized"])) > 1e-6 for q in keep):
            keep.append(r)
    for rank, r in enumerate(keep[: spec.k], 1):
        r["rank"] = rank
    return keep[: spec.k]


def _intervals_at(cal: Calibration | None, at: dict[str, float], step: int) -> dict[str, Any] | None:
    """{level: {metric: [lo, hi]}} at the target step, None without a calibration."""
    if cal is None:
        return None
    s = min(step, cal.steps)
    out: dict[str, Any] = {}
    for level in cal.levels:
        out[f"{level:g}"] = {
            m: [None if v is None else round(v, 3) for v in cal.interval(m, s, at[m], level)]
            for m in cal.metrics
            if m in at
        }
    return out


def _interval_note(ctx: DesignContext) -> dict[str, Any]:
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


# --- verification and the whole design ---------------------------------------------------------------

Simulate = Callable[[np.ndarray, int], np.ndarray]  # (raw (14,), steps) -> states (steps + 1, 2, D, H, W)
SimulateMetrics = Callable[[np.ndarray, int], dict[str, float]]  # (raw (14,), step) -> metrics at step, nm


def simulated_metrics(simulate: Simulate, scene: Any) -> SimulateMetrics:
    """The exact profile metrics at the target step of a simulator run (what verification compares)."""

    def metrics_at(raw: np.ndarray, step: int) -> dict[str, float]:
        states = simulate(raw, step)
        return {k: float(v[step]) for k, v in profile_metrics_batch(states, scene).items()}

    return metrics_at


def verify_recipe(
    rec: dict[str, Any], spec: DesignSpec, step: int, simulate: SimulateMetrics, rank: int = 1
) -> dict[str, Any]:
    """Simulate one recipe of a result and compare the simulator's metrics at ``step`` with the targets and
    with the recipe's predicted intervals."""
    raw = np.array([rec["controls"][n] for n in CONTROL_NAMES], dtype=np.float64)
    t0 = time.perf_counter()
    achieved = simulate(raw, step)
    sim_s = time.perf_counter() - t0
    inside = {}
    for level, per in (rec.get("intervals") or {}).items():
        inside[level] = {
            m: bool((lo is None or achieved[m] >= lo) and (hi is None or achieved[m] <= hi))
            for m, (lo, hi) in per.items()
        }
    tmiss = misses(achieved, spec)
    return {
        "rank": rec.get("rank", rank),
        "achieved": {k: round(float(v), 3) for k, v in achieved.items()},
        "targets": tmiss,
        "met": all(v["met"] for v in tmiss.values()),
        "within_intervals": inside,
        "simulator_s": round(sim_s, 3),
    }


def verify_recipes(
    result: dict[str, Any],
    spec: DesignSpec,
    scene: Any,
    simulate: Simulate,
    top: int = 1,
    on_progress: Progress | None = None,
) -> list[dict[str, Any]]:
    """Simulate the ``top`` recipes of a result and compare the simulator's exact metrics at the target step
    with the targets and with the predicted intervals (``verify_recipe``)."""
    out = []
    step = int(result["step"])
    recipes = result["recipes"][:top]
    metrics_at = simulated_metrics(simulate, scene)
    for i, rec in enumerate(recipes):
        if on_progress is not None:
            on_progress(i / len(recipes), f"simulating recipe {i + 1}/{len(recipes)}")
        out.append(verify_recipe(rec, spec, step, metrics_at, i + 1))
    return out


def run_design(
    ctx: DesignContext,
    spec: DesignSpec,
    *,
    seed: int = 0,
    verify: bool = False,
    verify_top: int = 1,
    sim_seed: int = 1,
    progress: bool = False,
    refine: RefineConfig | None = None,
) -> dict[str, Any]:
    """Search (and with ``verify`` simulate the top recipes in-process); the CLI's entry point.

    With ``refine`` (a ``nemsim.analysis.inverse_refine.RefineConfig``) the simulator is used inside the
    design loop instead (simulator-corrected rounds; implies ``verify``, and ``verify_top`` is the
    config's).
    """
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=100, desc="inverse design", unit="%", dynamic_ncols=True, leave=False)

    def report(f: float, msg: str) -> None:
        if bar is not None:
            bar.n = int(100 * f)
            bar.set_postfix_str(msg)
            bar.refresh()

    from nemsim.sim import run_trajectory

    config = simulator_config(ctx.loaded)

    def simulate(raw: np.ndarray, steps: int) -> np.ndarray:
        rng = np.random.default_rng(sim_seed)
        return run_trajectory(ctx.scene, ctx.loaded.rules, raw, rng, config, n_transitions=steps).states

    try:
        if refine is not None:
            from nemsim.analysis.inverse_refine import refine_design

            result = refine_design(
                ctx,
                spec,
                simulated_metrics(simulate, ctx.scene),
                refine=refine,
                seed=seed,
                sim_seed=sim_seed,
                on_progress=report,
            )
        else:
            result = search(ctx, spec, seed=seed, on_progress=report)
    finally:
        if bar is not None:
            bar.close()
    if verify and refine is None:
        result["verification"] = {
            "seed": sim_seed,
            "recipes": verify_recipes(result, spec, ctx.scene, simulate, verify_top),
        }
    result["spec"] = spec_to_dict(spec)
    return result


def spec_to_dict(spec: DesignSpec) -> dict[str, Any]:
    """The JSON form of a spec (inverse of ``spec_from_dict``)."""
    from dataclasses import asdict

    return {
        "targets": {k: {"value": t.value, "tol": t.tol} for k, t in spec.targets.items()},
        "step": spec.step,
        "fixed": dict(spec.fixed),
        "bounds": {k: list(v) for k, v in spec.bounds.items()},
        "secondary": None
        if spec.secondary is None
        else {"metric": spec.secondary[0], "goal": spec.secondary[1]},
        "k": spec.k,
        "search": asdict(spec.search),
    }


def format_result(result: dict[str, Any]) -> str:
    """A readable table of a design result."""
    lines = [
        f"{result['status'].upper()}: {result['message']}",
        f"targets at step {result['step']} ({result['time_s']:g} s); model {result['model_id']}",
        "",
    ]
    names = list(result["recipes"][0]["targets"]) if result["recipes"] else []
    level = None
    if result["recipes"] and result["recipes"][0].get("intervals"):
        level = (
            "0.9"
            if "0.9" in result["recipes"][0]["intervals"]
            else next(iter(result["recipes"][0]["intervals"]))
        )
    head = ["rank"] + [f"{n} (target)" for n in names] + ["objective", "data"]
    if result["recipes"] and "verified_by" in result["recipes"][0]:
        head.append("verified by")
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---:|" * len(head))
    for r in result["recipes"]:
        cells = [str(r["rank"])]
        for n in names:
            t = r["targets"][n]
            iv = ""
            if level is not None:
                lo, hi = r["intervals"][level][n]
                iv = f" [{_f(lo)}, {_f(hi)}]"
            value, met = f"{t['value']:.1f}{iv}", t["met"]
            if "simulated_targets" in r:  # simulated: the simulator's value decides
                st = r["simulated_targets"][n]
                value, met = f"{value} / sim {st['value']:.1f}", st["met"]
            cells.append(f"{value} ({t['target']:g}±{t['tol']:g}){'' if met else ' MISS'}")
        cells += [f"{r['objective']:.3g}", r["training_data"]["flag"]]
        if "verified_by" in r:
            cells.append(
                ("simulator " + ("MET" if r["simulator_met"] else "miss"))
                if r["verified_by"] == "simulator" else "surrogate"
            )
        lines.append("| " + " | ".join(cells) + " |")
    if level is not None:
        lines.append(f"(brackets: {100 * float(level):.0f} % conformal interval, nm)")
    if any("simulated_targets" in r for r in result["recipes"]):
        lines.append("(predicted / sim: the surrogate's prediction, the simulator's run of the recipe; nm)")
    lines.append("")
    for r in result["recipes"]:
        ctl = ", ".join(f"{k}={_ctl(k, v)}" for k, v in r["controls"].items())
        lines.append(f"recipe {r['rank']}: {ctl}")
    c = result["cost"]
    sims = ""
    if "simulator_runs" in c:
        sims = f", {c['simulator_runs']} simulator runs ({c['simulator_wall_s']:.1f} s)"
    lines.append(
        f"cost: {c['rollouts']} rollouts ({c['forward_rollouts']} forward, {c['gradient_rollouts']} "
        f"with gradients; {c['method']}){sims}, {c['wall_s']:.1f} s wall, {c['cpu_s']:.1f} s CPU"
    )
    ref = result.get("refinement")
    if ref:
        lines.append(
            f"simulator-corrected design: surrogate search {ref['surrogate_status']}; "
            f"stopped: {ref['stopped']}"
        )
        lines += [_round_line(rd) for rd in ref["rounds"]]
    ver = result.get("verification")
    if ver:
        for v in ver["recipes"]:
            parts = ", ".join(
                f"{k} {t['value']:.1f} ({'ok' if t['met'] else 'MISS'})" for k, t in v["targets"].items()
            )
            which = f"round {v['round']} recipe" if "round" in v else f"recipe {v['rank']}"
            lines.append(
                f"simulator (seed {ver['seed']}), {which}: {'MET' if v['met'] else 'NOT MET'}: {parts}"
            )
        for why in ver.get("skipped", []):
            lines.append(f"simulator skipped {why}")
    return "\n".join(lines)


def _round_line(rd: dict[str, Any]) -> str:
    """One simulator-corrected round: the offset it searched with, then predicted -> simulated metrics."""
    line = f"  round {rd['round']}: "
    if rd["round"] > 0:
        line += "offset " + ", ".join(f"{k} {v:+.1f}" for k, v in rd["offset"].items()) + "; "
    runs = []
    for s in rd["simulated"]:
        pairs = ", ".join(f"{k} {s['predicted'][k]:.1f} -> {s['simulated'][k]:.1f}" for k in s["predicted"])
        verdict = " MET" if s["met"] else f" (miss {', '.join(s['missed'])})"
        runs.append(f"predicted -> simulated {pairs}{verdict}")
    return line + ("; ".join(runs) or "nothing simulated")


def _f(v: float | None) -> str:
    return "-inf/inf" if v is None else f"{v:.1f}"


def _ctl(name: str, v: float) -> str:
    spec = CONTROL_SPECS[control_index(name)]
    return f"{int(v)}" if spec.kind == "int" else f"{v:.4g}"


__all__ = [
    "DEFAULT_LEVELS",
    "DesignSpec",
    "SearchConfig",
    "Target",
    "format_result",
    "load_design_context",
    "run_design",
    "search",
    "spec_from_dict",
    "simulated_metrics",
    "verify_recipe",
    "verify_recipes",
]
