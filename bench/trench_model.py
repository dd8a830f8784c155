"""The trench's cross-section model against the simulator: field and profile errors over the seed floor, and
its served speed against the 3-D simulator of the same trench.

  * field error on held-out trenches (``bench.geometry.field_errors``): Avg / Final RMSE of 100-step rollouts
    from each case's x_0 against a test file (``--test``) simulated twice (``--test-seed``, another simulator
    seed; the cross-section simulator, ``--sim-domain section``); the model's error is the mean of its errors
    against the two, the floor the same RMSE between the two simulations; target ratio <= 1.2;
  * profile errors: the final etch depth, top and bottom width and mask loss of every case, RMS over the
    cases of (model - simulation), mean over the two seeds, against the RMS of (seed A - seed B) (the floor;
    a model exactly at the mean scores about 0.71 of it); target ratio <= 1.2 per metric. Beside each ratio,
    its 90 % bootstrap interval over the cases (``bench.geometry.ratio_interval``: floor and model recomputed
    on each resample of the cases), the field ratio's too: a few cases far from the rest move an RMS over
    tens of cases;
  * speed (``--speed N``): ``bench.serving.bench_service`` on the checkpoint (N uncached ``POST /rollout``,
    one core, the whole app stack) and the full-domain (3-D) simulator of the checkpoint's own trench on the
    first recipes of the same run (``--sim-cases``): the speed-up, target >= 100.

Run: ``python -m bench.trench_model --checkpoint CKPT --test A.h5 --test-seed B.h5 --speed 20 --sim-cases 3
--out benchmarks/small/trench_model`` (writes .json and .md, stamped with the checkpoint id).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.arde import plural, write_report
from bench.geometry import TARGET_RATIO, field_errors, interval_note, interval_text, ratio_interval
from nemsim.controls import to_normalized
from nemsim.data.hdf5 import open_trajectories
from nemsim.evaluation.rollout import rollout
from nemsim.geometry.profile import measured_profile_metrics

PROFILE_METRICS = ("etch_depth", "top_width", "bottom_width", "mask_loss")
TARGET_SPEEDUP = 100.0  # served against the 3-D simulator of the same trench


def _final_metrics(states: Any, scene: Any) -> dict[str, float]:
    """The last state's profile metrics (nm, NaN where undefined) of a trajectory (T+1, 2, D, H, W)."""
    m = measured_profile_metrics(np.asarray(states[-1:], dtype=np.float32), scene)
    return {k: float(m[k][-1]) for k in PROFILE_METRICS}


def _rms(d: np.ndarray, ok: np.ndarray | None = None) -> float:
    d = d if ok is None else d[ok]
    return float(np.sqrt(np.mean(d**2))) if d.size else float("nan")


def _profile_ratio(m: np.ndarray, sa: np.ndarray, sb: np.ndarray) -> Callable[[np.ndarray], float]:
    """The profile ratio (``profile_errors``) of the cases idx, as ``ratio_interval`` resamples them."""
    def ratio(idx: np.ndarray) -> float:
        return 0.5 * (_rms(m[idx] - sa[idx]) + _rms(m[idx] - sb[idx])) / _rms(sa[idx] - sb[idx])
    return ratio


