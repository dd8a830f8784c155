"""Extrapolation benchmark: surrogate error outside the training box against the simulator.

``nemsim bench extrapolation`` simulates (two seeds) and predicts recipes of these kinds:

  * ``axis``: one control at a time moved out of the design box, every other control at the design centre:
    normalized value ±d for each d in ``distances`` (default 1.5 and 2, i.e. 1.5x and 2x the box's
    half-width from its centre: half and one half-width beyond each edge; fluxes move in log10 space).
    A point whose physical value would be inadmissible (a negative energy, spread or exponent) is skipped
    and listed; integer controls are rounded.
  * ``zero-flux``: each flux at 0, the three ion fluxes at 0, all four at 0;
  * ``isotropic``: all four angular exponents m = ``isotropic_m`` (cos^1: a broad spread);
    ``needle``: the three ion exponents at ``needle_m`` (a nearly collimated beam);
  * ``corner``: corners of the 14-control box (all-min, all-max, then random sign patterns), on its edge;
  * ``in-box``: the design centre and ``in_box`` Latin-hypercube points (a seed other than the training
    design's): the reference errors.

Per recipe (``truth.compare_case``): Avg RMSE (mean over the two seeds) beside the seed-to-seed floor and
the no-change baseline, and the final profile-metric errors beside the seed-to-seed differences. The
normalized distance from the box is max_j |u_j| - 1 (negative inside, 0 on an edge or corner); zero fluxes
lie far out (log10 of the epsilon 1e-12). Summary: the in-box mean Avg RMSE and profile errors, and per
(kind, distance) group the mean Avg RMSE and its ratio to the in-box mean. The figure plots Avg RMSE
against the distance (points beyond ``PLOT_CLIP`` drawn at it).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.invariants import ION_FLUXES, centre_raw
from bench.physics import METRIC_LABELS, SWEEP_METRICS, box_corners
from nemsim.controls import (
    CONTROL_INDEX,
    CONTROL_NAMES,
    CONTROL_SPECS,
    FLUX_INDICES,
    PHYS_MIN,
    from_normalized,
    from_unit,
    lhs_unit,
    round_int_controls,
    to_normalized,
)
from nemsim.evaluation.figure import pyplot, save_figure
from nemsim.evaluation.truth import SimTruth, compare_case, predict, write_report

ANGLES = tuple(s.name for s in CONTROL_SPECS if s.name.startswith("angle_"))
ION_ANGLES = ("angle_cl_plus", "angle_cl2_plus", "angle_ar_plus")
IN_BOX_DESIGN_SEED = 2027
PLOT_CLIP = 3.5


@dataclass(frozen=True)
class ExtrapolationConfig:
    distances: tuple[float, ...] = (1.5, 2.0)  # normalized |u| of the axis points (1 = the box edge)
    corners: int = 4  # corners of the 14-control box
    in_box: int = 6  # Latin-hypercube in-box reference points (plus the design centre)
    isotropic_m: float = 1.0  # angular exponent of the isotropic recipe
    needle_m: float = 10_000.0  # ion angular exponent of the needle-like recipe
    seeds: tuple[int, int] = (1, 2)
    design_seed: int = IN_BOX_DESIGN_SEED
    batch_size: int = 4

    def __post_init__(self) -> None:
        if not self.distances or any(d <= 1.0 for d in self.distances):
            raise ValueError(f"distances must be > 1 (outside the box, 1 = its edge), got {self.distances}")
        if self.corners < 0 or self.in_box < 0:
            raise ValueError(f"corners and in_box must be >= 0, got {self.corners} and {self.in_box}")
        if len(self.seeds) != 2 or self.seeds[0] == self.seeds[1]:
            raise ValueError(f"seeds must be two different integers, got {self.seeds}")


def box_distance(raw: np.ndarray) -> float:
    """max_j |u_j| - 1 of raw controls (14,): < 0 inside the box, 0 on its boundary."""
    return float(np.abs(to_normalized(np.asarray(raw, dtype=np.float64))).max() - 1.0)


def recipes(cfg: ExtrapolationConfig) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(cases [{"name", "kind", "group", "raw"}], skipped [{"name", "reason"}])."""
    centre = centre_raw()
    cases: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []

    def add(name: str, kind: str, group: str, raw: np.ndarray) -> None:
        cases.append({"name": name, "kind": kind, "group": group, "raw": np.asarray(raw, dtype=np.float64)})

    add("centre", "in-box", "in-box", centre)
    for i, row in enumerate(from_unit(lhs_unit(cfg.in_box, cfg.design_seed)) if cfg.in_box else []):
        add(f"lhs-{i}", "in-box", "in-box", row)
    for i, row in enumerate(box_corners(cfg.corners, cfg.design_seed)):
        add(f"corner-{i}", "corner", "corner", row)
    for j, name in enumerate(CONTROL_NAMES):
        for d in cfg.distances:
            for sign, tag in ((-1.0, "low"), (1.0, "high")):
                u = to_normalized(centre)
                u[j] = sign * d
                raw = round_int_controls(from_normalized(u))
                label = f"{name}-{tag}-{d:g}"
                if raw[j] < PHYS_MIN[j]:
                    reason = f"{name}={raw[j]:.4g} < {PHYS_MIN[j]:g} (inadmissible)"
                    skipped.append({"name": label, "reason": reason})
                    continue
                add(label, "axis", f"axis {d:g}", raw)
    for j in FLUX_INDICES:
        raw = centre.copy()
        raw[j] = 0.0
        add(f"zero-{CONTROL_NAMES[j]}", "zero-flux", "zero-flux", raw)
    raw = centre.copy()
    raw[[CONTROL_INDEX[n] for n in ION_FLUXES]] = 0.0
    add("zero-ion-fluxes", "zero-flux", "zero-flux", raw)
    raw = centre.copy()
    raw[list(FLUX_INDICES)] = 0.0
    add("zero-all-fluxes", "zero-flux", "zero-flux", raw)
    raw = centre.copy()
    raw[[CONTROL_INDEX[n] for n in ANGLES]] = cfg.isotropic_m
    add(f"isotropic-m{cfg.isotropic_m:g}", "angle", "angle", raw)
    raw = centre.copy()
    raw[[CONTROL_INDEX[n] for n in ION_ANGLES]] = cfg.needle_m
    add(f"needle-m{cfg.needle_m:g}", "angle", "angle", raw)
    for c in cases:
        c["distance"] = box_distance(c["raw"])
    return cases, skipped


