"""Profile statistics of a trajectory file's final states: the simulator's calibration figures over a design.

``nemsim data stats FILE [--against OTHER]`` reads the last state of every complete case, computes the
profile metrics of ``nemsim.geometry.profile`` (etch depth, top / bottom width, bowing, mask loss, nm) and
reports their distribution over the design (min, 5 %, median, 95 %, max), the number of cases whose bowing
exceeds one voxel, and, with ``--against``, the paired change on the case ids both files hold (the same
design simulated with another simulator configuration, e.g. before and after a physics change). Only the
final states are read, so a 500-case file takes seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.data.hdf5 import open_trajectories
from nemsim.geometry.profile import profile_metrics_batch

QUANTILES = (0.0, 0.05, 0.5, 0.95, 1.0)


@dataclass(frozen=True)
class FinalProfiles:
    """Final-state profile metrics of a file's complete cases."""

    path: str
    case_ids: np.ndarray  # (N,) int64
    metrics: dict[str, np.ndarray]  # name -> (N,) nm
    voxel_nm: float
    sim_config: dict[str, Any]  # the file's generator record (config entry), {} when absent


def final_profiles(path: str | Path, chunk: int = 64) -> FinalProfiles:
    """Profile metrics of the last state of every complete case of ``path``, reading the final states of
    ``chunk`` consecutive rows at a time (a ``paper`` file does not fit in memory)."""
    with open_trajectories(path) as tf:
        rows = np.flatnonzero(tf.complete)
        if len(rows) == 0:
            raise ValueError(f"{path}: no complete case")
        parts: list[dict[str, np.ndarray]] = []
        for start in range(0, tf.n_cases, chunk):
            keep = tf.complete[start : start + chunk]
            if keep.any():
                finals = np.asarray(tf.states[start : start + chunk, -1])[keep]  # (n, 2, D, H, W)
                parts.append(profile_metrics_batch(finals, tf.scene))
        metrics = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        config = tf.generator.get("config", {}) if isinstance(tf.generator, dict) else {}
        return FinalProfiles(str(path), tf.case_ids[rows], metrics, tf.scene.voxel_nm, dict(config))


def stats(profiles: FinalProfiles) -> dict[str, Any]:
    """Quantiles of every metric over the design and the count of cases bowed by more than one voxel."""
    table = {k: [float(v) for v in np.quantile(x, QUANTILES)] for k, x in profiles.metrics.items()}
    bowed = int((profiles.metrics["bowing"] > profiles.voxel_nm).sum())
    return {"path": profiles.path, "cases": len(profiles.case_ids), "quantiles": list(QUANTILES),
            "metrics": table, "bowed_over_one_voxel": bowed, "voxel_nm": profiles.voxel_nm}  # fmt: skip


def paired_change(new: FinalProfiles, old: FinalProfiles) -> dict[str, Any]:
    """Per-metric change new - old on the case ids both files hold: mean, median, mean |.|, 5-95 % range."""
    common, i_new, i_old = np.intersect1d(new.case_ids, old.case_ids, return_indices=True)
    if len(common) == 0:
        raise ValueError(f"{new.path} and {old.path} share no case id")
    out: dict[str, Any] = {"cases": len(common)}
    for k in new.metrics:
        d = new.metrics[k][i_new] - old.metrics[k][i_old]
        out[k] = {"mean": float(d.mean()), "median": float(np.median(d)), "mean_abs": float(np.abs(d).mean()),
                  "p05": float(np.quantile(d, 0.05)), "p95": float(np.quantile(d, 0.95))}  # fmt: skip
    return out


def stats_markdown(report: dict[str, Any], change: dict[str, Any] | None = None) -> str:
    """The report as Markdown tables (nm)."""
    q = " | ".join(f"{int(p * 100)} %" for p in report["quantiles"])
    lines = [f"{report['path']}: {report['cases']} complete cases, final state (nm)", "",
             f"| metric | {q} |", "|---|" + "---:|" * len(report["quantiles"])]  # fmt: skip
    for k, vals in report["metrics"].items():
        lines.append(f"| {k} | " + " | ".join(f"{v:.1f}" for v in vals) + " |")
    lines.append("")
    lines.append(f"bowing > 1 voxel ({report['voxel_nm']:g} nm): {report['bowed_over_one_voxel']} cases")
    if change is not None:
        lines += ["", f"paired change against the other file, {change['cases']} common cases (nm)", "",
                  "| metric | mean | median | mean abs | 5 % | 95 % |",
                  "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
        for k, c in change.items():
            if isinstance(c, dict):
                lines.append(f"| {k} | {c['mean']:+.2f} | {c['median']:+.2f} | {c['mean_abs']:.2f} | "
                             f"{c['p05']:+.2f} | {c['p95']:+.2f} |")  # fmt: skip
    return "\n".join(lines)
