"""`nemsim bench inverse`: inverse design judged by the simulator.

Reachable targets are the exact profile metrics (final step) of simulator runs (seed 1) of held-out recipes:
fresh Latin-hypercube points of the control box (``lhs_unit(n, seed)``, a seed other than the design's, so
no target recipe is a training case), with the default tolerances (depth +-5 nm, top and bottom width +-3
nm, mask loss +-2 nm). Unreachable targets ask for what no recipe in the box gives (``UNREACHABLE``). For
each target the search (``nemsim.analysis.inverse.search``, default configuration) returns recipes and the
simulator runs the top-1 with another seed (2): success when that run meets every tolerance (reachable) or
when the target is reported unreachable (unreachable). As a reference for the simulator's own noise, the
target recipe itself is simulated with seed 2 too ("oracle": the true recipe judged the same way).

``refine`` also (or only) runs the simulator-corrected design (``nemsim.analysis.inverse.refine``, variant
"<method>+refine"): its simulator runs inside the loop use seed 3 (``LOOP_SEED``), so the judging run
(seed 2) is an independent one and a recipe the loop verified can still miss there (the simulator's seed
noise). Its design cost includes those simulator runs (in-process, so in the CPU seconds too).

The target machinery (``held_out_unit``, ``reachable_case``, ``unreachable_cases``) is shared with
``nemsim bench design-cost`` (``bench.design_cost``), which also places held-out recipes near the faces and
the corners of the control box.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.controls import CONTROL_NAMES, from_unit, lhs_unit

REACHABLE_METRICS = ("etch_depth", "top_width", "bottom_width", "mask_loss")
UNREACHABLE: tuple[tuple[str, dict[str, Any]], ...] = (
    ("deeper than the Si layer (160 nm)", {"etch_depth": {"value": 200.0, "tol": 5.0}}),
    (
        "top opening far wider than the mask opening",
        {"etch_depth": {"value": 80.0, "tol": 5.0}, "top_width": {"value": 70.0, "tol": 3.0}},
    ),
    (
        "bottom wider than the mask opening",
        {"etch_depth": {"value": 100.0, "tol": 5.0}, "bottom_width": {"value": 50.0, "tol": 3.0}},
    ),
)
TARGET_SEED, VERIFY_SEED, LOOP_SEED = 1, 2, 3
REFINE_CHOICES = ("off", "on", "both")
PLACEMENTS = ("interior", "faces", "corners")  # where held-out recipes lie in the control box
EDGE = 0.05  # "near" a bound: within this share of the control's range (unit coordinates)
FinalMetrics = Callable[[np.ndarray, int], dict[str, float]]  # (raw (14,), seed) -> final-step metrics, nm


def held_out_unit(n: int, seed: int, placement: str = "interior") -> np.ndarray:
    """(n, 14) held-out recipes in unit coordinates of the control box (no training design uses ``seed``).

    "interior": ``lhs_unit(n, seed)``, the Latin-hypercube points ``run_bench`` takes. "faces": the same
    points with 1 to 3 random controls moved to within ``EDGE`` of a bound (near a face or an edge of the
    box). "corners": every control within ``EDGE`` of its low or high bound, at random (near a vertex).
    """
    if placement not in PLACEMENTS:
        raise ValueError(f"placement must be one of {list(PLACEMENTS)}, got {placement!r}")
    xi = lhs_unit(n, seed)
    if placement == "interior":
        return xi
    rng = np.random.default_rng([seed, PLACEMENTS.index(placement)])
    near = rng.uniform(0.0, EDGE, size=xi.shape)  # (n, 14) distance from the bound
    high = rng.random(xi.shape) < 0.5
    edge = np.where(high, 1.0 - near, near)
    if placement == "corners":
        return edge
    out = xi.copy()
    for i in range(n):
        cols = rng.choice(xi.shape[1], size=int(rng.integers(1, 4)), replace=False)
        out[i, cols] = edge[i, cols]
    return out


def reachable_case(name: str, raw: np.ndarray, final: FinalMetrics) -> dict[str, Any]:
    """A reachable target: the final-step metrics (``REACHABLE_METRICS``, default tolerances) of the
    simulator's run of ``raw`` with ``TARGET_SEED``; the "oracle" is the run with ``VERIFY_SEED`` (the
    target's own recipe judged as a designed one would be: the simulator's seed noise)."""
    m = final(raw, TARGET_SEED)
    return {
        "name": name,
        "reachable": True,
        "spec": {"targets": {k: {"value": round(float(m[k]), 2)} for k in REACHABLE_METRICS}},
        "recipe": {n: float(v) for n, v in zip(CONTROL_NAMES, raw, strict=True)},
        "oracle": {k: float(v) for k, v in final(raw, VERIFY_SEED).items()},
    }


def unreachable_cases(n: int = len(UNREACHABLE)) -> list[dict[str, Any]]:
    """The first ``n`` deliberately unreachable targets (``UNREACHABLE``) as cases."""
    if not 0 <= n <= len(UNREACHABLE):
        raise ValueError(f"--unreachable must be in 0..{len(UNREACHABLE)}, got {n}")
    return [
        {"name": name, "reachable": False, "spec": {"targets": targets}} for name, targets in UNREACHABLE[:n]
    ]


def run_bench(
    checkpoint: str | Path,
    *,
    n_targets: int = 8,
    seed: int = 7,
    methods: tuple[str, ...] = ("auto",),
    n_unreachable: int = len(UNREACHABLE),
    refine: str = "both",
    refine_config: Any = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run the benchmark (module docstring); returns the JSON-ready report.

    ``refine``: "off" (the search only), "on" (only the simulator-corrected variant of each method) or
    "both"; ``refine_config`` a ``RefineConfig`` (None: its defaults).
    """
    from nemsim.analysis.inverse import RefineConfig, load_inverse_context, simulator_config, spec_from_dict
    from nemsim.evaluation.truth import SimTruth

    if n_targets < 1:
        raise ValueError(f"--targets must be >= 1, got {n_targets}")
    if not 0 <= n_unreachable <= len(UNREACHABLE):
        raise ValueError(f"--unreachable must be in 0..{len(UNREACHABLE)}, got {n_unreachable}")
    bad = [m for m in methods if m not in ("auto", "adam", "cma")]
    if bad or not methods:
        raise ValueError(f"unknown methods {bad or methods}; expected a subset of ['auto', 'adam', 'cma']")
    if refine not in REFINE_CHOICES:
        raise ValueError(f"--refine must be one of {list(REFINE_CHOICES)}, got {refine!r}")
    rcfg = (refine_config or RefineConfig()).check()
    variants = [(m, m, False) for m in methods if refine != "on"]
    variants += [(f"{m}+refine", m, True) for m in methods if refine != "off"]
    ctx = load_inverse_context(checkpoint)
    scene = ctx.scene
    step = scene.n_transitions
    raw_targets = from_unit(held_out_unit(n_targets, seed))  # (n, 14) held-out recipes
    cases: list[dict[str, Any]] = []
    t_start, c_start = time.perf_counter(), time.process_time()
    with SimTruth(scene, ctx.loaded.rules, simulator_config(ctx.loaded), progress=progress) as truth:
        truth.ensure(
            [(r, TARGET_SEED) for r in raw_targets] + [(r, VERIFY_SEED) for r in raw_targets],
            desc="target runs",
        )

        def final(raw: np.ndarray, seed: int) -> dict[str, float]:
            return {k: float(v[step]) for k, v in truth.metrics(raw, seed).items()}

        cases += [reachable_case(f"held-out {i + 1}", raw, final) for i, raw in enumerate(raw_targets)]
        cases += unreachable_cases(n_unreachable)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(
                total=len(cases) * len(variants), unit="design", desc="inverse designs", dynamic_ncols=True
            )
        try:
            for case in cases:
                spec = spec_from_dict(case["spec"])
                case["spec"] = {
                    "targets": {k: {"value": t.value, "tol": t.tol} for k, t in spec.targets.items()}
                }
                if case["reachable"]:
                    case["oracle_met"] = all(
                        abs(case["oracle"][k] - t.value) <= t.tol for k, t in spec.targets.items()
                    )
                case["runs"] = {}
                for label, method, refined in variants:
                    case["runs"][label] = _inverse_run(
                        ctx, spec, method, case["reachable"], truth, step, rcfg if refined else None
                    )
                    if bar is not None:
                        bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        n_sim = truth.n_simulated
        sim_s = truth.sim_wall_s
    summary = {label: _summary(cases, label) for label, _, _ in variants}
    from bench.machine import cpu_name

    return {
        "checkpoint": Path(checkpoint).name,
        "model_id": ctx.model_id,
        "scene": scene.name,
        "step": step,
        "targets_seed": seed,
        "target_sim_seed": TARGET_SEED,
        "verify_sim_seed": VERIFY_SEED,
        "loop_sim_seed": LOOP_SEED,
        "refine_config": asdict(rcfg) if refine != "off" else None,
        "oracle_met": sum(bool(c.get("oracle_met")) for c in cases if c["reachable"]),
        "summary": summary,
        "cases": cases,
        "simulations": n_sim,
        "simulator_wall_s": round(sim_s, 1),
        "total_wall_s": round(time.perf_counter() - t_start, 1),
        "total_cpu_s": round(time.process_time() - c_start, 1),
        "cpu": cpu_name(),
        "intervals": {"available": ctx.calibration is not None},
    }


