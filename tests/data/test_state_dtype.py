"""float16 state storage: written as float16, read back as float32 within the float16 rounding."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from nemsim.controls import lhs_design
from nemsim.data.hdf5 import TrajectoryWriter, check_dataset, open_trajectories


def synthetic_states(scene, seed: int) -> np.ndarray:
    """(T, 2, D, H, W) float32 clipped planar SDFs whose Si surface moves with t (and the seed)."""
    T = scene.n_states
    _, D, H, W = scene.state_shape
    depth = np.arange(D, dtype=np.float32)[None, :, None, None]
    t = np.arange(T, dtype=np.float32)[:, None, None, None]
    si = np.clip((depth - scene.si_top + 0.013 * t * (1 + seed)) / scene.d_max_vox, -1, 1)
    mask = np.clip((depth - scene.resist_top) / scene.d_max_vox, -1, 1) + 0 * t
    return np.broadcast_to(np.stack([mask, si], axis=1), (T, 2, D, H, W)).astype(np.float32)


def _write(path, scene, dtype: str, rows=(0, 1)):
    raw = lhs_design(n=2, seed=1)
    with TrajectoryWriter(path, scene=scene, case_ids=[7, 8], controls_raw=raw, generator={"kind": "t"},
                          rules_sha256="ab" * 32, state_dtype=dtype) as w:  # fmt: skip
        for r in rows:
            w.write(r, synthetic_states(scene, r), seed=r)


def test_float16_storage_reads_back_as_float32(tmp_path, tiny_scene):
    path = tmp_path / "h.h5"
    _write(path, tiny_scene, "float16")
    with h5py.File(path, "r") as f:
        assert f["states"].dtype == np.float16
    with open_trajectories(path) as tf:
        assert tf.state_dtype == "float16"
        assert tf.states.dtype == np.float32 and tf.states.shape[0] == 2
        got = np.asarray(tf.states[1])
        one = np.asarray(tf.states[0, 3])
    assert got.dtype == np.float32 and one.dtype == np.float32
    want = synthetic_states(tiny_scene, 1)
    err = np.abs(got - want)
    assert err.max() <= 2.0**-12  # half the float16 spacing just below 1
    assert err.max() > 0  # really stored in half precision
    np.testing.assert_array_equal(one, synthetic_states(tiny_scene, 0)[3].astype(np.float16))
    rep = check_dataset(path)
    assert rep.ok, rep.text


def test_float16_items_of_the_training_datasets_are_float32(tmp_path, tiny_scene):
    from nemsim.data.dataset import TrajectoryDataset, TransitionDataset

    path = tmp_path / "h.h5"
    _write(path, tiny_scene, "float16")
    x, u, y = TransitionDataset(path, None, "train")[0]
    _, states, _ = TrajectoryDataset(path, None, "test")[0]
    assert x.dtype == y.dtype == states.dtype == u.dtype
    assert str(x.dtype) == "torch.float32"


def test_resume_keeps_the_files_state_dtype(tmp_path, tiny_scene):
    path = tmp_path / "h.h5"
    _write(path, tiny_scene, "float16", rows=(0,))
    with pytest.raises(ValueError, match="stores float16 states, float32 were requested.*dtype float16"):
        _write(path, tiny_scene, "float32", rows=(1,))
    _write(path, tiny_scene, "float16", rows=(1,))
    with open_trajectories(path) as tf:
        assert tf.complete.all()


def test_unknown_state_dtype_is_refused(tmp_path, tiny_scene):
    with pytest.raises(ValueError, match=r"state_dtype 'float64' is not one of \('float32', 'float16'\)"):
        _write(tmp_path / "h.h5", tiny_scene, "float64")


def test_float16_states_take_less_space(tmp_path, tiny_scene):
    rng = np.random.default_rng(0)
    states = synthetic_states(tiny_scene, 0)
    rough = rng.normal(0, 0.01, states.shape) * (np.abs(states) < 1)  # rough surfaces
    states = np.clip(states + rough, -1, 1)
    size = {}
    for dtype in ("float32", "float16"):
        path = tmp_path / f"{dtype}.h5"
        raw = lhs_design(n=1, seed=1)
        with TrajectoryWriter(path, scene=tiny_scene, case_ids=[7], controls_raw=raw, generator={"kind": "t"},
                              rules_sha256="ab" * 32, state_dtype=dtype) as w:  # fmt: skip
            w.write(0, states, seed=0)
        with h5py.File(path, "r") as f:
            size[dtype] = f["states"].id.get_storage_size()
    assert size["float16"] < 0.6 * size["float32"]
