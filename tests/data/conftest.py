"""Fixtures for the data tests: small synthetic trajectory files on the `tiny` scene."""

from __future__ import annotations

import numpy as np
import pytest


def synthetic_states(scene, seed: int) -> np.ndarray:
    """(T, 2, D, H, W) float32 clipped SDFs; value [t, c, 0, 0, 0] encodes (seed, t, c) for indexing tests."""
    T = scene.n_states
    C, D, H, W = scene.state_shape
    depth = np.arange(D, dtype=np.float32)[:, None, None]
    out = np.empty((T, C, D, H, W), dtype=np.float32)
    for t in range(T):
        out[t, 0] = np.clip((depth - scene.si_top) / scene.d_max_vox, -1, 1)
        out[t, 1] = np.clip((depth - scene.si_top + 0.01 * t * (1 + seed)) / scene.d_max_vox, -1, 1)
        out[t, :, 0, 0, 0] = -(seed / 10.0 + t / 10000.0)  # seed < 10
    return out


@pytest.fixture()
def synthetic():
    """synthetic_states(scene, seed): the states ``make_file`` writes for row ``seed``."""
    return synthetic_states


@pytest.fixture()
def decode():
    return code_of


def code_of(state) -> tuple[int, int]:
    """(seed, t) decoded from a state written by synthetic_states."""
    v = -float(state[0, 0, 0, 0])
    seed = int(v * 10 + 1e-6)
    t = int(round((v - seed / 10.0) * 10000))
    return seed, t


@pytest.fixture()
def make_file(tmp_path, tiny_scene):
    """make_file(n=6, write=None, schedule=False) -> path of a tiny trajectory file with rows `write` done."""
    from nemsim.controls import lhs_design
    from nemsim.data.hdf5 import TrajectoryWriter

    def _make(n: int = 6, write=None, schedule: bool = False, name: str = "t.h5", case_ids=None):
        raw = lhs_design(n=n, seed=1)
        ids = list(range(100, 100 + n)) if case_ids is None else case_ids
        sched = None
        if schedule:
            sched = np.repeat(raw[:, None, :], tiny_scene.n_transitions, axis=1).copy()
            sched[:, 50:, 0] = raw[:, 0:1] * 0.5  # Ar+ flux halves halfway: a two-step recipe
        path = tmp_path / name
        with TrajectoryWriter(path, scene=tiny_scene, case_ids=ids, controls_raw=raw,
                              generator={"kind": "synthetic-test"}, rules_sha256="ab" * 32,
                              controls_schedule=sched) as w:
            for row in range(n) if write is None else write:
                w.write(row, synthetic_states(tiny_scene, row), seed=1000 + row, meta={"row": row})
        return path

    return _make