def _inverse_run(
    ctx: Any, spec: Any, method: str, reachable: bool, truth: Any, step: int, refine: Any = None
) -> dict[str, Any]:
    """One inverse design of ``spec`` with ``method`` (simulator-corrected with a ``refine`` config), its
    top recipe simulated (verification seed) and judged: a reachable target succeeds when the simulator
    meets every tolerance, an unreachable one when the design says unreachable."""
    from dataclasses import replace

    from nemsim.analysis.inverse import TARGET_METRICS, refine_with_simulator, search

    s = replace(spec, search=replace(spec.search, method=method))  # type: ignore[arg-type]
    if refine is None:
        res = search(ctx, s, seed=0)
    else:

        def simulate(raw: np.ndarray, at: int) -> dict[str, float]:
            return {k: float(v[at]) for k, v in truth.metrics(raw, LOOP_SEED).items()}

        res = refine_with_simulator(ctx, s, simulate, refine=refine, seed=0, sim_seed=LOOP_SEED)
    top = res["recipes"][0]
    raw = np.array([top["controls"][n] for n in CONTROL_NAMES])
    achieved = {k: float(v[step]) for k, v in truth.metrics(raw, VERIFY_SEED).items()}
    sim_met = all(abs(achieved[k] - t.value) <= t.tol for k, t in spec.targets.items())
    covered = {}
    for level, per in (top.get("intervals") or {}).items():
        covered[level] = {
            k: bool(per[k][0] is not None and per[k][1] is not None and per[k][0] <= achieved[k] <= per[k][1])
            for k in spec.targets
            if k in per
        }
    success = sim_met if reachable else res["status"] == "unreachable"
    out = {
        "status": res["status"],
        "success": bool(success),
        "simulator_met": bool(sim_met),
        "predicted": {k: top["predicted"][k] for k in TARGET_METRICS},
        "achieved": {k: round(achieved[k], 3) for k in TARGET_METRICS},
        "interval_covers": covered,
        "training_data": top["training_data"]["flag"],
        "controls": top["controls"],
        "cost": res["cost"],
    }
    if refine is not None:
        out["refinement"] = res["refinement"]
        out["loop_simulated"] = top.get("simulated")
    return out


