"""`python -m bench.angle_response`: its fits, bins and field shares on synthetic data with a known
response in the angular spread of the ion exponents."""

from __future__ import annotations

import numpy as np

from bench.angle_response import (
    ION_ANGLES,
    ION_COLS,
    M_BINS,
    SWEEP_M,
    basis_fit,
    binned_response,
    design_matrix,
    ion_features,
    regressor_table,
    row_share,
    sweep_controls,
)
from nemsim.controls import lhs_design, to_normalized


def _synthetic(n: int = 300, noise: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Design rows and y = 40 + 3 / sqrt(m_Cl+) * 30 (broad ions widen) + flux term + noise."""
    raw = lhs_design(n, seed)
    rng = np.random.default_rng(seed)
    u = to_normalized(raw)
    y = 40.0 + 30.0 * 3.0 / np.sqrt(raw[:, ION_COLS[0]]) + 2.0 * u[:, 0] + noise * rng.standard_normal(n)
    return raw, y


def test_ion_features_span_the_box_and_rise_with_m():
    m = np.array([[50, 50, 50], [3000, 3000, 3000], [200, 1525, 100]], dtype=float)
    for basis in ("m", "log_m", "spread"):
        f = ion_features(m, basis)
        np.testing.assert_allclose(f[0], -1.0)
        np.testing.assert_allclose(f[1], 1.0)
        assert f[2, 0] < f[2, 1] and f[2, 2] < f[2, 1]
    # the linear basis is the model's own normalized input
    raw = lhs_design(5, 1)
    np.testing.assert_allclose(design_matrix(raw, "m"), to_normalized(raw), atol=1e-12)
    # m = 200 sits near the bottom of the linear axis, past the middle of the spread's
    assert ion_features(m[2:], "m")[0, 0] < -0.85 and ion_features(m[2:], "spread")[0, 0] > 0.0


def test_the_spread_basis_recovers_a_spread_response_the_linear_one_misses():
    raw, y = _synthetic()
    true_change = 90.0 / np.sqrt(3000) - 90.0 / np.sqrt(50)  # -11.08 nm from m = 50 to 3000
    fs, fm = basis_fit(raw, y, "spread"), basis_fit(raw, y, "m")
    ch = fs["change_by_exponent"]
    assert abs(ch[ION_ANGLES[0]]["change"] - true_change) < 3 * ch[ION_ANGLES[0]]["se"] + 0.05
    assert abs(ch[ION_ANGLES[1]]["change"]) < 4 * ch[ION_ANGLES[1]]["se"]  # no response to Cl2+
    assert fs["r2"] > fm["r2"] and fs["resid_sd"] < 0.3 < fm["resid_sd"]
    assert fs["ion_unique_r2"] > fm["ion_unique_r2"] > 0
    assert abs(fm["change_all_three"]) < abs(true_change)  # a line in m underestimates the fall


def test_bins_show_the_response_at_low_m():
    raw, y = _synthetic()
    b = binned_response(raw, y)
    rows = b["exponents"][ION_ANGLES[0]]
    assert sum(r["n"] for r in rows) == len(y) and b["edges"] == list(M_BINS)
    assert rows[0]["mean"] > rows[1]["mean"] > rows[-1]["mean"]  # widest at the broadest ions
    assert abs(b["exponents"][ION_ANGLES[2]][0]["mean"]) < 1.0  # Ar+ does nothing


def test_row_share_puts_the_ion_variance_in_the_row_that_carries_it():
    raw, y = _synthetic(n=120)
    rng = np.random.default_rng(1)
    field = 0.01 * rng.standard_normal((120, 3, 2, 2))  # (N, D, H, W)
    field[:, 2] += 0.01 * (y - y.mean())[:, None, None]  # only the top row follows the response
    rep = row_share(raw, field, noise_var=np.full((3, 2, 2), 1e-4))
    ion = [r["ion_var"] for r in rep["rows"]]
    assert ion[2] > 20 * max(ion[0], ion[1])
    assert rep["noise_var"] == 1e-4 and rep["ion_var"] <= rep["explained_var"] <= rep["total_var"]


def test_the_sweep_rows_and_a_regressor_along_them():
    sw = sweep_controls(repeats=2)
    assert sw.shape == (2 * len(SWEEP_M), 14)
    assert (sw[:, ION_COLS] == np.repeat(SWEEP_M, 2)[:, None]).all()
    assert np.ptp(np.delete(sw, ION_COLS, axis=1), axis=0).max() == 0  # the other controls at the centre
    raw, y = _synthetic(n=100, noise=0.05)
    reg = regressor_table(raw, y, sweep_controls(), only=("ridge, spread", "ridge, m"))
    rs, rm = reg["ridge, spread"], reg["ridge, m"]
    assert rs["cv_rmse"] < rm["cv_rmse"]
    assert rs["sweep"][0] - rs["sweep"][-1] > 8.0 > rm["sweep"][0] - rm["sweep"][-1]
