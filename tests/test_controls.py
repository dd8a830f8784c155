"""nemsim.controls: vocabulary, transforms, normalization, OOD coordinate, LHS design, CSV."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nemsim import controls as C


def test_vocabulary_order_and_ranges():
    assert C.CONTROL_NAMES == (
        "flux_ar_plus", "flux_cl_plus", "flux_cl2_plus", "flux_cl", "angle_cl", "angle_cl_plus",
        "angle_cl2_plus", "angle_ar_plus", "energy_mean_cl_plus", "energy_std_cl_plus",
        "energy_mean_cl2_plus", "energy_std_cl2_plus", "energy_mean_ar_plus", "energy_std_ar_plus",
    )
    kinds = [s.kind for s in C.CONTROL_SPECS]
    assert kinds == ["log"] * 4 + ["int"] * 4 + ["linear"] * 6
    assert (C.CONTROL_SPECS[2].low, C.CONTROL_SPECS[2].high) == (1e-6, 2e-4)
    assert (C.CONTROL_SPECS[4].low, C.CONTROL_SPECS[4].high) == (0, 20)
    assert (C.CONTROL_SPECS[9].low, C.CONTROL_SPECS[9].high) == (5.0, 10.0)
    assert all(s.phys_min == 0.0 and s.phys_max == math.inf for s in C.CONTROL_SPECS)


def test_transform_and_normalization_bounds():
    lo, hi = C.LOW[None], C.HIGH[None]
    np.testing.assert_allclose(C.to_normalized(lo), -1.0, atol=1e-12)
    np.testing.assert_allclose(C.to_normalized(hi), 1.0, atol=1e-12)
    t = C.transform(lo)
    assert t[0, 0] == pytest.approx(math.log10(1e-4 + 1e-12))
    assert t[0, 8] == 160.0
    # no clipping outside the range; zero flux is finite thanks to eps_u
    out = C.to_normalized(np.where(np.arange(14) < 4, 0.0, C.HIGH * 2)[None])
    assert np.all(np.isfinite(out)) and out[0, 0] < -1 and out[0, 8] > 1


def test_roundtrip_numpy_and_torch():
    import torch

    raw = C.lhs_design(20, seed=3)
    np.testing.assert_allclose(C.from_normalized(C.to_normalized(raw)), raw, rtol=1e-10)
    tn = C.to_normalized(torch.tensor(raw))
    np.testing.assert_allclose(tn.numpy(), C.to_normalized(raw), atol=1e-12)
    t32 = C.to_normalized(torch.tensor(raw, dtype=torch.float32))
    assert t32.dtype == torch.float32
    np.testing.assert_allclose(C.from_normalized(tn).numpy(), raw, rtol=1e-10)
    with pytest.raises(ValueError, match="14"):
        C.to_normalized(np.zeros((3, 13)))


def test_lhs_design_properties():
    xi = C.lhs_unit(500, 42)
    # one point per stratum in every column
    for j in range(14):
        assert sorted(np.floor(xi[:, j] * 500).astype(int)) == list(range(500))
    d = C.lhs_design(500, 42)
    assert d.shape == (500, 14)
    assert np.all(d >= C.LOW) and np.all(d <= C.HIGH)
    assert np.all(d[:, 4:8] == np.round(d[:, 4:8]))
    assert len(np.unique(d, axis=0)) == 500
    # q of a design row is its LHS coordinate
    np.testing.assert_allclose(C.ood_coordinate(d, "flux_cl_plus"), xi[:, 1], atol=1e-12)
    np.testing.assert_array_equal(C.lhs_design(500, 42), d)


def test_log_angle_design_spreads_the_ion_exponents_in_log_m():
    """lhs-log-angles: the same design except the three ion exponents, which are integers in [50, 3000]
    uniform in log m: 28.7 % of them below m = 162 (ln 3.24 / ln 60), against 3.8 % in the paper's design."""
    d, lin = C.lhs_design(2000, 7, log_angles=True), C.lhs_design(2000, 7)
    ions = [C.control_index(n) for n in C.CONTROL_GROUPS["ion_angle"]]
    rest = [j for j in range(14) if j not in ions]
    np.testing.assert_array_equal(d[:, rest], lin[:, rest])
    m = d[:, ions]
    assert np.all(m == np.round(m)) and m.min() >= 50 and m.max() <= 3000
    assert np.mean(m < 162) == pytest.approx(math.log(162 / 50) / math.log(60), abs=0.01)
    assert np.mean(lin[:, ions] < 162) == pytest.approx(112 / 2951, abs=0.01)
    # the stratification carries over: the log of each column fills its 20 equal bins with 100 points each
    bins = np.floor((np.log(m) - math.log(50)) / math.log(60) * 20).clip(0, 19)
    for k in range(3):
        assert np.bincount(bins[:, k].astype(int), minlength=20).tolist() == pytest.approx([100] * 20, abs=3)


