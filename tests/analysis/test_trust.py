"""Where a recipe lies (the extrapolation benchmark's groups) and the verdict from its measured error."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.analysis.intervals import Support
from nemsim.analysis.trust import assess, place
from nemsim.controls import CONTROL_INDEX, from_normalized, to_normalized

RATIOS = {"in-box": 1.0, "corner": 5.6, "zero-flux": 0.64, "axis 1.5": 1.87, "axis 2": 7.1, "angle": 2.7}
BENCH = {
    "in_box_avg_rmse": 0.01,
    "groups": {g: {"n": 3, "avg_rmse": 0.01 * r, "ratio_to_in_box": r,
                   "mae_nm": {"etch_depth": 2.0 * r, "top_width": 1.0, "bottom_width": 1.0, "mask_loss": 0.5},
                   "seed_diff_nm": {"etch_depth": 0.6, "top_width": 0.5, "bottom_width": 0.6,
                                    "mask_loss": 0.1}}
               for g, r in RATIOS.items()},
}


@pytest.fixture(scope="module")
def support():
    return Support.from_record(None)  # the whole Latin-hypercube design


def _place(support, u=None, raw=None):
    raw = from_normalized(np.asarray(u, dtype=np.float64)) if raw is None else raw
    return place(to_normalized(raw), raw, support)


def _axis(name: str, value: float) -> np.ndarray:
    u = np.zeros(14)
    u[CONTROL_INDEX[name]] = value
    return u


@pytest.mark.parametrize(("u", "group", "distance", "level"), [
    (np.zeros(14), "in-box", -1.0, "ok"),  # the design centre
    (np.ones(14), "corner", 0.0, "reject"),  # a box corner: far from every training case
    (_axis("flux_cl", 1.4), "axis 1.5", 0.4, "warn"),
    (_axis("energy_mean_ar_plus", -1.9), "axis 2", 0.9, "reject"),
    (_axis("flux_cl", 2.5), "beyond", 1.5, "reject"),  # nothing measured there
    (_axis("angle_cl_plus", 2.5), "angle", 1.5, "warn"),  # only angular exponents that far out
])
def test_groups_distances_and_levels(support, u, group, distance, level):
    p = _place(support, u)
    assert p.group == group and p.distance == pytest.approx(distance, abs=1e-6)
    verdict = assess(p, BENCH)
    assert verdict["level"] == level
    if group == "beyond":
        assert verdict["measured"] is None and "nothing measured" in verdict["reason"]
    else:
        assert verdict["measured"]["ratio_to_in_box"] == RATIOS[group]
        assert verdict["measured"]["mae_nm"]["etch_depth"] == pytest.approx(2.0 * RATIOS[group], abs=0.01)


def test_a_switched_off_flux_is_its_own_group_and_not_a_distance(support):
    raw = from_normalized(np.zeros(14))
    raw[CONTROL_INDEX["flux_ar_plus"]] = 0.0
    p = _place(support, raw=raw)
    assert p.group == "zero-flux" and p.distance == pytest.approx(-1.0)
    raw[CONTROL_INDEX["energy_mean_cl_plus"]] = from_normalized(_axis("energy_mean_cl_plus", 1.3))[
        CONTROL_INDEX["energy_mean_cl_plus"]]
    assert _place(support, raw=raw).group == "axis 1.5"  # another control outside decides


def test_a_recipe_is_judged_by_its_farthest_transition(support):
    u = np.stack([np.zeros(14), _axis("flux_cl", 1.8), np.zeros(14)])
    raw = from_normalized(u)
    p = place(to_normalized(raw), raw, support)
    assert p.group == "axis 2" and p.distance == pytest.approx(0.8)


def test_without_a_benchmark_the_region_alone_decides_and_says_so(support):
    inside, corner, beyond = (_place(support, u) for u in (np.zeros(14), -np.ones(14), _axis("flux_cl", 3.0)))
    assert [assess(p, None)["level"] for p in (inside, corner, beyond)] == ["ok", "warn", "reject"]
    assert all(assess(p, None)["measured"] is None for p in (inside, corner))
    assert "no extrapolation benchmark" in assess(corner, None)["reason"]
