"""Linear responses over a design: does the surrogate move each profile metric with each control as the
simulator's own data do? (issue "A surrogate engineers can trust"; ``nemsim bench responses``.)

``bench physics`` sweeps one control group at a time from the median recipe, with two seeds per level: a
slope there rests on 3 levels, and the simulator's seed noise leaves many slopes unresolved. This benchmark
asks the same question of a whole design at once, with no new simulation: for the cases of a data file (all
of them, or one split) the final profile metrics (``nemsim.geometry.profile``, nm) of the simulator's
trajectory and of the surrogate's rollout from the same x_0 under the same controls are each fitted by
least squares on the 14 normalized controls,

    m ≈ b_0 + Σ_j b_j u_j,

and the slopes b_j (nm per normalized unit: a flux's unit is half its log10 range) are compared. The
simulator's slope has the ordinary least-squares standard error, se_j = sqrt(σ̂² [(XᵀX)⁻¹]_jj) with
σ̂² = RSS / (N − 15); its residual holds the seed noise and whatever the linear form misses. A slope is
"resolved" where |b_j| > 2 se_j; for resolved slopes the ratio surrogate / simulator, its sign, and whether
it lies within ±25 % of 1 (the issue's target for sweeps) are reported.

What it shows and what it does not: on a training design it measures whether the model learned a response
(the diagnostic that found the bottom width's missed response to the neutral flux, levers.md); on a test
split it measures whether the response generalizes. A linear fit over the box is a summary, not the
response itself (curvature shows in the residual, not in the slopes); ``bench physics`` remains the judge
of single-control sweeps against fresh simulations.

``one_call`` (``--one-call T0``): instead of rollouts from x_0, one network call (its k states) from each
case's own simulator state at step T0, and the slopes of the metrics' increments over the call,
m(T0 + k) - m(T0), simulator against surrogate. This separates what one call has learned from how errors
compound over a rollout: a response right in one call but wrong over the rollout is a drift, one wrong in
one call was not learned (levers.md: the bottom width's increment is lost in per-call noise).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from bench.physics import METRIC_LABELS, SWEEP_METRICS
from nemsim.controls import CONTROL_NAMES, N_CONTROLS, to_normalized
from nemsim.evaluation.figure import pyplot, save_figure
from nemsim.evaluation.truth import predict, write_report
from nemsim.geometry.profile import profile_metrics_batch

RESOLVED_SE = 2.0  # a simulator slope counts as resolved beyond this many standard errors
RATIO_TOLERANCE = 0.25  # the target: within ±25 % of the simulator's slope


def fit_linear(u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares of y (N,) on [1, u] (u (N, 14)): coefficients (15,) and their standard errors (15,)."""
    n, p = len(y), u.shape[1] + 1
    if n <= p:
        raise ValueError(f"a linear fit on {u.shape[1]} controls needs more than {p} cases, got {n}")
    X = np.c_[np.ones(n), u]  # (N, 15)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    resid = y - X @ coef
    sigma2 = float(resid @ resid) / (n - p)
    se = np.sqrt(sigma2 * np.diag(np.linalg.pinv(X.T @ X)))
    return coef, se


def response_rows(u: np.ndarray, sim: dict[str, np.ndarray], model: dict[str, np.ndarray],
                  metrics: tuple[str, ...] = SWEEP_METRICS) -> list[dict[str, Any]]:
    """One row per (metric, control): simulator slope ± se, surrogate slope, ratio, resolved, sign, within."""
    rows = []
    for m in metrics:
        bs, ses = fit_linear(u, sim[m])
        bm, sem = fit_linear(u, model[m])
        for j, name in enumerate(CONTROL_NAMES):
            s, s_se, mo = float(bs[j + 1]), float(ses[j + 1]), float(bm[j + 1])
            resolved = abs(s) > RESOLVED_SE * s_se
            ratio = mo / s if s != 0 else None
            rows.append({
                "metric": m, "control": name, "slope_sim": s, "slope_sim_se": s_se, "slope_model": mo,
                "slope_model_se": float(sem[j + 1]), "ratio": ratio, "resolved": bool(resolved),
                "same_sign": bool(np.sign(mo) == np.sign(s)),
                "within": bool(resolved and ratio is not None and abs(ratio - 1.0) <= RATIO_TOLERANCE),
            })
    return rows


def summarize(rows: list[dict[str, Any]]) -> dict[str, int]:
    resolved = [r for r in rows if r["resolved"]]
    return {"resolved": len(resolved), "within_25pct": sum(r["within"] for r in resolved),
            "wrong_sign": sum(not r["same_sign"] for r in resolved)}


