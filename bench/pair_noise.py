"""Seed noise of a sweep pair's simulated difference: the simulator's shared stream against common random
numbers (``SimConfig.rng_mode``, ``nemsim.sim.kernels`` module docstring, "Random numbers").

``simulate_pair_noise`` simulates both recipes of a few sweep pairs (two recipes that differ in one
control group: an ion angular exponent, the ion energies, an ion and a neutral flux) with the same seeds,
once per random-number mode ("stream": one generator per kernel call, the data sets' simulator;
"counter": per-particle streams keyed by (seed, macro step, source, particle)). With x_a,s and x_b,s the
two members under seed s and D_s = x_b,s - x_a,s, per mode and pair:
  * paired noise: the seed-to-seed standard deviation (ddof 1) of D_s, of the profile metrics
    (``nemsim.geometry.profile``, nm, final state) and of the field (RMS over every voxel of the
    per-voxel standard deviation, normalized SDF; over the recorded transitions ``field_times`` and at the
    final state);
  * independent noise: sqrt(var_s x_a,s + var_s x_b,s), the standard deviation of the difference of two
    independently seeded runs, estimated from the same runs (every seed enters both variances; pairing
    seed s with seed s + 1 instead estimates the same with a noisier estimator);
  * ratio = paired / independent: what a shared seed leaves of the noise (1 - ratio: what it removes),
    with a 90 % bootstrap interval over the seeds for the metrics (seeds resampled jointly, 2000 draws);
    the field's ratio at every recorded transition shows how fast the two members' histories diverge;
  * the response: the mean of D_s, and its standard error paired std / sqrt(seeds).
The summary pools the pairs per mode: sqrt(sum paired^2 / sum independent^2), the ratio of the RMS noises
(the ratio of one pair is heavy-tailed with a few seeds: a depth read on one voxel column jumps by
voxels). Speed: CPU and wall seconds per trajectory,
median over the runs of each mode (the modes interleaved so that a changing machine load hits both).

Run: ``python -m bench.pair_noise --scene small --domain quarter --seeds 8 --out
benchmarks/small/pair_noise`` (writes results.json and results.md there).
"""

from __future__ import annotations

import argparse
import dataclasses
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
from nemsim.sim.config import DOMAINS, RNG_MODES, SimConfig
from nemsim.sim.events import build_event_tables
from nemsim.sim.process import run_trajectory

PAIR_METRICS = ("etch_depth", "top_width", "bottom_width")
N_BOOTSTRAP = 2000
Pairs = dict[str, tuple[dict[str, float], dict[str, float]]]


def default_pairs() -> Pairs:
    """{name: (changes of member a, changes of member b)} from the design centre (raw units)."""
    from bench.invariants import centre_raw

    c = dict(zip(CONTROL_NAMES, centre_raw().tolist(), strict=True))
    energies = ("energy_mean_cl_plus", "energy_mean_cl2_plus", "energy_mean_ar_plus")
    return {
        "angle_cl_plus 50 -> 3000": ({"angle_cl_plus": 50.0}, {"angle_cl_plus": 3000.0}),
        "ion energies +10 %": ({}, {k: 1.1 * c[k] for k in energies}),
        "flux_cl_plus +10 %": ({}, {"flux_cl_plus": 1.1 * c["flux_cl_plus"]}),
        "flux_cl +10 %": ({}, {"flux_cl": 1.1 * c["flux_cl"]}),
    }


def _raw(changes: dict[str, float]) -> np.ndarray:
    from bench.invariants import centre_raw

    u = centre_raw().copy()
    for name, value in changes.items():
        u[CONTROL_NAMES.index(name)] = value
    return u


def field_times(steps: int, stride: int) -> list[int]:
    """The transitions whose states are kept for the field noise: 1, 2, then every ``stride``-th and the
    last (the whole horizon would hold 101 states per run)."""
    return sorted({t for t in (1, 2, *range(stride, steps + 1, stride), steps) if 1 <= t <= steps})