def profile_errors(model: Any, test: Path, test_seed: Path) -> dict[str, Any]:
    """Per metric: RMS over cases of model - simulation (each seed, and their mean), RMS of seed A - seed B
    (the floor), the ratio and its 90 % bootstrap interval; cases where a metric is undefined in any of the
    three are left out of it."""
    a, b = open_trajectories(test), open_trajectories(test_seed)
    try:
        rows = [int(r) for r in np.flatnonzero(a.complete)]
        got: dict[str, list[dict[str, float]]] = {"model": [], "seed_a": [], "seed_b": []}
        for r in rows:
            scene = a.case_scene(r)
            sa = np.asarray(a.states[r], dtype=np.float32)
            sb = np.asarray(b.states[b.row_of(int(a.case_ids[r]))], dtype=np.float32)
            u = torch.from_numpy(to_normalized(a.controls_raw[r])).float()[None]
            with torch.no_grad():
                pred = rollout(model, torch.from_numpy(sa[None, 0]), u, a.n_states - 1)[0].numpy()
            for key, states in (("model", pred), ("seed_a", sa), ("seed_b", sb)):
                got[key].append(_final_metrics(states, scene))
    finally:
        a.close()
        b.close()
    out: dict[str, Any] = {}
    for k in PROFILE_METRICS:
        m, sa_, sb_ = (np.array([c[k] for c in got[key]]) for key in ("model", "seed_a", "seed_b"))
        ok = np.isfinite(m) & np.isfinite(sa_) & np.isfinite(sb_)
        floor = _rms(sa_ - sb_, ok)
        err = 0.5 * (_rms(m - sa_, ok) + _rms(m - sb_, ok))
        out[k] = {"cases": int(ok.sum()), "floor_nm": floor, "model_nm": err,
                  "vs_seed_a_nm": _rms(m - sa_, ok), "vs_seed_b_nm": _rms(m - sb_, ok),
                  "ratio_to_floor": err / floor if floor > 0 else float("nan"),
                  "ratio_interval_90": ratio_interval(_profile_ratio(m[ok], sa_[ok], sb_[ok]), int(ok.sum()))
                  if ok.any() else None,
                  "sim_mean_nm": float(np.mean(0.5 * (sa_[ok] + sb_[ok]))) if ok.any() else float("nan")}
    return out


def _trained(kind: str, r: dict[str, Any]) -> str:
    """'trenches of CD 24-64 nm under 40-120 nm of mask'."""
    return (f"{plural(kind)} of CD {r['cd_nm'][0]:.0f}-{r['cd_nm'][1]:.0f} nm under {r['mask_nm'][0]:.0f}-"
            f"{r['mask_nm'][1]:.0f} nm of mask")


