"""Physical invariants judged against the simulator (``nemsim stress``).

A finite, bounded rollout can still break laws that hold for every recipe. Each check runs on the
surrogate with a tolerance taken from the simulator's own seed-to-seed noise, and any violation fails:

  * ``zero flux``: all four fluxes 0 (other controls at the design centre and the two extreme corners) ->
    the state does not change: per-step RMSE to x_0, depth and mask-loss change over the whole rollout
    (past the horizon) within the simulator's own change (none) plus the noise tolerance.
  * ``ions off``: the three ion fluxes 0 -> the trajectory matches the simulator's neutral-only one at every
    step (RMSE, depth and mask-loss differences within the tolerances).
  * ``depth never decreases``: from one step to the next by more than the simulator's largest decrease on
    the suite's simulations (Ψ smoothing and redeposition make it slightly non-zero).
  * ``mask loss >= -tol``: the mask never grows above its initial top by more than the noise.
  * ``depth non-decreasing in X`` (each ion flux, and the three ion-energy means together): on ``levels``
    values of X around base recipes (the design centre and ``pair_bases`` Latin-hypercube points), depth at
    the higher level minus depth at the lower >= -tol_depth at every step. The simulator's pairs are checked
    the same way; where the simulator itself falls by more, the model may fall by the simulator's fall plus
    tol_depth (``pair_ok``): matching the truth is never a violation.
  * ``responds where the simulator does``: where the simulator's final depth rises by more than tol_depth,
    the model's must rise, so a model that predicts no change cannot pass (the size of the response is
    ``nemsim bench physics``'s).

Tolerances (``measure_noise``): every base recipe simulated with two seeds; tol_rmse, tol_depth and tol_mask
are the largest seed-to-seed per-step RMSE, depth and mask-loss differences, times ``tol_factor``; the
depth-decrease tolerance is the simulator's largest step-to-step decrease, at least
``depth_decrease_floor_nm``. A noise file (``write_noise`` / ``read_noise``) lets a rerun skip the seed pairs.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.controls import (
    CONTROL_GROUPS,
    CONTROL_INDEX,
    FLUX_INDICES,
    N_CONTROLS,
    from_normalized,
    from_unit,
    lhs_unit,
    set_group,
)
from nemsim.evaluation.truth import SimTruth, predict, step_rmse
from nemsim.geometry.profile import profile_metrics_batch

ION_FLUXES = ("flux_ar_plus", "flux_cl_plus", "flux_cl2_plus")
MONOTONE_AXES: dict[str, tuple[str, ...]] = {  # the control groups along which the etch must not slow
    g: CONTROL_GROUPS[g] for g in ("flux_ar_plus", "flux_cl_plus", "flux_cl2_plus", "ion_energy")}
NOISE_KEYS = ("rmse", "depth_nm", "mask_loss_nm", "depth_decrease_nm")
BASE_DESIGN_SEED = 7  # Latin-hypercube seed of the grid's extra base recipes (not the training design's 42)


@dataclass(frozen=True)
class InvariantConfig:
    seeds: tuple[int, int] = (1, 2)  # the seed pair of the noise measurement; grid runs use seeds[0]
    pair_bases: int = 2  # Latin-hypercube base recipes of the monotonicity grid beside the design centre
    levels: int = 3  # values of each monotone axis, design min..max (>= 2)
    tol_factor: float = 1.0  # every noise tolerance is multiplied by this
    depth_decrease_floor_nm: float = 0.05  # least depth-decrease tolerance
    batch_size: int = 4  # rollouts run together

    def __post_init__(self) -> None:
        if self.levels < 2:
            raise ValueError(f"levels must be >= 2, got {self.levels}")
        if self.pair_bases < 0:
            raise ValueError(f"pair_bases must be >= 0, got {self.pair_bases}")
        if len(self.seeds) != 2 or self.seeds[0] == self.seeds[1]:
            raise ValueError(f"seeds must be two different integers, got {self.seeds}")
        if not self.tol_factor > 0:
            raise ValueError(f"tol_factor must be > 0, got {self.tol_factor}")


# --- recipes -------------------------------------------------------------------------------------


def centre_raw() -> np.ndarray:
    """The design centre (normalized 0) in raw units, (14,)."""
    return from_normalized(np.zeros(N_CONTROLS))


def zero_flux_recipes() -> dict[str, np.ndarray]:
    """All fluxes 0; the other controls at the centre, the all-min and the all-max corner."""
    out = {}
    for tag, v in (("centre", 0.0), ("min", -1.0), ("max", 1.0)):
        raw = from_normalized(np.full(N_CONTROLS, v))
        raw[list(FLUX_INDICES)] = 0.0
        out[f"zero-flux-{tag}"] = raw
    return out


def ions_off_recipes() -> dict[str, np.ndarray]:
    """Ion fluxes 0, neutral Cl at the centre and at the maximum of its range."""
    out = {}
    for tag, v in (("centre", 0.0), ("max", 1.0)):
        u = np.zeros(N_CONTROLS)
        u[CONTROL_INDEX["flux_cl"]] = v
        raw = from_normalized(u)
        raw[[CONTROL_INDEX[n] for n in ION_FLUXES]] = 0.0
        out[f"ions-off-cl-{tag}"] = raw
    return out


def grid_bases(n: int) -> np.ndarray:
    """(1 + n, 14) raw base recipes: the centre, then ``n`` Latin-hypercube points of the design box."""
    rows = [centre_raw()]
    if n:
        rows.extend(from_unit(lhs_unit(n, BASE_DESIGN_SEED)))
    return np.stack(rows)


def monotone_grid(cfg: InvariantConfig) -> list[dict[str, Any]]:
    """Grid lines: [{"axis", "base", "levels" (L,), "raw" (L, 14)}], one per axis and base."""
    lines = []
    levels = np.linspace(-1.0, 1.0, cfg.levels)
    for b, base in enumerate(grid_bases(cfg.pair_bases)):
        for axis, names in MONOTONE_AXES.items():
            lines.append({"axis": axis, "base": b, "levels": levels,
                          "raw": np.stack([set_group(base, names, float(v)) for v in levels])})
    return lines


# --- noise ---------------------------------------------------------------------------------------


def measure_noise(truth: SimTruth, bases: np.ndarray, seeds: tuple[int, int], extra: list[np.ndarray]
                  ) -> dict[str, Any]:
    """Seed-to-seed differences on ``bases`` (K, 14) and the simulator's largest depth decrease.

    ``extra``: further raw recipes already simulated with seeds[0] (their depth decreases count too).
    """
    truth.ensure([(r, s) for r in bases for s in seeds], desc="noise")
    rmse = depth = mask = 0.0
    for r in bases:
        a, b = truth.states(r, seeds[0]), truth.states(r, seeds[1])
        rmse = max(rmse, float(step_rmse(a, b).max()))
        ma, mb = truth.metrics(r, seeds[0]), truth.metrics(r, seeds[1])
        depth = max(depth, float(np.abs(ma["etch_depth"] - mb["etch_depth"]).max()))
        mask = max(mask, float(np.abs(ma["mask_loss"] - mb["mask_loss"]).max()))
    decrease = 0.0
    runs = [(r, s) for r in bases for s in seeds] + [(r, seeds[0]) for r in extra]
    for r, s in runs:
        d = truth.metrics(r, s)["etch_depth"]
        decrease = max(decrease, float(np.max(d[:-1] - d[1:], initial=0.0)))
    return {"scene": truth.scene.name, "steps": truth.steps, "seeds": list(seeds), "n_cases": len(bases),
            "rmse": rmse, "depth_nm": depth, "mask_loss_nm": mask, "depth_decrease_nm": decrease}


def write_noise(path: str | Path, noise: dict[str, Any]) -> None:
    Path(path).write_text(json.dumps(noise, indent=2))


def read_noise(path: str | Path, scene_name: str) -> dict[str, Any]:
    """A noise file of ``write_noise``; ValueError naming the problem."""
    try:
        noise = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read noise file {path}: {exc}") from None
    missing = [k for k in NOISE_KEYS if not isinstance(noise.get(k), (int, float))]
    if missing:
        raise ValueError(f"noise file {path} lacks {missing}; write one with "
                         "`nemsim stress --noise-out FILE`")
    if noise.get("scene") != scene_name:
        raise ValueError(f"noise file {path} is for scene {noise.get('scene')!r}, the checkpoint's is "
                         f"{scene_name!r}")
    return noise


def tolerances(noise: dict[str, Any], cfg: InvariantConfig) -> dict[str, float]:
    f = cfg.tol_factor
    return {"rmse": f * noise["rmse"], "depth_nm": f * noise["depth_nm"],
            "mask_loss_nm": f * noise["mask_loss_nm"],
            "depth_decrease_nm": f * max(noise["depth_decrease_nm"], cfg.depth_decrease_floor_nm)}


# --- the checks -----------------------------------------------------------------------------------


def planned_runs(cfg: InvariantConfig, noise: dict[str, Any] | None) -> list[tuple[np.ndarray, int]]:
    """Every simulator run the invariants need (duplicates included; ``SimTruth.missing`` drops them)."""
    s0, s1 = cfg.seeds
    raws = list(zero_flux_recipes().values()) + list(ions_off_recipes().values())
    raws += [r for line in monotone_grid(cfg) for r in line["raw"]]
    runs = [(r, s0) for r in raws]
    if noise is None:
        runs += [(r, s) for r in grid_bases(cfg.pair_bases) for s in (s0, s1)]
    return runs


Item = dict[str, Any]  # one checked recipe, rollout or pair: {"case", "value", "ok", ...}


def _row(name: str, what: str, unit: str, items: list[Item], bound: str, tol: float, checked_unit: str,
         sim_violations: int | None = None) -> dict[str, Any]:
    """One invariant: ``value bound tol`` must hold for every item; ``worst`` is the extreme value."""
    vals = [it["value"] for it in items if it["value"] is not None and math.isfinite(it["value"])]
    worst = (max(vals) if bound == "<=" else min(vals)) if vals else None
    return {"name": name, "what": what, "unit": unit, "bound": bound, "tolerance": tol, "checked": len(items),
            "checked_unit": checked_unit, "violations": sum(not it["ok"] for it in items), "worst": worst,
            "simulator_violations": sim_violations, "items": items}


def _max_change(series: np.ndarray) -> float:
    return float(np.abs(series - series[0]).max())


def _zero_flux_rows(model: Any, truth: SimTruth, x0: np.ndarray, cfg: InvariantConfig, tol: dict[str, float],
                    long_steps: int, track: Any) -> list[dict[str, Any]]:
    """The model's largest change from x_0 under zero flux, beside the simulator's own (0) plus the noise."""
    recipes = zero_flux_recipes()
    raws = np.stack(list(recipes.values()))
    state, depth, mask = [], [], []  # type: ignore[var-annotated]
    for i, traj in predict(model, x0, raws, long_steps, cfg.batch_size):
        name = list(recipes)[i]
        sim = truth.states(raws[i], cfg.seeds[0])
        sm = truth.metrics(raws[i], cfg.seeds[0])
        m = profile_metrics_batch(traj, truth.scene)
        track(name, m)
        r = float(step_rmse(traj, np.broadcast_to(traj[0], traj.shape)).max())
        sim_r = float(step_rmse(sim, np.broadcast_to(sim[0], sim.shape)).max())
        state.append({"case": name, "value": r, "simulator": sim_r, "ok": r <= sim_r + tol["rmse"],
                      "max_abs_change": float(np.abs(traj - traj[0]).max())})
        for out, key, t in ((depth, "etch_depth", "depth_nm"), (mask, "mask_loss", "mask_loss_nm")):
            v, sim_v = _max_change(m[key]), _max_change(sm[key])
            out.append({"case": name, "value": v, "simulator": sim_v, "ok": v <= sim_v + tol[t]})

    def moved(items: list[Item]) -> int:
        return sum(it["simulator"] > 0 for it in items)

    return [
        _row("zero flux: state", "max_t RMSE(x_t, x_0), all fluxes 0", "SDF", state, "<=", tol["rmse"],
             "recipes", moved(state)),
        _row("zero flux: depth", "max_t |depth_t - depth_0|, all fluxes 0", "nm", depth, "<=",
             tol["depth_nm"], "recipes", moved(depth)),
        _row("zero flux: mask loss", "max_t |mask_loss_t - mask_loss_0|, all fluxes 0", "nm", mask, "<=",
             tol["mask_loss_nm"], "recipes", moved(mask)),
    ]


def _ions_off_rows(model: Any, truth: SimTruth, x0: np.ndarray, cfg: InvariantConfig, tol: dict[str, float],
                   track: Any) -> list[dict[str, Any]]:
    """The model's distance from the simulator's neutral-only trajectory, step by step."""
    recipes = ions_off_recipes()
    raws = np.stack(list(recipes.values()))
    state, depth, mask = [], [], []  # type: ignore[var-annotated]
    for i, traj in predict(model, x0, raws, truth.steps, cfg.batch_size):
        name = list(recipes)[i]
        sim = truth.states(raws[i], cfg.seeds[0])
        sm = truth.metrics(raws[i], cfg.seeds[0])
        m = profile_metrics_batch(traj, truth.scene)
        track(name, m)
        r = float(step_rmse(traj, sim).max())
        state.append({"case": name, "value": r, "ok": r <= tol["rmse"]})
        for out, key, t in ((depth, "etch_depth", "depth_nm"), (mask, "mask_loss", "mask_loss_nm")):
            v = float(np.abs(m[key] - sm[key]).max())
            out.append({"case": name, "value": v, "ok": v <= tol[t]})
    return [
        _row("ions off: state", "max_t RMSE(model_t, simulator_t), ion fluxes 0", "SDF", state, "<=",
             tol["rmse"], "recipes"),
        _row("ions off: depth", "max_t |depth model - simulator|, ion fluxes 0", "nm", depth, "<=",
             tol["depth_nm"], "recipes"),
        _row("ions off: mask loss", "max_t |mask loss model - simulator|, ion fluxes 0", "nm", mask, "<=",
             tol["mask_loss_nm"], "recipes"),
    ]


def pair_ok(model_rise_nm: float, sim_rise_nm: float, tol_nm: float) -> bool:
    """Monotone-pair check: the model's smallest depth rise (higher minus lower level, over the steps) is
    >= -tol, or, where the simulator's own pair falls by more than tol, >= the simulator's rise - tol."""
    return model_rise_nm >= min(-tol_nm, sim_rise_nm - tol_nm)


def _monotone_rows(model: Any, truth: SimTruth, x0: np.ndarray, cfg: InvariantConfig, tol: dict[str, float],
                   track: Any) -> list[dict[str, Any]]:
    """Depth at the higher minus the lower level of each grid pair (model, simulator); the response check."""
    mono: dict[str, list[Item]] = {a: [] for a in MONOTONE_AXES}
    sim_bad = dict.fromkeys(MONOTONE_AXES, 0)
    responds: list[Item] = []
    for line in monotone_grid(cfg):
        raws, levels = line["raw"], line["levels"]
        tags = [f"{line['axis']} base {line['base']} level {v:+.2f}" for v in levels]
        depth = []
        for k, traj in predict(model, x0, raws, truth.steps, cfg.batch_size):
            m = profile_metrics_batch(traj, truth.scene)
            track(tags[k], m)
            depth.append(m["etch_depth"])
        rise = np.diff(np.stack(depth), axis=0)  # (L-1, T+1) nm, model
        sim_rise = np.diff(np.stack([truth.metrics(r, cfg.seeds[0])["etch_depth"] for r in raws]), axis=0)
        for k in range(len(raws) - 1):
            tag = f"{tags[k]} -> {levels[k + 1]:+.2f}"
            worst, sim_worst = float(rise[k].min()), float(sim_rise[k].min())
            sim_bad[line["axis"]] += sim_worst < -tol["depth_nm"]
            mono[line["axis"]].append({"case": tag, "value": worst, "simulator": sim_worst,
                                       "ok": pair_ok(worst, sim_worst, tol["depth_nm"])})
            if sim_rise[k, -1] > tol["depth_nm"]:
                final = float(rise[k, -1])
                responds.append({"case": tag, "value": final, "simulator": float(sim_rise[k, -1]),
                                 "ok": final > 0.0})
    rows = [_row(f"depth non-decreasing in {axis}", "min_t (depth at the higher - at the lower level)", "nm",
                 items, ">=", -tol["depth_nm"], "pairs", sim_bad[axis]) for axis, items in mono.items()]
    rows.append(_row("responds where the simulator does", "final depth rise where the simulator's > tol",
                     "nm", responds, ">", 0.0, "pairs"))
    return rows


def run_invariants(model: Any, truth: SimTruth, x0: np.ndarray, cfg: InvariantConfig, *, long_steps: int,
                   stress_cases: list[dict[str, Any]] | None = None, abs_bound: float = 1.5,
                   noise: dict[str, Any] | None = None) -> dict[str, Any]:
    """Check every invariant of the module docstring; returns {"noise", "tolerances", "invariants", "passed"}.

    Args:
        model: the surrogate (called through ``rollout``). truth: the simulator runs (its ``steps`` is the
            compared horizon). x0: (2, D, H, W) the simulator's initial state.
        long_steps: rollout length of the zero-flux recipes (past the horizon, as the stability cases).
        stress_cases: per-case dicts of ``run_stress`` (their boundedness, depth drops and mask losses are
            checked); abs_bound: the bound ``run_stress`` used (reported).
        noise: a measured noise dict (``read_noise``); None measures it here.
    """
    truth.ensure(planned_runs(cfg, noise), desc="invariants")
    if noise is None:
        extra = [r for line in monotone_grid(cfg) for r in line["raw"]] + list(ions_off_recipes().values())
        noise = measure_noise(truth, grid_bases(cfg.pair_bases), cfg.seeds, extra)
    tol = tolerances(noise, cfg)
    drops: list[Item] = []  # per rollout: the largest step-to-step depth decrease
    masks: list[Item] = []  # per noise-free rollout: the smallest mask loss

    def track(name: str, m: dict[str, np.ndarray]) -> None:
        d = m["etch_depth"]
        drop = float(np.max(d[:-1] - d[1:], initial=0.0))
        drops.append({"case": name, "value": drop, "ok": drop <= tol["depth_decrease_nm"]})
        ml = float(m["mask_loss"].min())
        masks.append({"case": name, "value": ml, "ok": ml >= -tol["mask_loss_nm"]})

    cases = stress_cases or []
    bounded = [{"case": c["name"], "value": c["max_abs"], "ok": bool(c["bounded"])} for c in cases]
    for c in cases:
        drop, ml = c["depth_max_drop_nm"], c.get("mask_loss_min_nm")
        drops.append({"case": c["name"], "value": drop,
                      "ok": drop is not None and drop <= tol["depth_decrease_nm"]})
        if c.get("state_noise", 0.0) == 0.0:  # a noisy x_0 has a noisy mask top from the start
            masks.append({"case": c["name"], "value": ml,
                          "ok": ml is not None and ml >= -tol["mask_loss_nm"]})
    rows = []
    if bounded:
        rows.append(_row("finite and bounded", "max_t |x_t| of the stability cases", "SDF", bounded, "<=",
                         abs_bound, "cases"))
    rows += _zero_flux_rows(model, truth, x0, cfg, tol, long_steps, track)
    rows += _ions_off_rows(model, truth, x0, cfg, tol, track)
    mono = _monotone_rows(model, truth, x0, cfg, tol, track)  # adds to drops and masks: before their rows
    rows += [
        _row("depth never decreases", "max_t (depth_t - depth_t+1) per rollout", "nm", drops, "<=",
             tol["depth_decrease_nm"], "rollouts"),
        _row("mask loss >= -tol", "min_t mask loss per noise-free rollout", "nm", masks, ">=",
             -tol["mask_loss_nm"], "rollouts"),
    ]
    rows += mono
    return {"config": asdict(cfg), "noise": noise, "tolerances": tol, "invariants": rows,
            "passed": all(r["violations"] == 0 for r in rows)}


def format_invariants(rep: dict[str, Any]) -> str:
    """Plain-text table, one row per invariant, units in every cell."""
    head = (f"{'invariant':36s} {'checked':>14s} {'violations':>14s} {'worst':>15s} {'tolerance':>16s} "
            f"{'simulator':>14s}  result")
    lines = [head, "-" * len(head)]

    def v(x: float | None, unit: str) -> str:
        if x is None:
            return "n/a"
        return f"{x:.4f} {unit}" if unit == "SDF" else f"{x:.2f} {unit}"

    for r in rep["invariants"]:
        cu = r["checked_unit"]
        sim = "n/a" if r["simulator_violations"] is None else f"{r['simulator_violations']} {cu}"
        lines.append(
            f"{r['name']:36s} {str(r['checked']) + ' ' + cu:>14s} {str(r['violations']) + ' ' + cu:>14s} "
            f"{v(r['worst'], r['unit']):>15s} {r['bound'] + ' ' + v(r['tolerance'], r['unit']):>16s} "
            f"{sim:>14s}  "
            f"{'PASS' if r['violations'] == 0 else 'FAIL'}"
        )
    n, t = rep["noise"], rep["tolerances"]
    lines.append(
        f"tolerances = the simulator's seed-to-seed noise ({n['n_cases']} recipes, seeds {n['seeds']}, "
        f"{n['steps']} steps) x {rep['config']['tol_factor']:g}: RMSE {t['rmse']:.4f} SDF, depth "
        f"{t['depth_nm']:.2f} nm, mask loss {t['mask_loss_nm']:.2f} nm, depth decrease "
        f"{t['depth_decrease_nm']:.2f} nm; 'simulator' = the same check on the simulator's runs"
    )
    n_bad = sum(r["violations"] > 0 for r in rep["invariants"])
    verdict = "PASS" if rep["passed"] else "FAIL"
    lines.append(f"invariants: {n_bad} of {len(rep['invariants'])} violated -> {verdict}")
    return "\n".join(lines)
