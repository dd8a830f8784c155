"""`generate_dataset` / `nemsim generate`: file contents, seeds, resume, parallel executors, CLI errors."""

from __future__ import annotations

import importlib.util

import h5py
import numpy as np
import pytest

from nemsim.sim import SimConfig, run_trajectory
from nemsim.sim.generate import case_seed, generate_dataset


@pytest.fixture(scope="module")
def low_flux(make_controls):
    """(3, 14) cheap control rows (low fluxes: few particles per `tiny` trajectory)."""
    base = dict(flux_ar_plus=2e-4, flux_cl_plus=2e-4, flux_cl2_plus=2e-6, flux_cl=1e-3)
    return np.stack([make_controls(**base, energy_mean_ar_plus=e) for e in (200.0, 300.0, 400.0)])


def test_generate_writes_seeded_cases_and_resumes(tmp_path, tiny_scene, rules, low_flux):
    from nemsim.data.hdf5 import check_dataset, open_trajectories

    out = tmp_path / "t.h5"
    rep = generate_dataset(out, tiny_scene, rules, low_flux, [10, 11, 12], seed=5, progress=False)
    assert rep["written"] == 3 and rep["skipped"] == 0
    assert check_dataset(out).ok
    with open_trajectories(out) as tf:
        states = tf.states[()]
        np.testing.assert_array_equal(tf.case_ids, [10, 11, 12])
    with h5py.File(out, "r") as f:
        seeds = f["seeds"][()]
        gen = f.attrs["generator"]
    assert list(seeds) == [case_seed(5, c) for c in (10, 11, 12)]
    assert '"capacity": 16' in gen and '"base_seed": 5' in gen and '"flux_scale"' in gen
    # the stored trajectory is exactly the one run_trajectory gives with the recorded seed
    direct = run_trajectory(tiny_scene, rules, low_flux[1], np.random.default_rng(seeds[1]), SimConfig())
    np.testing.assert_array_equal(states[1], direct.states)

    # an interrupted run: case 12 half written (flag unset) -> only it is redone, identically
    with h5py.File(out, "r+") as f:
        f["complete"][2] = 0
        f["states"][2, 50:] = np.nan
    rep = generate_dataset(out, tiny_scene, rules, low_flux, [10, 11, 12], seed=5, progress=False)
    assert rep["written"] == 1 and rep["skipped"] == 2
    with open_trajectories(out) as tf:
        np.testing.assert_array_equal(tf.states[()], states)

    # a different seed or control set is not silently mixed into the file
    with pytest.raises(ValueError, match="mismatch"):
        generate_dataset(out, tiny_scene, rules, low_flux, [10, 11, 12], seed=6, progress=False)


def test_case_seed_is_stable_and_distinct():
    assert case_seed(0, 1) == case_seed(0, 1)
    assert len({case_seed(s, c) for s in range(3) for c in range(50)}) == 150
    assert all(0 <= case_seed(s, c) < 2**63 for s in range(3) for c in range(5))


@pytest.mark.slow
def test_process_pool_matches_serial(tmp_path, tiny_scene, rules, low_flux):
    from nemsim.data.hdf5 import open_trajectories

    a, b = tmp_path / "serial.h5", tmp_path / "pool.h5"
    generate_dataset(a, tiny_scene, rules, low_flux[:2], [0, 1], seed=1, workers=1, progress=False)
    generate_dataset(b, tiny_scene, rules, low_flux[:2], [0, 1], seed=1, workers=2, progress=False)
    with open_trajectories(a) as fa, open_trajectories(b) as fb:
        np.testing.assert_array_equal(fa.states[()], fb.states[()])


@pytest.mark.slow
@pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="Ray is not installed (optional extra: pip install 'nemsim[ray]')",
)
def test_ray_executor_matches_serial(tmp_path, tiny_scene, rules, low_flux):
    from nemsim.data.hdf5 import open_trajectories

    a, b = tmp_path / "serial.h5", tmp_path / "ray.h5"
    generate_dataset(a, tiny_scene, rules, low_flux[:2], [0, 1], seed=1, progress=False)
    generate_dataset(
        b, tiny_scene, rules, low_flux[:2], [0, 1], seed=1, workers=2, executor="ray", progress=False
    )
    with open_trajectories(a) as fa, open_trajectories(b) as fb:
        np.testing.assert_array_equal(fa.states[()], fb.states[()])


def test_ray_missing_gives_a_clear_error(tmp_path, tiny_scene, rules, low_flux, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray":
            raise ImportError("No module named 'ray'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(RuntimeError, match="pip install"):
        generate_dataset(
            tmp_path / "r.h5", tiny_scene, rules, low_flux[:1], [0], executor="ray", progress=False
        )


def test_cli_generate_from_controls_csv(tmp_path, low_flux, capsys):
    from nemsim.cli import main
    from nemsim.controls import write_controls_csv

    csv = tmp_path / "c.csv"
    write_controls_csv(csv, low_flux)
    out = tmp_path / "cli.h5"
    assert main(["generate", "--scene", "tiny", "--controls", str(csv), "--cases", "1-2", "--out", str(out),
                 "--no-progress"]) == 0  # fmt: skip
    with h5py.File(out, "r") as f:
        assert list(f["case_ids"][()]) == [1, 2]
        np.testing.assert_array_equal(f["controls_raw"][()], low_flux[1:])
    assert "2 cases simulated" in capsys.readouterr().out
    # bad input: one line, exit 2
    args = ["generate", "--scene", "tiny", "--controls", str(csv), "--out", str(out)]
    assert main([*args, "--cases", "2-7"]) == 2
    assert main(["generate", "--scene", "tiny", "--n", "2", "--set", "nope=1", "--out", str(out)]) == 2
    assert "--cases" in capsys.readouterr().err


def test_cli_generate_gives_a_row_the_seed_of_its_seed_id(tmp_path, tiny_scene, rules, low_flux):
    """A ``seed_id`` column (``nemsim design --kind pairs``) gives a row the seed of another case id: the
    file stores the shared seed, and the row's trajectory is the one that seed gives."""
    from nemsim.cli import main
    from nemsim.controls import write_controls_csv

    csv = tmp_path / "pairs.csv"
    write_controls_csv(csv, low_flux, seed_ids=np.array([0, 0, 2]))
    out = tmp_path / "pairs.h5"
    assert main(["generate", "--scene", "tiny", "--controls", str(csv), "--seed", "3", "--out", str(out),
                 "--no-progress"]) == 0  # fmt: skip
    with h5py.File(out, "r") as f:
        assert list(f["seeds"][()]) == [case_seed(3, 0), case_seed(3, 0), case_seed(3, 2)]
        states = f["states"][()]
    rng = np.random.default_rng(case_seed(3, 0))
    direct = run_trajectory(tiny_scene, rules, low_flux[1], rng, SimConfig())
    np.testing.assert_array_equal(states[1], direct.states)
    sliced = tmp_path / "sliced.h5"  # --cases keeps each row's seed id
    assert main(["generate", "--scene", "tiny", "--controls", str(csv), "--seed", "3", "--cases", "1-2",
                 "--out", str(sliced), "--no-progress"]) == 0  # fmt: skip
    with h5py.File(sliced, "r") as f:
        assert list(f["seeds"][()]) == [case_seed(3, 0), case_seed(3, 2)]
        np.testing.assert_array_equal(f["states"][0], states[1])
