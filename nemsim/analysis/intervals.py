"""Uncertainty of predicted profile metrics: split-conformal intervals per time step, and the distance of
a recipe from the training data.

Why conformal and not an ensemble: a deep ensemble needs >= 3 independently trained models (hours of CPU
each); split-conformal calibration needs one pass of rollouts over held-out validation cases and gives
intervals with a finite-sample coverage guarantee for cases exchangeable with them (controls drawn from
the same design), which is what an engineer choosing a recipe inside the training box asks for. Outside
the data the guarantee is void: that is what the distance flag reports.

Method (``calibrate``): roll the surrogate out on every calibration case (the validation split of a
setting, from each case's own x_0) and compute the exact profile metrics (``nemsim.geometry.profile``) of
prediction and simulator run at every step. The residual r = predicted - simulated of metric m at step t
over the n cases gives, for a nominal level 1 - a, the two one-sided split-conformal quantiles

    lo = r_(floor((n + 1) a / 2)),   hi = r_(ceil((n + 1) (1 - a / 2)))   (order statistics of the residuals)

and the interval [pred - hi, pred - lo] covers the simulated value with probability >= 1 - a for a new
exchangeable case. Signed rather than |r|: where the surrogate is biased the interval shifts instead of
widening. A rank beyond n (too few cases for the level) gives an infinite bound, reported as null.

Distance to the training data: the nearest training case's control vector (normalized, eq:supp_control_
normalization, the coordinates the model sees), compared with the training cases' own nearest-neighbour
distances. A recipe is ``inside`` when its nearest-neighbour distance is at most the 95th percentile of
those, ``far`` otherwise (and ``outside_box`` when a control leaves the training box).

File (``calibration_path``: next to the checkpoint, ``<stem>.calibration.json``): format version, the
checkpoint's file hash prefix, scene, levels, metrics, per-step offsets, the split and case counts, the
test coverage measured at calibration time, and the training support (case ids of the LHS design when the
data's controls are that design's rows, else the normalized controls).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.controls import DESIGN_N, DESIGN_SEED, lhs_design, to_normalized
from nemsim.geometry.profile import METRIC_NAMES
from nemsim.inference.checkpoint import checkpoint_id

CALIBRATION_FORMAT = 1
DEFAULT_LEVELS = (0.8, 0.9)
NEAR_QUANTILE = 0.95  # nearest-neighbour distance percentile of the training cases that still counts as near


def calibration_path(checkpoint: str | Path) -> Path:
    """Where the calibration of a checkpoint lives: ``<dir>/<stem>.calibration.json``."""
    p = Path(checkpoint)
    return p.with_name(p.stem + ".calibration.json")


# --- conformal quantiles ------------------------------------------------------------------------------


def conformal_offsets(residuals: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Split-conformal interval offsets from calibration residuals (module docstring).

    Args:
        residuals: (n, ...) predicted - true over n calibration cases.
        level: nominal coverage 1 - a in (0, 1).
    Returns:
        (lower, upper), each (...): the interval of a new prediction p is [p + lower, p + upper]
        (lower = -hi, upper = -lo). -inf / +inf where n is too small for the level.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    r = np.sort(np.asarray(residuals, dtype=np.float64), axis=0)  # (n, ...)
    n = r.shape[0]
    a = 1.0 - level
    k_lo = int(math.floor((n + 1) * a / 2.0))  # 1-based rank of the lower residual
    k_hi = int(math.ceil((n + 1) * (1.0 - a / 2.0)))
    lo = r[k_lo - 1] if k_lo >= 1 else np.full(r.shape[1:], -np.inf)
    hi = r[k_hi - 1] if k_hi <= n else np.full(r.shape[1:], np.inf)
    return -hi, -lo


def coverage(pred: np.ndarray, true: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
    """Fraction of ``true`` inside [pred + lower, pred + upper] (broadcast; all arrays share a shape)."""
    inside = (true >= pred + lower) & (true <= pred + upper)
    return float(np.mean(inside))


# --- the calibration ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Calibration:
    """Per-step conformal offsets of profile metrics and the training support of one checkpoint."""

    checkpoint_sha256: str  # first 12 hex digits of the checkpoint file's SHA-256
    scene: str
    levels: tuple[float, ...]
    metrics: tuple[str, ...]
    # offsets[str(level)][metric] = {"lower": [T+1], "upper": [T+1]} in nm (None = unbounded)
    offsets: dict[str, dict[str, dict[str, list[float | None]]]]
    calibration: dict[str, Any]  # {"setting", "split", "cases"}
    test_coverage: dict[str, Any] = field(default_factory=dict)  # measured at calibration time
    support: dict[str, Any] = field(default_factory=dict)  # training controls and their spacing
    format_version: int = CALIBRATION_FORMAT

    @property
    def steps(self) -> int:
        """Transitions covered (the offsets have steps + 1 entries)."""
        first = next(iter(self.offsets.values()))
        return len(next(iter(first.values()))["lower"]) - 1

    def interval(
        self, metric: str, step: int, value: float, level: float
    ) -> tuple[float | None, float | None]:
        """[lo, hi] (nm) around a predicted ``value`` of ``metric`` at ``step`` (None: unbounded side)."""
        key = _level_key(level, self.levels)
        if metric not in self.metrics:
            raise ValueError(f"no calibration for metric {metric!r}; calibrated: {list(self.metrics)}")
        if not 0 <= step <= self.steps:
            raise ValueError(f"step {step} outside the calibrated steps 0..{self.steps}")
        off = self.offsets[key][metric]
        lo, hi = off["lower"][step], off["upper"][step]
        return (None if lo is None else value + lo, None if hi is None else value + hi)

    def intervals(self, metrics: Mapping[str, Sequence[float | None]],
                  level: float) -> dict[str, dict[str, list]]:
        """Per-step intervals of a metrics trajectory {name: (T+1,)}: {name: {"lo": [...], "hi": [...]}}.
        Steps past the calibrated horizon reuse the last calibrated step's offsets (flagged by callers); a
        value that is undefined (None, e.g. no hole yet) has no interval (None, None)."""
        out: dict[str, dict[str, list]] = {}
        for name, values in metrics.items():
            if name not in self.metrics:
                continue
            pairs = [(None, None) if v is None else self.interval(name, min(t, self.steps), float(v), level)
                     for t, v in enumerate(values)]
            out[name] = {"lo": [p[0] for p in pairs], "hi": [p[1] for p in pairs]}
        return out

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["levels"] = list(self.levels)
        d["metrics"] = list(self.metrics)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Calibration:
        if int(d.get("format_version", 0)) > CALIBRATION_FORMAT:
            raise ValueError(
                f"calibration format {d.get('format_version')} is newer than this NEMSim reads "
                f"({CALIBRATION_FORMAT})"
            )
        keys = {f for f in cls.__dataclass_fields__}
        missing = sorted(
            k
            for k in ("checkpoint_sha256", "scene", "levels", "metrics", "offsets", "calibration")
            if k not in d
        )
        if missing:
            raise ValueError(f"not a NEMSim calibration file: lacks {missing}")
        kw = {k: v for k, v in d.items() if k in keys}
        kw["levels"] = tuple(float(v) for v in d["levels"])
        kw["metrics"] = tuple(d["metrics"])
        return cls(**kw)

    def write(self, path: str | Path) -> Path:
        """Indented JSON with every list of numbers on one line (a small, diff-friendly file)."""
        import re

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps(self.to_dict(), indent=1)
        numbers = re.compile(r"\[\s*([-+0-9.eE,\snul]*?)\s*\]")  # a list of numbers and nulls
        text = numbers.sub(lambda m: "[" + " ".join(m.group(1).split()) + "]", text)
        path.write_text(text + "\n")
        return path


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration file; ValueError if it is not one."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"{path}: not JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a NEMSim calibration file")
    return Calibration.from_dict(data)


def calibration_for(checkpoint: str | Path) -> Calibration | None:
    """The calibration stored next to ``checkpoint`` if it exists and belongs to this checkpoint file."""
    path = calibration_path(checkpoint)
    if not path.is_file():
        return None
    cal = load_calibration(path)
    return cal if cal.checkpoint_sha256 == checkpoint_id(checkpoint) else None


def _level_key(level: float, levels: Sequence[float]) -> str:
    for lv in levels:
        if abs(lv - level) < 1e-9:
            return _key(lv)
    raise ValueError(f"level {level} is not calibrated; calibrated levels: {list(levels)}")


def _key(level: float) -> str:
    return f"{level:g}"


def _clean(a: np.ndarray, digits: int = 3) -> list[float | None]:
    return [round(float(v), digits) if np.isfinite(v) else None for v in np.asarray(a).reshape(-1)]


def offsets_from_residuals(
    residuals: dict[str, np.ndarray], levels: Sequence[float]
) -> dict[str, dict[str, dict[str, list[float | None]]]]:
    """{level: {metric: {"lower", "upper"}}} from residuals {metric: (n, T+1)}."""
    out: dict[str, dict[str, dict[str, list[float | None]]]] = {}
    for level in levels:
        per = {}
        for m, r in residuals.items():
            lower, upper = conformal_offsets(r, level)
            per[m] = {"lower": _clean(lower), "upper": _clean(upper)}
        out[_key(level)] = per
    return out


def coverage_table(
    offsets: dict[str, dict[str, dict[str, list[float | None]]]],
    pred: dict[str, np.ndarray],
    true: dict[str, np.ndarray],
) -> dict[str, Any]:
    """Coverage of stored offsets on cases: {level: {"all": f, "final": f, "per_metric": {m: f},
    "per_metric_final": {m: f}}} over steps 1..T (step 0 is the given initial state) of arrays (n, T+1)."""
    out: dict[str, Any] = {}
    for key, per in offsets.items():
        rows, finals, all_in = {}, {}, []
        for m, off in per.items():
            lower = np.array([-np.inf if v is None else v for v in off["lower"]])[None, 1:]
            upper = np.array([np.inf if v is None else v for v in off["upper"]])[None, 1:]
            p, t = pred[m][:, 1:], true[m][:, 1:]
            inside = (t >= p + lower) & (t <= p + upper)  # (n, T)
            rows[m] = round(float(inside.mean()), 4)
            finals[m] = round(float(inside[:, -1].mean()), 4)
            all_in.append(inside)
        stacked = np.stack(all_in)  # (M, n, T)
        out[key] = {
            "all": round(float(stacked.mean()), 4),
            "final": round(float(stacked[:, :, -1].mean()), 4),
            "per_metric": rows,
            "per_metric_final": finals,
        }
    return out


# --- training support -----------------------------------------------------------------------------


def nn_distances(points: np.ndarray) -> np.ndarray:
    """(N,) distance of each point (N, 14) to its nearest other point."""
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)  # (N, N)
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1)


def support_from_controls(case_ids: Sequence[int], controls_raw: np.ndarray) -> dict[str, Any]:
    """The training support record: LHS design ids when the controls are that design's rows, else the
    normalized controls; plus the nearest-neighbour spacing statistics."""
    ids = [int(c) for c in case_ids]
    raw = np.asarray(controls_raw, dtype=np.float64)
    norm = np.asarray(to_normalized(raw))
    spacing = nn_distances(norm)
    rec: dict[str, Any] = {
        "n": len(ids),
        "nn_median": round(float(np.median(spacing)), 4),
        "nn_q95": round(float(np.quantile(spacing, NEAR_QUANTILE)), 4),
    }
    design = lhs_design(DESIGN_N, DESIGN_SEED)
    if ids and max(ids) < DESIGN_N and min(ids) >= 0 and np.allclose(design[ids], raw, rtol=1e-9, atol=0):
        rec["design"] = {"n": DESIGN_N, "seed": DESIGN_SEED, "case_ids": ids}
    else:
        rec["controls_normalized"] = [_clean(row, 5) for row in norm]
    return rec


@dataclass(frozen=True)
class Support:
    """Normalized training controls (N, 14) with their nearest-neighbour spacing."""

    points: np.ndarray
    nn_median: float
    nn_q95: float
    source: str

    @classmethod
    def from_record(cls, rec: dict[str, Any] | None) -> Support:
        """From a calibration's ``support``; without one, the whole LHS design (a superset of any split)."""
        if rec and "design" in rec:
            d = rec["design"]
            pts = np.asarray(to_normalized(lhs_design(int(d["n"]), int(d["seed"]))[d["case_ids"]]))
            return cls(
                pts, float(rec["nn_median"]), float(rec["nn_q95"]), "training cases (calibration file)"
            )
        if rec and "controls_normalized" in rec:
            pts = np.asarray(rec["controls_normalized"], dtype=np.float64)
            return cls(
                pts, float(rec["nn_median"]), float(rec["nn_q95"]), "training cases (calibration file)"
            )
        pts = np.asarray(to_normalized(lhs_design(DESIGN_N, DESIGN_SEED)))
        spacing = nn_distances(pts)
        return cls(
            pts,
            float(np.median(spacing)),
            float(np.quantile(spacing, NEAR_QUANTILE)),
            "the control design (no calibration file records the training cases)",
        )

    def describe(self, u_norm: np.ndarray) -> dict[str, Any]:
        """Distance flag of normalized controls (14,): nearest training case, its distance against the
        training cases' own spacing, and the flag inside / far / outside_box."""
        u = np.asarray(u_norm, dtype=np.float64).reshape(-1)
        d = np.linalg.norm(self.points - u[None], axis=1)
        k = int(np.argmin(d))
        nearest = float(d[k])
        outside = bool(np.any(np.abs(u) > 1.0 + 1e-9))
        flag = "outside_box" if outside else ("inside" if nearest <= self.nn_q95 else "far")
        return {
            "flag": flag,
            "nearest_distance": round(nearest, 4),
            "typical_spacing": round(self.nn_median, 4),
            "near_threshold": round(self.nn_q95, 4),
            "relative": round(nearest / self.nn_median, 3) if self.nn_median > 0 else None,
            "reference": self.source,
        }