def _ratio_interval(a: np.ndarray, b: np.ndarray, rng: np.random.Generator) -> list[float] | None:
    """90 % bootstrap interval of std(b - a) / sqrt(var a + var b) over the seeds (a, b: (S,)); None when
    no resample has any spread (a metric that no seed moves)."""
    idx = rng.integers(0, len(a), size=(N_BOOTSTRAP, len(a)))
    ra, rb = a[idx], b[idx]
    indep = np.sqrt(ra.var(axis=1, ddof=1) + rb.var(axis=1, ddof=1))
    paired = (rb - ra).std(axis=1, ddof=1)
    ok = indep > 0  # a resample of one repeated seed has no spread
    if not ok.any():
        return None
    lo, hi = np.quantile(paired[ok] / indep[ok], [0.05, 0.95])
    return [float(lo), float(hi)]


def _ratio(paired: float, indep: float) -> float | None:
    return paired / indep if indep > 0 else None


def pair_statistics(xa: np.ndarray, xb: np.ndarray, ma: dict[str, np.ndarray], mb: dict[str, np.ndarray],
                    times: list[int]) -> dict[str, Any]:  # fmt: skip
    """One pair under one mode (module docstring). xa, xb: (S, T', 2, D, H, W) states at ``times`` of the
    members under seeds 1..S; ma, mb: {metric: (S,)} final profile metrics."""
    d = xb - xa
    var_p = d.var(axis=0, ddof=1).mean(axis=(1, 2, 3, 4))  # (T',) mean over the voxels
    var_i = (xa.var(axis=0, ddof=1) + xb.var(axis=0, ddof=1)).mean(axis=(1, 2, 3, 4))
    paired = {"field": float(np.sqrt(var_p.mean())), "field_final": float(np.sqrt(var_p[-1]))}
    indep = {"field": float(np.sqrt(var_i.mean())), "field_final": float(np.sqrt(var_i[-1]))}
    n = len(next(iter(ma.values())))
    rng = np.random.default_rng(0)
    out: dict[str, Any] = {"response": {}, "response_se": {}, "ratio_ci90": {}}
    for k in PAIR_METRICS:
        a, b = ma[k], mb[k]
        paired[k] = float((b - a).std(ddof=1))
        indep[k] = float(np.sqrt(a.var(ddof=1) + b.var(ddof=1)))
        out["response"][k] = float((b - a).mean())
        out["response_se"][k] = paired[k] / float(np.sqrt(n))
        out["ratio_ci90"][k] = _ratio_interval(a, b, rng)
    out["paired"], out["independent"] = paired, indep
    out["ratio"] = {k: _ratio(paired[k], indep[k]) for k in paired}
    out["field_ratio_by_time"] = {str(t): _ratio(float(np.sqrt(p)), float(np.sqrt(i)))
                                  for t, p, i in zip(times, var_p, var_i, strict=True)}  # fmt: skip
    return out


