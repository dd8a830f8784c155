"""A trench's cross-section against its 3-D simulation: does ``SimConfig.domain = "section"`` give the 3-D
trench's mean profile, and how much faster?

One trench (``nemsim.geometry.feature.Feature``, default 40 nm wide under 80 nm of mask) on the scene's grid,
a few recipes (the centre of the control box and the corners ``bench.arde`` uses), each simulated on the full
3-D box and on the cross-section (``section_ny`` rows of y), seeds 1 and 2 each (recipe i, seed s:
``default_rng([s, i])``), the whole horizon.

Agreement, per recipe: the y-mean (mask, Si) field (the line's mean profile, (2, D, W)) at t = 2.5, 5, 7.5 and
10 s: RMS over the voxels of d = section mean - 3-D mean (each the mean of its two seeds) against the seed
spread s = sqrt(((f1 - f2)^2 + (q1 - q2)^2) / 4) (RMS over the voxels; the standard deviation of d when the
two agree in the mean), and the profile metrics of the final state (``nemsim.geometry.profile``: a trench is
read on its mean over y, widths across x) with the same d and s per metric. Speed: CPU seconds per
trajectory (one core, after a JIT warm-up; median over the runs), 3-D / section.

Run: ``python -m bench.trench_section --scene small --out benchmarks/small/trench_section`` (writes .json and
.md).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.geometry.feature import Feature
from nemsim.geometry.profile import profile_metrics
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene
from nemsim.sim.config import SimConfig
from nemsim.sim.events import build_event_tables
from nemsim.sim.process import run_trajectory

METRICS = ("etch_depth", "top_width", "bottom_width", "mask_loss")
TIMES_S = (2.5, 5.0, 7.5, 10.0)
SEEDS = (1, 2)


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a, dtype=np.float64))))


def bench_section(scene: Scene, rules: RuleTensors, recipes: dict[str, np.ndarray], section_ny: int = 2,
                  extra_timing_runs: int = 3) -> dict[str, Any]:
    """Simulate every recipe on both domains (module docstring); returns the JSON report."""
    configs = {"3d": SimConfig(), "section": SimConfig(domain="section", section_ny=section_ny)}
    tables = build_event_tables(rules, SimConfig().resolved(scene))
    idx = [int(round(t / scene.snapshot_dt_s)) for t in TIMES_S]
    cpu: dict[str, list[float]] = {k: [] for k in configs}
    run_trajectory(scene, rules, next(iter(recipes.values())), np.random.default_rng(0), configs["section"],
                   tables=tables, n_transitions=2)  # JIT warm-up
    rows = []
    for i, (name, u) in enumerate(recipes.items()):
        fields: dict[str, list[np.ndarray]] = {k: [] for k in configs}
        metrics: dict[str, list[dict[str, float]]] = {k: [] for k in configs}
        for key, cfg in configs.items():
            for s in SEEDS:
                c0 = time.process_time()
                r = run_trajectory(scene, rules, u, np.random.default_rng([s, i]), cfg, tables=tables)
                cpu[key].append(time.process_time() - c0)
                fields[key].append(r.states[idx].mean(axis=3, dtype=np.float64))  # (times, 2, D, W)
                metrics[key].append(profile_metrics(r.states[-1], scene))
            if key == "section":
                for k in range(extra_timing_runs):  # the section is fast: time it over more runs
                    c0 = time.process_time()
                    run_trajectory(scene, rules, u, np.random.default_rng([10 + k, i]), cfg, tables=tables)
                    cpu[key].append(time.process_time() - c0)
        f1, f2 = fields["3d"]
        q1, q2 = fields["section"]
        d = 0.5 * (q1 + q2) - 0.5 * (f1 + f2)  # (times, 2, D, W)
        spread = np.sqrt(((f1 - f2) ** 2 + (q1 - q2) ** 2) / 4.0)
        field = [{"t_s": t, "channel": ch, "rms_d": _rms(d[j, c]), "rms_s": _rms(spread[j, c])}
                 for j, t in enumerate(TIMES_S) for c, ch in enumerate(("mask", "si"))]
        per_metric = {}
        for m in METRICS:
            f = [x[m] for x in metrics["3d"]]
            q = [x[m] for x in metrics["section"]]
            spread_m = float(np.sqrt(((f[0] - f[1]) ** 2 + (q[0] - q[1]) ** 2) / 4.0))
            per_metric[m] = {"3d": f, "section": q, "d": float(np.mean(q) - np.mean(f)), "s": spread_m}
        rows.append({"recipe": name, "controls": [float(v) for v in u], "field": field,
                     "metrics": per_metric})
    med = {k: statistics.median(v) for k, v in cpu.items()}
    return {"scene": scene.name, "feature": Feature.of(scene).to_dict(), "section_ny": section_ny,
            "seeds": list(SEEDS), "recipes": rows, "cpu_s": med, "cpu_s_runs": cpu,
            "speedup_cpu": med["3d"] / med["section"]}


def to_markdown(rep: dict[str, Any], command: str, cpu: str) -> str:
    f = rep["feature"]
    out = [f"# Trench cross-section against the 3-D trench on `{rep['scene']}`", "",
           f"Command: `{command}`  ", f"CPU: {cpu}, one core per run (shared machine: CPU seconds)", "",
           f"Trench {f['cd_nm']:g} nm wide under {f['mask_nm']:g} nm of mask; cross-section of "
           f"{rep['section_ny']} rows of y (half the x extent between mirror walls); seeds "
           f"{rep['seeds']} per domain (bench/trench_section.py). d = section mean - 3-D mean; s = pooled "
           "seed spread, the standard deviation of d if the two agree in the mean (|d|/s ~ Student t, "
           "2 dof).",
           "", "## y-mean field (normalized SDF), RMS over voxels", "",
           "| recipe | t (s) | channel | RMS d | RMS s | d / s |", "|---|---:|---|---:|---:|---:|"]
    for row in rep["recipes"]:
        for x in row["field"]:
            out.append(f"| {row['recipe']} | {x['t_s']:g} | {x['channel']} | {x['rms_d']:.4f} | "
                       f"{x['rms_s']:.4f} | {x['rms_d'] / max(x['rms_s'], 1e-12):.2f} |")
    out += ["", "## Final profile metrics (nm; the 3-D trench read on its mean over y)", "",
            "| recipe | metric | 3-D seeds | section seeds | d | s | abs(d) / s |",
            "|---|---|---|---|---:|---:|---:|"]
    for row in rep["recipes"]:
        for m, x in row["metrics"].items():
            out.append(f"| {row['recipe']} | {m} | {x['3d'][0]:.1f}, {x['3d'][1]:.1f} | "
                       f"{x['section'][0]:.1f}, {x['section'][1]:.1f} | {x['d']:+.2f} | {x['s']:.2f} | "
                       f"{abs(x['d']) / max(x['s'], 1e-9):.2f} |")
    c = rep["cpu_s"]
    out += ["", "## Speed (CPU s per trajectory, median)", "",
            f"3-D: {c['3d']:.2f} s ({len(rep['cpu_s_runs']['3d'])} runs); section: {c['section']:.3f} s "
            f"({len(rep['cpu_s_runs']['section'])} runs); speed-up {rep['speedup_cpu']:.0f}x.", ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    from bench.arde import recipes as arde_recipes
    from bench.arde import write_report
    from bench.machine import cpu_name
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.scenes import get_scene

    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="python -m bench.trench_section", description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="small")
    ap.add_argument("--cd-nm", type=float, default=40.0)
    ap.add_argument("--mask-nm", type=float, default=80.0)
    ap.add_argument("--section-ny", type=int, default=2)
    ap.add_argument("--recipes", default="centre", help="comma-separated names from bench.arde.recipes()")
    ap.add_argument("--out", type=Path, default=None, help="writes OUT.json and OUT.md")
    args = ap.parse_args(argv)
    scene = Feature("trench", args.cd_nm, args.mask_nm).apply(get_scene(args.scene))
    all_recipes = arde_recipes()
    chosen = {n: all_recipes[n] for n in args.recipes.split(",")}
    rep = bench_section(scene, compile_rules(load_rules()), chosen, args.section_ny)
    command, cpu = " ".join(["python -m bench.trench_section", *argv]), cpu_name()
    write_report(args.out, to_markdown(rep, command, cpu), {"command": command, "cpu": cpu, **rep})


if __name__ == "__main__":
    main()
