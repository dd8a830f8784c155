"""Simulator-corrected inverse design: a few simulator runs inside the design loop.

The surrogate search puts a recipe on target in the surrogate, but the surrogate's own error there can
exceed the tolerances. The loop (an output-space trust region with an additive bias correction):

  round 0: the search gives K ranked recipes; the simulator runs the top ``verify_top``; one that meets
           every tolerance is the answer.
  round r: the best simulated recipe so far (fewest targets missed, then the least tolerance-scaled miss,
           on the mean of its runs) is the anchor; the offset d = simulated - predicted per metric near it
           is the surrogate's local bias (``_carried_offset``: every run so far, weighted by its distance
           from the anchor, so that seed noise averages out). The search is repeated for surrogate metrics
           = target - d inside a trust region of half-width ``radius`` (normalized controls) around the
           anchor, warm-started from every simulated recipe; its top recipe is simulated. Each run since
           the anchor's that did not replace it halves the region (``shrink``): the offset was measured at
           the anchor and holds best near it, as in any trust-region method whose model was wrong on the
           last step (``nemsim bench design-cost`` measures what it buys: benchmarks/small/design_cost).

Confirmation (optional ``confirm``, a second simulator with its own seed): a recipe that meets every
tolerance in its loop run is run again by ``confirm`` and is the answer only if that independent run meets
them too; otherwise both runs stay on record, the recipe's mean anchors the next round and the loop goes
on. A single lucky run (the simulator's seed noise near a tolerance edge) then never ends a design.

What the surrogate and its calibrated intervals (``nemsim.analysis.intervals``) decide before any run:
  * claim (``claim_level``): when the round-0 top recipe's interval at that level lies inside every
    tolerance, the design predicts a hit, and with ``confirm`` that recipe's first run is its confirmation
    (a hit in one call; a miss is a run like any other, so a claim never costs a call). The default level
    0 is the prediction itself: the round-0 recipe is chosen by the surrogate alone, before any simulator
    run, so its first run is already an independent test of it, and nothing was selected on that run's
    noise. The confirmation guards the later rounds, whose runs are searched for one that meets. On
    ``nemsim bench design-cost`` the claim met in one call, at the same recipes, the 14 of 22 targets
    that the loop without it met in two (benchmarks/small/design_cost). The calibrated levels (0.8, 0.9)
    never claimed there: the 80 % depth interval is wider than +-5 nm.
  * unreachable (``unreachable_level``): when the search finds no recipe predicted to meet the targets and
    every reported recipe has a target whose tolerance band lies wholly outside its interval at that
    level, no recipe near them is expected to meet it in the simulator: the design answers unreachable
    without running it.

It stops when a recipe is verified (met, and confirmed when ``confirm`` is given), after ``rounds`` rounds,
when the next run would pass ``max_runs`` simulator calls (confirmations count), when the next round's
estimated wall time would pass ``budget_s``, or when every recipe the corrected search reports was run
already (its best run already, the next best not yet run is simulated).
Status: ``verified``, ``unverified`` (some search predicted the targets met, no simulated recipe was
verified) or ``unreachable`` (no search predicted them met); ``refinement`` records every round and why
the loop stopped; ``cost.simulator_runs`` counts every call.

Why a constant offset rather than a learned correction: with one or two simulator runs there is nothing to
fit beyond a constant per metric, and the surrogate's errors at nearby controls are correlated, so the
constant is the first-order term the trust region keeps valid. Why one recipe per round by default
(``verify_top`` 1): a simulator call is the cost that counts (``nemsim bench design-cost``), and the
round-0 runner-up is chosen without what the top recipe's run showed, while the next round's recipe is
corrected by it. The simulators are caller-supplied ``SimulateMetrics`` (``verify``); they may raise
``SimulationSkipped`` to decline a recipe.
"""

from __future__ import annotations

import math
import resource
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from nemsim.analysis.inverse.context import InverseContext
from nemsim.analysis.inverse.spec import InverseSpec, Progress, SearchCancelled, Target, misses, objective
from nemsim.analysis.inverse.surrogate_search import LocalRegion, search
from nemsim.analysis.inverse.verify import SimulateMetrics, SimulationSkipped, interval_inside, verify_recipe

