"""nemsim.data.splits on the paper's 500-case design: set sizes of tab:supp_split_summary within one case,
the OOD-Joint test composition, nested data-efficiency subsets, and the `design` / `splits` CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nemsim.controls import lhs_design, ood_coordinate, read_controls_csv
from nemsim.data.splits import SETTINGS, data_efficiency_subsets, load_manifest, make_manifests

# tab:supp_split_summary: (train, val, test, unused, transitions per trajectory)
PAPER = {
    "control-id": (300, 100, 100, 0, 100),
    "ood-ar": (280, 70, 150, 0, 100),
    "ood-cl": (279, 70, 151, 0, 100),
    "ood-joint": (202, 50, 53, 195, 100),
    "vis-50": (300, 100, 100, 0, 50),
    "vis-60": (300, 100, 100, 0, 60),
}


@pytest.fixture(scope="module")
def design():
    return lhs_design(500, 42)


@pytest.fixture(scope="module")
def manifests(design):
    return make_manifests(design)


@pytest.mark.parametrize("setting", SETTINGS)
def test_split_sizes_match_paper_table(manifests, setting):
    m = manifests[setting]
    got = (len(m["train"]), len(m["val"]), len(m["test"]), len(m["unused"]))
    for g, want in zip(got, PAPER[setting][:4], strict=False):
        assert abs(g - want) <= 1, (setting, got, PAPER[setting])
    assert m["visible_transitions"] == PAPER[setting][4]
    ids = m["train"] + m["val"] + m["test"] + m["unused"]
    assert sorted(ids) == list(range(500))  # a partition of all cases, trajectory-level


def test_ood_joint_test_composition(manifests, design):
    m = manifests["ood-joint"]
    groups = {k: len(v) for k, v in m["test_groups"].items()}
    assert groups == {"LL": 14, "LH": 15, "HL": 13, "HH": 11}
    qa = ood_coordinate(design, "flux_ar_plus")
    qc = ood_coordinate(design, "flux_cl_plus")
    inside = lambda q: (q >= 0.15) & (q <= 0.85)  # noqa: E731
    test = np.array(m["test"])
    assert not inside(qa[test]).any() and not inside(qc[test]).any()
    pool = np.array(m["train"] + m["val"])
    assert inside(qa[pool]).all() and inside(qc[pool]).all()
    unused = np.array(m["unused"])
    assert (inside(qa[unused]) ^ inside(qc[unused])).all()


def test_ood_single_axis_boundaries(manifests):
    assert {k: len(v) for k, v in manifests["ood-ar"]["test_groups"].items()} == {"L": 75, "H": 75}
    cl = {k: len(v) for k, v in manifests["ood-cl"]["test_groups"].items()}
    assert abs(cl["L"] - 76) <= 1 and cl["H"] == 75


def test_vis_settings_share_control_id_partition(manifests):
    for s in ("vis-50", "vis-60"):
        for k in ("train", "val", "test"):
            assert manifests[s][k] == manifests["control-id"][k]


def test_data_efficiency_nested_and_stratified(manifests, design):
    m = manifests["ood-joint"]
    sub = data_efficiency_subsets(m, design[m["train"]])
    assert {k: len(v) for k, v in sub.items()} == {"0.1": 20, "0.2": 40, "0.5": 101, "1.0": 202}
    assert set(sub["0.1"]) < set(sub["0.2"]) < set(sub["0.5"]) < set(sub["1.0"]) == set(m["train"])
    assert sub == data_efficiency_subsets(m)  # stored in the manifest
    assert sub == data_efficiency_subsets(m, design[m["train"]], seed=0)  # deterministic
    # 3x3 strata over log Ar+/Cl+: the 20-case subset touches every non-empty stratum with >= 3 members
    t = np.log10(design[m["train"]][:, :2])
    b = np.clip(np.floor((t - t.min(0)) / np.ptp(t, axis=0) * 3), 0, 2).astype(int)
    strata = dict(zip(m["train"], b[:, 0] * 3 + b[:, 1], strict=True))
    counts = np.bincount(list(strata.values()), minlength=9)
    hit = {strata[c] for c in sub["0.1"]}
    assert all(s in hit for s in range(9) if counts[s] >= 5)
    with pytest.raises(ValueError, match="data_efficiency"):
        data_efficiency_subsets({"setting": "x", "train": [1]})


def test_design_and_splits_cli(tmp_path, capsys):
    from nemsim.cli import main

    csv = tmp_path / "design.csv"
    assert main(["design", "--n", "500", "--seed", "42", "--out", str(csv)]) == 0
    np.testing.assert_array_equal(read_controls_csv(csv), lhs_design(500, 42))
    capsys.readouterr()
    out = tmp_path / "splits"
    assert main(["splits", "--design", str(csv), "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "ood-joint" in table and "(L,L) 14, (L,H) 15, (H,L) 13, (H,H) 11" in table
    for s in SETTINGS:
        m = load_manifest(out, s)
        assert m["setting"] == s and json.loads((out / f"{s}.json").read_text()) == m
    bad = tmp_path / "bad.csv"
    bad.write_text(csv.read_text().replace("angle_cl,", "angle_xx,", 1))
    assert main(["splits", "--design", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "missing columns ['angle_cl']" in err and "angle_xx" in err and len(err.strip().splitlines()) == 1


def test_resolve_manifest_refuses_manifests_that_do_not_fit_the_data(tmp_path):
    from nemsim.data.splits import resolve_manifest, write_manifests

    raw = lhs_design(40)
    data = tmp_path / "tiny.h5"  # only named in messages and for the default splits/ folder
    # no manifests on disk: computed from the file's own cases
    m, source = resolve_manifest("control-id", data, np.arange(10), raw[:10], 100)
    assert sorted(m["train"] + m["val"] + m["test"]) == list(range(10)) and "computed" in source
    # the default splits/ folder made for a bigger design does not fit a 10-case file
    write_manifests(make_manifests(raw), tmp_path / "splits")
    with pytest.raises(ValueError, match=r"does not fit .*nemsim splits --data"):
        resolve_manifest("control-id", data, np.arange(10), raw[:10], 100)
    m, source = resolve_manifest("control-id", data, np.arange(40), raw, 100)
    assert source.endswith("control-id.json")
    with pytest.raises(ValueError, match="n_transitions must be >= 1"):
        make_manifests(raw, n_transitions=0)
