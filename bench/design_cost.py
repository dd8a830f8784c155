"""`nemsim bench design-cost`: simulator runs spent to reach a target, surrogate-guided design against
optimisation on the simulator alone.

Process development is judged by cost-to-target: how many expensive runs it takes to find a recipe that
meets a specification (Kanarik et al., Nature 2023, measured it for engineers and Bayesian optimisation on
a virtual etch process). Here the expensive run is the Monte Carlo simulator.

Targets (``bench.inverse``'s machinery): the final-step metrics (seed 1) of held-out recipes placed in the
interior of the control box, near its faces and near its corners (``held_out_unit``), with the default
tolerances (depth +-5 nm, top and bottom width +-3 nm, mask loss +-2 nm), and the deliberately unreachable
targets. Strategies, with the same tolerances, the same control box (the training box) and the same budget
of simulator calls per target:

  design  surrogate-guided design with simulator refinement: the library function `POST /design` runs with
          verify (``nemsim.analysis.inverse.refine_with_simulator``), handed the confirmation simulator;
  bo      Bayesian optimisation on the simulator alone (BoTorch: SingleTaskGP, qLogNoisyExpectedImprovement)
          of y = -log(1 + J), J the surrogate search's objective (``objective``: tolerance-scaled squared
          misses), in unit coordinates of the box, after ``BOConfig.init`` scrambled-Sobol recipes;
  random  uniform random recipes of the box.

Protocol: a strategy's own runs use seed 3 (``LOOP_SEED``); a recipe that meets every tolerance there is a
candidate and is run again with seed 2 (``VERIFY_SEED``), an independent run, the confirmation; the target
is hit when a confirmation meets every tolerance. Every simulator call counts, confirmations included, and
calls-to-target is the count up to the confirming run. The design's one exception is its round-0 claim
(``RefineConfig.claim_level``): the surrogate's own recipe, predicted to meet the targets before any
simulator run, goes straight to its confirmation run, one independent test of a prediction rather than a
run picked among others for having met. Each hit's recipe is then run once more with seed 4
(``RECHECK_SEED``), outside the budget: how often a strategy's answers meet the target again measures how
much of its hit rate rests on one run's luck, whatever route led to the answer. A strategy stops at the
hit, when the budget is spent, or (design) when it has answered: it reports a target unreachable, or its
rounds or simulator calls (``RefineConfig``) are used up. The design's wall-time budget is lifted here
(``budget_s`` = inf unless ``--refine`` sets it), so that its outcome does not depend on the load of a
shared machine; the table reports its time per design instead.

Budget (default 30 calls): ten times a median of 3 calls for the design, so a ">= 10x fewer calls"
comparison is decided inside the budget; the usual BO budgets in 14 dimensions (tens of points per
dimension) would cost hours of CPU per target here.

CPU sharing: simulator runs are cached by (recipe, seed) in the run folder as their final-step metrics
(``MetricRuns``, a JSON-lines file; trajectories are not kept). BO's initial Sobol recipes are the same for
every target, and random search draws each target's recipes without replacement from a shared pool of
``POOL_FACTOR`` x budget uniform random recipes, in an order of its own (each target still sees a uniform
random sample), so those runs are simulated once. Timings: a strategy's own CPU and wall time without the
simulator, plus its calls at the simulator's mean measured cost per run (a cached run costs nothing when
reused, so measured totals would flatter reruns and shared runs).

Resumable: one JSON per target in ``<out>/targets/``, rewritten after each strategy; a rerun skips what is
there. ``report`` rebuilds results.json, design_cost.md and design_cost.png from that folder.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bench.inverse import (
    LOOP_SEED,
    PLACEMENTS,
    TARGET_SEED,
    VERIFY_SEED,
    held_out_unit,
    reachable_case,
    unreachable_cases,
)
from nemsim.controls import CONTROL_NAMES, N_CONTROLS, from_unit

STRATEGIES = ("design", "bo", "random")
CONFIRM_MODES = ("inside", "after")
DOMAINS = ("quarter", "full")
POOL_FACTOR = 3  # random search: the shared pool holds this many times the budget
POOL_SEED, SOBOL_SEED = 11, 13
RECHECK_SEED = 4  # a hit's recipe run once more, outside the budget
BO_INSTALL = "pip install 'nemsim[design-bench]' (or: pip install botorch)"


class BudgetSpent(Exception):
    """A strategy asked for a simulator call beyond its budget."""


@dataclass(frozen=True)
class BOConfig:
    init: int = 8  # scrambled-Sobol recipes before the first acquisition (shared by every target)
    restarts: int = 8  # optimize_acqf num_restarts
    raw_samples: int = 256  # optimize_acqf raw_samples


@dataclass(frozen=True)
class DesignCostConfig:
    """What one benchmark run does (the CLI's options)."""

    interior: int = 12  # held-out targets inside the box
    faces: int = 6  # near a face of the box
    corners: int = 4  # near a vertex
    unreachable: int = 3
    seed: int = 7  # held-out recipes (``held_out_unit``)
    budget: int = 30  # simulator calls per strategy and target
    domain: str = "full"  # the simulator's domain (``SimConfig.domain``): the data's, as POST /design runs
    strategies: tuple[str, ...] = STRATEGIES
    confirm: str = "inside"  # design: confirmation inside the design loop, or of its answer after it
    design_label: str = "design"  # the design's name in the results (variants side by side)
    refine: dict[str, Any] = field(default_factory=dict)  # RefineConfig fields of the design
    search: dict[str, Any] = field(default_factory=dict)  # SearchConfig fields of the design's search
    step: int | None = None  # the targets' state index (None: the scene's horizon)
    bo: BOConfig = field(default_factory=BOConfig)

    def check(self) -> DesignCostConfig:
        """Self, or ValueError naming the bad option."""
        for name in ("interior", "faces", "corners"):
            if getattr(self, name) < 0:
                raise ValueError(f"--{name} must be >= 0, got {getattr(self, name)}")
        if self.interior + self.faces + self.corners < 1:
            raise ValueError("give at least one reachable target (--interior, --faces, --corners)")
        if not 1 <= self.budget <= 1000:
            raise ValueError(f"--budget must be in 1..1000 simulator calls, got {self.budget}")
        if self.domain not in DOMAINS:
            raise ValueError(f"--domain must be one of {list(DOMAINS)}, got {self.domain!r}")
        bad = [s for s in self.strategies if s not in STRATEGIES]
        if bad or not self.strategies:
            raise ValueError(
                f"unknown strategies {bad or list(self.strategies)}; expected some of {STRATEGIES}"
            )
        if self.confirm not in CONFIRM_MODES:
            raise ValueError(f"--confirm must be one of {list(CONFIRM_MODES)}, got {self.confirm!r}")
        if not self.design_label or self.design_label in ("bo", "random") or "/" in self.design_label:
            raise ValueError(
                f"--design-label must be a name other than bo and random, got {self.design_label!r}"
            )
        if self.bo.init < 1 or self.bo.restarts < 1 or self.bo.raw_samples < 1:
            raise ValueError("BO: init, restarts and raw_samples must be >= 1")
        return self


# --- simulator runs ------------------------------------------------------------------------------------


def read_runs(path: Path) -> dict[str, dict[str, Any]]:
    """The run records of a ``MetricRuns`` file by key (a line cut short by a stopped run is skipped)."""
    runs: dict[str, dict[str, Any]] = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            runs[rec["key"]] = rec
    return runs


def mean_cost(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Mean wall and CPU seconds per simulator run over ``records``."""
    if not records:
        return {"wall_s": 0.0, "cpu_s": 0.0, "runs": 0}
    return {
        "wall_s": round(float(np.mean([r["wall_s"] for r in records])), 3),
        "cpu_s": round(float(np.mean([r["cpu_s"] for r in records])), 3),
        "runs": len(records),
    }


class MetricRuns:
    """Simulator runs as their profile metrics at ``step``, cached by (recipe, seed) in a JSON-lines file.

    Each line: key, seed, controls, metrics (nm) and the run's wall and CPU seconds. A line cut short by a
    stopped run is ignored on reading (its run is simulated again).
    """

    def __init__(self, scene: Any, rules: Any, config: Any, step: int, path: str | Path) -> None:
        self.scene, self.rules, self.config, self.step = scene, rules, config.resolved(scene), step
        self.path = Path(path)
        meta = json.dumps(self.config.to_meta(scene), sort_keys=True, default=str)
        self._ident = f"|{step}|{scene.to_json()}|{getattr(rules, 'sha256', '')}|{meta}"
        self.runs = read_runs(self.path)

    def key(self, raw: np.ndarray, seed: int) -> str:
        raw = np.ascontiguousarray(np.asarray(raw, dtype=np.float64).reshape(N_CONTROLS))
        return hashlib.sha1(raw.tobytes() + f"|{int(seed)}{self._ident}".encode()).hexdigest()[:20]

    def __call__(self, raw: np.ndarray, seed: int) -> tuple[dict[str, float], dict[str, Any], bool]:
        """(metrics at ``step``, the run's record, whether it was simulated now)."""
        from nemsim.geometry.profile import profile_metrics_batch
        from nemsim.sim import run_trajectory

        k = self.key(raw, seed)
        if k in self.runs:
            return self.runs[k]["metrics"], self.runs[k], False
        t0, c0 = time.perf_counter(), time.process_time()
        states = run_trajectory(
            self.scene,
            self.rules,
            np.asarray(raw, dtype=np.float64),
            np.random.default_rng(seed),
            self.config,
            n_transitions=self.step,
        ).states
        metrics = {k: float(v[self.step]) for k, v in profile_metrics_batch(states, self.scene).items()}
        rec = {
            "key": k,
            "seed": int(seed),
            "controls": [float(v) for v in raw],
            "metrics": metrics,
            "wall_s": round(time.perf_counter() - t0, 3),
            "cpu_s": round(time.process_time() - c0, 3),
        }
        self.runs[k] = rec
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a") as f:
            f.write(json.dumps(rec) + "\n")
        return metrics, rec, True


@dataclass
class Ledger:
    """The simulator calls of one strategy on one target: counted against the budget, each recorded."""

    runs: MetricRuns
    targets: dict[str, Any]  # {metric: Target}
    budget: int
    calls: list[dict[str, Any]] = field(default_factory=list)
    hit_at: int | None = None  # calls up to and including the first confirmation that met
    hit_raw: np.ndarray | None = None  # that confirmation's recipe
    fresh_wall_s: float = 0.0  # simulator time of the runs simulated now (not cached)
    fresh_cpu_s: float = 0.0

    def met(self, m: dict[str, float]) -> bool:
        return all(abs(m[k] - t.value) <= t.tol for k, t in self.targets.items())

    def call(self, raw: np.ndarray, kind: str) -> dict[str, float]:
        """Run ``raw`` (kind "explore": the strategy's seed; "confirm": the independent one)."""
        if len(self.calls) >= self.budget:
            raise BudgetSpent(f"the budget of {self.budget} simulator calls is spent")
        seed = VERIFY_SEED if kind == "confirm" else LOOP_SEED
        m, rec, fresh = self.runs(raw, seed)
        if fresh:
            self.fresh_wall_s += rec["wall_s"]
            self.fresh_cpu_s += rec["cpu_s"]
        ok = self.met(m)
        self.calls.append(
            {"kind": kind, "met": ok, "key": rec["key"], "metrics": {k: round(m[k], 3) for k in self.targets}}
        )
        if kind == "confirm" and ok and self.hit_at is None:
            self.hit_at, self.hit_raw = len(self.calls), np.asarray(raw, dtype=np.float64)
        return m

    def metrics_fn(self, kind: str) -> Callable[[np.ndarray, int], dict[str, float]]:
        """A ``SimulateMetrics`` (raw, step) for the design; beyond the budget it declines the recipe."""
        from nemsim.analysis.inverse import SimulationSkipped

        def simulate(raw: np.ndarray, step: int) -> dict[str, float]:
            if step != self.runs.step:
                raise ValueError(f"the benchmark simulates to step {self.runs.step}, asked for {step}")
            try:
                return self.call(raw, kind)
            except BudgetSpent as exc:
                raise SimulationSkipped(str(exc)) from None

        return simulate

    def result(self) -> dict[str, Any]:
        return {
            "hit": self.hit_at is not None,
            "calls_to_target": self.hit_at,
            "calls": len(self.calls),
            "confirmations": sum(c["kind"] == "confirm" for c in self.calls),
            **({"hit_controls": [float(v) for v in self.hit_raw]} if self.hit_raw is not None else {}),
            "log": self.calls,
        }


# --- strategies ----------------------------------------------------------------------------------------


def run_design(ctx: Any, spec: Any, ledger: Ledger, refine: Any, confirm: str) -> dict[str, Any]:
    """Strategy "design": ``refine_with_simulator`` with the ledger's simulators. ``confirm`` "inside": the
    design gets the confirmation simulator (a recipe met in its loop is confirmed before it is its answer);
    "after": the design runs as without one and its verified answer is confirmed once afterwards."""
    from nemsim.analysis.inverse import refine_with_simulator

    kwargs: dict[str, Any] = {"refine": refine, "seed": 0, "sim_seed": LOOP_SEED}
    if confirm == "inside":
        kwargs["confirm"] = ledger.metrics_fn("confirm")
    res = refine_with_simulator(ctx, spec, ledger.metrics_fn("explore"), **kwargs)
    top = res["recipes"][0]
    if confirm == "after" and res["status"] == "verified":
        try:
            ledger.call(np.array([top["controls"][n] for n in CONTROL_NAMES], dtype=np.float64), "confirm")
        except BudgetSpent:
            pass
    ref = res.get("refinement") or {}
    return {
        "status": res["status"],
        "unreachable_reported": res["status"] == "unreachable",
        "stopped": ref.get("stopped"),
        "rounds": len(ref.get("rounds", [])),
        "design_wall_s": res["cost"]["wall_s"],
        "design_cpu_s": res["cost"]["cpu_s"],
        "rollouts": res["cost"]["rollouts"],
        "controls": top["controls"],
        "refinement": ref.get("rounds", []),  # every round's offset and runs (predicted against simulated)
    }


def _objective_y(m: dict[str, float], targets: dict[str, Any]) -> float:
    """BO's observation: -log(1 + J), J = sum of squared tolerance-scaled misses (the search's objective)."""
    j = sum(((m[k] - t.value) / t.tol) ** 2 for k, t in targets.items())
    return -math.log1p(j)


def sobol_unit(n: int, seed: int = SOBOL_SEED) -> np.ndarray:
    """(n, 14) scrambled-Sobol points of the unit box."""
    import warnings

    from scipy.stats import qmc

    with warnings.catch_warnings():  # any n, not only powers of 2
        warnings.simplefilter("ignore", UserWarning)
        return np.asarray(qmc.Sobol(d=N_CONTROLS, scramble=True, seed=seed).random(n))


def run_bo(ledger: Ledger, cfg: BOConfig, seed: int) -> dict[str, Any]:
    """Strategy "bo" (module docstring); ``seed`` seeds the acquisition's optimiser. Needs botorch."""
    try:
        import torch
        from botorch.acquisition.logei import qLogNoisyExpectedImprovement
        from botorch.fit import fit_gpytorch_mll
        from botorch.models import SingleTaskGP
        from botorch.models.transforms import Standardize
        from botorch.optim import optimize_acqf
        from gpytorch.mlls import ExactMarginalLogLikelihood
        from linear_operator.utils.warnings import NumericalWarning
    except ImportError:
        raise ValueError(f"strategy 'bo' needs the optional package botorch: {BO_INSTALL}") from None
    import warnings

    xs: list[np.ndarray] = []
    ys: list[float] = []
    fit_s = 0.0

    def observe(xi: np.ndarray) -> None:
        raw = from_unit(xi[None])[0]
        runs = [ledger.call(raw, "explore")]
        if ledger.met(runs[0]):  # a candidate: its independent run decides
            runs.append(ledger.call(raw, "confirm"))
        for m in runs:  # a confirmation is one more noisy observation of the same recipe
            xs.append(xi)
            ys.append(_objective_y(m, ledger.targets))

    bounds = torch.stack([torch.zeros(N_CONTROLS), torch.ones(N_CONTROLS)]).double()
    try:
        for xi in sobol_unit(cfg.init):
            observe(xi)
            if ledger.hit_at is not None:
                break
        it = 0
        while ledger.hit_at is None:
            t0 = time.process_time()
            X = torch.as_tensor(np.stack(xs), dtype=torch.float64)  # (n, 14)
            Y = torch.as_tensor(ys, dtype=torch.float64)[:, None]  # (n, 1)
            # repeated inputs (a confirmation reruns its recipe) leave the kernel matrix near-singular: the
            # GP adds jitter, as designed, and would warn at every fit
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", NumericalWarning)
                gp = SingleTaskGP(X, Y, outcome_transform=Standardize(m=1))
                fit_gpytorch_mll(ExactMarginalLogLikelihood(gp.likelihood, gp))
                acq = qLogNoisyExpectedImprovement(gp, X_baseline=X, prune_baseline=True)
                cand, _ = optimize_acqf(
                    acq,
                    bounds=bounds,
                    q=1,
                    num_restarts=cfg.restarts,
                    raw_samples=cfg.raw_samples,
                    options={"seed": seed * 1000 + it},
                )
            fit_s += time.process_time() - t0
            it += 1
            observe(cand.detach().numpy()[0].clip(0.0, 1.0))
    except BudgetSpent:
        pass
    return {
        "status": "hit" if ledger.hit_at else "budget spent",
        "unreachable_reported": False,
        "model_cpu_s": round(fit_s, 2),
    }


def random_order(index: int, budget: int) -> np.ndarray:
    """Target ``index``'s random recipes: (budget, 14) unit points drawn without replacement from the shared
    pool of ``POOL_FACTOR * budget`` uniform random recipes (``POOL_SEED``), in an order of its own."""
    pool = np.random.default_rng(POOL_SEED).random((POOL_FACTOR * budget, N_CONTROLS))
    order = np.random.default_rng([POOL_SEED, index]).permutation(len(pool))[:budget]
    return pool[order]


def run_random(ledger: Ledger, index: int) -> dict[str, Any]:
    """Strategy "random": each recipe run once, a candidate confirmed, until a hit or the budget."""
    try:
        for xi in random_order(index, ledger.budget):
            raw = from_unit(xi[None])[0]
            if ledger.met(ledger.call(raw, "explore")):
                ledger.call(raw, "confirm")
            if ledger.hit_at is not None:
                break
    except BudgetSpent:
        pass
    return {"status": "hit" if ledger.hit_at else "budget spent", "unreachable_reported": False}


# --- the benchmark -------------------------------------------------------------------------------------


def target_cases(cfg: DesignCostConfig, final: Callable[[np.ndarray, int], dict[str, float]]) -> list[dict]:
    """The reachable targets (interior, faces, corners: seeds ``seed``, +1, +2) and the unreachable ones."""
    cases: list[dict[str, Any]] = []
    counts = {"interior": cfg.interior, "faces": cfg.faces, "corners": cfg.corners}
    for j, placement in enumerate(PLACEMENTS):
        if counts[placement]:
            raws = from_unit(held_out_unit(counts[placement], cfg.seed + j, placement))  # (n, 14)
            for i, raw in enumerate(raws):
                cases.append({**reachable_case(f"{placement} {i + 1}", raw, final), "placement": placement})
    cases += [{**c, "placement": "unreachable"} for c in unreachable_cases(cfg.unreachable)]
    return cases


def _check_botorch() -> None:
    import importlib.util

    if importlib.util.find_spec("botorch") is None:
        raise ValueError(f"strategy 'bo' needs the optional package botorch: {BO_INSTALL}")


def _run_strategy(
    strategy: str,
    ctx: Any,
    case: dict[str, Any],
    index: int,
    runs: MetricRuns,
    cfg: DesignCostConfig,
    rcfg: Any,
) -> dict[str, Any]:
    """One strategy on one target: its ledger's calls, its outcome and its own time without the simulator."""
    from nemsim.analysis.inverse import spec_from_dict

    spec = spec_from_dict(
        {**case["spec"], "step": runs.step, **({"search": cfg.search} if cfg.search else {})}
    )
    ledger = Ledger(runs, spec.targets, cfg.budget)
    t0, c0 = time.perf_counter(), time.process_time()
    if strategy == "design":
        out = run_design(ctx, spec, ledger, rcfg, cfg.confirm)
        out["settings"] = {"refine": asdict(rcfg), "confirm": cfg.confirm, "search": asdict(spec.search)}
    elif strategy == "bo":
        out = run_bo(ledger, cfg.bo, seed=index)
        out["settings"] = asdict(cfg.bo)
    else:
        out = run_random(ledger, index)
        out["settings"] = {"pool": POOL_FACTOR * cfg.budget, "pool_seed": POOL_SEED}
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        **ledger.result(),
        **out,
        "own_wall_s": round(max(wall - ledger.fresh_wall_s, 0.0), 3),
        "own_cpu_s": round(max(cpu - ledger.fresh_cpu_s, 0.0), 3),
    }


_RUN_KEYS = ("interior", "faces", "corners", "unreachable", "seed", "budget", "domain", "step")


def run_design_cost(
    checkpoint: str | Path, out: str | Path, cfg: DesignCostConfig | None = None, progress: bool = True
) -> dict[str, Any]:
    """Run the benchmark into the run folder ``out`` (resuming what is there); returns ``report(out)``."""
    from nemsim.analysis.inverse import load_inverse_context, refine_config_from_dict, simulator_config
    from nemsim.sim import SimConfig

    cfg = (cfg or DesignCostConfig()).check()
    if "bo" in cfg.strategies:
        _check_botorch()
    rcfg = refine_config_from_dict({"budget_s": math.inf, **cfg.refine})  # rounds and calls bound it here
    out = Path(out)
    meta_path = out / "run.json"
    if meta_path.is_file():
        before = json.loads(meta_path.read_text())["config"]
        differ = [k for k in _RUN_KEYS if before.get(k) != asdict(cfg)[k]]
        if differ:
            was = ", ".join(f"{k}={before.get(k)}" for k in differ)
            raise ValueError(
                f"{out} holds a run with other {differ} ({was}); resume it with the same options or give "
                "another --out"
            )
    ctx = load_inverse_context(checkpoint)
    step = cfg.step or ctx.scene.n_transitions
    if not 1 <= step <= ctx.scene.n_transitions:
        raise ValueError(f"step must be in 1..{ctx.scene.n_transitions} (the model's horizon), got {step}")
    sim_cfg = replace(simulator_config(ctx.loaded) or SimConfig(), domain=cfg.domain)
    runs = MetricRuns(ctx.scene, ctx.loaded.rules, sim_cfg, step, out / "sims.jsonl")
    from bench.machine import cpu_name
    from nemsim.inference.checkpoint import checkpoint_id

    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "checkpoint": Path(checkpoint).name,
        "checkpoint_id": checkpoint_id(Path(checkpoint)),
        "model_id": ctx.model_id,
        "scene": ctx.scene.name,
        "step": step,
        "cpu": cpu_name(),
        "seeds": {"target": TARGET_SEED, "confirm": VERIFY_SEED, "strategy": LOOP_SEED},
        "config": {**asdict(cfg), "strategies": list(cfg.strategies)},
    }
    _write_atomically(meta_path, meta)
    labels = [(s, cfg.design_label if s == "design" else s) for s in cfg.strategies]
    bar = None
    if progress:
        from tqdm import tqdm

        n_cases = cfg.interior + cfg.faces + cfg.corners + cfg.unreachable
        bar = tqdm(total=n_cases * len(labels), unit="run", desc="design cost", dynamic_ncols=True)
    try:
        if bar is not None:
            bar.set_postfix_str("target runs")
        cases = target_cases(cfg, lambda raw, seed: runs(raw, seed)[0])
        for i, case in enumerate(cases):
            path = out / "targets" / f"{i + 1:02d}.json"
            rec = _target_record(path, case)
            for strategy, label in labels:
                if label not in rec["strategies"]:
                    if bar is not None:
                        bar.set_postfix_str(f"{case['name']}: {label}")
                    rec["strategies"][label] = _run_strategy(strategy, ctx, case, i, runs, cfg, rcfg)
                    _write_atomically(path, rec)
                if bar is not None:
                    bar.update(1)
            if any([recheck_hit(r, rec["spec"], runs) for r in rec["strategies"].values()]):
                _write_atomically(path, rec)
    finally:
        if bar is not None:
            bar.close()
    return report(out)


def recheck_hit(result: dict[str, Any], spec: dict[str, Any], runs: MetricRuns) -> bool:
    """Run a hit's recipe once more (``RECHECK_SEED``, outside the budget) into ``result["recheck"]``;
    whether it ran. The recipe: the confirming call's (``hit_controls``), else the design's answer."""
    raw = result.get("hit_controls") or (
        [result["controls"][n] for n in CONTROL_NAMES] if "controls" in result else None
    )
    if not result["hit"] or "recheck" in result or raw is None:
        return False
    m = runs(np.asarray(raw, dtype=np.float64), RECHECK_SEED)[0]
    result["recheck"] = {"met": _meets(m, spec), "metrics": {k: round(m[k], 3) for k in spec["targets"]}}
    return True


def _target_record(path: Path, case: dict[str, Any]) -> dict[str, Any]:
    """The target's JSON (resumed when it is this target's), else a new one."""
    spec = json.loads(json.dumps(case["spec"]))
    if path.is_file():
        rec = json.loads(path.read_text())
        if rec["spec"] != spec:
            raise ValueError(f"{path} holds another target ({rec['name']}); give another --out")
        return rec
    rec = {k: v for k, v in case.items() if k != "spec"}
    rec["spec"] = spec
    if case["reachable"]:
        rec["oracle_met"] = _meets(case["oracle"], spec)
    rec["strategies"] = {}
    return rec


def _meets(metrics: dict[str, float], spec: dict[str, Any]) -> bool:
    """Whether ``metrics`` meet every target of a JSON spec within its tolerance."""
    return all(abs(metrics[k] - t["value"]) <= _tol(k, t) for k, t in spec["targets"].items())


def _tol(metric: str, t: dict[str, Any]) -> float:
    from nemsim.analysis.inverse import DEFAULT_TOL

    return float(t.get("tol", DEFAULT_TOL[metric]))


def _finite(obj: Any) -> Any:
    """``obj`` with non-finite floats (an unlimited wall budget) as None: strict JSON."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def _write_atomically(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(_finite(obj), indent=1) + "\n")
    tmp.replace(path)


# --- the report ----------------------------------------------------------------------------------------


def _median(values: Sequence[float]) -> float | None:
    """The median, misses counted as +inf; None when it is infinite (more than half missed)."""
    if not values:
        return None
    m = float(np.median(np.asarray(values, dtype=np.float64)))
    return None if not math.isfinite(m) else m


def summarise(cases: list[dict[str, Any]], label: str, budget: int, sim: dict[str, float]) -> dict[str, Any]:
    """One strategy over the targets: hits, calls to target, unreachable reports and its cost."""
    reach = [c["strategies"][label] for c in cases if c["reachable"] and label in c["strategies"]]
    unreach = [c["strategies"][label] for c in cases if not c["reachable"] and label in c["strategies"]]
    every = reach + unreach
    to_target = sorted(r["calls_to_target"] for r in reach if r["hit"])
    hits = len(to_target)
    rechecked = [r["recheck"]["met"] for r in reach if r["hit"] and "recheck" in r]
    cost = [r["own_cpu_s"] + r["calls"] * sim["cpu_s"] for r in every]
    wall = [r["own_wall_s"] + r["calls"] * sim["wall_s"] for r in every]
    return {
        "reachable": len(reach),
        "hits": hits,
        "hit_rate": round(hits / len(reach), 3) if reach else None,
        "median_calls_to_target": _median([r["calls_to_target"] if r["hit"] else math.inf for r in reach]),
        "median_calls_of_hits": _median(to_target),
        "calls_to_target": to_target,
        "calls_per_hit": round(sum(r["calls"] for r in reach) / hits, 2) if hits else None,
        "calls_on_reachable_mean": round(float(np.mean([r["calls"] for r in reach])), 2) if reach else None,
        "false_unreachable": sum(r["unreachable_reported"] for r in reach),
        "unreachable": len(unreach),
        "unreachable_reported": sum(r["unreachable_reported"] for r in unreach),
        "calls_on_unreachable_mean": round(float(np.mean([r["calls"] for r in unreach])), 2)
        if unreach
        else None,
        "cumulative_hits": [sum(x <= n for x in to_target) for n in range(1, budget + 1)],
        "rechecked": len(rechecked),
        "recheck_met": sum(rechecked),
        "own_cpu_s_mean": round(float(np.mean([r["own_cpu_s"] for r in every])), 2) if every else None,
        "cpu_s_mean": round(float(np.mean(cost)), 1) if every else None,
        "wall_s_mean": round(float(np.mean(wall)), 1) if every else None,
        "wall_s_max": round(float(np.max(wall)), 1) if every else None,
    }


def compare(a: dict[str, Any], b: dict[str, Any], budget: int) -> dict[str, Any]:
    """Strategy a against b at equal hit rate, from the calls-to-target lists: at h hits a needs the h-th
    smallest of its calls-to-target per target (the cumulative-hits curve read sideways). ``common``: at the
    hits both reach; ``at_a``: at a's hits, b's calls or, when b does not reach them within the budget, the
    least ratio (budget / a's calls)."""
    ca, cb = a["calls_to_target"], b["calls_to_target"]
    out: dict[str, Any] = {"hits": [a["hits"], b["hits"]]}
    h = min(len(ca), len(cb))
    if h:
        out["common"] = {"hits": h, "calls": [ca[h - 1], cb[h - 1]], "ratio": round(cb[h - 1] / ca[h - 1], 2)}
    if ca:
        at = {"hits": len(ca), "calls": ca[-1]}
        if len(cb) >= len(ca):
            at["other_calls"] = cb[len(ca) - 1]
            at["ratio"] = round(cb[len(ca) - 1] / ca[-1], 2)
        else:
            at["ratio_at_least"] = round(budget / ca[-1], 2)
        out["at_a"] = at
    if a["calls_per_hit"] and b["calls_per_hit"]:
        out["calls_per_hit_ratio"] = round(b["calls_per_hit"] / a["calls_per_hit"], 2)
    return out


def report(out: str | Path) -> dict[str, Any]:
    """results.json's content from a run folder: the run's settings, per-strategy summaries, comparisons of
    each design variant with bo and random, and every target's record."""
    out = Path(out)
    meta = json.loads((out / "run.json").read_text())
    cases = [json.loads(p.read_text()) for p in sorted((out / "targets").glob("*.json"))]
    budget = int(meta["config"]["budget"])
    sim = mean_cost(list(read_runs(out / "sims.jsonl").values()))
    labels: list[str] = []
    for c in cases:
        labels += [k for k in c["strategies"] if k not in labels]
    summary = {lb: summarise(cases, lb, budget, sim) for lb in labels}
    comparisons = {
        f"{d} vs {o}": compare(summary[d], summary[o], budget)
        for d in labels
        if d not in ("bo", "random")
        for o in ("bo", "random")
        if o in summary
    }
    reach = [c for c in cases if c["reachable"]]
    return {
        **{k: meta[k] for k in ("checkpoint", "checkpoint_id", "model_id", "scene", "step", "cpu", "seeds")},
        "config": meta["config"],
        "simulator": {"domain": meta["config"]["domain"], **sim},
        "oracle_met": sum(bool(c.get("oracle_met")) for c in reach),
        "reachable": len(reach),
        "summary": summary,
        "comparisons": comparisons,
        "cases": cases,
    }


def _n(v: float | None, fmt: str = ".1f", none: str = "-") -> str:
    return none if v is None else format(v, fmt)


def format_markdown(rep: dict[str, Any]) -> str:
    """design_cost.md: the protocol, the summary per strategy, the comparisons and the per-target table."""
    cfg, sim = rep["config"], rep["simulator"]
    n_unreach = sum(not c["reachable"] for c in rep["cases"])
    lines = [
        f"# Simulator calls to target ({rep['checkpoint']}, scene {rep['scene']})",
        "",
        f"{rep['reachable']} reachable targets (final-step depth, top and bottom width and mask loss of "
        f"simulator runs, seed {rep['seeds']['target']}, of held-out recipes: {cfg['interior']} inside the "
        f"control box, {cfg['faces']} near its faces, {cfg['corners']} near its corners; held-out seed "
        f"{cfg['seed']}) and {n_unreach} unreachable ones; tolerances depth +-5 nm, widths +-3 nm, mask "
        f"loss +-2 nm. A strategy's own runs use seed {rep['seeds']['strategy']}; a recipe that meets every "
        f"tolerance there is run again with seed {rep['seeds']['confirm']} (an independent run), and the "
        "target is hit when that confirmation meets every tolerance (the design's round-0 claim: its first "
        "recipe, predicted to meet them before any run, goes straight to that run). Every simulator call "
        f"counts, confirmations included; budget {cfg['budget']} calls per strategy and target. Each hit's "
        f"recipe is run once more with seed {RECHECK_SEED}, outside the budget (hits met again). Simulator: "
        f"the {sim['domain']} domain, {sim['runs']} runs, {sim['cpu_s']:.2f} CPU s "
        f"({sim['wall_s']:.2f} s wall) per run on average. The target's own recipe, seed "
        f"{rep['seeds']['confirm']}, meets {rep['oracle_met']} of {rep['reachable']} targets (the "
        "simulator's seed noise).",
        "",
        "| strategy | reachable hit | median calls to target (misses infinite) | median calls of the hits | "
        f"calls per hit | hits met again (seed {RECHECK_SEED}) | unreachable reported | reachable reported "
        "unreachable | calls on an unreachable target (mean) | CPU s per target without / with the simulator "
        "(mean) | wall s per target (mean / max) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, s in rep["summary"].items():
        design = label not in ("bo", "random")
        cells = [
            label,
            f"{s['hits']}/{s['reachable']}",
            _n(s["median_calls_to_target"], "g", f"> {cfg['budget']}"),
            _n(s["median_calls_of_hits"], "g"),
            _n(s["calls_per_hit"]),
            f"{s['recheck_met']}/{s['rechecked']}" if s.get("rechecked") else "-",
            f"{s['unreachable_reported']}/{s['unreachable']}" if design else "-",
            str(s["false_unreachable"]) if design else "-",
            _n(s["calls_on_unreachable_mean"]),
            f"{_n(s['own_cpu_s_mean'])} / {_n(s['cpu_s_mean'])}",
            f"{_n(s['wall_s_mean'])} / {_n(s['wall_s_max'])}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "bo and random cannot report a target unreachable: they spend the budget.", ""]
    for name, c in rep["comparisons"].items():
        a, b = name.split(" vs ")
        parts = []
        if "common" in c:
            x = c["common"]
            parts.append(
                f"at {x['hits']} hits (both reach them) {a} needs {x['calls'][0]} calls per target, "
                f"{b} {x['calls'][1]} ({x['ratio']:g}x)"
            )
        if "at_a" in c:
            x = c["at_a"]
            if "ratio" in x:
                parts.append(
                    f"at {a}'s {x['hits']} hits: {x['calls']} against {x['other_calls']} calls "
                    f"({x['ratio']:g}x)"
                )
            else:
                parts.append(
                    f"{b} does not reach {a}'s {x['hits']} hits within {cfg['budget']} calls "
                    f"({a}: {x['calls']} calls; ratio >= {x['ratio_at_least']:g}x)"
                )
        if "calls_per_hit_ratio" in c:
            parts.append(f"calls per hit {c['calls_per_hit_ratio']:g}x")
        lines.append(
            f"- **{a} vs {b}** (hits {c['hits'][0]} and {c['hits'][1]}): " + "; ".join(parts or ["-"])
        )
    lines += [
        "",
        "Per target: calls to target (a miss: `miss/<calls spent>`; the design's status in brackets).",
        "",
        "| target | oracle met | " + " | ".join(rep["summary"]) + " |",
        "|---|---|" + "---|" * len(rep["summary"]),
    ]
    for c in rep["cases"]:
        cells = []
        for label in rep["summary"]:
            r = c["strategies"].get(label)
            if r is None:
                cells.append("")
                continue
            cell = str(r["calls_to_target"]) if r["hit"] else f"miss/{r['calls']}"
            if "stopped" in r:
                cell += f" ({r['status']})"
            cells.append(cell)
        oracle = ("yes" if c.get("oracle_met") else "NO") if c["reachable"] else "-"
        lines.append(f"| {c['name']} | {oracle} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"CPU: {rep['cpu']}. Times: each strategy's own CPU and wall time without the simulator, plus "
        "its calls at the mean cost per simulator run above (`bench/design_cost.py`).",
    ]
    return "\n".join(lines) + "\n"


def plot_design_cost(rep: dict[str, Any], path: str | Path) -> Path:
    """PNG: the share of reachable targets hit against the simulator calls spent per target."""
    from nemsim.evaluation.figure import pyplot, save_figure

    plt = pyplot()
    budget = int(rep["config"]["budget"])
    fig, ax = plt.subplots(figsize=(7.0, 4.5))
    x = np.arange(1, budget + 1)
    for label, s in rep["summary"].items():
        if s["reachable"]:
            y = np.asarray(s["cumulative_hits"]) / s["reachable"]
            ax.step(x, y, where="post", lw=2, label=f"{label} ({s['hits']}/{s['reachable']})")
    if rep["reachable"]:
        ax.axhline(
            rep["oracle_met"] / rep["reachable"],
            color="0.5",
            ls="--",
            lw=1,
            label="the target's own recipe (seed noise)",
        )
    ax.set_xscale("log")
    ax.set_xlim(1, budget)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("simulator calls per target (confirmations included)")
    ax.set_ylabel("share of reachable targets hit")
    ax.set_title(
        f"cost to target on {rep['scene']} ({rep['simulator']['domain']}-domain simulator)", fontsize=9
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(0.0, 0.35))
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def write_outputs(rep: dict[str, Any], out_dir: str | Path) -> dict[str, str]:
    """results.json, design_cost.md and design_cost.png in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(_finite(rep), indent=1) + "\n")
    (out / "design_cost.md").write_text(format_markdown(rep))
    plot_design_cost(rep, out / "design_cost.png")
    return {
        "json": str(out / "results.json"),
        "md": str(out / "design_cost.md"),
        "png": str(out / "design_cost.png"),
    }
