"""Why the served model misses the top width's response to the ion angular exponents:
is the response in the training data, how large is it against the seed noise, at which exponents and in
which coordinate does it happen, can a small regressor from the 14 controls learn it, and where along a
rollout does the surrogate lose it? ``python -m bench.angle_response``.

Inputs, all simulated on the quarter domain (``nemsim generate --sim-domain quarter``):
  * ``--data``: the training design (500-case Latin hypercube, seed 42), one simulator seed per case.
  * ``--noise-data`` (optional): some of the same cases under another base seed (``--n 60 --seed 1``):
    seed noise of a final metric, sd = std(a - b) / sqrt 2 over the shared case ids, and of the final Si
    field per voxel.
  * ``--sweep-data`` (optional): the issue's sweep, all three ion exponents together from the design centre
    (normalized 0) at m = ``SWEEP_M``, several seeds per level; ``--write-sweep-controls FILE.csv`` writes
    its control rows for ``nemsim generate --controls``.
  * ``--checkpoint`` (optional): the surrogate, rolled out from the data's x_0 over every design case (and
    the sweep), and called once from the simulator's own state at each ``--one-call`` step T0.

What is measured (the ion exponents m of Cl+, Cl2+, Ar+; a metric y = a final profile metric in nm):
  * **Bases.** y fitted by least squares on the 14 controls with the three ion exponents in one of three
    coordinates, each scaled to [-1, 1] over the design range with +1 at the largest m: ``m`` (the model's
    own normalized input), ``log_m``, ``spread`` s(m) = sqrt(2 / (m + 3)) (the RMS sine of the launch
    angle; ``nemsim.model.angle_features``). Per basis: R^2, residual sd (to set against the seed sd), the
    variance the three ion columns explain on their own (R^2 minus that without them), and per exponent the
    fitted change of y from m = 50 to m = 3000 (coefficient x 2) with its standard error. Their sum is the
    linear model's prediction of the sweep's change, all three moved together.
  * **Where in m.** Partial residuals (residual + the exponent's own term, spread basis) binned by that
    exponent's m (``M_BINS``): the response's shape without assuming a coordinate; and the share of the
    design's cases in each bin.
  * **Where in the field.** Per-voxel least squares of the final Si SDF on the same columns: per depth row,
    the variance the ion columns explain on their own, against the seed variance; and the same of the
    surrogate's final error field, whose mean square is what the training loss sees.
  * **Regressors** from the controls to the final top width, 5-fold cross-validated RMSE (overall and on the
    cases with an ion exponent below ``LOW_M``) and their prediction of the sweep: ridge on each basis and
    on quadratic features of the normalized controls; a small MLP (the mean of ``MLP_SEEDS``
    initializations) on m, on the spread basis, on both (the served model's inputs) and on both with the
    low-m cases weighted; boosted trees on both, free and constrained to fall with m; and single MLP
    initializations one at a time: whether fits of equal error agree on the response.
  * **The surrogate.** Its final metrics over the design, fitted the same way (its own response, the ratio
    to the simulator's); its error binned by m; the response at intermediate steps of the rollout; and
    the response of the increment over one call from the simulator's state at T0 (learned per call but lost
    along the rollout, or never learned).

Data (quarter domain, ~2-4 s per case on one core): ``nemsim generate --scene small --sim-domain quarter
--out data/angle/design500.h5``; ``nemsim generate --scene small --sim-domain quarter --n 60 --seed 1 --out
data/angle/noise60.h5``; ``python -m bench.angle_response --write-sweep-controls data/angle/sweep.csv``;
``nemsim generate --scene small --sim-domain quarter --controls data/angle/sweep.csv --seed 991 --out
data/angle/sweep.h5``. Run: ``python -m bench.angle_response --data data/angle/design500.h5 --noise-data
data/angle/noise60.h5 --sweep-data data/angle/sweep.h5 --checkpoint checkpoints/nemsim-small.pt --out
benchmarks/small`` (writes angle_response.json and angle_response.md there, stamped with the checkpoint id).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nemsim.controls import CONTROL_GROUPS, CONTROL_INDEX, CONTROL_SPECS, to_normalized

Basis = Literal["m", "log_m", "spread"]
BASES: tuple[Basis, ...] = ("m", "log_m", "spread")
ION_ANGLES: tuple[str, ...] = CONTROL_GROUPS["ion_angle"]  # Cl+, Cl2+, Ar+
ION_COLS = [CONTROL_INDEX[n] for n in ION_ANGLES]
M_BINS = (50, 100, 200, 500, 1500, 3001)  # bin edges of m (the last includes 3000)
SWEEP_M = (50, 100, 200, 500, 1500, 3000)  # the issue's sweep levels
METRICS = ("top_width", "etch_depth")  # the response asked about, and the contrast
STEPS = (25, 50, 75, 100)  # rollout steps at which the response is read
FOLDS = 5


# --- coordinates -------------------------------------------------------------------------------------
def _basis_value(m: np.ndarray, basis: Basis) -> np.ndarray:
    if basis == "m":
        return np.asarray(m, dtype=np.float64)
    if basis == "log_m":
        return np.log(m)
    if basis == "spread":
        return -np.sqrt(2.0 / (np.asarray(m, dtype=np.float64) + 3.0))  # minus: rises with m like the others
    raise ValueError(f"basis {basis!r}; expected one of {BASES}")


def ion_features(m: np.ndarray, basis: Basis) -> np.ndarray:
    """The ion exponents m (N, 3) in ``basis``, scaled to [-1, 1] over each one's design range, +1 at the
    largest m."""
    lo = np.array([CONTROL_SPECS[j].low for j in ION_COLS])
    hi = np.array([CONTROL_SPECS[j].high for j in ION_COLS])
    f, f_lo, f_hi = (_basis_value(v, basis) for v in (m, lo, hi))
    return 2.0 * (f - f_lo) / (f_hi - f_lo) - 1.0


def design_matrix(raw: np.ndarray, basis: Basis) -> np.ndarray:
    """(N, 14): the normalized controls with the three ion-exponent columns in ``basis``."""
    x = np.asarray(to_normalized(np.asarray(raw, dtype=np.float64)), dtype=np.float64)
    x[:, ION_COLS] = ion_features(raw[:, ION_COLS], basis)
    return x


def sweep_controls(levels: Sequence[int] = SWEEP_M, repeats: int = 1) -> np.ndarray:
    """(L * repeats, 14) raw controls: the design centre with the three ion exponents at each level."""
    from bench.invariants import centre_raw

    rows = []
    for m in levels:
        for _ in range(repeats):
            r = centre_raw()
            r[ION_COLS] = m
            rows.append(r)
    return np.array(rows)


# --- linear fits -------------------------------------------------------------------------------------
def ols(x: np.ndarray, y: np.ndarray) -> dict[str, Any]:
    """Least squares of y (N,) or (N, V) on [1, x] (x (N, p)): coef (p+1, ...), se (p+1, ...), rss."""
    n, p = x.shape[0], x.shape[1] + 1
    if n <= p:
        raise ValueError(f"a fit on {p - 1} columns needs more than {p} cases, got {n}")
    X = np.c_[np.ones(n), x]  # (N, p)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    resid = y - X @ coef
    rss = (resid**2).sum(axis=0)
    cov = np.linalg.pinv(X.T @ X)  # (p, p)
    se = np.sqrt(np.multiply.outer(np.diag(cov), rss / (n - p)))
    return {"coef": coef, "se": se, "rss": rss, "resid": resid}


def basis_fit(raw: np.ndarray, y: np.ndarray, basis: Basis) -> dict[str, Any]:
    """R^2, residual sd, the variance the ion columns explain alone, and each ion exponent's fitted change
    of y from the smallest to the largest m (nm) with its standard error (module docstring)."""
    x = design_matrix(raw, basis)
    full = ols(x, y)
    rest = ols(np.delete(x, ION_COLS, axis=1), y)
    tss = float(((y - y.mean()) ** 2).sum())
    n = len(y)
    delta = {name: {"change": float(2 * full["coef"][j + 1]), "se": float(2 * full["se"][j + 1])}
             for name, j in zip(ION_ANGLES, ION_COLS, strict=True)}
    # the sweep moves all three together: the change of the sum and its se from the coefficients' covariance
    X = np.c_[np.ones(n), x]
    cov = np.linalg.pinv(X.T @ X) * float(full["rss"]) / (n - X.shape[1])
    idx = [j + 1 for j in ION_COLS]
    return {
        "r2": 1.0 - float(full["rss"]) / tss,
        "resid_sd": float(np.sqrt(full["rss"] / (n - X.shape[1]))),
        "ion_unique_r2": (float(rest["rss"]) - float(full["rss"])) / tss,
        "change_by_exponent": delta,
        "change_all_three": float(2 * full["coef"][idx].sum()),
        "change_all_three_se": float(2 * np.sqrt(cov[np.ix_(idx, idx)].sum())),
    }


def group_unique_r2(raw: np.ndarray, y: np.ndarray, basis: Basis = "spread") -> dict[str, float]:
    """Variance of y each control group explains on its own (R^2 lost without its columns)."""
    x = design_matrix(raw, basis)
    tss = float(((y - y.mean()) ** 2).sum())
    rss = float(ols(x, y)["rss"])
    out = {}
    for g, names in CONTROL_GROUPS.items():
        cols = [CONTROL_INDEX[n] for n in names]
        out[g] = (float(ols(np.delete(x, cols, axis=1), y)["rss"]) - rss) / tss
    return out


def binned_response(raw: np.ndarray, y: np.ndarray, bins: Sequence[int] = M_BINS) -> dict[str, Any]:
    """Per ion exponent: partial residuals (spread basis) averaged in bins of its m, relative to the
    overall mean (nm), with their standard errors and counts."""
    x = design_matrix(raw, "spread")
    fit = ols(x, y)
    out: dict[str, Any] = {"edges": list(bins), "exponents": {}}
    for name, j in zip(ION_ANGLES, ION_COLS, strict=True):
        part = fit["resid"] + fit["coef"][j + 1] * x[:, j]
        part = part - part.mean()
        which = np.digitize(raw[:, j], bins) - 1
        rows = []
        for b in range(len(bins) - 1):
            sel = which == b
            k = int(sel.sum())
            rows.append({"n": k, "mean": float(part[sel].mean()) if k else None,
                         "se": float(part[sel].std(ddof=1) / np.sqrt(k)) if k > 1 else None})
        out["exponents"][name] = rows
    return out


def row_share(raw: np.ndarray, field: np.ndarray, noise_var: np.ndarray | None) -> dict[str, Any]:
    """Where in a final Si field (the simulator's, or the surrogate's error) the ion exponents act (module
    docstring, "Where in the field").

    Args:
        field: (N, D, H, W) per case: the final normalized Si SDF, or the surrogate's minus the simulator's.
        noise_var: (D, H, W) seed variance per voxel or None.
    Returns:
        per depth row, the mean over the row's voxels of: the variance the three ion columns explain on
        their own (least squares, spread basis; minus its expectation without any response, 3 residual
        variances / N), the variance all 14 explain, the variance, the mean square and the seed variance
        (normalized SDF^2); and the same over the whole field.
    """
    n, d = field.shape[0], field.shape[1]
    y = field.reshape(n, -1).astype(np.float64)  # (N, V)
    x = design_matrix(raw, "spread")
    rss_full = ols(x, y)["rss"]  # (V,)
    rss_rest = ols(np.delete(x, ION_COLS, axis=1), y)["rss"]
    dof = n - x.shape[1] - 1
    parts = {
        "ion_var": (rss_rest - rss_full - len(ION_COLS) * rss_full / dof) / n,
        "explained_var": y.var(axis=0) - rss_full / n,
        "total_var": y.var(axis=0),
        "mean_sq": (y**2).mean(axis=0),
    }
    if noise_var is not None:
        parts["noise_var"] = np.asarray(noise_var, dtype=np.float64).reshape(-1)
    by_row = {k: v.reshape(d, -1).mean(axis=1) for k, v in parts.items()}  # (D,)
    rows = [{"row": r, **{k: float(v[r]) for k, v in by_row.items()}} for r in range(d)]
    out: dict[str, Any] = {"rows": rows, **{k: float(v.mean()) for k, v in parts.items()}}
    rows_any: list[dict[str, Any]] = rows
    out.setdefault("noise_var", None)
    for r in rows_any:
        r.setdefault("noise_var", None)
    return out


# --- regressors --------------------------------------------------------------------------------------
LOW_M = 200  # "low m": a case whose broadest ion exponent lies below this
OVERSAMPLE = 5  # the low-m cases' weight in the oversampled regressors (copies in the training folds)
MLP_SEEDS = 3  # the MLPs are averages of this many initializations (one alone varies by nm on the sweep)


def regressor_inputs(raw: np.ndarray, inputs: str) -> np.ndarray:
    """A regressor's input columns: a basis of ``design_matrix``, or "m+spread": the 14 normalized controls
    followed by the three ion exponents' spread columns (what the served model reads with
    ``angle_features``, less the neutral's column)."""
    if inputs == "m+spread":
        return np.c_[design_matrix(raw, "m"), ion_features(raw[:, ION_COLS], "spread")]
    return design_matrix(raw, inputs)  # type: ignore[arg-type]


