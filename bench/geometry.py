"""The surrogate across hole geometries: field error, ARDE and today's geometry, vs the simulator.

Three measurements of a model (``--checkpoint``) beside a baseline (``--baseline``, the served model):

  * field error on held-out holes: Avg / Final RMSE (DESIGN.md "Metrics": RMSE_t over cases, then the mean
    over the 100 steps) of 100-step rollouts from each case's x_0 against the simulator, a test file
    (``--test``) simulated twice with other seeds (``--test-seed``, the same design). The seed-to-seed floor
    is the same RMSE between the two simulations; each model's error is the mean of its errors against the
    two; ``ratio`` = that / floor (target: <= 1.2 in the trained ranges);
  * ARDE: depth against CD at the recipes of ``bench.arde`` (``model_arde``), each slope's ratio to the
    simulator's, whose results are read from ``--arde`` (``benchmarks/small/arde.json``, not simulated again);
  * today's geometry: Avg RMSE on a file of held-out cases at the scene's own feature (``--default``).

It also counts the cases whose simulated hole reached the bottom of the Si (depth >= the Si thickness less
one voxel: a thick mask leaves less Si) in every file it reads, and in ``--train`` files if given.

Run: ``python -m bench.geometry --checkpoint CKPT --test A.h5 --test-seed B.h5 --default D.h5
--out benchmarks/small/geometry`` (writes geometry.json and geometry.md, stamped with the checkpoint id).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.arde import model_arde, model_markdown, write_report
from nemsim.controls import to_normalized
from nemsim.data.hdf5 import open_trajectories
from nemsim.evaluation.metrics import case_step_mse
from nemsim.evaluation.rollout import rollout
from nemsim.geometry.profile import profile_metrics
from nemsim.sim.config import SimConfig

TARGET_RATIO = 1.2  # field error / seed-to-seed floor, the target
BOOTSTRAP = 2000  # resamples of the cases behind a ratio's 90 % interval


def ratio_interval(ratio_of: Callable[[np.ndarray], float], n_cases: int, n: int = BOOTSTRAP,
                   seed: int = 0) -> tuple[float, float]:
    """5th and 95th percentile of ``ratio_of(idx)`` over n resamples idx (n_cases,) of the cases, drawn with
    replacement: how far a ratio over tens of held-out cases could move with other cases of the design."""
    rng = np.random.default_rng(seed)
    ratios = np.array([ratio_of(rng.integers(0, n_cases, size=n_cases)) for _ in range(n)])
    lo, hi = np.nanpercentile(ratios, [5.0, 95.0])
    return float(lo), float(hi)


def _avg_final(mse: np.ndarray) -> dict[str, float]:
    """Avg and Final RMSE of per-case per-step MSEs (n, T) (RMSE_t over cases, then the mean over t)."""
    rmse_t = np.sqrt(mse.mean(axis=0))
    return {"avg_rmse": float(rmse_t.mean()), "final_rmse": float(rmse_t[-1])}


def _states(tf: Any, row: int) -> torch.Tensor:
    return torch.from_numpy(np.asarray(tf.states[row], dtype=np.float32))  # (T+1, 2, D, H, W)


def through_count(path: Path) -> dict[str, Any]:
    """How many complete cases of a file reached the bottom of the Si by their last state, and their ids."""
    with open_trajectories(path) as tf:
        rows = np.flatnonzero(tf.complete)
        hit = []
        for row in rows:
            scene = tf.case_scene(int(row))
            depth = profile_metrics(np.asarray(tf.states[row, -1], dtype=np.float32), scene)["etch_depth"]
            if depth >= (scene.si_top - 1) * scene.voxel_nm:
                hit.append({"case_id": int(tf.case_ids[row]), "depth_nm": depth,
                            "si_nm": scene.si_top * scene.voxel_nm, **tf.case_feature(int(row)).to_dict()})
    return {"file": str(path), "cases": int(len(rows)), "through": len(hit), "through_cases": hit}


def _field_ratio(per_seed: list[np.ndarray], floor: np.ndarray) -> Callable[[np.ndarray], float]:
    """The field ratio (``field_errors``) of the cases idx, from per-case per-step MSEs (n, T) against each
    seed and between the seeds, as ``ratio_interval`` resamples them."""
    def ratio(idx: np.ndarray) -> float:
        model = float(np.mean([_avg_final(m[idx])["avg_rmse"] for m in per_seed]))
        return model / _avg_final(floor[idx])["avg_rmse"]
    return ratio


def field_errors(models: dict[str, Any], test: Path, test_seed: Path | None) -> dict[str, Any]:
    """Per model: Avg / Final RMSE against each simulation of the test design, their mean, the ratio to the
    seed-to-seed floor and its 90 % bootstrap interval over the cases, and per-case Avg RMSE (module
    docstring)."""
    a = open_trajectories(test)
    b = open_trajectories(test_seed) if test_seed is not None else None
    try:
        rows = [int(r) for r in np.flatnonzero(a.complete)]
        if b is not None and not np.array_equal(a.controls_raw, b.controls_raw):
            raise ValueError(f"{test} and {test_seed} are not the same design (their controls differ)")
        cases = [{"case_id": int(a.case_ids[r]), **a.case_feature(r).to_dict()} for r in rows]
        out: dict[str, Any] = {"file": str(test), "seed_file": None if b is None else str(test_seed),
                               "cases": cases}
        seeds = ["seed_a", *(["seed_b"] if b is not None else [])]
        floor: list[np.ndarray] = []
        mse: dict[str, dict[str, list[np.ndarray]]] = {n: {k: [] for k in seeds} for n in models}
        seconds = dict.fromkeys(models, 0.0)
        for r in rows:  # one case's simulations in memory at a time (a test file can outgrow the memory)
            truth = {"seed_a": _states(a, r)}
            if b is not None:
                truth["seed_b"] = _states(b, b.row_of(int(a.case_ids[r])))
                floor.append(case_step_mse(truth["seed_a"][None, 1:], truth["seed_b"][None, 1:])[0])
            x0 = truth["seed_a"][None, 0]  # (1, 2, D, H, W): x_0 is the same for both seeds
            u = torch.from_numpy(to_normalized(a.controls_raw[r])).float()[None]  # (1, 14)
            for name, loaded in models.items():
                t0 = time.perf_counter()
                with torch.no_grad():
                    pred = rollout(loaded.model, x0, u, a.n_states - 1)  # (1, T+1, 2, D, H, W)
                seconds[name] += time.perf_counter() - t0
                for k, states in truth.items():
                    mse[name][k].append(case_step_mse(pred[:, 1:].float(), states[None, 1:])[0])
        if b is not None:
            fl = np.stack(floor)  # (n, T)
            out["floor"] = {**_avg_final(fl), "per_case": [float(np.sqrt(m).mean()) for m in fl]}
        for name in models:
            row: dict[str, Any] = {k: _avg_final(np.stack(v)) for k, v in mse[name].items()}
            both = np.stack([np.sqrt(np.stack(v)).mean(axis=1) for v in mse[name].values()]).mean(axis=0)
            row["avg_rmse"] = float(np.mean([row[k]["avg_rmse"] for k in mse[name]]))
            row["per_case"] = [float(v) for v in both]  # (n,) Avg RMSE per case, mean over the seeds
            row["rollout_s_per_case"] = seconds[name] / len(rows)
            if "floor" in out:
                row["ratio_to_floor"] = row["avg_rmse"] / out["floor"]["avg_rmse"]
                per_seed = [np.stack(v) for v in mse[name].values()]  # each (n, T)
                row["ratio_interval_90"] = ratio_interval(_field_ratio(per_seed, fl), len(rows))
            out[name] = row
    finally:
        a.close()
        if b is not None:
            b.close()
    return out


def interval_note() -> str:
    """The reports' sentence on the interval column."""
    return (f"the interval: 5th-95th percentile of the ratio over {BOOTSTRAP} bootstrap resamples of the "
            "cases.")


