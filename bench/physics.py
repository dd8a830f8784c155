"""Physics benchmark: does the surrogate respond to each control as the simulator does?

``nemsim bench physics`` compares a surrogate with the Monte Carlo simulator (two seeds per recipe) on
what a process engineer reads, the profile metrics of ``nemsim.geometry.profile`` (nm):

  (a) **Sweeps**: one control group at a time from the median recipe (the design centre, normalized 0,
      which is the median of every column of the Latin-hypercube design) to ``levels`` values spread
      evenly over the design range (normalized -1..1): the Cl+, Ar+, Cl2+ and neutral Cl fluxes, the three
      ion-energy means together, the three ion angular exponents together, the neutral angular exponent.
      Per group and metric (final depth, top and bottom width, mask loss, bowing at the last compared
      step): the simulator's mean of the two seeds and the surrogate at each level, the least-squares
      slopes against the normalized level (nm per unit; a flux's unit is half its log10 range), the slope
      ratio surrogate / simulator with its sign, and the standard error of the simulator's slope (half the
      difference of the two seeds' slopes): a slope is "resolved", and its ratio and sign meaningful,
      where it exceeds twice that error.
  (b) **Held-out cases**: ``heldout`` Latin-hypercube points of the design box drawn with a seed other than
      the training design's (42), plus ``corners`` corners of the 14-control box (all-min and all-max
      first, then random sign patterns), each simulated with two seeds; or, with a data file and split,
      the split's controls (both seeds simulated afresh, so the pair is like for like). Per case: final
      profile-metric errors beside the seed-to-seed differences, Avg RMSE beside the seed-to-seed floor.
  (c) **No change**: per case the Avg RMSE of holding x_0 for every step; a case where the surrogate is
      worse counts (reported for the held-out cases and for the sweep recipes).

Common random numbers: the commands run the simulator with counter-based streams by default (``--sim-rng
counter``, ``SimConfig.rng_mode``), so every sweep level of one seed shares that seed's noise as far as the
physics allows, and a slope and its standard error carry less of it than with independent runs.

Choices: every comparison uses the simulator's run length (``SimTruth.steps``, default the horizon);
integer controls (angular exponents) are rounded at each sweep level; Avg RMSE against the two seeds is
the mean of the two (so the floor and the model error are on the same footing).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.invariants import centre_raw
from nemsim.controls import (
    CONTROL_GROUPS,
    HELDOUT_CORNERS,
    HELDOUT_SEED,
    N_CONTROLS,
    box_corners,
    from_unit,
    lhs_unit,
    round_int_controls,
    set_group,
)
from nemsim.evaluation.figure import pyplot, save_figure
from nemsim.evaluation.truth import SimTruth, compare_case, predict, write_report

RNG_LABELS = {"counter": "common random numbers", "stream": "independent streams"}  # SimConfig.rng_mode
SWEEP_METRICS = ("etch_depth", "top_width", "bottom_width", "mask_loss", "bowing")
RESOLVED_SE = 2.0  # a simulator slope counts as resolved beyond this many standard errors


@dataclass(frozen=True)
class PhysicsConfig:
    levels: int = 3  # sweep levels per group, design min..max (>= 3)
    heldout: int = 12  # fresh Latin-hypercube held-out cases (ignored with explicit held-out controls)
    corners: int = HELDOUT_CORNERS  # corners of the 14-control box among the held-out cases (`nemsim design
    # --kind corners` never draws these, so a model trained on corners is still judged on unseen ones)
    seeds: tuple[int, int] = (1, 2)
    heldout_seed: int = HELDOUT_SEED  # Latin-hypercube seed of the fresh held-out controls
    batch_size: int = 4  # rollouts run together

    def __post_init__(self) -> None:
        if self.levels < 3:
            raise ValueError(f"levels must be >= 3, got {self.levels}")
        if self.heldout < 0 or self.corners < 0:
            raise ValueError(f"heldout and corners must be >= 0, got {self.heldout} and {self.corners}")
        if len(self.seeds) != 2 or self.seeds[0] == self.seeds[1]:
            raise ValueError(f"seeds must be two different integers, got {self.seeds}")


def sweep_recipes(levels: int) -> dict[str, dict[str, Any]]:
    """{group: {"levels" (L,) normalized, "raw" (L, 14)}} from the median recipe."""
    base = centre_raw()
    u = np.linspace(-1.0, 1.0, levels)
    out = {}
    for g, names in CONTROL_GROUPS.items():
        raw = np.stack([set_group(base, names, float(v)) for v in u])  # (L, 14)
        out[g] = {"levels": u, "raw": round_int_controls(raw)}
    return out


def heldout_recipes(cfg: PhysicsConfig) -> tuple[list[str], np.ndarray]:
    """Names and (N, 14) raw controls of the fresh held-out cases (module docstring)."""
    rows = [from_unit(lhs_unit(cfg.heldout, cfg.heldout_seed))] if cfg.heldout else []
    names = [f"lhs-{i}" for i in range(cfg.heldout)]
    corners = box_corners(cfg.corners, cfg.heldout_seed)
    rows.append(corners)
    names += ["corner-min", "corner-max"][: cfg.corners] + [f"corner-{i}" for i in range(2, cfg.corners)]
    return names, np.concatenate(rows) if rows else np.zeros((0, N_CONTROLS))


def planned_runs(cfg: PhysicsConfig, heldout_raw: np.ndarray) -> list[tuple[np.ndarray, int]]:
    raws = [r for g in sweep_recipes(cfg.levels).values() for r in g["raw"]] + list(heldout_raw)
    return [(r, s) for r in raws for s in cfg.seeds]


def _slope(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.polyfit(x, y, 1)[0])


def run_physics(model: Any, truth: SimTruth, x0: np.ndarray, cfg: PhysicsConfig,
                heldout: tuple[list[str], np.ndarray] | None = None) -> dict[str, Any]:
    """The benchmark of the module docstring; JSON-ready report.

    Args:
        model: the surrogate (called through ``rollout``). truth: simulator runs (its ``steps`` = compared
            horizon). x0: (2, D, H, W) the simulator's initial state.
        heldout: (names, (N, 14) raw controls) of held-out cases; None: ``heldout_recipes(cfg)``.
    """
    names, held_raw = heldout if heldout is not None else heldout_recipes(cfg)
    truth.ensure(planned_runs(cfg, held_raw), desc="physics")
    T = truth.steps
    seeds = cfg.seeds

    def records(raws: np.ndarray) -> list[dict[str, Any]]:
        return [compare_case(truth, raws[i], traj, seeds)
                for i, traj in predict(model, x0, raws, T, cfg.batch_size)]

    sweeps = {}
    for group, rec in sweep_recipes(cfg.levels).items():
        cases = records(rec["raw"])
        x = rec["levels"]
        metrics = {}
        for m in SWEEP_METRICS:
            sim = np.array([c["sim"][m] for c in cases])
            sa = np.array([c["sim_a"][m] for c in cases])
            sb = np.array([c["sim_b"][m] for c in cases])
            mod = np.array([c["model"][m] for c in cases])
            s_sim, s_mod = _slope(x, sim), _slope(x, mod)
            noise = 0.5 * abs(_slope(x, sa) - _slope(x, sb))
            metrics[m] = {
                "simulator": sim.tolist(), "model": mod.tolist(), "seed_diff": np.abs(sa - sb).tolist(),
                "slope_sim": s_sim, "slope_model": s_mod, "slope_noise": noise,
                "slope_ratio": s_mod / s_sim if s_sim != 0 else None,
                "same_sign": bool(np.sign(s_mod) == np.sign(s_sim)),
                "resolved": bool(abs(s_sim) > RESOLVED_SE * noise),
            }
        sweeps[group] = {"controls": list(CONTROL_GROUPS[group]), "levels": x.tolist(),
                         "raw": rec["raw"].tolist(), "metrics": metrics, "cases": cases}

    held = [dict(name=n, **c) for n, c in zip(names, records(held_raw), strict=True)]
    return {
        "config": asdict(cfg), "scene": truth.scene.name, "steps": T, "time_s": T * truth.scene.snapshot_dt_s,
        "sweeps": sweeps, "heldout": held, "summary": summarize(sweeps, held),
    }


def summarize(sweeps: dict[str, Any], held: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {"n_heldout": len(held)}
    if held:
        out["heldout_avg_rmse_mean"] = float(np.mean([c["avg_rmse"] for c in held]))
        out["heldout_floor_mean"] = float(np.mean([c["floor"] for c in held]))
        out["heldout_rmse_over_floor_median"] = float(np.median([c["avg_rmse"] / max(c["floor"], 1e-12)
                                                                 for c in held]))

        def mean(f: Any) -> dict[str, float]:
            return {m: float(np.mean([f(c, m) for c in held])) for m in SWEEP_METRICS}

        out["heldout_mae_nm"] = mean(lambda c, m: abs(c["error"][m]))
        out["heldout_bias_nm"] = mean(lambda c, m: c["error"][m])
        out["heldout_seed_diff_nm"] = mean(lambda c, m: c["seed_diff"][m])
    out["heldout_worse_than_no_change"] = sum(c["worse_than_no_change"] for c in held)
    sweep_cases = [c for g in sweeps.values() for c in g["cases"]]
    out["sweep_worse_than_no_change"] = sum(c["worse_than_no_change"] for c in sweep_cases)
    out["n_sweep_cases"] = len(sweep_cases)
    resolved = [(g, m, v) for g, s in sweeps.items() for m, v in s["metrics"].items() if v["resolved"]]
    out["slopes_resolved"] = len(resolved)
    out["slopes_wrong_sign"] = sum(not v["same_sign"] for _, _, v in resolved)
    out["slopes_within_25pct"] = sum(v["slope_ratio"] is not None and abs(v["slope_ratio"] - 1) <= 0.25
                                     for _, _, v in resolved)
    return out


# --- outputs ---------------------------------------------------------------------------------------

METRIC_LABELS = {"etch_depth": "depth", "top_width": "top w", "bottom_width": "bottom w",
                 "mask_loss": "mask loss", "bowing": "bowing"}


def format_markdown(rep: dict[str, Any]) -> str:
    """Markdown tables: sweeps (per group and metric), held-out cases, summary."""
    nl = len(rep["config"]["seeds"])
    rng = rep.get("simulator_cost", {}).get("rng_mode", "stream")
    lines = [f"# Physics benchmark ({rep['scene']}, {rep['steps']} transitions, simulator seeds "
             f"{rep['config']['seeds']}, {nl} runs per recipe, {RNG_LABELS.get(rng, rng)})", "",
             "## (a) One control group at a time from the median recipe (final state)", "",
             "Levels are normalized controls (-1 = design minimum, +1 = maximum). Slopes in nm per "
             f"normalized unit ± the standard error of the simulator's (half the difference of its two "
             f"seeds' slopes); the ratio is surrogate / simulator; 'resolved' = |slope sim| > "
             f"{RESOLVED_SE:g} standard errors.", "",
             "| group | metric | levels [1] | simulator [nm] | surrogate [nm] | seed diff [nm] "
             "| slope sim [nm/1] | slope model [nm/1] | ratio [1] | sign | resolved |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]

    def seq(v: list[float]) -> str:
        return ", ".join(f"{x:.1f}" for x in v)

    for g, s in rep["sweeps"].items():
        for m, v in s["metrics"].items():
            ratio = "n/a" if v["slope_ratio"] is None else f"{v['slope_ratio']:+.2f}"
            lines.append(f"| {g} | {METRIC_LABELS[m]} | {seq(s['levels'])} | {seq(v['simulator'])} | "
                         f"{seq(v['model'])} | {seq(v['seed_diff'])} | "
                         f"{v['slope_sim']:+.2f} ± {v['slope_noise']:.2f} | "
                         f"{v['slope_model']:+.2f} | {ratio} | {'ok' if v['same_sign'] else 'WRONG'} | "
                         f"{'yes' if v['resolved'] else 'no'} |")
    lines += ["", "## (b) Held-out cases (final state; error = surrogate - mean of the two seeds)", "",
              "| case | Avg RMSE [SDF] | floor [SDF] | ratio [1] | no change [SDF] | "
              + " | ".join(f"{METRIC_LABELS[m]} err / seed diff [nm]" for m in SWEEP_METRICS) + " |",
              "|---|---|---|---|---|" + "---|" * len(SWEEP_METRICS)]
    for c in rep["heldout"]:
        flag = " **worse than no change**" if c["worse_than_no_change"] else ""
        lines.append(f"| {c['name']} | {c['avg_rmse']:.4f}{flag} | {c['floor']:.4f} | "
                     f"{c['avg_rmse'] / max(c['floor'], 1e-12):.2f} | {c['no_change']:.4f} | "
                     + " | ".join(f"{c['error'][m]:+.1f} / {c['seed_diff'][m]:.1f}" for m in SWEEP_METRICS)
                     + " |")
    s = rep["summary"]
    lines += ["", "## Summary", ""]
    if s["n_heldout"]:
        lines.append(f"- held-out Avg RMSE mean {s['heldout_avg_rmse_mean']:.4f} SDF against the "
                     f"seed-to-seed floor {s['heldout_floor_mean']:.4f} SDF (per-case ratio median "
                     f"{s['heldout_rmse_over_floor_median']:.2f})")
        lines.append("- held-out mean |error| / mean bias / mean seed-to-seed difference [nm]: " + "; ".join(
            f"{METRIC_LABELS[m]} {s['heldout_mae_nm'][m]:.2f} / {s['heldout_bias_nm'][m]:+.2f} / "
            f"{s['heldout_seed_diff_nm'][m]:.2f}" for m in SWEEP_METRICS))
    lines.append(f"- (c) worse than predicting no change: {s['heldout_worse_than_no_change']} of "
                 f"{s['n_heldout']} held-out cases, {s['sweep_worse_than_no_change']} of "
                 f"{s['n_sweep_cases']} sweep recipes")
    lines.append(f"- slopes the simulator resolves: {s['slopes_resolved']}; wrong sign "
                 f"{s['slopes_wrong_sign']}; within ±25 % {s['slopes_within_25pct']}")
    return "\n".join(lines) + "\n"


def plot_physics(rep: dict[str, Any], path: str | Path) -> Path:
    """PNG: one panel per (metric, group): simulator (two seeds, mean) and surrogate against the level."""
    plt = pyplot()

    groups = list(rep["sweeps"])
    rows, cols = len(SWEEP_METRICS), len(groups)
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols, 2.0 * rows), squeeze=False, sharex=True)
    for j, g in enumerate(groups):
        s = rep["sweeps"][g]
        x = np.array(s["levels"])
        for i, m in enumerate(SWEEP_METRICS):
            ax = axes[i, j]
            v = s["metrics"][m]
            sa = [c["sim_a"][m] for c in s["cases"]]
            sb = [c["sim_b"][m] for c in s["cases"]]
            ax.fill_between(x, np.minimum(sa, sb), np.maximum(sa, sb), color="k", alpha=0.15, lw=0)
            ax.plot(x, v["simulator"], "o-", color="k", ms=3, lw=1, label="simulator (2 seeds)")
            ax.plot(x, v["model"], "s--", color="tab:red", ms=3, lw=1, label="surrogate")
            if i == 0:
                ax.set_title(g, fontsize=8)
            if j == 0:
                ax.set_ylabel(f"{METRIC_LABELS[m]} [nm]", fontsize=8)
            if i == len(SWEEP_METRICS) - 1:
                ax.set_xlabel("normalized level [1]", fontsize=8)
            ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=6)
    fig.suptitle(f"one-at-a-time sweeps from the median recipe ({rep['scene']}, final state after "
                 f"{rep['steps']} transitions)", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def write_outputs(rep: dict[str, Any], out_dir: str | Path) -> dict[str, str]:
    """physics.md, physics.json and physics.png in ``out_dir``."""
    return write_report(rep, out_dir, "physics", format_markdown, plot_physics)


def heldout_from_data(path: str | Path, manifest: dict | None, split: str, limit: int | None = None
                      ) -> tuple[list[str], np.ndarray, dict]:
    """Names, raw controls (N, 14) and the simulator configuration (``generator["config"]``) of a data
    file's split (all its cases without a manifest); the first ``limit`` cases if given."""
    from nemsim.data.hdf5 import open_trajectories

    with open_trajectories(path) as tf:
        ids = [int(c) for c in (manifest[split] if manifest else tf.case_ids)]
        if not ids:
            raise ValueError(f"split {split!r} of {path} is empty")
        raw = np.stack([tf.controls_raw[tf.row_of(c)] for c in ids])
        sim_meta = dict(tf.generator.get("config") or {})
    if limit is not None:
        raw, ids = raw[:limit], ids[:limit]
    return [f"case-{c}" for c in ids], raw, sim_meta