def _regressors(seed: int) -> dict[str, tuple[str, int, Any]]:
    """{name: (inputs, low-m weight, estimator)}."""
    from sklearn.compose import TransformedTargetRegressor
    from sklearn.ensemble import HistGradientBoostingRegressor, VotingRegressor
    from sklearn.linear_model import RidgeCV
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import PolynomialFeatures, StandardScaler

    alphas = np.logspace(-4, 3, 15)

    def mlp() -> Any:  # standardized inputs and target, the mean of MLP_SEEDS initializations
        nets = [(f"s{k}", make_pipeline(StandardScaler(), MLPRegressor(
            hidden_layer_sizes=(32, 32), alpha=1e-2, solver="lbfgs", max_iter=3000, random_state=seed + k)))
            for k in range(MLP_SEEDS)]
        return TransformedTargetRegressor(VotingRegressor(nets), transformer=StandardScaler())

    def trees(monotone: bool) -> Any:  # on "m+spread"; monotone: y may only fall as an ion exponent rises
        cst = None
        if monotone:  # the three ion m columns and the three spread columns (both rise with m)
            cst = [-1 if j in ION_COLS else 0 for j in range(len(CONTROL_SPECS))] + [-1] * len(ION_COLS)
        return HistGradientBoostingRegressor(max_iter=300, learning_rate=0.05, min_samples_leaf=5,
                                             monotonic_cst=cst, random_state=seed)

    return {
        "ridge, m": ("m", 1, RidgeCV(alphas)),
        "ridge, log m": ("log_m", 1, RidgeCV(alphas)),
        "ridge, spread": ("spread", 1, RidgeCV(alphas)),
        "ridge, quadratic in m": ("m", 1, make_pipeline(PolynomialFeatures(2), StandardScaler(),
                                                        RidgeCV(alphas))),
        "MLP 32x32, m": ("m", 1, mlp()),
        "MLP 32x32, spread": ("spread", 1, mlp()),
        "MLP 32x32, m + spread": ("m+spread", 1, mlp()),
        f"MLP 32x32, m + spread, low m x{OVERSAMPLE}": ("m+spread", OVERSAMPLE, mlp()),
        "boosted trees, m + spread": ("m+spread", 1, trees(False)),
        "boosted trees, m + spread, falling in m": ("m+spread", 1, trees(True)),
    }