# verification (CLI --verify, service "verify": true) refines unless told not to: on held-out targets it met
# more of them in an independent simulator run than verifying the surrogate's top recipe, within the
# design budget (benchmarks/small/inverse)
REFINE_WITH_VERIFY = True


@dataclass(frozen=True)
class RefineConfig:
    verify_top: int = 1  # round-0 recipes simulated (module docstring: why one)
    rounds: int = 5  # corrected rounds at most (0: verify round 0 only; 5: benchmarks/small/design_cost)
    budget_s: float = 60.0  # wall seconds of the whole design; a round starts only if its estimate fits
    max_runs: int = 8  # simulator calls of the design at most, confirmations included
    radius: float = 0.35  # trust-region half-width around the anchor, normalized units (the box is 2 wide)
    shrink: float = 0.5  # the radius times this per round whose run did not become the anchor (1: fixed)
    screen: int = 6  # quasi-random recipes in the trust region per round (beside the warm starts)
    starts: int = 2  # Adam starts per round (method adam)
    iterations: int = 6  # Adam steps per round (method adam)
    cma_evals: int = 48  # CMA-ES rollouts per round (method cma)
    cma_sigma: float = 0.12  # CMA-ES initial step, normalized units
    claim_level: float = 0.0  # interval level of a round-0 claim (0: the prediction itself; 1: never claim)
    unreachable_level: float = 0.9  # interval level of an answer "unreachable" without a run (0: never)

    def check(self) -> RefineConfig:
        """Self, or ValueError naming the bad field."""
        if not 1 <= self.verify_top <= 10:
            raise ValueError(f"refine.verify_top must be in 1..10, got {self.verify_top}")
        if not 0 <= self.rounds <= 10:
            raise ValueError(f"refine.rounds must be in 0..10, got {self.rounds}")
        if not (math.isfinite(self.budget_s) or self.budget_s == math.inf) or self.budget_s < 0:
            raise ValueError(f"refine.budget_s must be >= 0 s, got {self.budget_s}")
        if not 1 <= self.max_runs <= 100:
            raise ValueError(f"refine.max_runs must be in 1..100 simulator calls, got {self.max_runs}")
        if not 0 < self.radius <= 2:
            raise ValueError(f"refine.radius must be in (0, 2] normalized units, got {self.radius}")
        if not 0 < self.shrink <= 1:
            raise ValueError(f"refine.shrink must be in (0, 1], got {self.shrink}")
        if self.screen < 0 or self.starts < 1 or self.iterations < 0 or self.cma_evals < 1:
            raise ValueError("refine: screen and iterations must be >= 0, starts and cma_evals >= 1")
        if not self.cma_sigma > 0:
            raise ValueError(f"refine.cma_sigma must be > 0, got {self.cma_sigma}")
        if not 0 <= self.claim_level <= 1:
            raise ValueError(f"refine.claim_level must be in [0, 1] (1: never), got {self.claim_level}")
        if not 0 <= (level := self.unreachable_level) < 1:
            raise ValueError(f"refine.unreachable_level must be in [0, 1) (0: off), got {level}")
        return self


_FLOATS = ("budget_s", "radius", "shrink", "cma_sigma", "claim_level", "unreachable_level")


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
    ints = {k: int(v) for k, v in d.items() if k not in _FLOATS}
    if any(ints[k] != d[k] for k in ints):
        raise ValueError(f"refine: {sorted(k for k in ints if ints[k] != d[k])} must be integers")
    return replace(RefineConfig(), **{**d, **ints}).check()


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