def simulate_pair_noise(
    scene: Scene,
    rules: RuleTensors,
    pairs: Pairs | None = None,
    seeds: tuple[int, ...] = (1, 2, 3),
    config: SimConfig | None = None,
    modes: tuple[str, ...] = RNG_MODES,
    n_transitions: int | None = None,
    stride: int = 5,
) -> dict[str, Any]:
    """The measurement of the module docstring; JSON-ready. ``config``: the simulator (its ``rng_mode`` is
    replaced by each of ``modes``; its ``domain`` is kept); ``n_transitions``: a shorter horizon (default
    the scene's); ``stride``: the field is kept every ``stride`` transitions (``field_times``)."""
    if len(seeds) < 2:
        raise ValueError(f"need at least two seeds, got {seeds}")
    if not modes or any(m not in RNG_MODES for m in modes):
        raise ValueError(f"modes are some of {RNG_MODES}, got {modes}")
    pairs = pairs if pairs is not None else default_pairs()
    base = (config or SimConfig()).resolved(scene)
    steps = scene.n_transitions if n_transitions is None else int(n_transitions)
    times = field_times(steps, stride)
    recipes: dict[str, np.ndarray] = {}
    for a, b in pairs.values():
        for changes in (a, b):
            recipes.setdefault(json.dumps(changes, sort_keys=True), _raw(changes))
    states: dict[tuple[str, str, int], np.ndarray] = {}
    final: dict[tuple[str, str, int], dict[str, float]] = {}
    timing: dict[str, dict[str, list[float]]] = {m: {"cpu_s": [], "wall_s": []} for m in modes}
    tables = build_event_tables(rules, base)
    for mode in modes:  # compile outside the timings
        run_trajectory(scene, rules, recipes[next(iter(recipes))], np.random.default_rng(0),
                       dataclasses.replace(base, rng_mode=mode), tables=tables, n_transitions=1)  # fmt: skip
    for s in seeds:
        for key, u in recipes.items():
            for mode in modes:
                cfg = dataclasses.replace(base, rng_mode=mode)
                c0, w0 = time.process_time(), time.perf_counter()
                res = run_trajectory(scene, rules, u, np.random.default_rng(s), cfg, tables=tables,
                                     n_transitions=steps)  # fmt: skip
                timing[mode]["cpu_s"].append(time.process_time() - c0)
                timing[mode]["wall_s"].append(time.perf_counter() - w0)
                states[mode, key, s] = res.states[times]
                m = profile_metrics_batch(res.states[-1:], scene)
                final[mode, key, s] = {k: float(m[k][0]) for k in PAIR_METRICS}

    report: dict[str, Any] = {"scene": scene.name, "domain": base.domain, "seeds": list(seeds),
                              "steps": steps, "field_times": times, "modes": list(modes), "pairs": {},
                              "summary": {}, "speed": {}}  # fmt: skip
    for name, (a, b) in pairs.items():
        ka, kb = json.dumps(a, sort_keys=True), json.dumps(b, sort_keys=True)
        row: dict[str, Any] = {"a": a, "b": b}
        for mode in modes:
            xa = np.stack([states[mode, ka, s] for s in seeds])
            xb = np.stack([states[mode, kb, s] for s in seeds])
            ma = {k: np.array([final[mode, ka, s][k] for s in seeds]) for k in PAIR_METRICS}
            mb = {k: np.array([final[mode, kb, s][k] for s in seeds]) for k in PAIR_METRICS}
            row[mode] = pair_statistics(xa, xb, ma, mb, times)
        report["pairs"][name] = row
    report["summary"] = pooled_ratios(report["pairs"], modes)
    for mode in modes:
        report["speed"][mode] = {k: float(np.median(v)) for k, v in timing[mode].items()}
        report["speed"][mode]["runs"] = len(timing[mode]["cpu_s"])
    return report


def pooled_ratios(pairs: dict[str, Any], modes: list[str] | tuple[str, ...]) -> dict[str, dict[str, Any]]:
    """{mode: {quantity: sqrt(sum over pairs of paired^2 / sum of independent^2)}} (module docstring)."""
    out: dict[str, dict[str, Any]] = {}
    for mode in modes:
        rows = [row[mode] for row in pairs.values()]
        out[mode] = {}
        for k in rows[0]["paired"]:
            paired = sum(r["paired"][k] ** 2 for r in rows)
            out[mode][k] = _ratio(paired**0.5, sum(r["independent"][k] ** 2 for r in rows) ** 0.5)
    return out


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


_INTRO = (
    "Seed-to-seed std of the paired difference (both members one seed; field: normalized SDF, "
    "metrics: nm); in brackets its ratio to the independent-seed noise, i.e. what a shared seed leaves "
    "(metrics: with the 90 % bootstrap interval over the seeds)."
)


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    """A markdown table."""
    return ["| " + " | ".join(r) + " |" for r in [head, ["---"] * len(head), *rows]]