def _rmse(e: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(e**2))) if len(e) else None


def _oversampled(idx: np.ndarray, low: np.ndarray, weight: int) -> np.ndarray:
    """idx with each low-m case repeated ``weight`` times in all."""
    return np.concatenate([idx, *([idx[low[idx]]] * (weight - 1))])


def regressor_table(raw: np.ndarray, y: np.ndarray, sweep_raw: np.ndarray, seed: int = 0,
                    only: Sequence[str] | None = None) -> dict[str, Any]:
    """Per regressor: 5-fold CV RMSE of y (nm), overall and on the low-m cases, and, fitted on every case,
    its prediction at ``sweep_raw``."""
    from sklearn.base import clone
    from sklearn.model_selection import KFold

    out = {}
    folds = list(KFold(FOLDS, shuffle=True, random_state=seed).split(raw))
    low = raw[:, ION_COLS].min(axis=1) < LOW_M
    for name, (inputs, weight, est) in _regressors(seed).items():
        if only is not None and name not in only:
            continue
        t0 = time.perf_counter()
        x, xs = regressor_inputs(raw, inputs), regressor_inputs(sweep_raw, inputs)
        pred = np.empty_like(y)
        for tr, te in folds:
            tr = _oversampled(tr, low, weight)
            pred[te] = clone(est).fit(x[tr], y[tr]).predict(x[te])
        every = _oversampled(np.arange(len(y)), low, weight)
        sweep = clone(est).fit(x[every], y[every]).predict(xs)
        out[name] = {"inputs": inputs, "low_m_weight": weight,
                     "cv_rmse": float(np.sqrt(np.mean((pred - y) ** 2))),
                     "cv_rmse_low_m": _rmse(pred[low] - y[low]),
                     "sweep": [float(v) for v in sweep], "wall_s": time.perf_counter() - t0}
    return out


