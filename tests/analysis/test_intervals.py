"""Conformal intervals: finite-sample coverage on exchangeable residuals, the too-few-cases edge, the
coverage table, the calibration file round trip and the distance-to-training-data flag."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.analysis.intervals import (
    Calibration,
    Support,
    conformal_offsets,
    coverage,
    coverage_table,
    load_calibration,
    offsets_from_residuals,
    support_from_controls,
)
from nemsim.controls import lhs_design


@pytest.mark.parametrize("level", [0.8, 0.9])
def test_conformal_offsets_cover_fresh_residuals_at_the_nominal_level(level):
    rng = np.random.default_rng(0)
    # a biased, skewed error: prediction - truth = 2 + gamma noise
    cal = 2.0 + rng.gamma(2.0, 1.5, size=(200, 3))
    pred = rng.normal(size=(20000, 3))
    true = pred - (2.0 + rng.gamma(2.0, 1.5, size=(20000, 3)))
    lower, upper = conformal_offsets(cal, level)
    assert lower.shape == upper.shape == (3,)
    assert np.all(lower < upper)
    cov = coverage(pred, true, lower, upper)
    assert level - 0.03 <= cov <= level + 0.05  # >= nominal up to sampling; not much wider


def test_too_few_cases_give_unbounded_sides():
    lower, upper = conformal_offsets(np.array([[0.5], [1.0], [-0.3]]), 0.9)
    assert np.isneginf(lower).all() and np.isposinf(upper).all()


def test_conformal_offsets_reject_a_bad_level():
    with pytest.raises(ValueError, match="level"):
        conformal_offsets(np.zeros((10, 2)), 1.5)


def test_coverage_table_counts_steps_after_the_initial_state():
    n, T = 50, 4
    rng = np.random.default_rng(1)
    res = {"etch_depth": rng.normal(size=(n, T + 1))}
    res["etch_depth"][:, 0] = 0.0
    offsets = offsets_from_residuals(res, (0.8,))
    pred = {"etch_depth": np.zeros((n, T + 1))}
    true = {"etch_depth": -res["etch_depth"]}  # truth = pred - residual: every calibration case
    table = coverage_table(offsets, pred, true)
    row = table["0.8"]
    assert 0.8 <= row["all"] <= 0.9 and set(row["per_metric"]) == {"etch_depth"}
    # every case outside: coverage 0
    far = {"etch_depth": np.full((n, T + 1), 1e6)}
    assert coverage_table(offsets, pred, far)["0.8"]["all"] == 0.0


def test_calibration_round_trip_and_interval(tmp_path):
    res = {"etch_depth": np.tile(np.arange(-10, 11, dtype=float)[:, None], (1, 3))}  # (21, 3)
    cal = Calibration(
        checkpoint_sha256="0" * 12,
        scene="tiny",
        levels=(0.8, 0.9),
        metrics=("etch_depth",),
        offsets=offsets_from_residuals(res, (0.8, 0.9)),
        calibration={"setting": "control-id", "split": "val", "cases": 21},
    )
    path = cal.write(tmp_path / "x.calibration.json")
    back = load_calibration(path)
    assert back.steps == 2 and back.levels == (0.8, 0.9)
    lo, hi = back.interval("etch_depth", 2, 50.0, 0.9)
    assert lo is not None and hi is not None and lo < 50.0 < hi
    lo8, hi8 = back.interval("etch_depth", 2, 50.0, 0.8)
    assert lo8 is not None and hi8 is not None and lo <= lo8 and hi8 <= hi  # 80 % nests inside 90 %
    with pytest.raises(ValueError, match="not calibrated"):
        back.interval("etch_depth", 1, 1.0, 0.5)
    with pytest.raises(ValueError, match="metric"):
        back.interval("mask_loss", 1, 1.0, 0.8)
    (tmp_path / "bad.json").write_text('{"scene": "tiny"}')
    with pytest.raises(ValueError, match="lacks"):
        load_calibration(tmp_path / "bad.json")


def test_support_flags_inside_far_and_outside():
    ids = list(range(0, 60))
    rec = support_from_controls(ids, lhs_design()[ids])
    assert "design" in rec and rec["design"]["case_ids"] == ids  # stored as ids, not as numbers
    sup = Support.from_record(rec)
    assert sup.points.shape == (60, 14)
    assert sup.describe(sup.points[3])["flag"] == "inside"  # a training case itself
    corner = np.ones(14) * 0.999
    assert sup.describe(corner)["flag"] == "far"
    assert sup.describe(np.full(14, 1.5))["flag"] == "outside_box"
    other = support_from_controls([0, 1, 2], lhs_design()[[0, 1, 2]] * 1.01)
    assert "controls_normalized" in other  # not the design's rows: the controls themselves