def format_markdown(rep: dict[str, Any], command: str | None = None, cpu: str | None = None) -> str:
    """The report as markdown: paired noise per pair and mode with its ratio to the independent noise."""
    modes, pairs = rep["modes"], rep["pairs"]
    cols = ["field", "field_final", *PAIR_METRICS]
    lines = [f"# Seed noise of sweep-pair differences on `{rep['scene']}` ({rep['domain']} domain)", ""]
    lines += [f"Command: `{command}`  "] if command else []
    lines += [f"CPU: {cpu}, one core"] if cpu else []
    lines += ["", f"Seeds {rep['seeds']}, {rep['steps']} transitions. {_INTRO}", ""]
    rows = []
    for name, row in pairs.items():
        for mode in modes:
            r = row[mode]
            cells = [f"{r['paired'][c]:.4f} ({_num(r['ratio'][c])})" for c in cols[:2]]
            for c in PAIR_METRICS:
                ci = r["ratio_ci90"][c]
                band = f" [{ci[0]:.2f}, {ci[1]:.2f}]" if ci else ""
                cells.append(f"{r['paired'][c]:.2f} ({_num(r['ratio'][c])}{band})")
            rows.append([name, mode, *cells])
    lines += _table(["pair", "rng", *cols], rows)
    lines += [
        "",
        "Pooled over the pairs, RMS paired / RMS independent noise (1 - ratio: what a shared seed removes):",
        "",
    ]
    lines += _table(["rng", *cols], [[m, *(_num(rep["summary"][m][c]) for c in cols)] for m in modes])
    times = [str(t) for t in rep["field_times"] if t in (1, 2, 5, 10, 20, 50, rep["steps"])]
    lines += ["", "Field ratio (paired / independent) at transition t: how fast the members diverge:", ""]
    rows = [[name, m, *(_num(row[m]["field_ratio_by_time"][t]) for t in times)]
            for name, row in pairs.items() for m in modes]  # fmt: skip
    lines += _table(["pair", "rng", *(f"t={t}" for t in times)], rows)
    lines += ["", "Response (mean paired difference +- its standard error, nm):", ""]
    for name, row in pairs.items():
        parts = []
        for m in modes:
            resp, se = row[m]["response"], row[m]["response_se"]
            parts.append(f"{m} " + ", ".join(f"{k} {resp[k]:+.2f} +- {se[k]:.2f}" for k in PAIR_METRICS))
        lines.append(f"- {name}: " + "; ".join(parts))
    speed = [f"{m} {v['cpu_s']:.2f} CPU s ({v['wall_s']:.2f} wall s, {v['runs']} runs)"
             for m, v in rep["speed"].items()]  # fmt: skip
    lines += ["", "Speed (median per trajectory): " + "; ".join(speed)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    from bench.machine import cpu_name
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.scenes import SCENES

    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(prog="python -m bench.pair_noise", description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="small", choices=sorted(SCENES))
    ap.add_argument("--seeds", type=int, default=3, help="seeds 1..N (N >= 2; default 3)")
    ap.add_argument(
        "--rng",
        default="both",
        choices=(*RNG_MODES, "both"),
        help="the simulator's random numbers: one mode or both, compared (default both)",
    )
    ap.add_argument("--domain", default="full", choices=DOMAINS, help="simulated domain (default full)")
    ap.add_argument("--steps", type=int, default=None, help="transitions (default: the scene's horizon)")
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="write results.json and results.md into this directory",
    )
    args = ap.parse_args(argv)
    modes = RNG_MODES if args.rng == "both" else (args.rng,)
    rep = simulate_pair_noise(SCENES[args.scene], compile_rules(load_rules()),
                              seeds=tuple(range(1, args.seeds + 1)), config=SimConfig(domain=args.domain),
                              modes=modes, n_transitions=args.steps)  # fmt: skip
    command, cpu = " ".join(["python -m bench.pair_noise", *argv]), cpu_name()
    text = format_markdown(rep, command, cpu)
    sys.stdout.write(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.json").write_text(json.dumps({"command": command, "cpu": cpu, **rep}, indent=1))
        (args.out / "results.md").write_text(text)


if __name__ == "__main__":
    main()