def init_spread(raw: np.ndarray, y: np.ndarray, sweep_raw: np.ndarray, inputs: str, seeds: int = 5
                ) -> list[dict[str, float]]:
    """Single-initialization MLPs (those averaged in ``regressor_table``), seeds 0..seeds-1: each one's
    5-fold CV RMSE and its sweep change (last level minus first, nm): how well the loss pins the response."""
    from sklearn.base import clone
    from sklearn.compose import TransformedTargetRegressor
    from sklearn.model_selection import KFold
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    x, xs = regressor_inputs(raw, inputs), regressor_inputs(sweep_raw, inputs)
    folds = list(KFold(FOLDS, shuffle=True, random_state=0).split(raw))
    out = []
    for k in range(seeds):
        est = TransformedTargetRegressor(make_pipeline(StandardScaler(), MLPRegressor(
            hidden_layer_sizes=(32, 32), alpha=1e-2, solver="lbfgs", max_iter=3000, random_state=k)),
            transformer=StandardScaler())
        pred = np.empty_like(y)
        for tr, te in folds:
            pred[te] = clone(est).fit(x[tr], y[tr]).predict(x[te])
        sw = clone(est).fit(x, y).predict(xs)
        out.append({"seed": k, "cv_rmse": float(np.sqrt(np.mean((pred - y) ** 2))),
                    "sweep_change": float(sw[-1] - sw[0])})
    return out


# --- data --------------------------------------------------------------------------------------------
def final_metrics(states: Any, rows: Sequence[int], steps: Sequence[int], scene: Any
                  ) -> dict[int, dict[str, np.ndarray]]:
    """{step: {metric: (N,) nm}} of ``states[row, step]`` for the given rows."""
    from nemsim.geometry.profile import profile_metrics_batch

    out: dict[int, dict[str, list[float]]] = {t: {m: [] for m in METRICS} for t in steps}
    for r in rows:
        x = np.stack([np.asarray(states[r, t]) for t in steps])  # (S, 2, D, H, W)
        met = profile_metrics_batch(x, scene)
        for i, t in enumerate(steps):
            for m in METRICS:
                out[t][m].append(float(met[m][i]))
    return {t: {m: np.array(v) for m, v in d.items()} for t, d in out.items()}


def _rollouts(model: Any, x0: np.ndarray, raw: np.ndarray, steps: Sequence[int], scene: Any,
              progress: bool) -> tuple[dict[int, dict[str, np.ndarray]], np.ndarray]:
    """({step: {metric: (N,) nm}}, the final Si channels (N, D, H, W)) of the surrogate's rollouts."""
    from tqdm import tqdm

    from nemsim.evaluation.truth import predict
    from nemsim.geometry.profile import profile_metrics_batch

    out: dict[int, dict[str, np.ndarray]] = {t: {m: np.empty(len(raw)) for m in METRICS} for t in steps}
    si = np.empty((len(raw), *scene.state_shape[1:]), dtype=np.float32)
    with tqdm(total=len(raw), desc="rollouts", unit="case", disable=not progress) as bar:
        for i, traj in predict(model, x0, raw, max(steps), batch_size=8):
            met = profile_metrics_batch(traj[list(steps)], scene)
            for k, t in enumerate(steps):
                for m in METRICS:
                    out[t][m][i] = met[m][k]
            si[i] = traj[max(steps), 1]
            bar.update(1)
    return out, si


def _one_call(model: Any, states: Any, raw: np.ndarray, rows: Sequence[int], t0: int, scene: Any
              ) -> dict[str, Any]:
    """Increments of the metrics over one call from the simulator's state at t0: simulator and surrogate."""
    from nemsim.evaluation.rollout import steps_per_call
    from nemsim.evaluation.truth import predict
    from nemsim.geometry.profile import profile_metrics_batch

    k = steps_per_call(model)
    start = np.stack([np.asarray(states[r, t0]) for r in rows])  # (N, 2, D, H, W)
    end = np.stack([np.asarray(states[r, t0 + k]) for r in rows])
    pred = np.zeros_like(end)
    for i, traj in predict(model, start, raw, k, batch_size=8):
        pred[i] = traj[-1]
    m0, ms, mm = (profile_metrics_batch(a, scene) for a in (start, end, pred))
    out: dict[str, Any] = {"k": k, "sim": {m: ms[m] - m0[m] for m in METRICS},
                           "model": {m: mm[m] - m0[m] for m in METRICS}}
    return out