@dataclass
class _Simulated:
    """One simulated recipe: the round that proposed it, its search record, its first run's verification
    entry and every run's metrics (the loop run, then the confirmation if one was made)."""

    round: int
    recipe: dict[str, Any]  # as in a search result's "recipes" (predicted metrics, intervals, ...)
    entry: dict[str, Any]  # as from verify_recipe (achieved, targets, met, within_intervals, simulator_s)
    runs: list[dict[str, float]] = field(default_factory=list)
    confirmed: bool | None = None  # the confirmation's verdict; None: no confirmation run
    claimed: bool = False  # the first run was the confirmation (an interval claim)

    @property
    def u(self) -> np.ndarray:
        return np.asarray(self.recipe["controls_normalized"], dtype=np.float64)

    def mean(self) -> dict[str, float]:
        """The mean of its runs per metric, nm."""
        return {m: float(np.mean([r[m] for r in self.runs])) for m in self.runs[0]}

    def offset(self, names: Any) -> dict[str, float]:
        """simulated (mean of its runs) - predicted per metric, nm."""
        mean = self.mean()
        return {m: mean[m] - float(self.recipe["predicted"][m]) for m in names}

    def verified(self, with_confirm: bool) -> bool:
        return bool(self.confirmed) if with_confirm else bool(self.entry["met"])

    def key(self, spec: InverseSpec) -> tuple[int, float]:
        """Ranking: targets missed by the mean of its runs, then the sum of tolerance-scaled misses."""
        t = misses(self.mean(), spec)
        return sum(not v["met"] for v in t.values()), sum(v["miss"] / v["tol"] for v in t.values())


def _beyond(rec: dict[str, Any], spec: InverseSpec, level: float) -> list[str]:
    """The targets whose tolerance band lies wholly outside the recipe's interval at ``level``."""
    per = (rec.get("intervals") or {}).get(f"{level:g}")
    if not level or per is None:
        return []
    out = []
    for m, t in spec.targets.items():
        lo, hi = per.get(m, (None, None))
        if (hi is not None and hi < t.value - t.tol) or (lo is not None and lo > t.value + t.tol):
            out.append(m)
    return out


