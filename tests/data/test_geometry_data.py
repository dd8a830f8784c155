"""Per-case geometry in designs and trajectory files: `nemsim design/generate --feature`, the HDF5 `geometry`
dataset and `feature_kind` attribute, old files without them, and `nemsim data check`."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from nemsim.cli import main
from nemsim.controls import read_controls_csv, read_geometry_csv
from nemsim.data.hdf5 import check_dataset, open_trajectories
from nemsim.geometry.feature import Feature


def test_design_adds_geometry_columns_and_keeps_the_controls(tmp_path):
    plain, geo = tmp_path / "plain.csv", tmp_path / "geo.csv"
    assert main(["design", "--n", "20", "--out", str(plain)]) == 0
    assert main(["design", "--n", "20", "--feature", "trench", "--cd-nm", "24:64", "--mask-nm", "40:120",
                 "--out", str(geo)]) == 0
    np.testing.assert_array_equal(read_controls_csv(geo), read_controls_csv(plain))
    assert read_geometry_csv(plain) is None
    kind, rows = read_geometry_csv(geo)
    assert kind == "trench" and rows.shape == (20, 2)
    assert rows[:, 0].min() >= 24 and rows[:, 0].max() <= 64 and rows[:, 1].min() >= 40
    # a Latin hypercube column: one value in each of the 20 strata
    assert sorted(np.floor((rows[:, 0] - 24) / 40 * 20).astype(int).tolist()) == list(range(20))


def test_generate_holes_and_trench_section_then_check(tmp_path, capsys):
    from nemsim.scenes import TINY
    from nemsim.sim import SimConfig, initial_state

    out = tmp_path / "holes.h5"
    assert main(["generate", "--scene", "tiny", "--n", "2", "--feature", "hole", "--cd-nm", "24:64",
                 "--mask-nm", "40:120", "--no-progress", "--out", str(out)]) == 0
    assert main(["data", "check", str(out)]) == 0
    assert "PASS  geometry" in capsys.readouterr().out
    with open_trajectories(out) as tf:
        assert tf.has_geometry and tf.feature_kind == "hole" and tf.geometry.shape == (2, 2)
        assert np.all(tf.geometry[:, 1] % TINY.voxel_nm == 0)  # the mask as built: whole voxels
        for row in range(2):
            scene = tf.case_scene(row)
            assert scene.resist_top - scene.si_top == tf.geometry[row, 1] / TINY.voxel_nm
            np.testing.assert_array_equal(tf.states[row, 0], initial_state(scene))
    out = tmp_path / "trench.h5"
    assert main(["generate", "--scene", "tiny", "--n", "1", "--feature", "trench", "--sim-domain", "section",
                 "--no-progress", "--out", str(out)]) == 0
    assert check_dataset(out).ok
    with open_trajectories(out) as tf:
        assert tf.case_feature(0) == Feature("trench", 40.0, 80.0)
        x0 = initial_state(tf.case_scene(0), SimConfig(domain="section"))
        np.testing.assert_array_equal(tf.states[0, 0], x0)
    with pytest.raises(SystemExit):  # argparse refuses an unknown kind
        main(["generate", "--scene", "tiny", "--n", "1", "--feature", "via", "--out", str(tmp_path / "x.h5")])
    assert main(["generate", "--scene", "tiny", "--n", "1", "--sim-domain", "section", "--no-progress",
                 "--out", str(tmp_path / "y.h5")]) != 0  # the cross-section of a hole: refused


def test_old_file_without_geometry_reads_as_the_default_feature(make_file, tiny_scene):
    path = make_file(n=3)
    with h5py.File(path, "r") as f:
        assert "geometry" not in f and "feature_kind" not in f.attrs
    with open_trajectories(path) as tf:
        assert not tf.has_geometry and tf.feature_kind == "hole"
        np.testing.assert_array_equal(tf.geometry, [[40.0, 80.0]] * 3)
        assert tf.case_scene(2) == tiny_scene
    rep = check_dataset(path)
    assert rep.ok and any(n == "geometry" and "default feature" in d for n, _, d in rep.checks), rep.text


def test_check_and_resume_refuse_bad_geometry(tmp_path, tiny_scene):
    from nemsim.controls import lhs_design
    from nemsim.data.hdf5 import TrajectoryWriter

    raw = lhs_design(n=2, seed=1)
    geo = ("hole", np.array([[24.0, 40.0], [64.0, 120.0]]))
    kw = dict(scene=tiny_scene, case_ids=[0, 1], controls_raw=raw, generator={"k": 1}, rules_sha256="ab" * 32)
    path = tmp_path / "g.h5"
    TrajectoryWriter(path, geometry=geo, **kw).close()
    assert check_dataset(path, require_complete=False).ok
    with pytest.raises(ValueError, match="geometry mismatch"):
        TrajectoryWriter(path, geometry=("trench", geo[1]), **kw)
    with pytest.raises(ValueError, match="geometry mismatch"):
        TrajectoryWriter(path, **kw)
    with h5py.File(path, "r+") as f:
        f["geometry"][1, 0] = 100.0  # no mask left between neighbours on tiny's 104 nm pitch
    rep = check_dataset(path, require_complete=False)
    assert not rep.ok and any("cd_nm=100" in e for e in rep.errors), rep.text