def _summary(cases: list[dict[str, Any]], method: str) -> dict[str, Any]:
    """Successes, detections and design cost of one method over the cases."""
    reach = [c["runs"][method] for c in cases if c["reachable"]]
    unreach = [c["runs"][method] for c in cases if not c["reachable"]]
    costs = [c["runs"][method]["cost"] for c in cases]
    runs = [c["runs"][method]["cost"].get("simulator_runs", 0) for c in cases]
    return {
        "reachable_success": sum(r["success"] for r in reach),
        "loop_verified": sum(r["status"] == "verified" for r in reach),
        "reachable": len(reach),
        "unreachable_detected": sum(r["success"] for r in unreach),
        "unreachable": len(unreach),
        "false_unreachable": sum(r["status"] == "unreachable" for r in reach),
        "design_cpu_s_mean": round(float(np.mean([c["cpu_s"] for c in costs])), 2),
        "design_cpu_s_max": round(float(np.max([c["cpu_s"] for c in costs])), 2),
        "design_wall_s_mean": round(float(np.mean([c["wall_s"] for c in costs])), 2),
        "design_wall_s_max": round(float(np.max([c["wall_s"] for c in costs])), 2),
        "simulator_runs_mean": round(float(np.mean(runs)), 2),
        "rollouts_mean": round(float(np.mean([c["rollouts"] for c in costs])), 1),
    }


