"""How far a recipe lies from where the model was trained, and the error measured there.

A prediction looks as confident at a corner of the control box, or beyond its edge, as at its centre. This
module places a recipe in the groups of the extrapolation benchmark (``nemsim bench extrapolation``) and
reports that group's measured error beside a verdict, so the answer carries its own trust.

Groups, judged on the farthest transition of a recipe (normalized controls u, the coordinates the model
sees, fluxes in log10; ``nemsim.inference.range_check``), with d = the largest excursion past the box in box
half-widths (max_j |u_j| - 1 over the controls outside it):

  ``in-box``     inside the box and near the training cases: the nearest one no farther than the training
                 cases' own 95th-percentile spacing (``nemsim.analysis.intervals.Support``);
  ``corner``     inside the box, farther from every training case than that (towards its faces and corners,
                 which a Latin hypercube does not sample: the benchmark measures box corners);
  ``zero-flux``  some fluxes exactly 0, every other control inside the box (the flux gate's regime);
  ``axis 1.5``   0 < d <= 0.5 (the benchmark moves one control to 1.5 half-widths from the centre);
  ``axis 2``     0.5 < d <= 1;
  ``angle``      d > 1 from the angular exponents alone (measured at m = 1 and m = 10,000);
  ``beyond``     d > 1 otherwise: nothing measured there.

Verdict from the group's measured Avg RMSE over the in-box one (``ratio``): ``ok`` at most ``OK_RATIO``
(1.5: the error the issue of trust asks at 1.5 half-widths), ``warn`` at most ``WARN_RATIO``, else
``reject``; ``beyond`` is ``reject``. Without a benchmark of the model the verdict follows the group alone
(``in-box`` ok, ``beyond`` reject, the rest warn) and says that nothing was measured. The verdict is advice:
whether the server answers, clips or refuses is its extrapolation policy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from nemsim.analysis.intervals import Support
from nemsim.controls import CONTROL_SPECS, FLUX_INDICES

OK_RATIO = 1.5
WARN_RATIO = 3.0
ANGLE_INDICES = tuple(i for i, s in enumerate(CONTROL_SPECS) if s.name.startswith("angle_"))
UNMEASURED_LEVEL = {"in-box": "ok", "beyond": "reject"}  # without a benchmark; other groups: warn
REPORTED_METRICS = ("etch_depth", "top_width", "bottom_width", "mask_loss")


@dataclass(frozen=True)
class Placement:
    """Where a recipe lies: its group (module docstring), d, and the nearest-training-case record."""

    group: str
    distance: float  # d: max_j |u_j| - 1 over the transitions and the controls but zero fluxes (< 0 inside)
    training_data: dict[str, Any]  # ``Support.describe`` of the farthest transition


def place(u: np.ndarray, raw: np.ndarray, support: Support) -> Placement:
    """The group of normalized controls u (T, 14) or (14,) with their physical values raw (same shape)."""
    u2 = np.atleast_2d(np.asarray(u, dtype=np.float64))
    raw2 = np.atleast_2d(np.asarray(raw, dtype=np.float64))
    zero = np.zeros(u2.shape[1], dtype=bool)
    zero[list(FLUX_INDICES)] = True
    zero &= (raw2 == 0.0).any(axis=0)  # fluxes switched off in some transition
    past = np.abs(u2) - 1.0  # (T, 14) > 0 outside the box
    past[:, zero] = -np.inf  # a zero flux is its own group, not a distance
    t = int(np.argmax(past.max(axis=1)))  # the farthest transition
    d = float(past[t].max())
    near = support.describe(np.clip(u2[t], -1.0, 1.0))
    if d <= 1e-9:
        group = "zero-flux" if zero.any() else ("in-box" if near["flag"] == "inside" else "corner")
    elif d <= 0.5 + 1e-9:
        group = "axis 1.5"
    elif d <= 1.0 + 1e-9:
        group = "axis 2"
    else:
        outside = np.flatnonzero(past[t] > 1.0 + 1e-9)
        group = "angle" if set(outside.tolist()) <= set(ANGLE_INDICES) else "beyond"
    return Placement(group, d, near)


def assess(placement: Placement, benchmark: dict[str, Any] | None) -> dict[str, Any]:
    """The verdict (module docstring) with the measured error of the placement's group. ``benchmark``: the
    summary of the model's extrapolation benchmark ({"model_id", "in_box_avg_rmse", "groups": {name:
    {"n", "avg_rmse", "ratio_to_in_box", "mae_nm", "seed_diff_nm", ...}}}), or None."""
    out: dict[str, Any] = {
        "group": placement.group,
        "box_distance": round(placement.distance, 4),
        "training_data": placement.training_data,
    }
    stats = (benchmark or {}).get("groups", {}).get(placement.group)
    if stats is None or stats.get("ratio_to_in_box") is None:
        out["level"] = UNMEASURED_LEVEL.get(placement.group, "warn")
        out["measured"] = None
        out["reason"] = (
            "nothing measured beyond one box half-width past the edge" if placement.group == "beyond"
            else "no extrapolation benchmark of this model measured this region"
        )
        return out
    ratio = float(stats["ratio_to_in_box"])
    out["level"] = "ok" if ratio <= OK_RATIO else ("warn" if ratio <= WARN_RATIO else "reject")
    out["measured"] = {
        "cases": int(stats["n"]),
        "avg_rmse": round(float(stats["avg_rmse"]), 5),
        "ratio_to_in_box": round(ratio, 3),
        "mae_nm": {m: round(float(stats["mae_nm"][m]), 2) for m in REPORTED_METRICS if m in stats["mae_nm"]},
        "seed_to_seed_nm": {m: round(float(stats["seed_diff_nm"][m]), 2)
                            for m in REPORTED_METRICS if m in stats.get("seed_diff_nm", {})},
        "source": (benchmark or {}).get("source", "nemsim bench extrapolation"),
    }
    out["reason"] = (f"the benchmark's {placement.group} recipes ({int(stats['n'])}) erred {ratio:.2g}x "
                     "the in-box error")
    return out
