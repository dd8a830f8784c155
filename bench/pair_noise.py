"""Seed noise of a sweep pair's simulated difference, today's random streams against counter streams.

``simulate_pair_noise`` simulates each recipe of a few sweep pairs (two recipes that differ in one
control group) with the same seeds, once per random-number mode of the simulator (``SimConfig.rng_mode``:
"stream", one generator per kernel call; "counter", common random numbers keyed by (seed, macro step,
particle), ``nemsim.sim.kernels`` module docstring). With D_s = x_b,s - x_a,s the pair's difference under
seed s (both members one seed), per mode and pair:
  * paired noise: the seed-to-seed standard deviation (ddof 1) of D_s: of the final profile metrics
    (``nemsim.geometry.profile``, nm) and of the field (RMS over t = 1..T and every voxel of the
    per-voxel standard deviation, normalized SDF; also at the final state);
  * independent noise: the same for x_b,s+1 - x_a,s (cyclic in the seeds), two independently seeded runs;
    the ratio paired / independent is what a shared seed leaves of the noise;
  * the response: the mean of D_s.
Speed: CPU and wall seconds per trajectory, median over the runs of each mode.

Run: ``python -m bench.pair_noise --scene small --seeds 5 --out benchmarks/small/pair_noise.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.controls import CONTROL_NAMES
from nemsim.geometry.profile import profile_metrics_batch
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene
from nemsim.sim.config import RNG_MODES, SimConfig
from nemsim.sim.events import build_event_tables
from nemsim.sim.process import run_trajectory

PAIR_METRICS = ("etch_depth", "top_width", "bottom_width")


def default_pairs() -> dict[str, tuple[dict[str, float], dict[str, float]]]:
    """{name: (changes of member a, changes of member b)} from the design centre (raw units)."""
    from bench.invariants import centre_raw

    c = dict(zip(CONTROL_NAMES, centre_raw().tolist(), strict=True))
    energies = ("energy_mean_cl_plus", "energy_mean_cl2_plus", "energy_mean_ar_plus")
    return {
        "angle_cl_plus 50 -> 3000": ({"angle_cl_plus": 50.0}, {"angle_cl_plus": 3000.0}),
        "ion energies +10 %": ({}, {k: 1.1 * c[k] for k in energies}),
        "flux_cl_plus +10 %": ({}, {"flux_cl_plus": 1.1 * c["flux_cl_plus"]}),
    }


def _raw(changes: dict[str, float]) -> np.ndarray:
    from bench.invariants import centre_raw

    u = centre_raw().copy()
    for name, value in changes.items():
        u[CONTROL_NAMES.index(name)] = value
    return u


def _noise(diffs: list[np.ndarray], metrics: list[dict[str, float]]) -> dict[str, float]:
    d = np.stack(diffs)  # (S, T, 2, D, H, W)
    out = {"field": float(np.sqrt(np.mean(d.var(axis=0, ddof=1)))),
           "field_final": float(np.sqrt(np.mean(d[:, -1].var(axis=0, ddof=1))))}  # fmt: skip
    for k in PAIR_METRICS:
        out[k] = float(np.std([m[k] for m in metrics], ddof=1))
    return out


def simulate_pair_noise(
    scene: Scene,
    rules: RuleTensors,
    pairs: dict[str, tuple[dict[str, float], dict[str, float]]] | None = None,
    seeds: tuple[int, ...] = (1, 2, 3),
    config: SimConfig | None = None,
    modes: tuple[str, ...] = RNG_MODES,
    n_transitions: int | None = None,
) -> dict[str, Any]:
    """The measurement of the module docstring; JSON-ready. ``config``: the simulator (its ``rng_mode`` is
    replaced by each of ``modes``); ``n_transitions``: a shorter horizon (default the scene's)."""
    import dataclasses

    if len(seeds) < 2:
        raise ValueError(f"need at least two seeds, got {seeds}")
    pairs = pairs if pairs is not None else default_pairs()
    base = (config or SimConfig()).resolved(scene)
    recipes: dict[str, np.ndarray] = {}
    for a, b in pairs.values():
        for changes in (a, b):
            recipes.setdefault(json.dumps(changes, sort_keys=True), _raw(changes))
    states: dict[tuple[str, str, int], np.ndarray] = {}
    final: dict[tuple[str, str, int], dict[str, float]] = {}
    timing: dict[str, dict[str, list[float]]] = {m: {"cpu_s": [], "wall_s": []} for m in modes}
    tables = build_event_tables(rules, base)
    run_trajectory(scene, rules, recipes[next(iter(recipes))], np.random.default_rng(0), base, tables=tables,
                   n_transitions=1)  # compile outside the timings  # fmt: skip
    for s in seeds:
        for key, u in recipes.items():
            for mode in modes:  # interleaved so that a changing machine load hits both modes alike
                cfg = dataclasses.replace(base, rng_mode=mode)
                c0, w0 = time.process_time(), time.perf_counter()
                res = run_trajectory(scene, rules, u, np.random.default_rng(s), cfg, tables=tables,
                                     n_transitions=n_transitions)  # fmt: skip
                timing[mode]["cpu_s"].append(time.process_time() - c0)
                timing[mode]["wall_s"].append(time.perf_counter() - w0)
                states[mode, key, s] = res.states[1:]
                m = profile_metrics_batch(res.states[-1:], scene)
                final[mode, key, s] = {k: float(v[0]) for k, v in m.items()}

    steps = scene.n_transitions if n_transitions is None else n_transitions
    report: dict[str, Any] = {"scene": scene.name, "seeds": list(seeds), "steps": steps, "pairs": {},
                              "speed": {}}  # fmt: skip
    for name, (a, b) in pairs.items():
        ka, kb = json.dumps(a, sort_keys=True), json.dumps(b, sort_keys=True)
        row: dict[str, Any] = {"a": a, "b": b}
        for mode in modes:
            n = len(seeds)
            paired = [states[mode, kb, s] - states[mode, ka, s] for s in seeds]
            indep = [states[mode, kb, seeds[(i + 1) % n]] - states[mode, ka, seeds[i]] for i in range(n)]
            m_paired = [{k: final[mode, kb, s][k] - final[mode, ka, s][k] for k in PAIR_METRICS}
                        for s in seeds]  # fmt: skip
            m_indep = [{k: final[mode, kb, seeds[(i + 1) % n]][k] - final[mode, ka, seeds[i]][k]
                        for k in PAIR_METRICS} for i in range(n)]  # fmt: skip
            row[mode] = {
                "response": {k: float(np.mean([m[k] for m in m_paired])) for k in PAIR_METRICS},
                "paired": _noise(paired, m_paired),
                "independent": _noise(indep, m_indep),
            }
        report["pairs"][name] = row
    for mode in modes:
        report["speed"][mode] = {k: float(np.median(v)) for k, v in timing[mode].items()}
        report["speed"][mode]["runs"] = len(timing[mode]["cpu_s"])
    return report


def format_markdown(rep: dict[str, Any]) -> str:
    """The report as a markdown table: paired noise per mode, and its ratio to the independent noise."""
    modes = list(rep["speed"])
    cols = ("field", "field_final", *PAIR_METRICS)
    lines = [f"Scene {rep['scene']}, seeds {rep['seeds']}: seed-to-seed std of the paired difference "
             "(same seed for both members); in brackets: paired / independent seeds.", "",
             "| pair | mode | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]  # fmt: skip
    for name, row in rep["pairs"].items():
        for mode in modes:
            p, i = row[mode]["paired"], row[mode]["independent"]
            cells = []
            for c in cols:
                value = f"{p[c]:.4f}" if c.startswith("field") else f"{p[c]:.2f}"
                cells.append(f"{value} ({p[c] / i[c]:.2f})" if i[c] > 0 else value)
            lines.append(f"| {name} | {mode} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Response (mean paired difference, nm): " + "; ".join(
        f"{name}: " + ", ".join(f"{k} {row[modes[0]]['response'][k]:+.2f}" for k in PAIR_METRICS)
        for name, row in rep["pairs"].items()))  # fmt: skip
    lines.append("Speed (median per trajectory): " + "; ".join(
        f"{m} {v['cpu_s']:.2f} CPU s ({v['wall_s']:.2f} wall s)" for m, v in rep["speed"].items()))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.scenes import SCENES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="small", choices=sorted(SCENES))
    ap.add_argument("--seeds", type=int, default=3, help="seeds 1..N (N >= 2)")
    ap.add_argument("--out", type=Path, default=None, help="write the report as JSON (and .md beside it)")
    args = ap.parse_args(argv)
    rep = simulate_pair_noise(SCENES[args.scene], compile_rules(load_rules()),
                              seeds=tuple(range(1, args.seeds + 1)))  # fmt: skip
    text = format_markdown(rep)
    sys.stdout.write(text + "\n")
    if args.out is not None:
        args.out.write_text(json.dumps(rep, indent=1))
        args.out.with_suffix(".md").write_text(text + "\n")


if __name__ == "__main__":
    main()
