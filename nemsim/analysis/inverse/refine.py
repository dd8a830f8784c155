"""Simulator-corrected inverse design: a few simulator runs inside the design loop.

The surrogate search puts a recipe on target in the surrogate, but the surrogate's own error there can
exceed the tolerances. The loop (an output-space trust region with an additive bias correction):

  round 0: the search gives K ranked recipes; the simulator runs the top ``verify_top``; one that meets
           every tolerance is the answer.
  round r: the best simulated recipe so far (fewest targets missed, then the least tolerance-scaled miss)
           is the anchor, and its offset d = simulated - predicted per metric is the surrogate's local
           bias. The search is repeated for surrogate metrics = target - d inside a trust region of
           half-width ``radius`` (normalized controls) around the anchor, warm-started from every simulated
           recipe; its top recipe is simulated.

It stops when a simulated recipe meets every tolerance, after ``rounds`` rounds, when the next round's
estimated wall time would pass ``budget_s``, or when the corrected search returns a recipe already run.
Status: ``verified`` (a simulated recipe meets every target), ``unverified`` (some search predicted them
met, no simulated recipe did) or ``unreachable`` (no search predicted them met); ``refinement`` records
every round and why the loop stopped.

Why a constant offset rather than a learned correction: with one or two simulator runs there is nothing to
fit beyond a constant per metric, and the surrogate's errors at nearby controls are correlated, so the
constant is the first-order term the trust region keeps valid. The simulator is a caller-supplied
``SimulateMetrics`` (``verify``); it may raise ``SimulationSkipped`` to decline a recipe.
"""

from __future__ import annotations

import math
import resource
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from nemsim.analysis.inverse.context import InverseContext
from nemsim.analysis.inverse.spec import InverseSpec, Progress, SearchCancelled, Target, misses, objective
from nemsim.analysis.inverse.surrogate_search import LocalRegion, search
from nemsim.analysis.inverse.verify import SimulateMetrics, SimulationSkipped, verify_recipe

# verification (CLI --verify, service "verify": true) refines unless told not to: on held-out targets it met
# more of them in an independent simulator run than verifying the surrogate's top recipe, within the
# design budget (benchmarks/small/inverse)
REFINE_WITH_VERIFY = True



@dataclass(frozen=True)
class RefineConfig:
    verify_top: int = 2  # round-0 recipes simulated
    rounds: int = 2  # corrected rounds at most (0: verify round 0 only)
    budget_s: float = 60.0  # wall seconds of the whole design; a round starts only if its estimate fits
    radius: float = 0.35  # trust-region half-width around the anchor, normalized units (the box is 2 wide)
    screen: int = 6  # quasi-random recipes in the trust region per round (beside the warm starts)
    starts: int = 2  # Adam starts per round (method adam)
    iterations: int = 6  # Adam steps per round (method adam)
    cma_evals: int = 48  # CMA-ES rollouts per round (method cma)
    cma_sigma: float = 0.12  # CMA-ES initial step, normalized units

    def check(self) -> RefineConfig:
        """Self, or ValueError naming the bad field."""
        if not 1 <= self.verify_top <= 10:
            raise ValueError(f"refine.verify_top must be in 1..10, got {self.verify_top}")
        if not 0 <= self.rounds <= 10:
            raise ValueError(f"refine.rounds must be in 0..10, got {self.rounds}")
        if not (math.isfinite(self.budget_s) or self.budget_s == math.inf) or self.budget_s < 0:
            raise ValueError(f"refine.budget_s must be >= 0 s, got {self.budget_s}")
        if not 0 < self.radius <= 2:
            raise ValueError(f"refine.radius must be in (0, 2] normalized units, got {self.radius}")
        if self.screen < 0 or self.starts < 1 or self.iterations < 0 or self.cma_evals < 1:
            raise ValueError("refine: screen and iterations must be >= 0, starts and cma_evals >= 1")
        if not self.cma_sigma > 0:
            raise ValueError(f"refine.cma_sigma must be > 0, got {self.cma_sigma}")
        return self


