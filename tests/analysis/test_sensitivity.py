"""Control importance (eq:supp_control_importance) on synthetic data where one control drives depth."""

from __future__ import annotations

import numpy as np
import pytest

from nemsim.analysis.sensitivity import SENSITIVITY_METRICS, control_sensitivity, importance_scores

NAMES = tuple(f"c{j}" for j in range(14))


def _hole(scene, radius, depth):
    d, h, w = scene.field_shape
    z = np.arange(d)[:, None, None] - 1.0
    y = np.arange(h)[None, :, None] - 1.0
    x = np.arange(w)[None, None, :] - 1.0
    cx, cy = scene.opening_centre
    r = np.hypot(x - cx, y - cy)
    top = scene.si_top - 0.5
    si = np.maximum(z - top, np.minimum(radius - r, z - (top - depth)))
    mask = np.maximum(np.maximum(z - (scene.resist_top - 0.5), top - z), scene.opening_radius_vox - r)
    st = np.stack([np.broadcast_to(mask, (d, h, w)), np.broadcast_to(si, (d, h, w))])
    return np.clip(st / scene.d_max_vox, -1, 1).astype(np.float32)


def test_hand_case_single_driver():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, size=(200, 14))
    y = np.stack([3.0 * x[:, 2] + 0.01 * rng.normal(size=200)] * 5, axis=1)
    res = importance_scores(x, y, NAMES)
    assert res.ranking()[0] == 2
    # beta ~ 1 and rho ~ 1 for the driver: I ~ 0.7 + 0.3
    assert res.importance[2] == pytest.approx(np.ones(5), abs=0.02)
    assert res.share_percent.sum() == pytest.approx(100.0)
    assert res.share_percent[2] > 50
    table = res.table()
    assert table.splitlines()[2].split()[:2] == ["1", "c2"]


def test_constant_metric_and_control_are_skipped():
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, size=(60, 14))
    x[:, 5] = 0.3  # constant control
    y = np.stack([x[:, 0], x[:, 0] + x[:, 1], np.zeros(60), x[:, 1], x[:, 3]], axis=1)
    res = importance_scores(x, y, NAMES)
    assert res.skipped_metrics == ("neck_width",)
    assert res.metric_names == tuple(m for m in SENSITIVITY_METRICS if m != "neck_width")
    assert res.score[5] == 0.0
    with pytest.raises(ValueError, match="constant"):
        importance_scores(x, np.zeros((60, 5)), NAMES)


def test_profile_driven_by_one_control(tiny_scene):
    rng = np.random.default_rng(2)
    n = 40
    u = rng.uniform(-1, 1, size=(n, 14))
    depth = 8.0 + 5.0 * u[:, 4]  # control 4 drives depth (voxels)
    radius = 2.0 + 0.3 * u[:, 9]  # control 9 drives the widths
    states = np.stack([_hole(tiny_scene, r, d) for r, d in zip(radius, depth, strict=True)])
    res = control_sensitivity(u, states, tiny_scene, NAMES)
    assert set(res.ranking()[:2]) == {4, 9}
    d = res.metric_names.index("etch_depth")
    assert abs(res.beta[4, d]) > 0.9 and abs(res.rho[4, d]) > 0.9


def test_cli_on_a_trajectory_file(tmp_path, tiny_scene, capsys):
    from nemsim.cli import main
    from nemsim.controls import CONTROL_NAMES, lhs_design
    from nemsim.data.hdf5 import TrajectoryWriter

    n = 16  # > 14 controls + intercept: the regression is determined
    raw = lhs_design(n=n, seed=0)
    depth = 3.0 + 8.0 * (np.log10(raw[:, 0]) - np.log10(raw[:, 0]).min()) / np.ptp(np.log10(raw[:, 0]))
    path = tmp_path / "t.h5"
    with TrajectoryWriter(
        str(path), scene=tiny_scene, case_ids=list(range(n)), controls_raw=raw, generator={"test": True},
        rules_sha256="0" * 64,
    ) as w:
        for i in range(n):
            final = _hole(tiny_scene, 2.0, depth[i])  # depth driven by the Ar+ flux only
            states = np.repeat(final[None], tiny_scene.n_states, axis=0)
            w.write(i, states, seed=i, meta={})
    out_json = tmp_path / "s.json"
    assert main(["sensitivity", str(path), "--json", str(out_json)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].split()[1] == CONTROL_NAMES[0]
    assert out_json.exists()
    assert main(["sensitivity", str(tmp_path / "missing.h5")]) == 2


def test_cli_with_a_stub_reader(tmp_path, tiny_scene, monkeypatch, capsys):
    """The file path through the `open_trajectories` contract, independent of the real HDF5 module."""
    import sys
    import types

    from nemsim.cli import main

    rng = np.random.default_rng(4)
    n = 30
    u = rng.uniform(-1, 1, size=(n, 14))
    finals = np.stack([_hole(tiny_scene, 2.0, 8.0 + 5.0 * u[i, 7]) for i in range(n)])  # only depth varies

    class _File:
        scene = tiny_scene
        n_cases = n
        controls_normalized = u
        control_names = NAMES
        states = np.repeat(finals[:, None], 2, axis=1)  # (N, T=2, 2, D, H, W)
        closed = False

        def close(self):
            _File.closed = True

    stub = types.ModuleType("nemsim.data.hdf5")
    stub.open_trajectories = lambda path: _File()
    monkeypatch.setitem(sys.modules, "nemsim.data.hdf5", stub)
    path = tmp_path / "fake.h5"
    path.write_bytes(b"")
    assert main(["sensitivity", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[2].split()[:2] == ["1", "c7"] and _File.closed