def test_corner_design_draws_distinct_corners_and_never_an_excluded_one():
    banned = np.stack([C.LOW, C.HIGH])  # all-min and all-max
    d = C.corner_design(200, 3, exclude=banned)
    assert d.shape == (200, 14)
    assert np.all((d == C.LOW) | (d == C.HIGH))  # every control exactly at a bound
    assert len(np.unique(d, axis=0)) == 200
    assert not any(np.array_equal(row, b) for row in d for b in banned)
    frac_high = np.mean(d == C.HIGH, axis=0)  # (14,) each bound about half the time
    assert np.all((frac_high > 0.35) & (frac_high < 0.65))
    assert not C.check_admissible(d)
    np.testing.assert_array_equal(C.corner_design(200, 3, exclude=banned), d)  # the seed decides
    with pytest.raises(ValueError, match="distinct corners"):
        C.corner_design(2**14 - 1, 0, exclude=banned)  # only 2**14 - 2 are left


def test_lhs_matches_scipy_sampler():
    from scipy.stats import qmc

    ref = qmc.LatinHypercube(d=14, seed=42).random(500)
    np.testing.assert_array_equal(C.lhs_unit(500, 42), ref)


def test_int_mapping_covers_endpoints():
    xi = np.tile(np.array([0.0, 0.999999, 0.5])[:, None], (1, 14))
    raw = C.from_unit(xi)
    assert raw[0, 4] == 0 and raw[1, 4] == 20 and raw[0, 5] == 50 and raw[1, 5] == 3000


def test_ood_coordinate_unknown_name():
    with pytest.raises(ValueError, match="flux_ar_plus"):
        C.ood_coordinate(np.zeros((1, 14)), "flux_argon")


def test_admissibility_helpers():
    raw = C.lhs_design(1, 0)[0].copy()
    assert C.check_admissible(raw) == [] and C.outside_design_range(raw) == []
    raw[0] = -1.0
    raw[8] = 900.0
    msgs = C.check_admissible(raw)
    assert len(msgs) == 1 and "flux_ar_plus" in msgs[0]
    assert C.outside_design_range(raw) == ["flux_ar_plus", "energy_mean_cl_plus"]


def test_csv_roundtrip_and_header_validation(tmp_path):
    raw = C.lhs_design(7, 5)
    p = tmp_path / "d.csv"
    C.write_controls_csv(p, raw)
    assert p.read_text().splitlines()[0] == ",".join(C.CONTROL_NAMES)
    np.testing.assert_array_equal(C.read_controls_csv(p), raw)
    # reordered columns are fine
    lines = [line.split(",") for line in p.read_text().splitlines()]
    perm = list(reversed(range(14)))
    (tmp_path / "r.csv").write_text("\n".join(",".join(r[i] for i in perm) for r in lines) + "\n")
    np.testing.assert_array_equal(C.read_controls_csv(tmp_path / "r.csv"), raw)
    bad = p.read_text().replace("flux_cl2_plus", "flux_cl3_plus", 1)
    (tmp_path / "b.csv").write_text(bad)
    msg = r"missing columns \['flux_cl2_plus'\].*unknown columns \['flux_cl3_plus'\]"
    with pytest.raises(ValueError, match=msg):
        C.read_controls_csv(tmp_path / "b.csv")
    (tmp_path / "n.csv").write_text(",".join(C.CONTROL_NAMES) + "\n" + ",".join(["x"] + ["1"] * 13) + "\n")
    with pytest.raises(ValueError, match="row 2, column 'flux_ar_plus'"):
        C.read_controls_csv(tmp_path / "n.csv")