def run_responses(model: Any, states: Any, raw: np.ndarray, rows: list[int], scene: Any,
                  batch_size: int = 8, progress: bool = True, one_call: int | None = None) -> dict[str, Any]:
    """Final metrics of the simulator (``states[row, -1]``) and of the surrogate's rollout (from
    ``states[row, 0]`` under ``raw[row]``) for the given rows of a trajectory file, and their responses.

    Args:
        model: anything ``rollout`` accepts. states: (N, T, 2, D, H, W) array-like (an HDF5 dataset).
        raw: (N, 14) raw controls. rows: the rows to use (> 15). scene: the data's scene.
        one_call: T0: the metrics' increments over one call from the simulator's state at T0 instead
            (module docstring).
    """
    from tqdm import tqdm

    if len(rows) <= N_CONTROLS + 1:
        raise ValueError(f"need more than {N_CONTROLS + 1} cases for a linear fit, got {len(rows)}")
    steps = int(states.shape[1]) - 1
    u = to_normalized(raw[rows])  # (N, 14)
    if one_call is None:  # rollouts from the initial state every case of a design shares, to the end
        t0, k = 0, steps
        start = np.asarray(states[rows[0], 0])  # (2, D, H, W)
    else:  # one call from each case's own simulator state at t0
        from nemsim.evaluation.rollout import steps_per_call

        t0, k = one_call, steps_per_call(model)
        if not 0 <= t0 <= steps - k:
            raise ValueError(f"one call of {k} states from step {t0} leaves the data's horizon: "
                             f"choose a start step from 0 to {steps - k}")
        start = np.stack([np.asarray(states[r, t0]) for r in rows])  # (N, 2, D, H, W)
    sim_end = np.stack([np.asarray(states[r, t0 + k]) for r in rows])  # (N, 2, D, H, W)
    pred_end = np.zeros(sim_end.shape, dtype=np.float32)  # the surrogate in full (the data may be float16)
    with tqdm(total=len(rows), unit="case", desc="rollouts", dynamic_ncols=True, disable=not progress) as bar:
        for i, traj in predict(model, start, raw[rows], k, batch_size=batch_size):
            pred_end[i] = traj[-1]
            bar.update(1)
    ms, mm = profile_metrics_batch(sim_end, scene), profile_metrics_batch(pred_end, scene)
    if one_call is not None:  # increments over the call
        m0 = profile_metrics_batch(start, scene)
        ms, mm = ({m: v - m0[m] for m, v in d.items()} for d in (ms, mm))
    table = response_rows(u, ms, mm)
    return {
        "scene": scene.name, "steps": steps, "n_cases": len(rows),
        "one_call": None if one_call is None else {"t0": t0, "k": k},
        "mae_nm": {m: float(np.mean(np.abs(mm[m] - ms[m]))) for m in SWEEP_METRICS},
        "bias_nm": {m: float(np.mean(mm[m] - ms[m])) for m in SWEEP_METRICS},
        "rows": table, "summary": summarize(table),
    }


def format_markdown(rep: dict[str, Any]) -> str:
    """The resolved slopes per metric, the summary and the per-metric errors."""
    s = rep["summary"]
    call = rep.get("one_call")
    what = (f"final state after {rep['steps']} transitions" if not call else
            f"increments over one call ({call['k']} step{'s' if call['k'] > 1 else ''}) from the simulator's "
            f"state at step {call['t0']}")
    lines = [f"# Linear responses over a design ({rep['scene']}, {rep['n_cases']} cases of "
             f"{rep.get('data', 'a data file')}, {rep.get('cases', '')}; {what})", "",
             f"Slopes of each profile metric's {'increment' if call else 'final value'} on the 14 normalized "
             f"controls (least squares with an "
             f"intercept; nm per normalized unit). 'Resolved': |simulator slope| > {RESOLVED_SE:g} standard "
             f"errors. Ratio = surrogate / simulator. Checkpoint: {rep.get('checkpoint', '?')}.", "",
             f"**{s['within_25pct']} of {s['resolved']} resolved slopes within ±{RATIO_TOLERANCE:.0%}; "
             f"{s['wrong_sign']} with the wrong sign.**", "",
             "| metric | MAE [nm] (surrogate vs the data's one seed) | mean error [nm] |", "|---|---:|---:|"]
    lines += [f"| {METRIC_LABELS[m]} | {rep['mae_nm'][m]:.2f} | {rep['bias_nm'][m]:+.2f} |"
              for m in rep["mae_nm"]]
    lines += ["", "| metric | control | simulator [nm/1] | surrogate [nm/1] | ratio [1] | verdict |",
              "|---|---|---:|---:|---:|---|"]
    for r in rep["rows"]:
        if not r["resolved"]:
            continue
        verdict = "ok" if r["within"] else ("WRONG SIGN" if not r["same_sign"] else "off")
        lines.append(f"| {METRIC_LABELS[r['metric']]} | {r['control']} | {r['slope_sim']:+.2f} ± "
                     f"{r['slope_sim_se']:.2f} | {r['slope_model']:+.2f} | {r['ratio']:+.2f} | {verdict} |")
    return "\n".join(lines) + "\n"


def plot_responses(rep: dict[str, Any], path: str | Path) -> Path:
    """PNG: surrogate slope against simulator slope, one panel per metric, resolved slopes filled."""
    plt = pyplot()

    fig, axes = plt.subplots(1, len(SWEEP_METRICS), figsize=(3.0 * len(SWEEP_METRICS), 3.0), squeeze=False)
    for ax, m in zip(axes[0], SWEEP_METRICS, strict=True):
        rows = [r for r in rep["rows"] if r["metric"] == m]
        sim = np.array([r["slope_sim"] for r in rows])
        mod = np.array([r["slope_model"] for r in rows])
        res = np.array([r["resolved"] for r in rows], dtype=bool)
        ax.errorbar(sim, mod, xerr=[r["slope_sim_se"] for r in rows], fmt="none", ecolor="0.6", lw=0.8)
        ax.scatter(sim[res], mod[res], s=14, color="tab:red", label="resolved", zorder=3)
        ax.scatter(sim[~res], mod[~res], s=14, facecolors="none", edgecolors="0.4", label="not resolved")
        lim = float(max(np.abs(sim).max(), np.abs(mod).max(), 1e-6)) * 1.1
        ax.plot([-lim, lim], [-lim, lim], "k-", lw=0.6)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_title(METRIC_LABELS[m], fontsize=9)
        ax.set_xlabel("simulator slope [nm/1]", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0, 0].set_ylabel("surrogate slope [nm/1]", fontsize=8)
    axes[0, 0].legend(fontsize=6)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


def write_outputs(rep: dict[str, Any], out_dir: str | Path) -> dict[str, str]:
    """responses.md, responses.json and responses.png in ``out_dir``."""
    return write_report(rep, out_dir, "responses", format_markdown, plot_responses)