def refine_config_from_dict(d: Any) -> RefineConfig:
    """A ``RefineConfig`` from its JSON form (any subset of its fields); ValueError naming the bad key."""
    if d is None:
        return RefineConfig()
    fields_ = set(RefineConfig.__dataclass_fields__)
    if not isinstance(d, dict) or set(d) - fields_:
        bad = sorted(set(d) - fields_) if isinstance(d, dict) else d
        raise ValueError(f"refine: unknown keys {bad!r}; expected some of {sorted(fields_)}")
    for k, v in d.items():
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ValueError(f"refine.{k} must be a number, got {v!r}")
    ints = {k: int(v) for k, v in d.items() if k not in ("budget_s", "radius", "cma_sigma")}
    if any(ints[k] != d[k] for k in ints):
        raise ValueError(f"refine: {sorted(k for k in ints if ints[k] != d[k])} must be integers")
    return replace(RefineConfig(), **{**d, **ints}).check()


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _sim_key(entry: dict[str, Any]) -> tuple[int, float]:
    """Ranking of simulated recipes: targets missed, then the sum of tolerance-scaled misses."""
    t = entry["targets"]
    return sum(not v["met"] for v in t.values()), sum(v["miss"] / v["tol"] for v in t.values())


@dataclass
class _Simulated:
    """One simulated recipe: the round that proposed it, its search record and its verification entry."""

    round: int
    recipe: dict[str, Any]  # as in a search result's "recipes" (predicted metrics, intervals, ...)
    entry: dict[str, Any]  # as from verify_recipes (achieved, targets, met, within_intervals, simulator_s)

    @property
    def u(self) -> np.ndarray:
        return np.asarray(self.recipe["controls_normalized"], dtype=np.float64)

    def offset(self, names: Any) -> dict[str, float]:
        """simulated - predicted per metric, nm."""
        return {m: float(self.entry["achieved"][m]) - float(self.recipe["predicted"][m]) for m in names}