def planned_runs(cfg: ExtrapolationConfig) -> list[tuple[np.ndarray, int]]:
    return [(c["raw"], s) for c in recipes(cfg)[0] for s in cfg.seeds]


def run_extrapolation(model: Any, truth: SimTruth, x0: np.ndarray, cfg: ExtrapolationConfig
                      ) -> dict[str, Any]:
    """The benchmark of the module docstring; JSON-ready report."""
    cases, skipped = recipes(cfg)
    truth.ensure(planned_runs(cfg), desc="extrapolation")
    raws = np.stack([c["raw"] for c in cases])
    rows = []
    for i, traj in predict(model, x0, raws, truth.steps, cfg.batch_size):
        c = cases[i]
        rows.append({"name": c["name"], "kind": c["kind"], "group": c["group"], "distance": c["distance"],
                     **compare_case(truth, c["raw"], traj, cfg.seeds)})
    return {"config": asdict(cfg), "scene": truth.scene.name, "steps": truth.steps, "cases": rows,
            "skipped": skipped, "summary": summarize(rows)}


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    inbox = [r for r in rows if r["kind"] == "in-box"]
    ref = float(np.mean([r["avg_rmse"] for r in inbox])) if inbox else None
    groups: dict[str, Any] = {}
    for g in dict.fromkeys(r["group"] for r in rows):
        sel = [r for r in rows if r["group"] == g]
        rm = float(np.mean([r["avg_rmse"] for r in sel]))
        groups[g] = {
            "n": len(sel),
            "avg_rmse": rm,
            "floor": float(np.mean([r["floor"] for r in sel])),
            "ratio_to_in_box": rm / ref if ref else None,
            "mae_nm": {m: float(np.mean([abs(r["error"][m]) for r in sel])) for m in SWEEP_METRICS},
            "seed_diff_nm": {m: float(np.mean([r["seed_diff"][m] for r in sel])) for m in SWEEP_METRICS},
            "worse_than_no_change": sum(r["worse_than_no_change"] for r in sel),
        }
    return {"in_box_avg_rmse": ref, "groups": groups}


