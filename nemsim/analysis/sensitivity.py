"""Control importance over final-state morphology: [supp_protocols] "Selection of OOD Control Axes".

For process variable j and morphology quantity m (etch depth, top-opening width, neck width, bottom width,
bowing at the final state; definitions in ``nemsim.geometry.profile``), eq:supp_control_importance:

    I_{j,m} = 0.7 |beta_{j,m}| + 0.3 |rho_{j,m}|

beta_{j,m}: standardized coefficient of a multivariate least-squares regression of m on all 14 controls
(controls and m z-scored, intercept included); rho_{j,m}: Spearman rank correlation of control j with m.
The overall score is the mean of I_{j,m} over the quantities; the "normalized importance contribution"
(the paper's percentages, e.g. 34.13 % for the Ar+ flux) is score_j / sum_j score_j * 100.

Choices where the paper is silent:
  * the regression uses the transformed controls (log10 fluxes, [supp_representation]); any affine map of
    them (e.g. the [-1, 1] normalization) gives the same standardized coefficients, and Spearman's rho
    is unchanged by the monotone transform;
  * a quantity that is constant over the cases (zero variance, e.g. bowing of a data set without bow)
    carries no information and is left out of the mean (reported in ``skipped_metrics``); a constant
    control gets beta = rho = 0 and is left out of the regression;
  * cases with a non-finite quantity are dropped for that quantity only.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from nemsim.scenes import Scene

log = logging.getLogger(__name__)

SENSITIVITY_METRICS = ("etch_depth", "top_width", "neck_width", "bottom_width", "bowing")
W_BETA, W_RHO = 0.7, 0.3  # eq:supp_control_importance


@dataclass(frozen=True)
class SensitivityResult:
    control_names: tuple[str, ...]
    metric_names: tuple[str, ...]  # quantities used in the mean
    beta: np.ndarray  # (J, M) standardized regression coefficients
    rho: np.ndarray  # (J, M) Spearman correlations
    importance: np.ndarray  # (J, M) I_{j,m}
    score: np.ndarray  # (J,) mean over m of I_{j,m}
    share_percent: np.ndarray  # (J,) score / sum(score) * 100
    n_cases: int
    skipped_metrics: tuple[str, ...] = ()

    def ranking(self) -> list[int]:
        """Control indices, most important first (stable on ties)."""
        return [int(i) for i in np.argsort(-self.score, kind="stable")]

    def table(self) -> str:
        """Ranked plain-text table: rank, control, share %, score, I_{j,m} per quantity."""
        short = {"etch_depth": "depth", "top_width": "top", "neck_width": "neck", "bottom_width": "bottom"}
        cols = [short.get(m, m) for m in self.metric_names]
        name_w = max(len("control"), *(len(n) for n in self.control_names))
        head = f"{'rank':>4}  {'control':<{name_w}}  {'share %':>8}  {'score':>6}  " + "  ".join(
            f"{c:>6}" for c in cols
        )
        lines = [head, "-" * len(head)]
        for r, j in enumerate(self.ranking(), start=1):
            per = "  ".join(f"{v:6.3f}" for v in self.importance[j])
            lines.append(
                f"{r:>4}  {self.control_names[j]:<{name_w}}  {self.share_percent[j]:8.2f}  "
                f"{self.score[j]:6.3f}  {per}"
            )
        lines.append(
            f"{self.n_cases} cases; I = {W_BETA}|beta| + {W_RHO}|rho| averaged over {', '.join(cols)}"
        )
        if self.skipped_metrics:
            lines.append(f"skipped (constant over the cases): {', '.join(self.skipped_metrics)}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "n_cases": self.n_cases,
            "metrics": list(self.metric_names),
            "skipped_metrics": list(self.skipped_metrics),
            "controls": [
                {
                    "name": self.control_names[j],
                    "rank": r,
                    "share_percent": float(self.share_percent[j]),
                    "score": float(self.score[j]),
                    "importance": dict(zip(self.metric_names, map(float, self.importance[j]), strict=True)),
                    "beta": dict(zip(self.metric_names, map(float, self.beta[j]), strict=True)),
                    "rho": dict(zip(self.metric_names, map(float, self.rho[j]), strict=True)),
                }
                for r, j in enumerate(self.ranking(), start=1)
            ],
        }


def _zscore(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column z-scores (N, K) and the mask of non-constant columns (K,)."""
    sd = a.std(axis=0)
    ok = sd > 1e-12 * np.maximum(1.0, np.abs(a).max(axis=0))
    return (a - a.mean(axis=0)) / np.where(ok, sd, 1.0), ok