def refine_with_simulator(
    ctx: InverseContext,
    spec: InverseSpec,
    simulate: SimulateMetrics,
    *,
    refine: RefineConfig | None = None,
    seed: int = 0,
    sim_seed: int | None = None,
    on_progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> dict[str, Any]:
    """Surrogate search, then simulator-corrected rounds (module docstring). Returns the JSON-ready result.

    ``sim_seed`` is only recorded (the caller's ``simulate`` owns the randomness).
    """
    cfg = (refine or RefineConfig()).check()
    t0, c0, ch0 = time.perf_counter(), time.process_time(), _children_cpu()
    progress = on_progress or (lambda f, m: None)

    def check() -> None:
        if should_stop is not None and should_stop():
            raise SearchCancelled

    def span(base: float, width: float) -> Progress:
        return lambda f, m: progress(base + width * f, m)

    res0 = search(ctx, spec, seed=seed, on_progress=span(0.0, 0.45), should_stop=should_stop)
    step = int(res0["step"])
    names = list(spec.targets)
    sims: list[_Simulated] = []
    skipped: list[str] = []
    rounds: list[dict[str, Any]] = []
    searches = [res0["cost"]]
    predicted_met = res0["status"] == "met"

    def run_sim(rec: dict[str, Any], rnd: int) -> _Simulated | None:
        check()
        try:
            entry = verify_recipe(rec, spec, step, simulate)
        except SimulationSkipped as exc:
            skipped.append(f"round {rnd}, recipe {rec.get('rank', '?')}: {exc}")
            return None
        entry["round"] = rnd
        s = _Simulated(rnd, rec, entry)
        sims.append(s)
        return s

    # round 0: simulate the surrogate's best recipes
    top = res0["recipes"][: cfg.verify_top]
    done0 = []
    for i, rec in enumerate(top):
        progress(0.45 + 0.15 * i / len(top), f"simulating round-0 recipe {i + 1}/{len(top)}")
        s = run_sim(rec, 0)
        if s is not None:
            done0.append(s)
            if s.entry["met"]:
                break  # the answer: the next recipes need no simulator run
    rounds.append(
        {
            "round": 0,
            "targets": {m: spec.targets[m].value for m in names},
            "search": _search_summary(res0),
            "simulated": [_sim_record(s, names) for s in done0],
        }
    )
    stopped = "rounds"
    per_rollout = res0["cost"]["wall_s"] / max(res0["cost"]["rollouts"], 1)
    last_round_s: float | None = None
    for rnd in range(1, cfg.rounds + 1):
        if any(s.entry["met"] for s in sims):
            stopped = "met"
            break
        if not sims:
            stopped = "no simulated recipe"
            break
        elapsed = time.perf_counter() - t0
        if last_round_s is None:
            est = per_rollout * _round_rollouts(cfg, res0["cost"]["method"], spec.k, len(sims)) + max(
                s.entry["simulator_s"] for s in sims
            )
        else:
            est = last_round_s
        if elapsed + est > cfg.budget_s:
            stopped = "budget"
            break
        r0 = time.perf_counter()
        base, width = 0.6 + 0.4 * (rnd - 1) / cfg.rounds, 0.4 / cfg.rounds
        res, record = _corrected_search(
            ctx, spec, cfg, sims, rnd, seed=seed + rnd, on_progress=span(base, 0.7 * width),
            should_stop=should_stop,
        )
        searches.append(res["cost"])
        predicted_met = predicted_met or res["status"] == "met"
        rounds.append(record)
        new = res["recipes"][0]
        if any(np.linalg.norm(np.asarray(new["controls_normalized"]) - s.u) <= 1e-6 for s in sims):
            stopped = "converged"  # the corrected search's best was simulated already: nothing new to try
            break
        rec = _restate(new, spec)
        progress(base + 0.7 * width, f"simulating round-{rnd} recipe")
        s = run_sim(rec, rnd)
        if s is not None:
            record["simulated"].append(_sim_record(s, names))
        last_round_s = time.perf_counter() - r0
    else:
        if any(s.entry["met"] for s in sims):
            stopped = "met"
    progress(1.0, "done")
    return _assemble(ctx, spec, res0, sims, skipped, rounds, searches, stopped, predicted_met, cfg, sim_seed,
                     time.perf_counter() - t0, time.process_time() - c0 + _children_cpu() - ch0)


def _corrected_search(
    ctx: InverseContext,
    spec: InverseSpec,
    cfg: RefineConfig,
    sims: list[_Simulated],
    rnd: int,
    *,
    seed: int,
    on_progress: Progress,
    should_stop: Callable[[], bool] | None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """One corrected round's search: the targets shifted by the offset at the best simulated recipe (the
    anchor), searched in the trust region around it, warm-started from every simulated recipe. Returns
    the search result and the round's record (its ``simulated`` list still empty)."""
    names = list(spec.targets)
    anchor = min(sims, key=lambda s: _sim_key(s.entry))
    offset = anchor.offset(names)
    shifted = {m: Target(spec.targets[m].value - offset[m], spec.targets[m].tol) for m in names}
    round_spec = replace(
        spec,
        targets=shifted,
        k=max(spec.k, 3),
        search=replace(
            spec.search,
            screen=max(cfg.screen, 1),
            starts=cfg.starts,
            iterations=cfg.iterations,
            cma_evals=cfg.cma_evals,
            cma_sigma=cfg.cma_sigma,
        ),
    )
    warm = np.stack([anchor.u] + [s.u for s in sims if s is not anchor])  # (W, 14)
    region = LocalRegion(anchor=anchor.u, radius=cfg.radius, warm=warm)
    res = search(ctx, round_spec, seed=seed, on_progress=on_progress, should_stop=should_stop, local=region)
    record: dict[str, Any] = {
        "round": rnd,
        "anchor": {"round": anchor.round, "controls": anchor.recipe["controls"]},
        "offset": {m: round(v, 3) for m, v in offset.items()},
        "shifted_targets": {m: round(t.value, 3) for m, t in shifted.items()},
        "search": _search_summary(res),
        "simulated": [],
    }
    return res, record


def _round_rollouts(cfg: RefineConfig, method: str, k: int, warm: int) -> int:
    """Rollouts a corrected round is expected to take (screening, refinement, final re-evaluation)."""
    stage = cfg.cma_evals if method == "cma" else cfg.starts * (cfg.iterations + 1)
    k = max(k, 3)
    return warm + max(cfg.screen, 1) + stage + max(k + 2, 2 * k)


def _restate(rec: dict[str, Any], spec: InverseSpec) -> dict[str, Any]:
    """A corrected round's recipe with its targets and objective against the real targets (the round
    searched shifted ones)."""
    out = dict(rec)
    out["targets"] = misses(rec["predicted"], spec)
    out["objective"] = round(float(objective(rec["predicted"], spec)), 5)
    return out


def _search_summary(res: dict[str, Any]) -> dict[str, Any]:
    c = res["cost"]
    return {
        "status": res["status"],
        "rollouts": c["rollouts"],
        "wall_s": c["wall_s"],
        "cpu_s": c["cpu_s"],
    }


def _sim_record(s: _Simulated, names: list[str]) -> dict[str, Any]:
    return {
        "controls": s.recipe["controls"],
        "predicted": {m: s.recipe["predicted"][m] for m in names},
        "simulated": {m: s.entry["achieved"][m] for m in names},
        "offset": {m: round(v, 3) for m, v in s.offset(names).items()},
        "met": s.entry["met"],
        "missed": [m for m, v in s.entry["targets"].items() if not v["met"]],
        "simulator_s": s.entry["simulator_s"],
    }


def _assemble(
    ctx: InverseContext,
    spec: InverseSpec,
    res0: dict[str, Any],
    sims: list[_Simulated],
    skipped: list[str],
    rounds: list[dict[str, Any]],
    searches: list[dict[str, Any]],
    stopped: str,
    predicted_met: bool,
    cfg: RefineConfig,
    sim_seed: int | None,
    wall_s: float,
    cpu_s: float,
) -> dict[str, Any]:
    """The final result: rank 1 the best simulated recipe, then the surrogate's other round-0 recipes."""
    result = dict(res0)
    recipes: list[dict[str, Any]] = []
    best = min(sims, key=lambda s: _sim_key(s.entry)) if sims else None

    def labelled(rec: dict[str, Any]) -> dict[str, Any]:
        out = dict(rec)
        hit = next(
            (s for s in sims
             if np.linalg.norm(np.asarray(rec["controls_normalized"]) - s.u) <= 1e-6),
            None,
        )
        out["verified_by"] = "simulator" if hit is not None else "surrogate"
        if hit is not None:
            out["simulated"] = hit.entry["achieved"]
            out["simulated_targets"] = hit.entry["targets"]
            out["simulator_met"] = hit.entry["met"]
            out["round"] = hit.round
        return out

    if best is not None:
        recipes.append(labelled(best.recipe))
    for rec in res0["recipes"]:
        if len(recipes) == spec.k:
            break
        if best is None or np.linalg.norm(np.asarray(rec["controls_normalized"]) - best.u) > 1e-6:
            recipes.append(labelled(rec))
    for rank, r in enumerate(recipes, 1):
        r["rank"] = rank
    result["recipes"] = recipes
    if best is None:
        pass  # nothing simulated: the surrogate's status and message stand
    elif best.entry["met"]:
        result["status"] = "verified"
        result["message"] = (
            f"the top recipe meets every target within its tolerance in the simulator (round {best.round}, "
            f"{len(sims)} simulator run{'s' if len(sims) != 1 else ''})"
        )
    else:
        result["status"] = "unverified" if predicted_met else "unreachable"
        missed = {k: v for k, v in best.entry["targets"].items() if not v["met"]}
        parts = ", ".join(
            f"{k} {v['value']:.1f} nm (target {v['target']:g} +- {v['tol']:g}, miss {v['miss']:.1f} nm)"
            for k, v in missed.items()
        )
        lead = (
            "unverified: the surrogate finds recipes that meet the targets, but none of the "
            if predicted_met
            else "unreachable: no search finds a recipe predicted to meet the targets, and none of the "
        )
        result["message"] = (
            f"{lead}{len(sims)} simulated recipes meets them; the closest simulated gives {parts}"
        )
    sim_s = [s.entry["simulator_s"] for s in sims]
    fwd = sum(c["forward_rollouts"] for c in searches)
    grad = sum(c["gradient_rollouts"] for c in searches)
    result["cost"] = {
        "method": res0["cost"]["method"],
        "forward_rollouts": fwd,
        "gradient_rollouts": grad,
        "rollouts": fwd + grad,
        "simulator_runs": len(sims),
        "simulator_wall_s": round(float(sum(sim_s)), 3),
        "search_wall_s": round(float(sum(c["wall_s"] for c in searches)), 3),
        "wall_s": round(wall_s, 3),
        "cpu_s": round(cpu_s, 3),
        "objective_trace": res0["cost"]["objective_trace"],
    }
    result["verification"] = {
        "seed": sim_seed,
        "recipes": [s.entry for s in sims],
        **({"skipped": skipped} if skipped else {}),
    }
    result["refinement"] = {
        "surrogate_status": res0["status"],
        "rounds": rounds,
        "stopped": stopped,
        "config": asdict(cfg),
    }
    return result
