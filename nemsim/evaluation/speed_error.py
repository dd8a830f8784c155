"""Speed against error (`nemsim bench speed-error`): what a trajectory costs and how far it is from the truth.

On the first N test cases of a split setting, every method produces the same 100-step trajectory and is
scored against one **reference**: an independent full-budget simulator run of the case, seeded differently
from the data file (``np.random.default_rng([seed, case_id, 0])``; the file's cases use
``default_rng(case_seed(base_seed, case_id))``, another stream). Methods:

  * the simulator at particle budget 1, 1/4, 1/16 (``SimConfig.particle_budget``; the budget-b reruns use
    ``default_rng([seed, case_id, k])``, k = 1, 2, ...). At budget 1 the compared trajectory is the data
    file's own (a second full-budget seed), so that row **is the noise floor**: two equally good
    simulator runs differ by this much; its time is the reference run's wall time;
  * every checkpoint (NEMSim or a baseline) in fp32 and under ``torch.autocast("cpu", torch.bfloat16)``,
    rolled out from the case's x_0 with the file's controls, batch 1 (``nemsim.evaluation.rollout``).

Errors go through ``nemsim.evaluation.metrics``: Avg / Final RMSE over t = 1..H (RMSE_t over cases, then
sqrt), and the final-step Chamfer distance (voxels) averaged over cases. The error against the data file
(what ``nemsim train`` reports) is kept in the JSON as ``avg_rmse_vs_data``.

Timing: methods run side by side, case by case (reference, budgets, then each model and precision), after
one warm-up of every kernel and precision, so load from other jobs on the machine hits them alike. Reported:
the median over cases of the wall seconds per trajectory and of the CPU seconds (``time.process_time``;
honest on a shared machine). The simulator is single-threaded; the CLI runs torch with one thread by default
so both sides use one core. A precision "keeps the error" when its Avg RMSE is within ``keep_error_rel``
(5 %) of the same model's fp32; the fastest such precision is marked, and NEMSim's is ``speed.nemsim_s``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import statistics
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

PRECISIONS = ("fp32", "bf16")
NOISE_FLOOR_NOTE = "noise floor (two full-budget seeds)"


@dataclass(frozen=True)
class SpeedErrorConfig:
    cases: int = 5  # first N test cases of the setting
    budgets: tuple[float, ...] = (1.0, 0.25, 0.0625)  # simulator particle budgets (1 = noise floor row)
    precisions: tuple[str, ...] = PRECISIONS  # model precisions ("fp32" always runs)
    seed: int = 1  # entropy of the reference / reruns: default_rng([seed, case_id, k])
    steps: int | None = None  # transitions per trajectory (default: the scene's horizon, 100)
    keep_error_rel: float = 0.05  # a precision keeps the error if Avg RMSE <= fp32 * (1 + this)


def budget_label(b: float) -> str:
    """1.0 -> '1', 0.25 -> '1/4', 0.0625 -> '1/16'."""
    f = Fraction(b).limit_denominator(1000)
    return str(f.numerator) if f.denominator == 1 else f"{f.numerator}/{f.denominator}"


def _autocast(precision: str):
    import torch

    if precision == "fp32":
        return contextlib.nullcontext()
    if precision == "bf16":
        return torch.autocast("cpu", dtype=torch.bfloat16)
    raise ValueError(f"unknown precision {precision!r}; expected one of {PRECISIONS}")


def _timed(fn):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


class _Scores:
    """Streaming Avg/Final RMSE (vs reference and vs data), final CD and times of one method."""

    def __init__(self) -> None:
        from nemsim.evaluation.metrics import StepRmse

        self.vs_ref = StepRmse()
        self.vs_data = StepRmse()
        self.cd: list[float] = []
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def add(self, pred, ref, data, scene, case_id: int, steps: int, wall: float, cpu: float, cache) -> None:
        """pred, ref, data: (T+1, 2, D, H, W); step 0 (the shared x_0) is excluded from the RMSE."""
        from nemsim.evaluation.metrics import chamfer_distance

        self.vs_ref.update(pred[None, 1:], ref[None, 1:])
        self.vs_data.update(pred[None, 1:], data[None, 1:])
        self.cd.append(float(chamfer_distance(pred[-1], ref[-1], scene, case_id, steps, cache=cache)))
        self.wall.append(float(wall))
        self.cpu.append(float(cpu))

    def summary(self) -> dict[str, Any]:
        return {
            "wall_s": statistics.median(self.wall),
            "cpu_s": statistics.median(self.cpu),
            "avg_rmse": self.vs_ref.avg(),
            "final_rmse": self.vs_ref.final(),
            "cd": float(np.mean(self.cd)),
            "avg_rmse_vs_data": self.vs_data.avg(),
            "wall_s_per_case": self.wall,
            "cpu_s_per_case": self.cpu,
            "cd_per_case": self.cd,
        }


def run_speed_error(
    data: str | Path,
    checkpoints: Sequence[str | Path],
    manifest: dict,
    config: SpeedErrorConfig = SpeedErrorConfig(),
) -> dict[str, Any]:
    """Measure every method on the first ``config.cases`` test cases of ``manifest`` (module docstring).

    Args:
        data: HDF5 trajectory file (``nemsim generate``); its ``generator`` constants configure the reruns.
        checkpoints: ``.pt`` files (any registered model); their scene must be the data file's.
        manifest: split manifest of the setting (``{"setting", "test": [case ids], ...}``).
    Returns:
        JSON-able report: ``rows`` (one per method: label, kind, budget / precision, wall_s, cpu_s,
        avg_rmse, final_rmse, cd, avg_rmse_vs_data, speedup, noise_floor, keeps_error, fastest), plus
        ``noise_floor`` {avg_rmse, final_rmse, cd} and ``speed`` {simulator_s, nemsim_s, nemsim_precision}.
    """
    import torch

    from nemsim.data.hdf5 import open_trajectories
    from nemsim.evaluation.rollout import rollout
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.sim import SimConfig, run_trajectory
    from nemsim.sim.events import build_event_tables
    from nemsim.training.checkpoint import load_checkpoint

    precisions = ["fp32"] + [p for p in config.precisions if p != "fp32"]
    for p in precisions:
        _autocast(p)  # validates the name
    budgets = [1.0] + [float(b) for b in config.budgets if float(b) != 1.0]
    if config.cases < 1:
        raise ValueError(f"cases must be >= 1, got {config.cases}")

    tf = open_trajectories(data)
    try:
        scene = tf.scene
        steps = scene.n_transitions if config.steps is None else int(config.steps)
        if not 1 <= steps <= tf.n_states - 1:
            raise ValueError(f"steps must be in [1, {tf.n_states - 1}], got {steps}")
        test_ids = [int(c) for c in manifest.get("test", [])][: config.cases]
        if not test_ids:
            raise ValueError(f"setting {manifest.get('setting')!r} has no test cases")
        rows = [tf.row_of(c) for c in test_ids]
        unfinished = [c for c, r in zip(test_ids, rows) if not tf.complete[r]]
        if unfinished:
            raise ValueError(f"test cases {unfinished} are unfinished in {data}; finish generation first")

        rules = compile_rules(load_rules())
        if tf.rules_sha256 and tf.rules_sha256 != rules.sha256:
            log.warning("data %s was generated with rules %s..., the library is %s...", data,
                        tf.rules_sha256[:12], rules.sha256[:12])  # fmt: skip
        gen_cfg = tf.generator.get("config") if isinstance(tf.generator, dict) else None
        base_cfg = SimConfig.from_meta(gen_cfg) if gen_cfg else SimConfig()
        sim_cfgs = {b: replace(base_cfg, particle_budget=b).resolved(scene) for b in budgets}
        tables = build_event_tables(rules, base_cfg.resolved(scene))

        models: list[tuple[str, Any, Any]] = []  # (label, LoadedModel, path)
        for path in checkpoints:
            loaded = load_checkpoint(path, scene=scene)
            label = loaded.name
            if any(label == m[0] for m in models):
                label = f"{loaded.name} ({Path(path).stem})"
            models.append((label, loaded, Path(path)))

        def controls_of(row: int):
            sched = tf.controls_raw_schedule
            raw = sched[row] if sched is not None else tf.controls_raw[row]
            u = torch.as_tensor(tf.controls_normalized_schedule(row)[:steps], dtype=torch.float32)[None]
            return np.asarray(raw), u  # (14,) or (T, 14) raw; (1, T, 14) normalized

        # ---- warm-up: JIT kernels, first-call allocations of every model and precision ----
        raw0, u0 = controls_of(rows[0])
        x00 = torch.as_tensor(np.asarray(tf.states[rows[0], 0], dtype=np.float32))[None]
        for b in budgets:
            run_trajectory(scene, rules, raw0, np.random.default_rng(0), sim_cfgs[b], tables=tables,
                           n_transitions=1)  # fmt: skip
        for _, loaded, _ in models:
            for p in precisions:
                with _autocast(p):
                    rollout(loaded.model, x00, u0, min(2, steps))

        keys = [("sim", b) for b in budgets] + [(label, p) for label, _, _ in models for p in precisions]
        scores = {k: _Scores() for k in keys}
        cd_cache: dict = {}
        for case_id, row in zip(test_ids, rows):
            raw, u = controls_of(row)
            data_states = np.asarray(tf.states[row, : steps + 1], dtype=np.float32)  # (T+1, 2, D, H, W)
            ref_res, wall, cpu = _timed(lambda: run_trajectory(
                scene, rules, raw, np.random.default_rng([config.seed, case_id, 0]), sim_cfgs[1.0],
                tables=tables, n_transitions=steps))  # fmt: skip
            ref = ref_res.states
            if np.array_equal(ref, data_states):
                raise ValueError(f"case {case_id}: the reference rerun equals the data file's trajectory; "
                                 "choose another --seed")  # fmt: skip
            # budget 1: the data file's trajectory is the second full-budget seed (noise floor)
            scores[("sim", 1.0)].add(data_states, ref, data_states, scene, case_id, steps, wall, cpu,
                                     cd_cache)  # fmt: skip
            for k, b in enumerate(budgets[1:], start=1):
                res, wall, cpu = _timed(lambda: run_trajectory(
                    scene, rules, raw, np.random.default_rng([config.seed, case_id, k]), sim_cfgs[b],
                    tables=tables, n_transitions=steps))  # fmt: skip
                scores[("sim", b)].add(res.states, ref, data_states, scene, case_id, steps, wall, cpu,
                                       cd_cache)  # fmt: skip
            x0 = torch.as_tensor(data_states[0])[None]  # (1, 2, D, H, W)
            for label, loaded, _ in models:
                for p in precisions:
                    def run(model=loaded.model, p=p):
                        with _autocast(p):
                            return rollout(model, x0, u, steps)

                    pred, wall, cpu = _timed(run)
                    pred = pred[0].float().numpy()  # (T+1, 2, D, H, W)
                    scores[(label, p)].add(pred, ref, data_states, scene, case_id, steps, wall, cpu, cd_cache)
            log.info("case %d done", case_id)
        data_seeds = [int(tf.seeds[r]) for r in rows]
    finally:
        tf.close()

    from nemsim.evaluation.metrics import count_params

    sim_full = scores[("sim", 1.0)].summary()
    report_rows: list[dict[str, Any]] = []
    for b in budgets:
        s = scores[("sim", b)].summary()
        report_rows.append({
            "label": f"simulator, budget {budget_label(b)}", "kind": "simulator", "model": "simulator",
            "budget": b, "precision": None, "params": None, "noise_floor": b == 1.0,
            "note": NOISE_FLOOR_NOTE if b == 1.0 else "", **s,
        })  # fmt: skip
    fastest: dict[str, str] = {}
    for label, loaded, path in models:
        group = []
        for p in precisions:
            s = scores[(label, p)].summary()
            group.append({"label": f"{label} {p}", "kind": "model", "model": label, "checkpoint": str(path),
                          "budget": None, "precision": p, "params": int(count_params(loaded.model)),
                          "noise_floor": False, "note": "", **s})  # fmt: skip
        fp32 = group[0]["avg_rmse"]
        for r in group:
            r["keeps_error"] = bool(r["avg_rmse"] <= fp32 * (1.0 + config.keep_error_rel))
        best = min((r for r in group if r["keeps_error"]), key=lambda r: r["wall_s"])
        best["fastest"] = True
        fastest[label] = best["precision"]
        report_rows.extend(group)
    for r in report_rows:
        r.setdefault("keeps_error", None)
        r.setdefault("fastest", False)
        r["speedup"] = sim_full["wall_s"] / max(r["wall_s"], 1e-12)

    nemsim_rows = [r for r in report_rows if r["kind"] == "model" and r["fastest"]
                   and r["model"].split(" (")[0] == "nemsim"]  # fmt: skip
    return {
        "scene": scene.name,
        "data": str(data),
        "setting": manifest.get("setting"),
        "case_ids": test_ids,
        "steps": steps,
        "torch_threads": torch.get_num_threads(),
        "config": asdict(config),
        "reference": {
            "what": "independent full-budget simulator run per case",
            "rng": f"numpy default_rng([{config.seed}, case_id, 0]); budget-b reruns [seed, case_id, k]",
            "data_seeds": data_seeds,
            "sim_config": sim_cfgs[1.0].to_meta(scene),
        },
        "rows": report_rows,
        "fastest_keeping_error": fastest,
        "noise_floor": {k: sim_full[k] for k in ("avg_rmse", "final_rmse", "cd")},
        "speed": {
            "simulator_s": sim_full["wall_s"],
            "simulator_cpu_s": sim_full["cpu_s"],
            "nemsim_s": nemsim_rows[0]["wall_s"] if nemsim_rows else None,
            "nemsim_precision": nemsim_rows[0]["precision"] if nemsim_rows else None,
        },
    }


def _fmt(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


def format_markdown(report: dict[str, Any]) -> str:
    """The report as a Markdown table (one row per method; the noise floor and fastest precisions marked)."""
    lines = [
        f"## Speed against error: {report['scene']}, {report['setting']}, {len(report['case_ids'])} test "
        f"cases, {report['steps']} steps",
        "",
        "Errors are against an independent full-budget simulator run of each case (not the data file). "
        f"Times: median over cases, one trajectory, batch 1, torch threads {report['torch_threads']}.",
        "",
        "| method | s / trajectory | CPU s | speed-up vs simulator | Avg RMSE | Final RMSE | CD (vox) | "
        "Avg RMSE vs data | note |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in report["rows"]:
        note = r["note"]
        if r.get("fastest"):
            note = "fastest precision keeping the error"
        elif r.get("keeps_error") is False:
            note = "loses accuracy vs fp32"
        label = f"**{r['label']}**" if r["noise_floor"] else r["label"]
        lines.append(
            f"| {label} | {_fmt(r['wall_s'], '.3g')} | {_fmt(r['cpu_s'], '.3g')} | "
            f"{_fmt(r['speedup'], '.3g')}x | "
            f"{_fmt(r['avg_rmse'], '.4f')} | {_fmt(r['final_rmse'], '.4f')} | {_fmt(r['cd'], '.3f')} | "
            f"{_fmt(r['avg_rmse_vs_data'], '.4f')} | {note} |"
        )
    nf = report["noise_floor"]
    lines += ["", f"Noise floor (simulator vs itself, two seeds): Avg RMSE {nf['avg_rmse']:.4f}, "
              f"CD {nf['cd']:.3f} vox."]  # fmt: skip
    return "\n".join(lines) + "\n"


def plot_speed_error(report: dict[str, Any], path: str | Path) -> Path:
    """Log-log PNG: wall seconds per trajectory (x) against Avg RMSE (y); the noise floor marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    tiny = 1e-12
    sim = [r for r in report["rows"] if r["kind"] == "simulator"]
    ax.plot([max(r["wall_s"], tiny) for r in sim], [max(r["avg_rmse"], tiny) for r in sim], "o-", color="k",
            label="simulator (particle budget)")  # fmt: skip
    for r in sim:
        ax.annotate(f"budget {budget_label(r['budget'])}", (max(r["wall_s"], tiny), max(r["avg_rmse"], tiny)),
                    textcoords="offset points", xytext=(6, 4), fontsize=8)  # fmt: skip
    markers = {"fp32": "s", "bf16": "^"}
    models = sorted({r["model"] for r in report["rows"] if r["kind"] == "model"})
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, m in enumerate(models):
        for r in (r for r in report["rows"] if r["model"] == m):
            ax.plot(max(r["wall_s"], tiny), max(r["avg_rmse"], tiny), markers.get(r["precision"], "o"),
                    color=colors[i % len(colors)], label=r["label"], ms=8)  # fmt: skip
    nf = report["noise_floor"]["avg_rmse"]
    ax.axhline(max(nf, tiny), color="tab:red", ls="--", lw=1.2, label=f"noise floor (Avg RMSE {nf:.4f})")
    floor = next(r for r in sim if r["noise_floor"])
    ax.plot(max(floor["wall_s"], tiny), max(nf, tiny), "*", color="tab:red", ms=16, zorder=5)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per trajectory (s, median)")
    ax.set_ylabel("Avg RMSE vs independent full-budget run")
    ax.set_title(f"speed vs error: {report['scene']} {report['setting']}, {len(report['case_ids'])} cases")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_speed_error(report: dict[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """speed_error.json, speed_error.md and speed_error.png in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "speed_error.json", "md": out / "speed_error.md", "png": out / "speed_error.png"}
    paths["json"].write_text(json.dumps(report, indent=2))
    paths["md"].write_text(format_markdown(report))
    plot_speed_error(report, paths["png"])
    return paths