def _spearman(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Spearman rho of every column of x (N, J) with y (N,); 0 for constant columns."""
    from scipy.stats import rankdata

    rx = rankdata(x, axis=0)  # average ranks for ties
    ry = rankdata(y)
    zx, okx = _zscore(rx)
    zy = (ry - ry.mean()) / ry.std()
    return np.where(okx, zx.T @ zy / len(y), 0.0)


def importance_scores(
    controls: Any,
    quantities: Any,
    control_names: Sequence[str],
    metric_names: Sequence[str] = SENSITIVITY_METRICS,
) -> SensitivityResult:
    """eq:supp_control_importance from arrays.

    Args:
        controls: (N, J) controls in regression coordinates (transformed or normalized, not raw fluxes).
        quantities: (N, M) morphology quantities, one column per ``metric_names``.
        control_names, metric_names: column names.
    """
    x = np.asarray(controls, dtype=np.float64)
    y_all = np.asarray(quantities, dtype=np.float64)
    if x.ndim != 2 or y_all.ndim != 2 or x.shape[0] != y_all.shape[0]:
        raise ValueError(f"controls {x.shape} and quantities {y_all.shape} must be (N, J) and (N, M)")
    if len(control_names) != x.shape[1] or len(metric_names) != y_all.shape[1]:
        raise ValueError(
            f"{len(control_names)} control names for {x.shape[1]} columns, "
            f"{len(metric_names)} metric names for {y_all.shape[1]} columns"
        )
    if not np.all(np.isfinite(x)):
        raise ValueError("controls contain non-finite values")
    n, j = x.shape
    betas, rhos, used, skipped = [], [], [], []
    for m, name in enumerate(metric_names):
        keep = np.isfinite(y_all[:, m])
        xm, y = x[keep], y_all[keep, m]
        if len(y) < 3 or y.std() <= 1e-12 * max(1.0, float(np.abs(y).max())):
            skipped.append(name)
            continue
        zx, okx = _zscore(xm)
        zy = (y - y.mean()) / y.std()
        if len(y) <= int(okx.sum()) + 1:
            log.warning(
                "%s: %d cases for %d controls; the regression is underdetermined", name, len(y), okx.sum()
            )
        coef, *_ = np.linalg.lstsq(zx[:, okx], zy, rcond=None)  # z-scored: no intercept needed
        beta = np.zeros(j)
        beta[okx] = coef
        betas.append(beta)
        rhos.append(_spearman(xm, y))
        used.append(name)
    if not used:
        raise ValueError(f"every quantity is constant over the {n} cases; nothing to rank")
    beta = np.stack(betas, axis=1)  # (J, M)
    rho = np.stack(rhos, axis=1)
    imp = W_BETA * np.abs(beta) + W_RHO * np.abs(rho)
    score = imp.mean(axis=1)
    total = score.sum()
    share = score / total * 100.0 if total > 0 else np.zeros_like(score)
    return SensitivityResult(
        control_names=tuple(control_names),
        metric_names=tuple(used),
        beta=beta,
        rho=rho,
        importance=imp,
        score=score,
        share_percent=share,
        n_cases=n,
        skipped_metrics=tuple(skipped),
    )


def final_state_quantities(final_states: Any, scene: Scene, metric_names=SENSITIVITY_METRICS) -> np.ndarray:
    """(N, 2, D, H, W) final states -> (N, M) profile quantities in nm."""
    from nemsim.geometry.profile import profile_metrics_batch

    pm = profile_metrics_batch(final_states, scene)
    return np.stack([pm[k] for k in metric_names], axis=1)


def control_sensitivity(
    controls: Any, final_states: Any, scene: Scene, control_names: Sequence[str]
) -> SensitivityResult:
    """Importance ranking from controls (N, J) (transformed/normalized) and final states (N, 2, D, H, W)."""
    return importance_scores(controls, final_state_quantities(final_states, scene), control_names)


def sensitivity_from_file(path: str, *, block: int = 64) -> SensitivityResult:
    """Importance ranking of a trajectory file (``nemsim.data.hdf5`` format), reading the final state of
    each case in blocks of ``block`` cases (a ``paper`` file does not fit in memory)."""
    from nemsim.data.hdf5 import open_trajectories

    tf = open_trajectories(path)
    try:
        scene = tf.scene
        n = int(tf.n_cases)
        controls = np.asarray(tf.controls_normalized, dtype=np.float64)
        names = _control_names(tf, controls.shape[1])
        states = tf.states  # (N, T, 2, D, H, W), lazy
        q = [final_state_quantities(np.asarray(states[i : i + block, -1]), scene) for i in range(0, n, block)]
    finally:
        close = getattr(tf, "close", None)
        if callable(close):
            close()
    return importance_scores(controls, np.concatenate(q, axis=0), names)


def _control_names(tf: Any, j: int) -> tuple[str, ...]:
    names = getattr(tf, "control_names", None)
    if names is None:
        from nemsim.controls import CONTROL_NAMES

        names = CONTROL_NAMES
    names = tuple(str(s) for s in names)
    if len(names) != j:
        raise ValueError(f"{len(names)} control names for {j} control columns")
    return names