def format_markdown(rep: dict[str, Any]) -> str:
    s = rep["summary"]
    lines = [f"# Extrapolation benchmark ({rep['scene']}, {rep['steps']} transitions, simulator seeds "
             f"{rep['config']['seeds']})", "",
             "Distance = max_j |u_j| - 1 in normalized controls (< 0 inside the training box, 0 on its "
             "edge). Errors are final-state surrogate - mean of the two seeds.", "",
             "## Per group", "",
             "| group | cases [1] | Avg RMSE [SDF] | floor [SDF] | / in-box [1] "
             "| worse than no change [cases] | "
             + " | ".join(f"{METRIC_LABELS[m]} MAE / seed diff [nm]" for m in SWEEP_METRICS) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(SWEEP_METRICS)]
    for g, v in s["groups"].items():
        ratio = "n/a" if v["ratio_to_in_box"] is None else f"{v['ratio_to_in_box']:.2f}"
        lines.append(f"| {g} | {v['n']} | {v['avg_rmse']:.4f} | {v['floor']:.4f} | {ratio} | "
                     f"{v['worse_than_no_change']} | "
                     + " | ".join(f"{v['mae_nm'][m]:.1f} / {v['seed_diff_nm'][m]:.1f}" for m in SWEEP_METRICS)
                     + " |")
    lines += ["", "## Per case", "",
              "| case | kind | distance [1] | Avg RMSE [SDF] | floor [SDF] | no change [SDF] | "
              + " | ".join(f"{METRIC_LABELS[m]} err [nm]" for m in SWEEP_METRICS)
              + " | depth seed diff [nm] |",
              "|---|---|---|---|---|---|" + "---|" * len(SWEEP_METRICS) + "---|"]
    for r in rep["cases"]:
        lines.append(f"| {r['name']} | {r['kind']} | {r['distance']:+.2f} | {r['avg_rmse']:.4f} | "
                     f"{r['floor']:.4f} | "
                     f"{r['no_change']:.4f} | " + " | ".join(f"{r['error'][m]:+.1f}" for m in SWEEP_METRICS)
                     + f" | {r['seed_diff']['etch_depth']:.1f} |")
    if rep["skipped"]:
        lines += ["", "Skipped (physically inadmissible): " + "; ".join(f"{k['name']} ({k['reason']})"
                                                                       for k in rep["skipped"])]
    return "\n".join(lines) + "\n"


def plot_extrapolation(rep: dict[str, Any], path: str | Path) -> Path:
    """PNG: Avg RMSE against the normalized distance from the box, by kind; in-box mean and floor marked."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    markers = {"in-box": "o", "corner": "D", "axis": "s", "zero-flux": ">", "angle": "^"}
    for kind, mk in markers.items():
        sel = [r for r in rep["cases"] if r["kind"] == kind]
        if not sel:
            continue
        x = [min(r["distance"], PLOT_CLIP) for r in sel]
        ax.plot(x, [r["avg_rmse"] for r in sel], mk, ms=6, alpha=0.8, label=f"{kind} (surrogate)")
        ax.plot(x, [r["floor"] for r in sel], mk, ms=4, mfc="none", color="0.5")
    ref = rep["summary"]["in_box_avg_rmse"]
    if ref:
        ax.axhline(ref, color="k", ls="--", lw=1, label=f"in-box mean {ref:.4f}")
    ax.axvline(0.0, color="0.6", lw=0.8)
    ax.plot([], [], "o", mfc="none", color="0.5", label="seed-to-seed floor (open)")
    ax.set_xlabel(f"normalized distance from the training box, max|u| - 1 [1] (clipped at {PLOT_CLIP:g})")
    ax.set_ylabel("Avg RMSE [normalized SDF]")
    ax.set_yscale("log")
    ax.set_title(f"surrogate vs simulator outside the box ({rep['scene']}, {rep['steps']} transitions)",
                 fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def write_outputs(rep: dict[str, Any], out_dir: str | Path) -> dict[str, str]:
    """extrapolation.md, extrapolation.json and extrapolation.png in ``out_dir``."""
    return write_report(rep, out_dir, "extrapolation", format_markdown, plot_extrapolation)