def test_check_admissible_checks_every_row():
    raw = C.lhs_design(3, 0)
    assert C.check_admissible(raw) == []
    raw[2, 0] = -1.0  # only the last row is impossible
    raw[1, 9] = float("nan")
    msgs = C.check_admissible(raw)
    assert len(msgs) == 2
    assert msgs[0].startswith("row 1: energy_std_cl_plus") and msgs[1].startswith("row 2: flux_ar_plus")
    raw[0, 8] = 900.0
    assert C.outside_design_range(raw) == ["flux_ar_plus", "energy_mean_cl_plus", "energy_std_cl_plus"]


def test_n_controls_is_defined_once():
    """Other modules import N_CONTROLS from nemsim.controls instead of typing 14 again."""
    import re
    from pathlib import Path

    root = Path(C.__file__).parent
    pattern = re.compile(r"^N_CONTROLS\s*=", re.MULTILINE)
    defining = [p.relative_to(root).as_posix() for p in root.rglob("*.py") if pattern.search(p.read_text())]
    assert defining == ["controls.py"]
    assert C.N_CONTROLS == len(C.CONTROL_SPECS) == 14


def test_pair_design_moves_one_group_per_pair_and_shares_the_seed(tmp_path):
    raw, seed_ids = C.pair_design(21, 5)
    assert raw.shape == (42, 14) and not C.check_admissible(raw) and not C.outside_design_range(raw)
    np.testing.assert_array_equal(seed_ids, np.repeat(np.arange(0, 42, 2), 2))  # the base's case id, twice
    np.testing.assert_array_equal(raw[0::2], C.lhs_design(21, 5))  # the bases are a Latin hypercube
    groups = list(C.CONTROL_GROUPS.values())
    for i in range(21):
        names = groups[i % 7]  # the groups in turn
        cols = [C.CONTROL_INDEX[n] for n in names]
        others = [j for j in range(14) if j not in cols]
        np.testing.assert_array_equal(raw[2 * i + 1, others], raw[2 * i, others])
        level = C.sweep_coordinate(raw[2 * i + 1], names)  # one level for the whole group (integers rounded)
        assert np.ptp(level) < 0.02
        assert abs(level.mean() - C.sweep_coordinate(raw[2 * i], names).mean()) >= 0.5 - 0.02  # min_move
    many, _ = C.pair_design(700, 5)  # 100 pairs per group
    ions = many[1::2][5::7, C.CONTROL_INDEX["angle_cl_plus"]]  # the partners of the ion-angle pairs
    assert 0.5 < np.mean(ions < 500) < 0.95  # uniform in log m, moved away from the bases: uniform in m, 15 %
    again, _ = C.pair_design(21, 5)
    np.testing.assert_array_equal(again, raw)  # the seed decides
    with pytest.raises(ValueError, match="n_pairs"):
        C.pair_design(0, 5)
    lo, hi = C.LOW.copy(), C.HIGH.copy()  # the sweep coordinate: -1 and +1 at the design bounds
    np.testing.assert_allclose(C.sweep_coordinate(np.stack([lo, hi]), tuple(C.CONTROL_NAMES)),
                               [[-1.0] * 14, [1.0] * 14], atol=1e-12)
    mid = C.set_sweep_level(lo, ("angle_cl_plus", "angle_cl"), 0.0)  # log m for the ions, m for the neutral
    assert mid[C.CONTROL_INDEX["angle_cl_plus"]] == pytest.approx(math.sqrt(50.0 * 3000.0))
    assert mid[C.CONTROL_INDEX["angle_cl"]] == pytest.approx(10.0)

    path = tmp_path / "pairs.csv"  # the seed ids travel in a column the controls reader ignores
    C.write_controls_csv(path, raw, seed_ids)
    np.testing.assert_array_equal(C.read_controls_csv(path), raw)
    np.testing.assert_array_equal(C.read_seed_ids(path), seed_ids)
    C.write_controls_csv(path, raw)
    assert C.read_seed_ids(path) is None