def to_markdown(rep: dict[str, Any]) -> str:
    f, p = rep["field"], rep["profile"]
    m = f["model"]
    lines = ["# The trench's cross-section model against the simulator", "",
             f"Command: `{rep['command']}`  ", f"CPU: {rep['cpu']}, one core", "",
             f"Model `{rep['checkpoint']}` (id `{rep['checkpoint_id']}`), trained on "
             + "; ".join(_trained(k, r) for k, r in rep["geometry"].items()) + ".", "",
             f"## Field error on {len(f['cases'])} held-out trenches", "",
             f"`{f['file']}` and `{f['seed_file']}`: one design (held-out recipe, width and mask), two "
             "seeds of the cross-section simulator. Avg RMSE of 100-step rollouts from x_0 against each "
             "(mean of the two); floor = the same RMSE between the two simulations; target ratio <= "
             f"{TARGET_RATIO:g}; {interval_note()}", "",
             "| | vs seed A | vs seed B | mean | Final RMSE (seed A) | ratio to floor | 90 % interval |",
             "|---|---:|---:|---:|---:|---:|---:|",
             f"| seed-to-seed floor | | | {f['floor']['avg_rmse']:.4f} | {f['floor']['final_rmse']:.4f} "
             "| 1.00 | |",
             f"| model | {m['seed_a']['avg_rmse']:.4f} | {m['seed_b']['avg_rmse']:.4f} | {m['avg_rmse']:.4f} "
             f"| {m['seed_a']['final_rmse']:.4f} | {m['ratio_to_floor']:.2f} "
             f"| {interval_text(m.get('ratio_interval_90'))} |", "",
             "## Profile errors at 10 s", "",
             "RMS over the cases of (model - simulation), mean over the two seeds, against the RMS of "
             f"(seed A - seed B); a model at the simulator's mean scores about 0.71; {interval_note()}", "",
             "| metric | cases | simulator mean (nm) | floor (nm) | model (nm) | ratio to floor "
             "| 90 % interval |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for k, r in p.items():
        lines.append(f"| {k} | {r['cases']} | {r['sim_mean_nm']:.1f} | {r['floor_nm']:.2f} "
                     f"| {r['model_nm']:.2f} | {r['ratio_to_floor']:.2f} "
                     f"| {interval_text(r.get('ratio_interval_90'))} |")
    if "speed" in rep:
        s = rep["speed"]
        u, sim = s["uncached"], s["simulator"]
        lines += ["", "## Served against the 3-D simulator of the same trench", "",
                  f"`POST /rollout` (100 steps, uncached, {u['n']} recipes, runtime "
                  f"{s['runtime'].get('backend')} {s['runtime'].get('precision')}): p50 {u['p50_ms']:.1f} ms "
                  f"(rollout {u['rollout_p50_ms']:.1f} ms), p95 {u['p95_ms']:.1f} ms. The full-domain "
                  "simulator of the served trench "
                  f"({sim['feature']}) on the first {sim['n_cases']} of the same recipes: median "
                  f"{sim['median']['wall_s']:.2f} s wall, {sim['median']['cpu_s']:.2f} s CPU. "
                  f"Speed-up {s['simulator_speedup']:.0f}x (target >= {TARGET_SPEEDUP:g})."]
    lines += ["", "## Against the targets", "", *verdict(rep)]
    return "\n".join(lines) + "\n"


def verdict(rep: dict[str, Any]) -> list[str]:
    """One line per trench target (Markdown list items)."""
    f = rep["field"]
    ratio = f["model"]["ratio_to_floor"]
    out = [f"- field Avg RMSE <= {TARGET_RATIO:g} x the floor: {ratio:.2f} (90 % interval "
           f"{interval_text(f['model'].get('ratio_interval_90'))}), "
           f"{'met' if ratio <= TARGET_RATIO else 'not met'}."]
    worst = max(rep["profile"].items(), key=lambda kv: kv[1]["ratio_to_floor"])
    met = all(r["ratio_to_floor"] <= TARGET_RATIO for r in rep["profile"].values())
    out.append(f"- profile errors <= {TARGET_RATIO:g} x the floor: "
               + ", ".join(f"{k} {r['ratio_to_floor']:.2f}" for k, r in rep["profile"].items())
               + f"; {'met' if met else 'not met'} (worst: {worst[0]}).")
    if "speed" in rep:
        sp = rep["speed"]["simulator_speedup"]
        out.append(f"- served >= {TARGET_SPEEDUP:g}x the 3-D simulator: {sp:.0f}x, "
                   f"{'met' if sp >= TARGET_SPEEDUP else 'not met'}.")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    from bench.machine import cpu_name
    from bench.serving import bench_service
    from nemsim.inference.checkpoint import checkpoint_geometry, checkpoint_id, load_checkpoint

    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="python -m bench.trench_model", description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, required=True, help="a section-domain (trench) checkpoint")
    ap.add_argument("--test", type=Path, required=True, help="held-out trenches, simulator seed A")
    ap.add_argument("--test-seed", type=Path, required=True, help="the same design, simulator seed B (floor)")
    ap.add_argument("--speed", type=int, default=0, metavar="N",
                    help="also time N uncached POST /rollout calls (default 0: no speed figure)")
    ap.add_argument("--sim-cases", type=int, default=3, help="3-D simulator runs beside --speed (default 3)")
    ap.add_argument("--out", type=Path, default=None, help="writes OUT.json and OUT.md")
    args = ap.parse_args(argv)
    loaded = load_checkpoint(args.checkpoint)
    if getattr(loaded.model.config, "domain", "full") != "section":
        ap.error(f"{args.checkpoint} is not a cross-section (trench) model: its domain is "
                 f"{getattr(loaded.model.config, 'domain', 'full')!r}")
    torch.set_num_threads(1)
    rep: dict[str, Any] = {
        "command": " ".join(["python -m bench.trench_model", *argv]), "cpu": cpu_name(),
        "checkpoint": args.checkpoint.name, "checkpoint_id": checkpoint_id(args.checkpoint),
        "geometry": checkpoint_geometry(loaded).as_dict()["kinds"],
        "field": field_errors({"model": loaded}, args.test, args.test_seed),
        "profile": profile_errors(loaded.model, args.test, args.test_seed)}
    if args.speed > 0:
        rep["speed"] = bench_service(args.checkpoint, n=args.speed, n_cached=20, sim_cases=args.sim_cases)
    write_report(args.out, to_markdown(rep), rep, (str(args.checkpoint), rep["checkpoint_id"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