def format_bench(rep: dict[str, Any]) -> str:
    """Markdown report."""
    lines = [
        f"# Inverse design judged by the simulator ({rep['checkpoint']}, scene {rep['scene']})",
        "",
        f"{sum(c['reachable'] for c in rep['cases'])} reachable targets (final-step metrics of simulator "
        f"runs, seed {rep['target_sim_seed']}, of held-out Latin-hypercube recipes, seed "
        f"{rep['targets_seed']}) and {sum(not c['reachable'] for c in rep['cases'])} unreachable ones. "
        f"Success: the simulator run (seed {rep['verify_sim_seed']}) of the top-1 recipe meets every "
        "tolerance (depth +-5 nm, widths +-3 nm, mask loss +-2 nm); an unreachable target must be "
        f"reported unreachable. Oracle: the target's own recipe, seed {rep['verify_sim_seed']}, meets "
        f"{rep['oracle_met']} of the reachable targets (the simulator's seed noise).",
        "",
        "| method | reachable met (simulator) | verified in the loop | unreachable detected | "
        "reachable called unreachable | design CPU s (mean / max) | wall s (mean / max) | rollouts (mean) | "
        "simulator runs in the design (mean) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for m, s in rep["summary"].items():
        loop = f"{s['loop_verified']}/{s['reachable']}" if m.endswith("+refine") else "-"
        lines.append(
            f"| {m} | {s['reachable_success']}/{s['reachable']} | {loop} | {s['unreachable_detected']}/"
            f"{s['unreachable']} | {s['false_unreachable']} | {s['design_cpu_s_mean']:.1f} / "
            f"{s['design_cpu_s_max']:.1f} | {s['design_wall_s_mean']:.1f} / {s['design_wall_s_max']:.1f} | "
            f"{s['rollouts_mean']:.0f} | {s['simulator_runs_mean']:.1f} |"
        )
    if rep.get("refine_config"):
        lines += [
            "",
            "+refine: simulator-corrected design, its in-loop simulator runs with seed "
            f"{rep['loop_sim_seed']} (independent of the judging seed {rep['verify_sim_seed']}); "
            "configuration "
            + ", ".join(f"{k}={v}" for k, v in rep["refine_config"].items())
            + ". 'verified in the loop': the design's own simulator run met every tolerance.",
        ]
    lines += [
        "",
        "Per target (predicted / simulated at the top-1 recipe, nm; targets in brackets):",
        "",
        "| target | method | status | success | etch depth | top width | bottom width | mask loss | data |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in rep["cases"]:
        for m, r in c["runs"].items():
            cells = []
            for k in ("etch_depth", "top_width", "bottom_width", "mask_loss"):
                t = c["spec"]["targets"].get(k)
                tgt = f" ({t['value']:g})" if t else ""
                cells.append(f"{r['predicted'][k]:.1f} / {r['achieved'][k]:.1f}{tgt}")
            lines.append(
                f"| {c['name']} | {m} | {r['status']} | {'yes' if r['success'] else 'NO'} | "
                + " | ".join(cells)
                + f" | {r['training_data']} |"
            )
    lines += [
        "",
        f"{rep['simulations']} simulator runs ({rep['simulator_wall_s']} s wall); whole benchmark "
        f"{rep['total_wall_s']} s wall, {rep['total_cpu_s']} s CPU of this process (CPU: {rep['cpu']}).",
    ]
    return "\n".join(lines) + "\n"


def write_bench(rep: dict[str, Any], out_dir: str | Path) -> dict[str, str]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "inverse.md").write_text(format_bench(rep))
    (out / "inverse.json").write_text(json.dumps(rep, indent=1))
    return {"md": str(out / "inverse.md"), "json": str(out / "inverse.json")}