class _Loop:
    """The state of one simulator-corrected design: the simulated recipes, the calls and what was skipped."""

    def __init__(
        self,
        spec: InverseSpec,
        step: int,
        simulate: SimulateMetrics,
        confirm: SimulateMetrics | None,
        cfg: RefineConfig,
        check: Callable[[], None],
    ) -> None:
        self.spec, self.step, self.simulate, self.confirm, self.cfg = spec, step, simulate, confirm, cfg
        self.check = check
        self.sims: list[_Simulated] = []
        self.entries: list[dict[str, Any]] = []  # every simulator call's verification entry, in order
        self.skipped: list[str] = []

    def calls_left(self) -> int:
        return self.cfg.max_runs - len(self.entries)

    def can_run(self) -> bool:
        """Room for a run and, with a confirmation simulator, for its confirmation."""
        return self.calls_left() >= (2 if self.confirm is not None else 1)

    def verified(self) -> _Simulated | None:
        return next((s for s in self.sims if s.verified(self.confirm is not None)), None)

    def _call(
        self, rec: dict[str, Any], rnd: int, simulate: SimulateMetrics, role: str
    ) -> dict[str, Any] | None:
        self.check()
        try:
            entry = verify_recipe(rec, self.spec, self.step, simulate)
        except SimulationSkipped as exc:
            self.skipped.append(f"round {rnd}, recipe {rec.get('rank', '?')} ({role}): {exc}")
            return None
        entry["round"], entry["run"] = rnd, role
        self.entries.append(entry)
        return entry

    def run(self, rec: dict[str, Any], rnd: int, claim: bool = False) -> _Simulated | None:
        """Simulate a recipe (its loop run, then its confirmation if it met; with ``claim`` only the
        confirmation); None when the simulator declined it."""
        if claim and self.confirm is not None:
            entry = self._call(rec, rnd, self.confirm, "claim")
            if entry is None:
                return None
            s = _Simulated(rnd, rec, entry, [entry["achieved"]], confirmed=entry["met"], claimed=True)
            self.sims.append(s)
            return s
        entry = self._call(rec, rnd, self.simulate, "loop")
        if entry is None:
            return None
        s = _Simulated(rnd, rec, entry, [entry["achieved"]])
        self.sims.append(s)
        if entry["met"] and self.confirm is not None:
            again = self._call(rec, rnd, self.confirm, "confirmation")
            if again is not None:
                s.runs.append(again["achieved"])
                s.confirmed = again["met"]
        return s


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
    confirm: SimulateMetrics | None = None,
) -> dict[str, Any]:
    """Surrogate search, then simulator-corrected rounds (module docstring). Returns the JSON-ready result.

    ``confirm``: a simulator independent of ``simulate`` (another seed) that must also meet the targets at
    a recipe before it is verified. ``sim_seed`` is only recorded (the caller's simulators own the
    randomness).
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
    names = list(spec.targets)
    loop = _Loop(spec, int(res0["step"]), simulate, confirm, cfg, check)
    rounds: list[dict[str, Any]] = [
        {
            "round": 0,
            "targets": {m: spec.targets[m].value for m in names},
            "search": _search_summary(res0),
            "simulated": [],
        }
    ]
    searches = [res0["cost"]]
    predicted_met = res0["status"] == "met"
    beyond = (
        {} if predicted_met else {r["rank"]: _beyond(r, spec, cfg.unreachable_level) for r in res0["recipes"]}
    )

    def finish(stopped: str, met: bool) -> dict[str, Any]:
        progress(1.0, "done")
        return _assemble(res0, spec, loop, rounds, searches, stopped, met, cfg, sim_seed,
                         time.perf_counter() - t0, time.process_time() - c0 + _children_cpu() - ch0)

    if beyond and all(beyond.values()):
        rounds[0]["beyond_intervals"] = {str(k): v for k, v in beyond.items()}
        return finish("intervals", predicted_met)
    # round 0: the surrogate's best recipes, a claim when the intervals lie inside the tolerances
    top = res0["recipes"][: cfg.verify_top]
    for i, rec in enumerate(top):
        if not loop.can_run():
            break
        progress(0.45 + 0.15 * i / len(top), f"simulating round-0 recipe {i + 1}/{len(top)}")
        s = loop.run(rec, 0, claim=i == 0 and interval_inside(rec, spec, cfg.claim_level))
        if s is not None:
            rounds[0]["simulated"].append(_sim_record(s, names))
            if loop.verified() is not None:
                break
    stopped = _rounds(ctx, spec, cfg, loop, rounds, searches, res0, seed, t0, span, progress, should_stop)
    return finish(stopped, predicted_met or any(r["search"]["status"] == "met" for r in rounds))


def _rounds(
    ctx: InverseContext,
    spec: InverseSpec,
    cfg: RefineConfig,
    loop: _Loop,
    rounds: list[dict[str, Any]],
    searches: list[dict[str, Any]],
    res0: dict[str, Any],
    seed: int,
    t0: float,
    span: Callable[[float, float], Progress],
    progress: Progress,
    should_stop: Callable[[], bool] | None,
) -> str:
    """The corrected rounds after round 0 (module docstring); returns why they stopped."""
    names = list(spec.targets)
    per_rollout = res0["cost"]["wall_s"] / max(res0["cost"]["rollouts"], 1)
    last_round_s: float | None = None
    for rnd in range(1, cfg.rounds + 1):
        if loop.verified() is not None:
            return "met"
        if not loop.sims:
            return "no simulated recipe"
        if not loop.can_run():
            return "max runs"
        if last_round_s is None:
            sim_s = max(e["simulator_s"] for e in loop.entries)
            est = per_rollout * _round_rollouts(cfg, res0["cost"]["method"], spec.k, len(loop.sims)) + sim_s
        else:
            est = last_round_s
        if time.perf_counter() - t0 + est > cfg.budget_s:
            return "budget"
        r0 = time.perf_counter()
        base, width = 0.6 + 0.4 * (rnd - 1) / cfg.rounds, 0.4 / cfg.rounds
        res, record = _corrected_search(
            ctx,
            spec,
            cfg,
            loop.sims,
            rnd,
            seed=seed + rnd,
            on_progress=span(base, 0.7 * width),
            should_stop=should_stop,
        )
        searches.append(res["cost"])
        rounds.append(record)
        fresh = [r for r in res["recipes"] if _run_of(r, loop.sims) is None]
        if not fresh:
            return "converged"  # every recipe the corrected search reports was simulated already
        new = fresh[0]  # its best not yet run (the best itself may be: its run already counted)
        progress(base + 0.7 * width, f"simulating round-{rnd} recipe")
        s = loop.run(_restate(new, spec), rnd)
        if s is not None:
            record["simulated"].append(_sim_record(s, names))
        last_round_s = time.perf_counter() - r0
    return "met" if loop.verified() is not None else "rounds"


def _run_of(recipe: dict[str, Any], sims: list[_Simulated]) -> _Simulated | None:
    """The simulated recipe among ``sims`` that is ``recipe`` (a search result's), or None."""
    u = np.asarray(recipe["controls_normalized"])
    return next((s for s in sims if np.linalg.norm(u - s.u) <= 1e-6), None)


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
    anchor = min(sims, key=lambda s: s.key(spec))
    offset = _carried_offset(anchor, sims, names, cfg.radius)
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
    stale = next(i for i, s in enumerate(reversed(sims)) if s is anchor)  # later runs that did not replace it
    radius = cfg.radius * cfg.shrink**stale
    region = LocalRegion(anchor=anchor.u, radius=radius, warm=warm)
    res = search(ctx, round_spec, seed=seed, on_progress=on_progress, should_stop=should_stop, local=region)
    record: dict[str, Any] = {
        "round": rnd,
        "anchor": {"round": anchor.round, "controls": anchor.recipe["controls"], "runs": len(anchor.runs)},
        "radius": round(radius, 4),
        "offset": {m: round(v, 3) for m, v in offset.items()},
        "shifted_targets": {m: round(t.value, 3) for m, t in shifted.items()},
        "search": _search_summary(res),
        "simulated": [],
    }
    return res, record


def _carried_offset(
    anchor: _Simulated, sims: list[_Simulated], names: list[str], length: float
) -> dict[str, float]:
    """The surrogate's bias at the anchor from every simulated run: each run's offset (simulated -
    predicted) weighted by exp(-d^2 / (2 length^2)), d its recipe's distance from the anchor in normalized
    controls. The anchor's runs weigh 1 each; a run one trust radius away weighs 0.61, three radii away
    0.01. Seed noise in one run's offset is as large as the tolerances, and nearby recipes share the bias,
    so the runs around the anchor average the noise out while far ones barely count."""
    num = {m: 0.0 for m in names}
    den = 0.0
    for s in sims:
        w = math.exp(-0.5 * (float(np.linalg.norm(s.u - anchor.u)) / length) ** 2)
        for run in s.runs:
            for m in names:
                num[m] += w * (float(run[m]) - float(s.recipe["predicted"][m]))
            den += w
    return {m: num[m] / den for m in names}


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
    out = {
        "controls": s.recipe["controls"],
        "predicted": {m: s.recipe["predicted"][m] for m in names},
        "simulated": {m: s.entry["achieved"][m] for m in names},
        "offset": {
            m: round(float(s.entry["achieved"][m]) - float(s.recipe["predicted"][m]), 3) for m in names
        },
        "met": s.entry["met"],
        "missed": [m for m, v in s.entry["targets"].items() if not v["met"]],
        "simulator_s": s.entry["simulator_s"],
    }
    if s.confirmed is not None:
        out["confirmed"] = s.confirmed
        out["claimed"] = s.claimed
        if len(s.runs) > 1:
            out["confirmation"] = {m: round(float(s.runs[1][m]), 3) for m in names}
    return out


def _assemble(
    res0: dict[str, Any],
    spec: InverseSpec,
    loop: _Loop,
    rounds: list[dict[str, Any]],
    searches: list[dict[str, Any]],
    stopped: str,
    predicted_met: bool,
    cfg: RefineConfig,
    sim_seed: int | None,
    wall_s: float,
    cpu_s: float,
) -> dict[str, Any]:
    """The final result: rank 1 the verified (else the best simulated) recipe, then the surrogate's other
    round-0 recipes."""
    result = dict(res0)
    sims, confirming = loop.sims, loop.confirm is not None
    best = loop.verified() or (min(sims, key=lambda s: s.key(spec)) if sims else None)
    recipes: list[dict[str, Any]] = [_labelled(best.recipe, sims)] if best is not None else []
    for rec in res0["recipes"]:
        if len(recipes) == spec.k:
            break
        if best is None or _run_of(rec, [best]) is None:
            recipes.append(_labelled(rec, sims))
    for rank, r in enumerate(recipes, 1):
        r["rank"] = rank
    result["recipes"] = recipes
    runs = len(loop.entries)
    if stopped == "intervals":
        result["status"] = "unreachable"
        result["message"] = (
            f"{res0['message']}; every recipe found misses a target beyond its "
            f"{100 * cfg.unreachable_level:g} % interval, so no simulator run was made"
        )
    elif best is None:
        pass  # nothing simulated: the surrogate's status and message stand
    elif best.verified(confirming):
        how = "and in an independent confirmation run " if confirming else ""
        result["status"] = "verified"
        result["message"] = (
            f"the top recipe meets every target within its tolerance in the simulator {how}(round "
            f"{best.round}, {runs} simulator run{'s' if runs != 1 else ''})"
        )
    else:
        result["status"] = "unverified" if predicted_met else "unreachable"
        result["message"] = _miss_message(best, spec, predicted_met, len(sims), confirming)
    result["cost"] = _cost(res0, searches, loop, wall_s, cpu_s)
    result["simulator_calls"] = runs
    result["verification"] = {
        "seed": sim_seed,
        "recipes": loop.entries,
        **({"skipped": loop.skipped} if loop.skipped else {}),
    }
    result["refinement"] = {
        "surrogate_status": res0["status"],
        "rounds": rounds,
        "stopped": stopped,
        "confirmation": confirming,
        "config": asdict(cfg),
    }
    return result


def _labelled(rec: dict[str, Any], sims: list[_Simulated]) -> dict[str, Any]:
    """A recipe with what the simulator said of it (``verified_by``, the mean of its runs, its verdict)."""
    out = dict(rec)
    hit = _run_of(rec, sims)
    out["verified_by"] = "simulator" if hit is not None else "surrogate"
    if hit is not None:
        out["simulated"] = hit.entry["achieved"]
        out["simulated_targets"] = hit.entry["targets"]
        out["simulator_met"] = hit.entry["met"]
        out["round"] = hit.round
        if hit.confirmed is not None:
            out["confirmed"] = hit.confirmed
    return out


def _miss_message(best: _Simulated, spec: InverseSpec, predicted_met: bool, n: int, confirming: bool) -> str:
    missed = {k: v for k, v in misses(best.mean(), spec).items() if not v["met"]}
    parts = ", ".join(
        f"{k} {v['value']:.1f} nm (target {v['target']:g} +- {v['tol']:g}, miss {v['miss']:.1f} nm)"
        for k, v in missed.items()
    )
    lead = (
        "unverified: the surrogate finds recipes that meet the targets, but none of the "
        if predicted_met
        else "unreachable: no search finds a recipe predicted to meet the targets, and none of the "
    )
    if not parts:  # the mean meets them, but no single recipe met them twice
        return f"{lead}{n} simulated recipes met them in a run and its confirmation"
    what = " (mean of its runs)" if confirming else ""
    return f"{lead}{n} simulated recipes meets them; the closest simulated{what} gives {parts}"


def _cost(
    res0: dict[str, Any], searches: list[dict[str, Any]], loop: _Loop, wall_s: float, cpu_s: float
) -> dict[str, Any]:
    sim_s = [e["simulator_s"] for e in loop.entries]
    fwd = sum(c["forward_rollouts"] for c in searches)
    grad = sum(c["gradient_rollouts"] for c in searches)
    return {
        "method": res0["cost"]["method"],
        "forward_rollouts": fwd,
        "gradient_rollouts": grad,
        "rollouts": fwd + grad,
        "simulator_runs": len(loop.entries),
        "confirmation_runs": sum(e["run"] != "loop" for e in loop.entries),
        "simulator_wall_s": round(float(sum(sim_s)), 3),
        "search_wall_s": round(float(sum(c["wall_s"] for c in searches)), 3),
        "wall_s": round(wall_s, 3),
        "cpu_s": round(cpu_s, 3),
        "objective_trace": res0["cost"]["objective_trace"],
    }