def interval_text(ci: Sequence[float] | None) -> str:
    return "" if ci is None else f"{ci[0]:.2f}-{ci[1]:.2f}"


def to_markdown(rep: dict[str, Any]) -> str:
    f = rep["field"]
    names = list(rep["models"])
    lines = ["# The surrogate across hole geometries", "", f"Command: `{rep['command']}`  ",
             f"CPU: {rep['cpu']}, one core", "",
             "Models: " + "; ".join(f"{n} `{m['checkpoint']}` (id `{m['checkpoint_id']}`, trained geometry "
                                    f"{m['geometry']})" for n, m in rep["models"].items()) + ".", "",
             f"## Field error on {len(f['cases'])} held-out holes", "",
             f"`{f['file']}` and `{f['seed_file']}` (one design, two simulator seeds). Avg RMSE of 100-step "
             "rollouts from x_0 against each simulation (mean of the two); floor = the same RMSE between the "
             f"two simulations; target: ratio <= {TARGET_RATIO:g}; {interval_note()}", "",
             "| | Avg RMSE vs seed A | vs seed B | mean | Final RMSE (seed A) | ratio to floor "
             "| 90 % interval |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    if "floor" in f:
        fl = f["floor"]
        lines.append(f"| seed-to-seed floor | | | {fl['avg_rmse']:.4f} | {fl['final_rmse']:.4f} | 1.00 | |")
    for n in names:
        r = f[n]
        seed_b = f"{r['seed_b']['avg_rmse']:.4f}" if "seed_b" in r else ""
        lines.append(f"| {n} | {r['seed_a']['avg_rmse']:.4f} | {seed_b} | {r['avg_rmse']:.4f} "
                     f"| {r['seed_a']['final_rmse']:.4f} | {r.get('ratio_to_floor', float('nan')):.2f} "
                     f"| {interval_text(r.get('ratio_interval_90'))} |")
    lines += ["", "Per case (Avg RMSE, mean over the two seeds):", "",
              "| case | CD (nm) | mask (nm) | floor | " + " | ".join(names) + " |",
              "|---:|---:|---:|---:|" + "---:|" * len(names)]
    for i, c in enumerate(f["cases"]):
        floor = f"{f['floor']['per_case'][i]:.4f}" if "floor" in f else ""
        lines.append(f"| {c['case_id']} | {c['cd_nm']:.1f} | {c['mask_nm']:.0f} | {floor} | "
                     + " | ".join(f"{f[n]['per_case'][i]:.4f}" for n in names) + " |")
    lines += ["", "## ARDE: depth against CD (80 nm mask)", "",
              f"Simulator: `{rep['arde']['file']}` (bench.arde, two seeds, not simulated again).", ""]
    for n in names:
        lines += model_markdown(rep["arde"]["simulator"], {**rep["arde"][n], **rep["models"][n]}) + [""]
    if "default" in rep:
        d = rep["default"]
        each = "; ".join(f"{n} Avg RMSE {d[n]['avg_rmse']:.4f}, Final {d[n]['final_rmse']:.4f}"
                         for n in names)
        lines += [f"## Today's geometry ({d['cases']} held-out cases at the scene's own feature)", "",
                  f"`{d['file']}`, one seed: {each}.", ""]
    lines += ["## Holes that reached the bottom of the Si", ""]
    for t in rep["through"]:
        ids = ", ".join(f"{c['case_id']} (CD {c['cd_nm']:.0f}, mask {c['mask_nm']:.0f})"
                        for c in t["through_cases"])
        lines.append(f"- `{t['file']}`: {t['through']} of {t['cases']}" + (f": {ids}" if ids else ""))
    lines += ["", "## Against the targets", "", *verdict(rep)]
    return "\n".join(lines) + "\n"


def verdict(rep: dict[str, Any], tolerance: float = 0.25) -> list[str]:
    """One line per geometry target for the measured model (Markdown list items)."""
    f, model = rep["field"], rep["field"]["model"]
    out = []
    if "ratio_to_floor" in model:
        met = "met" if model["ratio_to_floor"] <= TARGET_RATIO else "not met"
        out.append(f"- field Avg RMSE <= {TARGET_RATIO:g} x the seed-to-seed floor: "
                   f"{model['avg_rmse']:.4f} / {f['floor']['avg_rmse']:.4f} = {model['ratio_to_floor']:.2f} "
                   f"(90 % interval {interval_text(model.get('ratio_interval_90'))}), {met} (served model "
                   f"{f['baseline'].get('ratio_to_floor', float('nan')):.2f}).")
    t = str(max(float(x) for x in rep["arde"]["simulator"]["times_s"]))
    ratios = {r["recipe"]: r["ratio"][t] for r in rep["arde"]["model"]["recipes"]}
    inside = [n for n, r in ratios.items() if abs(r - 1.0) <= tolerance]
    out.append(f"- ARDE slope within +-{100 * tolerance:g} % of the simulator's at {float(t):g} s: "
               f"{len(inside)} of {len(ratios)} recipes ("
               + ", ".join(f"{n} {r:.2f}" for n, r in ratios.items()) + ").")
    if "default" in rep:
        d = rep["default"]
        worse = d["model"]["avg_rmse"] / d["baseline"]["avg_rmse"] - 1.0
        out.append(f"- today's geometry no worse than the served model: Avg RMSE "
                   f"{d['model']['avg_rmse']:.4f} against {d['baseline']['avg_rmse']:.4f} "
                   f"({100 * worse:+.0f} %) on {d['cases']} cases.")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    from bench.machine import cpu_name
    from nemsim.inference.checkpoint import checkpoint_geometry, checkpoint_id, load_checkpoint

    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="python -m bench.geometry", description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, required=True, help="the model measured (stamps the results)")
    ap.add_argument("--baseline", type=Path, default=Path("checkpoints/nemsim-small.pt"),
                    help="measured beside it (default: the served model)")
    ap.add_argument("--test", type=Path, required=True, help="held-out holes, simulator seed A")
    ap.add_argument("--test-seed", type=Path, default=None, help="the same design, simulator seed B (floor)")
    ap.add_argument("--default", type=Path, default=None, help="held-out cases at the scene's own feature")
    ap.add_argument("--arde", type=Path, default=Path("benchmarks/small/arde.json"),
                    help="bench.arde's simulator results")
    ap.add_argument("--train", type=Path, nargs="*", default=[], help="training files (bottom count only)")
    ap.add_argument("--out", type=Path, default=None, help="writes OUT.json and OUT.md")
    args = ap.parse_args(argv)
    with open_trajectories(args.test) as tf:
        scene = tf.scene
    paths = {"model": args.checkpoint, "baseline": args.baseline}
    loaded = {n: load_checkpoint(p, scene=scene.name) for n, p in paths.items()}
    rep: dict[str, Any] = {
        "command": " ".join(["python -m bench.geometry", *argv]), "cpu": cpu_name(), "scene": scene.name,
        "models": {n: {"checkpoint": str(p), "checkpoint_id": checkpoint_id(p),
                       "geometry": checkpoint_geometry(loaded[n]).as_dict()["kinds"]}
                   for n, p in paths.items()},
        "field": field_errors(loaded, args.test, args.test_seed)}
    arde = json.loads(args.arde.read_text())
    domain = SimConfig(domain=arde["domain"])
    rep["arde"] = {"file": str(args.arde), "simulator": {k: arde[k] for k in
                                                         ("scene", "mask_nm", "cds_nm", "domain", "times_s",
                                                          "recipes")}}
    for n, m in loaded.items():
        rep["arde"][n] = model_arde(m, scene, arde, domain)
    if args.default is not None:
        d = field_errors(loaded, args.default, None)
        rep["default"] = {"file": str(args.default), "cases": len(d["cases"]),
                          **{n: d[n]["seed_a"] for n in loaded}}
    files = [args.test, *([args.test_seed] if args.test_seed else []),
             *([args.default] if args.default else []), *args.train]
    rep["through"] = [through_count(p) for p in files]
    stamp = (str(args.checkpoint), rep["models"]["model"]["checkpoint_id"])
    write_report(args.out, to_markdown(rep), rep, stamp)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