def _noise(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, float]:
    return {m: float(np.std(a[m] - b[m], ddof=1) / np.sqrt(2.0)) for m in METRICS}


def _sweep_truth(raw: np.ndarray, y: dict[str, np.ndarray]) -> dict[str, Any]:
    m = raw[:, ION_COLS[0]]
    out: dict[str, Any] = {"m": [], "n": []} | {k: [] for k in METRICS} | {k + "_se": [] for k in METRICS}
    for level in sorted(set(m.tolist())):
        sel = m == level
        out["m"].append(int(level))
        out["n"].append(int(sel.sum()))
        for k in METRICS:
            out[k].append(float(y[k][sel].mean()))
            k_se = float(y[k][sel].std(ddof=1) / np.sqrt(sel.sum())) if sel.sum() > 1 else None
            out[k + "_se"].append(k_se)
    return out


def analyse(data: Path, noise_data: Path | None = None, sweep_data: Path | None = None,
            checkpoint: Path | None = None, one_call: Sequence[int] = (0, 20, 50, 80),
            regressors: bool = True, progress: bool = True, max_cases: int | None = None) -> dict[str, Any]:
    """The whole report (module docstring) as a JSON-able dict."""
    from nemsim.data.hdf5 import open_trajectories

    rep: dict[str, Any] = {"data": str(data)}
    with open_trajectories(data) as tf:
        rows = [r for r in range(tf.n_cases) if tf.complete[r]][:max_cases]
        raw = tf.controls_raw[rows]
        scene, n_steps = tf.scene, tf.n_states - 1
        steps = tuple(t for t in STEPS if t <= n_steps)
        sim = final_metrics(tf.states, rows, steps, scene)
        si_final = np.stack([np.asarray(tf.states[r, n_steps, 1]) for r in rows])  # (N, D, H, W)
        ids = tf.case_ids[rows]
        x0 = np.asarray(tf.states[rows[0], 0])
        rep |= {"scene": scene.name, "n_cases": len(rows), "steps": n_steps,
                "generator_domain": tf.generator.get("config", {}).get("domain")}
        loaded = None
        if checkpoint is not None:
            from nemsim.inference.checkpoint import load_checkpoint

            loaded = load_checkpoint(checkpoint)
            if loaded.scene != scene:
                raise ValueError(f"{data} is on scene {scene.name!r}, {checkpoint} on {loaded.scene.name!r}")
            oc = {t0: _one_call(loaded.model, tf.states, raw, rows, t0, scene) for t0 in one_call}
    y = {m: sim[n_steps][m] for m in METRICS}
    share = np.mean(raw[:, ION_COLS] < 200, axis=0)
    rep["design"] = {"share_below_200": dict(zip(ION_ANGLES, share.tolist(), strict=True)),
                     "normalized_at_200": float(to_normalized(np.r_[np.zeros(5), 200.0, np.zeros(8)])[5]),
                     "mean_nm": {m: float(y[m].mean()) for m in METRICS},
                     "sd_nm": {m: float(y[m].std(ddof=1)) for m in METRICS}}

    noise_var = None
    if noise_data is not None:  # the same cases under another seed
        with open_trajectories(noise_data) as nf:
            pos = {int(c): i for i, c in enumerate(ids)}
            nrows = [r for r in range(nf.n_cases) if nf.complete[r] and int(nf.case_ids[r]) in pos]
            mine = [rows[pos[int(nf.case_ids[r])]] for r in nrows]
            with open_trajectories(data) as tf:
                a = final_metrics(tf.states, mine, (n_steps,), scene)[n_steps]
                sa = np.stack([np.asarray(tf.states[r, n_steps, 1]) for r in mine])
            b = final_metrics(nf.states, nrows, (n_steps,), scene)[n_steps]
            sb = np.stack([np.asarray(nf.states[r, n_steps, 1]) for r in nrows])
        noise_var = 0.5 * ((sa.astype(np.float64) - sb) ** 2).mean(axis=0)  # (D, H, W)
        rep["noise"] = {"data": str(noise_data), "n_cases": len(nrows), "sd_nm": _noise(a, b)}

    rep["fits"] = {m: {b: basis_fit(raw, y[m], b) for b in BASES} for m in METRICS}
    rep["group_unique_r2"] = {m: group_unique_r2(raw, y[m]) for m in METRICS}
    rep["binned"] = {m: binned_response(raw, y[m]) for m in METRICS}
    rep["by_step"] = {"sim": {str(t): basis_fit(raw, sim[t]["top_width"], "spread")["change_all_three"]
                              for t in steps}}
    rep["field"] = row_share(raw, si_final, noise_var)
    rep["field"]["si_top_row"] = int(scene.si_top)

    sweep_raw = sweep_controls()
    sweep_truth = None
    if sweep_data is not None:
        with open_trajectories(sweep_data) as sf:
            srows = [r for r in range(sf.n_cases) if sf.complete[r]]
            s_end = final_metrics(sf.states, srows, (sf.n_states - 1,), scene)[sf.n_states - 1]
            sweep_truth = _sweep_truth(sf.controls_raw[srows], s_end)
        sweep_truth["data"] = str(sweep_data)
    rep["sweep"] = {"m": list(SWEEP_M), "simulator": sweep_truth}
    if regressors:
        rep["regressors"] = {"top_width": regressor_table(raw, y["top_width"], sweep_raw)}
        rep["mlp_inits"] = {inp: init_spread(raw, y["top_width"], sweep_raw, inp)
                            for inp in ("m", "m+spread")}

    if loaded is not None:
        from nemsim.inference.checkpoint import checkpoint_id

        ck = checkpoint
        assert ck is not None
        pred, pred_si = _rollouts(loaded.model, x0, raw, steps, scene, progress)
        sweep_pred = _rollouts(loaded.model, x0, sweep_raw, (n_steps,), scene, False)[0][n_steps]
        err = pred[n_steps]["top_width"] - y["top_width"]
        spread_m = raw[:, ION_COLS].min(axis=1)  # the broadest ion: where the response lives
        which = np.digitize(spread_m, M_BINS) - 1
        rep["model"] = {
            "checkpoint": str(ck), "checkpoint_id": checkpoint_id(ck),
            "fits": {m: {b: basis_fit(raw, pred[n_steps][m], b) for b in BASES} for m in METRICS},
            "mae_nm": {m: float(np.mean(np.abs(pred[n_steps][m] - y[m]))) for m in METRICS},
            "top_width_error_by_min_m": [
                {"n": int((which == b).sum()),
                 "mean": float(err[which == b].mean()) if (which == b).any() else None,
                 "mae": float(np.abs(err[which == b]).mean()) if (which == b).any() else None}
                for b in range(len(M_BINS) - 1)],
            "corr_top_width": float(np.corrcoef(pred[n_steps]["top_width"], y["top_width"])[0, 1]),
            "rmse_top_width": _rmse(err), "rmse_top_width_low_m": _rmse(err[spread_m < LOW_M]),
            "by_step": {str(t): basis_fit(raw, pred[t]["top_width"], "spread")["change_all_three"]
                        for t in steps},
            "sweep": {m: [float(v) for v in sweep_pred[m]] for m in METRICS},
            "error_field": row_share(raw, pred_si - si_final, None),
        }
        calls = []
        for t0, c in oc.items():
            fs, fm = (basis_fit(raw, c[who]["top_width"], "spread") for who in ("sim", "model"))
            calls.append({"t0": t0, "k": c["k"], "sim": fs["change_all_three"],
                          "sim_se": fs["change_all_three_se"], "model": fm["change_all_three"],
                          "sim_resid_sd": fs["resid_sd"]})
        rep["model"]["one_call"] = calls
    return rep


