"""`nemsim bench learning-curve`: the errors at the edges of the control box against the simulator cases an
active-learning run spent, beside a run that spent the same cases on Latin hypercubes.

Each arm is the output directory of one `nemsim learn run` (``--acquisition lhs`` for the control arm; the
same checkpoint, rounds, batch and fine-tuning otherwise). Its points: the starting checkpoint (0 cases,
shared by the arms) and every trained round's model (``round.json``'s checkpoint; cases = the recipes
simulated in its rounds so far). Each model is judged by the physics benchmark (16 box corners and 12 fresh
Latin-hypercube recipes never in any training set, the one-at-a-time slopes; ``bench.physics``) and the
extrapolation benchmark (each control at 1.5 box half-widths, corners past the box; ``bench.extrapolation``),
all against the same simulator runs (``SimTruth``; a cache makes a rerun free). Per model:

* ``corner_depth_mae_nm``, ``corner_avg_rmse``: the 16 box corners (depth error against the mean of the
  simulator's two seeds);
* ``lhs_depth_mae_nm``, ``lhs_avg_rmse``: the 12 interior recipes (what seeking the corners may cost);
* ``slopes_within_25pct`` of ``slopes_resolved``, ``slopes_wrong_sign``: the responses to each control group;
* ``band_avg_rmse``, ``band_ratio``: at 1.5 box half-widths, and over the in-box error;
* ``outer_corner_depth_mae_nm``: the extrapolation benchmark's box corners;
* ``worse_than_no_change``: held-out recipes predicted worse than no change.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.evaluation.truth import write_report

METRICS = {  # key: (label, lower is better)
    "corner_depth_mae_nm": ("corner depth MAE (nm)", True),
    "corner_avg_rmse": ("corner Avg RMSE", True),
    "lhs_depth_mae_nm": ("interior depth MAE (nm)", True),
    "band_avg_rmse": ("Avg RMSE at 1.5 half-widths", True),
    "outer_corner_depth_mae_nm": ("outer corner depth MAE (nm)", True),
    "slopes_within_25pct": ("slopes within ±25 %", False),
}
BAND = "axis 1.5"  # the extrapolation benchmark's group at 1.5 box half-widths


def arm_points(run_dir: str | Path) -> tuple[str, list[tuple[int, Path]]]:
    """(the run's starting checkpoint, [(cases simulated so far, round checkpoint)] of its trained rounds)."""
    run_dir = Path(run_dir)
    learn = run_dir / "learn.json"
    if not learn.is_file():
        raise FileNotFoundError(f"{run_dir} is no `nemsim learn run` directory (no learn.json)")
    points, cases, start = [], 0, None
    for state_path in sorted(run_dir.glob("round-*/round.json")):
        state = json.loads(state_path.read_text())
        start = start or state.get("checkpoint_in")
        if state.get("status") != "trained":
            break  # a round still running, and every later one
        with open(state_path.parent / "batch.csv") as fh:  # the round's recipes, all simulated
            cases += sum(1 for line in fh if line.strip()) - 1
        points.append((cases, Path(state["checkpoint"])))
    if start is None:
        raise ValueError(f"{run_dir}: no round has started")
    return str(start), points


def common_start(found: Any) -> str:
    """The checkpoint every arm's points (``arm_points``) start from; ValueError if they differ."""
    starts = {start for start, _ in found}
    if len(starts) != 1:
        raise ValueError(f"the arms start from different checkpoints {sorted(starts)}: no common curve")
    return starts.pop()


def summarize(physics: dict[str, Any], extrapolation: dict[str, Any]) -> dict[str, Any]:
    """The module docstring's figures of one model from its physics and extrapolation reports."""
    held = physics["heldout"]

    def group(prefix: str) -> tuple[float, float]:
        rows = [h for h in held if h["name"].startswith(prefix)]
        return (float(np.mean([abs(h["error"]["etch_depth"]) for h in rows])),
                float(np.mean([h["avg_rmse"] for h in rows])))  # fmt: skip

    s, groups = physics["summary"], extrapolation["summary"]["groups"]
    (corner_depth, corner_rmse), (lhs_depth, lhs_rmse) = group("corner"), group("lhs")
    return {
        "corner_depth_mae_nm": corner_depth, "corner_avg_rmse": corner_rmse,
        "lhs_depth_mae_nm": lhs_depth, "lhs_avg_rmse": lhs_rmse,
        "slopes_within_25pct": int(s["slopes_within_25pct"]), "slopes_resolved": int(s["slopes_resolved"]),
        "slopes_wrong_sign": int(s["slopes_wrong_sign"]),
        "worse_than_no_change": int(s["heldout_worse_than_no_change"]),
        "band_avg_rmse": float(groups[BAND]["avg_rmse"]),
        "band_ratio": float(groups[BAND]["ratio_to_in_box"]),
        "outer_corner_depth_mae_nm": float(groups["corner"]["mae_nm"]["etch_depth"]),
    }  # fmt: skip


def run_learning_curve(arms: dict[str, str | Path], judge: Any) -> dict[str, Any]:
    """The report: per arm its points [{cases, checkpoint, **summarize}], the shared start first.
    ``judge(checkpoint) -> (physics report, extrapolation report)``."""
    found = {label: arm_points(d) for label, d in arms.items()}
    start = common_start(found.values())
    start_point = {"cases": 0, "checkpoint": start, **summarize(*judge(start))}
    report: dict[str, Any] = {"start": start, "arms": {}}
    for label, (_, points) in found.items():
        report["arms"][label] = {"run": str(arms[label]), "points": [start_point] + [
            {"cases": cases, "checkpoint": str(ckpt), **summarize(*judge(ckpt))} for cases, ckpt in points
        ]}  # fmt: skip
    return report


def format_markdown(rep: dict[str, Any]) -> str:
    lines = ["# Learning curve: errors at the edges against simulator cases spent", "",
             f"Every arm fine-tunes `{rep['start']}` round by round (`nemsim learn run`; its directory "
             "below); each point is that round's model judged on the same simulator runs (physics and "
             "extrapolation benchmarks, two seeds per recipe).", "",
             "| arm | cases | corner depth MAE nm | corner Avg RMSE | interior depth MAE nm | interior Avg "
             "RMSE | slopes ±25 % (wrong sign) | 1.5 half-widths Avg RMSE (/ in-box) | outer corners depth "
             "MAE nm | worse than no change |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for label, arm in rep["arms"].items():
        for p in arm["points"]:
            lines.append(
                f"| {label} | {p['cases']} | {p['corner_depth_mae_nm']:.2f} | {p['corner_avg_rmse']:.4f} | "
                f"{p['lhs_depth_mae_nm']:.2f} | {p['lhs_avg_rmse']:.4f} | {p['slopes_within_25pct']} / "
                f"{p['slopes_resolved']} ({p['slopes_wrong_sign']}) | {p['band_avg_rmse']:.4f} "
                f"({p['band_ratio']:.2f}) | {p['outer_corner_depth_mae_nm']:.2f} | "
                f"{p['worse_than_no_change']} |"
            )
    runs = "; ".join(f"{label}: `{arm['run']}`" for label, arm in rep["arms"].items())
    lines += ["", f"Runs: {runs}."]
    return "\n".join(lines) + "\n"


def plot_learning_curve(rep: dict[str, Any], path: str | Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    for ax, (key, (label, _)) in zip(axes.ravel(), METRICS.items(), strict=True):
        for arm_label, arm in rep["arms"].items():
            pts = arm["points"]
            ax.plot([p["cases"] for p in pts], [p[key] for p in pts], marker="o", label=arm_label)
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("simulator cases spent")
        ax.grid(alpha=0.3)
    axes[0, 0].legend()
    fig.suptitle("Learning curve: active learning against Latin hypercubes at the same budget")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def write_outputs(rep: dict[str, Any], out_dir: str | Path) -> dict[str, str]:
    """learning_curve.md, learning_curve.json and learning_curve.png in ``out_dir``."""
    return write_report(rep, out_dir, "learning_curve", format_markdown, plot_learning_curve)
