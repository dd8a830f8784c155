"""Quarter-domain validation (``nemsim bench sim-quarter``): does the simulator's quarter domain
(``SimConfig.domain = "quarter"``, ``nemsim.sim.config`` module docstring) give the full domain's profiles
at a fraction of the time?

Recipes: a fresh Latin hypercube of the control box (``nemsim.controls.lhs_design`` with its own seed, not
the training design's), each simulated on the scene's full box and on its quarter, each with two seeds
(recipe i, seed s: ``default_rng([s, i])``, as ``nemsim bench noise``), the whole horizon.

Per recipe and profile metric (``nemsim.geometry.profile``, final state, nm): the full and the quarter mean
of the two seeds, their difference d = quarter - full, and the seed spread

    s = sqrt(((f1 - f2)^2 + (q1 - q2)^2) / 4),

the pooled estimate of one run's seed-to-seed standard deviation sigma, which is also the standard deviation
of d when the two domains agree in the mean (each mean of two seeds has sigma / sqrt(2)). The ratio |d| / s
then follows Student's t with 2 degrees of freedom: heavy-tailed, it exceeds 1 for 42 % and 2 for 18 % of
the recipes by chance alone. Over the recipes: RMS d / RMS s, about 1 when the domains agree (its square
follows F(n, 2n) for n recipes of equal spread, so beyond ``rms_ratio_95`` = sqrt(F_0.95(n, 2n)), 1.53 for
10 recipes, it is unlikely by chance; unequal spreads widen that); the mean d with its standard error (a
systematic shift); each domain's own seed-to-seed standard deviation (RMS over the recipes of
|x1 - x2| / sqrt(2)). The quarter's noise is mirrored into four copies, so a metric that averages around the
hole (a width) may be noisier in the quarter at the same noise per voxel, while one read at a point (the
depth on the axis) is not; s pools both. Fields: the Avg RMSE (``nemsim.evaluation.metrics``, t = 1..H)
between the two full seeds, the two quarter seeds and full against quarter (mean of the four pairs); the
last is the floor of the first two when the domains agree. Speed: wall and CPU seconds per trajectory of
each run (one core, after a JIT warm-up), and the Psi (SDF) seconds of one trajectory's states, which the
quarter keeps at full size.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from collections.abc import Callable

import numpy as np

from nemsim.evaluation.metrics import rmse_per_step
from nemsim.geometry.profile import profile_metrics
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene
from nemsim.sim.config import SimConfig
from nemsim.sim.events import build_event_tables
from nemsim.sim.process import initial_state, run_trajectory

METRICS = ("etch_depth", "top_width", "bottom_width", "mask_loss")
DOMAINS = ("full", "quarter")
# P(|t_2| > 1), P(|t_2| > 2): the share of recipes beyond 1 and 2 seed spreads by chance (module docstring)
CHANCE_OVER = {1: 1.0 - 1.0 / math.sqrt(3.0), 2: 1.0 - 2.0 / math.sqrt(6.0)}


def _psi_seconds(scene: Scene, config: SimConfig) -> float:
    """Wall seconds of the n_states Psi evaluations of one trajectory (``initial_state`` = one Psi)."""
    initial_state(scene, config)  # compiled
    t0 = time.perf_counter()
    for _ in range(scene.n_states):
        initial_state(scene, config)
    return time.perf_counter() - t0


def bench_quarter(
    scene: Scene,
    rules: RuleTensors,
    design: np.ndarray,
    config: SimConfig | None = None,
    seeds: tuple[int, int] = (1, 2),
    log: Callable[[str], None] | None = None,
) -> dict:
    """Full against quarter domain on the recipes ``design`` (n, 14) (module docstring): the report."""
    base = (config or SimConfig()).resolved(scene)
    configs = {d: dataclasses.replace(base, domain=d) for d in DOMAINS}
    configs["quarter"].check_scene(scene)
    tables = build_event_tables(rules, base)
    for cfg in configs.values():  # JIT warm-up of both kernels' paths
        run_trajectory(scene, rules, design[0], np.random.default_rng(0), cfg, tables=tables, n_transitions=1)
    rows = []
    for i, u in enumerate(design):
        runs: dict[str, list[dict]] = {d: [] for d in DOMAINS}
        states: dict[str, list[np.ndarray]] = {d: [] for d in DOMAINS}
        for s in seeds:
            for d in DOMAINS:
                c0 = time.process_time()
                res = run_trajectory(
                    scene, rules, u, np.random.default_rng([s, i]), configs[d], tables=tables
                )
                cpu = time.process_time() - c0
                m = profile_metrics(res.states[-1], scene)
                runs[d].append(
                    {
                        "seed": s,
                        "wall_s": res.wall_s,
                        "cpu_s": cpu,
                        "primaries": res.counters["primary"],
                        **{k: m[k] for k in METRICS},
                    }
                )
                states[d].append(res.states[1:])
        row: dict = {"recipe": i, "controls": [float(v) for v in u], "runs": runs}
        for k in METRICS:
            f = [r[k] for r in runs["full"]]
            q = [r[k] for r in runs["quarter"]]
            diff = float(np.mean(q) - np.mean(f))
            spread = math.sqrt(((f[0] - f[1]) ** 2 + (q[0] - q[1]) ** 2) / 4.0)
            row[k] = {
                "full_mean": float(np.mean(f)),
                "quarter_mean": float(np.mean(q)),
                "diff": diff,
                "spread": spread,
                "ratio": abs(diff) / spread if spread > 0 else None,
            }

        def avg_rmse(a: np.ndarray, b: np.ndarray) -> float:
            return float(rmse_per_step(a[None], b[None]).mean())

        cross = [avg_rmse(a, b) for a in states["full"] for b in states["quarter"]]
        row["avg_rmse"] = {
            "full_full": avg_rmse(*states["full"]),
            "quarter_quarter": avg_rmse(*states["quarter"]),
            "full_quarter": float(np.mean(cross)),
        }
        rows.append(row)
        if log is not None:
            log(_row_line(row))
    return {
        "scene": scene.name,
        "seeds": list(seeds),
        "n_recipes": len(rows),
        "metrics": list(METRICS),
        "rows": rows,
        "summary": _summary(rows),
        "speed": _speed(rows, {d: _psi_seconds(scene, cfg) for d, cfg in configs.items()}),
    }


def _row_line(row: dict) -> str:
    cells = [f"{k} {row[k]['diff']:+.2f}/{row[k]['spread']:.2f}" for k in METRICS]
    w = [statistics.mean(r["wall_s"] for r in row["runs"][d]) for d in DOMAINS]
    return (
        f"recipe {row['recipe']}: " + ", ".join(cells) + f" nm; wall {w[0]:.2f} s full, {w[1]:.2f} s quarter"
    )


def _summary(rows: list[dict]) -> dict:
    """Per metric over the recipes: RMS d, RMS s, their ratio, mean d and its standard error, counts of
    |d| / s beyond 1 and 2 (with the share expected by chance); the mean Avg RMSEs."""
    from scipy.stats import f as f_dist

    out: dict = {}
    n = len(rows)
    out["rms_ratio_95"] = float(math.sqrt(f_dist.ppf(0.95, n, 2 * n)))
    for k in METRICS:
        d = np.array([r[k]["diff"] for r in rows])
        s = np.array([r[k]["spread"] for r in rows])
        ratios = [r[k]["ratio"] for r in rows if r[k]["ratio"] is not None]
        rms_d, rms_s = float(np.sqrt(np.mean(d**2))), float(np.sqrt(np.mean(s**2)))
        # each domain's own seed-to-seed standard deviation, RMS over the recipes: (x1 - x2)^2 / 2 per recipe
        seed_sd = {
            dom: float(
                np.sqrt(np.mean([(r["runs"][dom][0][k] - r["runs"][dom][1][k]) ** 2 / 2.0 for r in rows]))
            )
            for dom in DOMAINS
        }
        se = float(d.std(ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
        out[k] = {
            "full_mean": float(np.mean([r[k]["full_mean"] for r in rows])),
            "quarter_mean": float(np.mean([r[k]["quarter_mean"] for r in rows])),
            "rms_diff": rms_d,
            "rms_spread": rms_s,
            "rms_ratio": rms_d / rms_s if rms_s > 0 else None,
            "mean_diff": float(d.mean()),
            "mean_diff_se": se,
            "seed_sd_full": seed_sd["full"],
            "seed_sd_quarter": seed_sd["quarter"],
            "max_ratio": max(ratios) if ratios else None,
            "n_over_1": sum(v > 1 for v in ratios),
            "n_over_2": sum(v > 2 for v in ratios),
            "chance_over_1": CHANCE_OVER[1] * len(ratios),
            "chance_over_2": CHANCE_OVER[2] * len(ratios),
        }
    out["avg_rmse"] = {
        key: float(np.mean([r["avg_rmse"][key] for r in rows]))
        for key in ("full_full", "quarter_quarter", "full_quarter")
    }
    return out


def _speed(rows: list[dict], psi_s: dict[str, float]) -> dict:
    out: dict = {}
    for d in DOMAINS:
        runs = [r for row in rows for r in row["runs"][d]]
        out[d] = {
            key: {
                "median": statistics.median(r[key] for r in runs),
                "mean": statistics.mean(r[key] for r in runs),
            }
            for key in ("wall_s", "cpu_s", "primaries")
        }
        out[d]["psi_s_per_trajectory"] = psi_s[d]
    for key in ("wall_s", "cpu_s"):
        out[f"speedup_{key}"] = out["full"][key]["median"] / out["quarter"][key]["median"]
    return out


def to_markdown(rep: dict, command: str, cpu: str) -> str:
    """The report as Markdown: the verdict per metric, the recipes, the speed."""
    s, sp = rep["summary"], rep["speed"]
    lines = [
        f"# Quarter domain against full domain on `{rep['scene']}`",
        "",
        f"Command: `{command}`  ",
        f"CPU: {cpu}, one core per run (shared machine: compare CPU seconds)",
        "",
        f"{rep['n_recipes']} Latin-hypercube recipes, each simulated on the full box and on its quarter "
        f"between mirror walls (`SimConfig.domain`), seeds {rep['seeds'][0]} and {rep['seeds'][1]} each, "
        "final state. d = quarter mean - full mean of the two seeds; s = sqrt(((f1 - f2)^2 + (q1 - q2)^2) "
        "/ 4), the pooled seed-to-seed standard deviation of one run, which is the standard deviation of d "
        "if the domains agree in the mean. |d| / s then follows Student's t with 2 degrees of freedom "
        "(beyond 1 for 42 %, beyond 2 for 18 % of the recipes by chance); RMS d / RMS s is about 1 when "
        "they agree "
        "(bench/sim_quarter.py).",
        "",
        "## Per metric over the recipes (nm)",
        "",
        "| metric | full mean | quarter mean | mean d +- SE | RMS d | RMS s | RMS d / RMS s | max abs(d)/s "
        "| recipes abs(d)/s > 1 (chance) | > 2 (chance) | seed sd full | seed sd quarter |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for k in METRICS:
        m = s[k]
        lines.append(
            f"| {k} | {m['full_mean']:.2f} | {m['quarter_mean']:.2f} | {m['mean_diff']:+.2f} +- "
            f"{m['mean_diff_se']:.2f} | {m['rms_diff']:.2f} | {m['rms_spread']:.2f} | "
            f"{_num(m['rms_ratio'])} | {_num(m['max_ratio'])} | {m['n_over_1']} ({m['chance_over_1']:.1f}) | "
            f"{m['n_over_2']} ({m['chance_over_2']:.1f}) | {m['seed_sd_full']:.2f} | "
            f"{m['seed_sd_quarter']:.2f} |"
        )
    a = s["avg_rmse"]
    lines += [
        "",
        f"RMS d / RMS s beyond {s['rms_ratio_95']:.2f} (sqrt of the 95 % point of F({rep['n_recipes']}, "
        f"{2 * rep['n_recipes']})) would be unlikely by chance if the domains agreed in the mean.",
        "",
        f"Field Avg RMSE (normalized SDF, t = 1..H, mean over recipes): full seed vs full seed "
        f"{a['full_full']:.5f}, quarter vs quarter {a['quarter_quarter']:.5f}, full vs quarter "
        f"{a['full_quarter']:.5f} (mean of the 4 pairs).",
        "",
        "## Speed per trajectory (seconds; median over all runs)",
        "",
        "| domain | wall s | CPU s | primaries | Psi s (of the wall) |",
        "|---|---:|---:|---:|---:|",
    ]
    for d in DOMAINS:
        v = sp[d]
        lines.append(
            f"| {d} | {v['wall_s']['median']:.2f} | {v['cpu_s']['median']:.2f} | "
            f"{v['primaries']['median']:.0f} | {v['psi_s_per_trajectory']:.2f} |"
        )
    lines += [
        "",
        f"Speed-up full / quarter: {sp['speedup_wall_s']:.2f}x wall, {sp['speedup_cpu_s']:.2f}x CPU. The "
        "quarter traces a quarter of the particles; Psi still runs on the full box.",
        "",
        "## Per recipe: d / s per metric (nm), Avg RMSE, wall s (mean of the two seeds)",
        "",
        "| recipe | " + " | ".join(METRICS) + " | Avg RMSE full-full | quarter-quarter | full-quarter "
        "| wall full | wall quarter |",
        "|---:|" + "---:|" * (len(METRICS) + 5),
    ]
    for row in rep["rows"]:
        cells = [f"{row[k]['diff']:+.2f} / {row[k]['spread']:.2f}" for k in METRICS]
        r = row["avg_rmse"]
        w = [statistics.mean(x["wall_s"] for x in row["runs"][d]) for d in DOMAINS]
        lines.append(
            f"| {row['recipe']} | " + " | ".join(cells) + f" | {r['full_full']:.5f} | "
            f"{r['quarter_quarter']:.5f} | {r['full_quarter']:.5f} | {w[0]:.2f} | {w[1]:.2f} |"
        )
    return "\n".join(lines) + "\n"


def _num(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}"