# --- report ------------------------------------------------------------------------------------------
def _f(v: float | None, fmt: str = "+.2f") -> str:
    return "–" if v is None else format(v, fmt)


def _bin_header(first: str, edges: Sequence[int]) -> list[str]:
    names = [f"{edges[i]}–{edges[i + 1] - (i == len(edges) - 2)}" for i in range(len(edges) - 1)]
    return [f"| {first} | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]


def _design_lines(rep: dict[str, Any]) -> list[str]:
    d = rep["design"]
    mean, sd = d["mean_nm"], d["sd_nm"]
    below = ", ".join(f"{k} {v:.1%}" for k, v in d["share_below_200"].items())
    lines = [f"Data: `{rep['data']}` ({rep['generator_domain']} domain), final state after {rep['steps']} "
             f"transitions. Over the cases (mean ± sd): top width {mean['top_width']:.1f} ± "
             f"{sd['top_width']:.2f} nm, etch depth {mean['etch_depth']:.1f} ± {sd['etch_depth']:.2f} nm. "
             f"Cases with m < 200: {below}; m = 200 is at {d['normalized_at_200']:+.3f} of the model's "
             f"normalized input.", ""]
    if "noise" in rep:
        nz = rep["noise"]
        lines += [f"Seed noise (`{nz['data']}`, {nz['n_cases']} of the cases under a second seed, sd of one "
                  "run): " + ", ".join(f"{m} {v:.2f} nm" for m, v in nz["sd_nm"].items()), ""]
    return lines


def _fit_lines(rep: dict[str, Any]) -> list[str]:
    lines = ["## Fits of the final metric on the 14 controls, the ion exponents in three coordinates", "",
             "Change = fitted change from m = 50 to 3000 (nm ± se); 'all three' = the sweep's, the three "
             "exponents moved together. 'Ion R²' = variance the three ion columns explain on their own.", "",
             "| metric | basis | R² | resid sd nm | ion R² | Cl+ | Cl2+ | Ar+ | all three |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for m, fits in rep["fits"].items():
        for b, f in fits.items():
            ch = f["change_by_exponent"]
            per = " | ".join(f"{ch[n]['change']:+.2f} ± {ch[n]['se']:.2f}" for n in ION_ANGLES)
            lines.append(f"| {m} | {b} | {f['r2']:.3f} | {f['resid_sd']:.2f} | {f['ion_unique_r2']:.3f} | "
                         f"{per} | {f['change_all_three']:+.2f} ± {f['change_all_three_se']:.2f} |")
    lines += ["", "Variance each control group explains on its own (spread basis):", "",
              "| metric | " + " | ".join(CONTROL_GROUPS) + " |", "|---|" + "---:|" * len(CONTROL_GROUPS)]
    for m, g in rep["group_unique_r2"].items():
        lines.append(f"| {m} | " + " | ".join(f"{v:.3f}" for v in g.values()) + " |")
    b = rep["binned"]["top_width"]
    lines += ["", "## Where in m: the top width's partial residual by bin of each exponent (nm, relative to "
              "the mean; ± se, (cases))", "", *_bin_header("exponent", b["edges"])]
    for n, rows in b["exponents"].items():
        lines.append(f"| {n} | " + " | ".join(f"{_f(r['mean'])} ± {_f(r['se'], '.2f')} ({r['n']})"
                                             for r in rows) + " |")
    return lines


def _field_lines(rep: dict[str, Any]) -> list[str]:
    fld = rep["field"]
    top = fld["si_top_row"]
    noise = "" if fld["noise_var"] is None else f", seed noise {fld['noise_var'] * 1e4:.3f}"
    err = rep.get("model", {}).get("error_field")
    lines = ["", "## Where in the field: final Si SDF, per voxel (normalized SDF², ×1e-4)", "",
             "Simulator: the variance the three ion columns explain alone (spread basis, less its chance "
             "expectation), the variance all 14 explain, the variance over the design, the seed variance. "
             "Surrogate error (its final state minus the simulator's): the mean square (what the training "
             "loss sees), the part the ion columns explain alone.", "",
             f"Whole field: ion columns alone {fld['ion_var'] * 1e4:.3f}, all controls "
             f"{fld['explained_var'] * 1e4:.3f}, total {fld['total_var'] * 1e4:.3f}{noise}"
             + ("" if err is None else f"; surrogate error: mean square {err['mean_sq'] * 1e4:.3f}, ion "
                f"columns alone {err['ion_var'] * 1e4:.3f}") + ".", "",
             f"| depth row (top Si row = {top}) | ion alone | all controls | total | seed noise | "
             "error mean sq | error ion alone |", "|---:|---:|---:|---:|---:|---:|---:|"]
    for i, r in enumerate(fld["rows"]):
        if top - 14 <= r["row"] <= top + 2:
            nv = None if r["noise_var"] is None else r["noise_var"] * 1e4
            e = None if err is None else err["rows"][i]
            lines.append(f"| {r['row']} | {r['ion_var'] * 1e4:.2f} | {r['explained_var'] * 1e4:.2f} | "
                         f"{r['total_var'] * 1e4:.2f} | {_f(nv, '.2f')} | "
                         f"{_f(None if e is None else e['mean_sq'] * 1e4, '.2f')} | "
                         f"{_f(None if e is None else e['ion_var'] * 1e4, '.2f')} |")
    return lines


def _sweep_lines(rep: dict[str, Any]) -> list[str]:
    sw = rep["sweep"]
    lines = ["", "## The sweep from the design centre (all three ion exponents = m), final top width nm", "",
             f"Regressors: 5-fold CV RMSE over the design and over its cases with an ion exponent below "
             f"{LOW_M} (nm); each MLP the mean of {MLP_SEEDS} initializations; 'low m x{OVERSAMPLE}': those "
             "cases weighted by copies in training.", "",
             "| source | " + " | ".join(f"m={m}" for m in sw["m"]) + " | 50→3000 | CV RMSE | low-m CV RMSE |",
             "|---|" + "---:|" * (len(sw["m"]) + 3)]
    truth = sw["simulator"]
    if truth is not None:
        mean = dict(zip(truth["m"], truth["top_width"], strict=True))
        se = dict(zip(truth["m"], truth["top_width_se"], strict=True))
        cells = " | ".join(f"{_f(mean.get(m), '.1f')} ± {_f(se.get(m), '.1f')}" for m in sw["m"])
        lo, hi = mean.get(sw["m"][0]), mean.get(sw["m"][-1])
        lines.append(f"| simulator (mean of {min(truth['n'])} seeds ± se) | {cells} | "
                     f"{_f(None if lo is None or hi is None else hi - lo)} | | |")
    for name, r in rep.get("regressors", {}).get("top_width", {}).items():
        lines.append(f"| {name} | " + " | ".join(f"{v:.1f}" for v in r["sweep"])
                     + f" | {r['sweep'][-1] - r['sweep'][0]:+.2f} | {r['cv_rmse']:.2f} | "
                     f"{_f(r['cv_rmse_low_m'], '.2f')} |")
    if "model" in rep:
        s = rep["model"]["sweep"]["top_width"]
        lines.append(f"| surrogate `{rep['model']['checkpoint_id']}` | " + " | ".join(f"{v:.1f}" for v in s)
                     + f" | {s[-1] - s[0]:+.2f} | | |")
    inits = rep.get("mlp_inits")
    if inits:
        lines += ["", "The MLP 32x32 one initialization at a time (seeds 0, 1, ...): CV RMSE nm / sweep "
                  "change 50→3000 nm:", ""]
        lines += [f"- inputs {inp}: " + "; ".join(f"{r['cv_rmse']:.2f} / {r['sweep_change']:+.2f}"
                                                  for r in rs) for inp, rs in inits.items()]
    return lines


def _model_lines(rep: dict[str, Any]) -> list[str]:
    mo = rep["model"]
    mae = ", ".join(f"{m} {v:.2f} nm" for m, v in mo["mae_nm"].items())
    lines = ["", f"## The surrogate (`{mo['checkpoint']}`, id `{mo['checkpoint_id']}`) on the design", "",
             f"MAE against the data's seed: {mae}; correlation of its final top width with the simulator's "
             f"{mo['corr_top_width']:.3f}; top-width RMSE {mo['rmse_top_width']:.2f} nm, on the cases with an"
             f" ion exponent below {LOW_M} {_f(mo['rmse_top_width_low_m'], '.2f')} nm.", "",
             "| metric | basis | simulator all three | surrogate all three | ratio | surrogate ion R² |",
             "|---|---|---:|---:|---:|---:|"]
    for m in METRICS:
        for b in BASES:
            fs, fm = rep["fits"][m][b], mo["fits"][m][b]
            s, sm = fs["change_all_three"], fm["change_all_three"]
            lines.append(f"| {m} | {b} | {s:+.2f} ± {fs['change_all_three_se']:.2f} | {sm:+.2f} | "
                         f"{sm / s:+.2f} | {fm['ion_unique_r2']:.3f} |")
    err = mo["top_width_error_by_min_m"]
    lines += ["", "Top-width error (surrogate − simulator, nm) by the smallest of the three ion exponents:",
              "",
              *_bin_header("min m", rep["binned"]["top_width"]["edges"]),
              "| mean (cases) | " + " | ".join(f"{_f(r['mean'])} ({r['n']})" for r in err) + " |",
              "| MAE | " + " | ".join(_f(r["mae"], ".2f") for r in err) + " |", "",
              "The top width's response to the three ion exponents together (spread basis, nm from m = 50 to "
              "3000) at steps of the rollout:", "",
              "| step | " + " | ".join(rep["by_step"]["sim"]) + " |",
              "|---|" + "---:|" * len(mo["by_step"]),
              "| simulator | " + " | ".join(f"{v:+.2f}" for v in rep["by_step"]["sim"].values()) + " |",
              "| surrogate rollout | " + " | ".join(f"{v:+.2f}" for v in mo["by_step"].values()) + " |"]
    if mo.get("one_call"):
        lines += ["", "One call from the simulator's state at step T0: the response of the top width's "
                  "increment over the call (spread basis, all three exponents, nm):", "",
                  "| T0 | states | simulator | surrogate | ratio | simulator resid sd |",
                  "|---:|---:|---:|---:|---:|---:|"]
        lines += [f"| {c['t0']} | {c['k']} | {c['sim']:+.2f} ± {c['sim_se']:.2f} | {c['model']:+.2f} | "
                  f"{c['model'] / c['sim']:+.2f} | {c['sim_resid_sd']:.2f} |" for c in mo["one_call"]]
    return lines


def format_markdown(rep: dict[str, Any], command: str, cpu: str) -> str:
    """The report's tables (module docstring)."""
    lines = [f"# Why the ion-angle response of the top width is not learned ({rep['scene']}, "
             f"{rep['n_cases']} design cases)", "", f"Command: `{command}`  ", f"CPU: {cpu}, one core", "",
             *_design_lines(rep), *_fit_lines(rep), *_field_lines(rep), *_sweep_lines(rep)]
    if "model" in rep:
        lines += _model_lines(rep)
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    from bench.machine import cpu_name
    from bench.stamp import stamp_json, stamp_markdown

    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="python -m bench.angle_response", description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="the design's trajectories (HDF5, `nemsim generate`)")
    ap.add_argument("--noise-data", type=Path, help="some of the same cases under another seed (HDF5)")
    ap.add_argument("--sweep-data", type=Path, help="the sweep of --write-sweep-controls, simulated (HDF5)")
    ap.add_argument("--checkpoint", type=Path, help="the surrogate to judge (default: none)")
    ap.add_argument("--one-call", type=int, nargs="*", default=[0, 20, 50, 80], metavar="T0",
                    help="one call from the simulator's state at each T0 (default 0 20 50 80; none: no)")
    ap.add_argument("--no-regressors", action="store_true", help="skip the cross-validated regressors")
    ap.add_argument("--out", type=Path, metavar="DIR", help="write angle_response.{json,md} into DIR")
    ap.add_argument("--write-sweep-controls", type=Path, metavar="FILE.csv",
                    help="only write the sweep's control rows (--sweep-repeats per level) and exit")
    ap.add_argument("--sweep-repeats", type=int, default=4, help="rows per sweep level (default 4)")
    ap.add_argument("--max-cases", type=int, help="only the first N complete cases (a quick look)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if args.write_sweep_controls is not None:
        from nemsim.controls import write_controls_csv

        write_controls_csv(args.write_sweep_controls, sweep_controls(repeats=args.sweep_repeats))
        sys.stdout.write(f"wrote {args.write_sweep_controls}\n")
        return 0
    if args.data is None or not args.data.is_file():
        ap.error(f"--data: a trajectory file is needed, got {args.data}")
    rep = analyse(args.data, args.noise_data, args.sweep_data, args.checkpoint,
                  tuple(args.one_call), not args.no_regressors, not args.no_progress,
                  args.max_cases)
    command, cpu = " ".join(["python -m bench.angle_response", *argv]), cpu_name()
    text = format_markdown(rep, command, cpu)
    sys.stdout.write(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        js, md = args.out / "angle_response.json", args.out / "angle_response.md"
        js.write_text(json.dumps({"command": command, "cpu": cpu, **rep}, indent=1) + "\n")
        md.write_text(text)
        if args.checkpoint is not None:
            from nemsim.inference.checkpoint import checkpoint_id

            cid = checkpoint_id(args.checkpoint)
            stamp_json(js, args.checkpoint.name, cid)
            stamp_markdown(md, args.checkpoint.name, cid)
    return 0


if __name__ == "__main__":
    sys.exit(main())