# --- calibration run ----------------------------------------------------------------------------------


def metric_trajectories(
    model: Any, tf: Any, case_ids: Sequence[int], *, batch_size: int = 4, on_case: Any = None
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Exact profile metrics of the surrogate's rollouts and of the data, per case and step.

    Args:
        model: a surrogate ``rollout`` accepts. tf: an open ``TrajectoryFile``. case_ids: cases to use.
        on_case: called once per finished case (progress).
    Returns:
        (pred, true): {metric: (n, T+1)} in nm each.
    """
    from nemsim.evaluation.truth import predict
    from nemsim.geometry.profile import profile_metrics_batch

    steps = tf.n_states - 1
    rows = [tf.row_of(c) for c in case_ids]
    pred: dict[str, list[np.ndarray]] = {m: [] for m in METRIC_NAMES}
    true: dict[str, list[np.ndarray]] = {m: [] for m in METRIC_NAMES}
    for start in range(0, len(rows), batch_size):
        chunk = rows[start : start + batch_size]
        x0s = [np.asarray(tf.states[r, 0]) for r in chunk]
        # one batch when the cases share x_0 (a data set from one simulator configuration), else one by one
        groups = [chunk] if all(np.array_equal(x0s[0], x) for x in x0s[1:]) else [[r] for r in chunk]
        for group in groups:
            x0 = np.asarray(tf.states[group[0], 0])
            for i, traj in predict(model, x0, tf.controls_raw[group], steps, batch_size=len(group)):
                mp = profile_metrics_batch(traj, tf.scene)
                mt = profile_metrics_batch(np.asarray(tf.states[group[i]]), tf.scene)
                for m in METRIC_NAMES:
                    pred[m].append(mp[m])
                    true[m].append(mt[m])
                if on_case is not None:
                    on_case()
    return ({m: np.stack(v) for m, v in pred.items()}, {m: np.stack(v) for m, v in true.items()})


def calibrate(
    loaded: Any,
    tf: Any,
    manifest: dict[str, Any],
    checkpoint: str | Path,
    *,
    split: str = "val",
    test_split: str | None = "test",
    levels: Sequence[float] = DEFAULT_LEVELS,
    max_cases: int | None = None,
    progress: bool = False,
) -> Calibration:
    """Split-conformal calibration of a checkpoint on one split of a data file (module docstring), with
    the coverage measured on ``test_split`` (None: not measured).

    Args:
        loaded: ``LoadedModel`` of ``checkpoint``. tf: its data (``TrajectoryFile``). manifest: a split
            manifest of tf (``resolve_manifest``). levels: nominal coverages.
        max_cases: use the first N cases of each split (quick runs).
    """
    for part in (split, test_split):
        if part is not None and part not in ("train", "val", "test"):
            raise ValueError(f"unknown split {part!r}; expected one of ['train', 'val', 'test']")
    cal_ids = list(manifest[split])[:max_cases]
    test_ids = list(manifest[test_split])[:max_cases] if test_split else []
    if len(cal_ids) < 2:
        raise ValueError(
            f"split {split!r} of setting {manifest.get('setting')!r} has {len(cal_ids)} cases; "
            "conformal calibration needs at least 2 (better 50 or more)"
        )
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            total=len(cal_ids) + len(test_ids), unit="case", desc="calibration rollouts", dynamic_ncols=True
        )
    tick = None if bar is None else (lambda: bar.update(1))
    try:
        pred, true = metric_trajectories(loaded.model, tf, cal_ids, on_case=tick)
        residuals = {m: pred[m] - true[m] for m in METRIC_NAMES}
        offsets = offsets_from_residuals(residuals, levels)
        test_cov: dict[str, Any] = {}
        if test_ids:
            tp, tt = metric_trajectories(loaded.model, tf, test_ids, on_case=tick)
            test_cov = {
                "split": test_split,
                "cases": len(test_ids),
                "coverage": coverage_table(offsets, tp, tt),
            }
    finally:
        if bar is not None:
            bar.close()
    train_ids = list(manifest["train"])
    train_raw = (
        np.stack([tf.controls_raw[tf.row_of(c)] for c in train_ids]) if train_ids else np.zeros((0, 14))
    )
    return Calibration(
        checkpoint_sha256=checkpoint_id(checkpoint),
        scene=tf.scene.name,
        levels=tuple(float(lv) for lv in levels),
        metrics=tuple(METRIC_NAMES),
        offsets=offsets,
        calibration={
            "setting": manifest.get("setting"),
            "split": split,
            "cases": len(cal_ids),
            "method": "split-conformal, signed residuals, two one-sided quantiles per step",
        },
        test_coverage=test_cov,
        support=support_from_controls(train_ids, train_raw) if len(train_ids) > 1 else {},
    )


def format_coverage(cal: Calibration) -> str:
    """A small markdown table of the test coverage recorded in a calibration."""
    cov = cal.test_coverage.get("coverage") if cal.test_coverage else None
    if not cov:
        return "no test coverage recorded"
    lines = [
        f"coverage on {cal.test_coverage['cases']} {cal.test_coverage['split']} cases "
        f"(calibrated on {cal.calibration['cases']} {cal.calibration['split']} cases), steps 1..T:",
        "",
        "| nominal | all metrics | final step | " + " | ".join(cal.metrics) + " |",
        "|---:|---:|---:|" + "---:|" * len(cal.metrics),
    ]
    for key, row in cov.items():
        per = " | ".join(f"{100 * row['per_metric'][m]:.1f}" for m in cal.metrics)
        lines.append(
            f"| {100 * float(key):.0f} % | {100 * row['all']:.1f} | {100 * row['final']:.1f} | {per} |"
        )
    return "\n".join(lines)
