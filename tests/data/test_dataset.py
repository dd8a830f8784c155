"""nemsim.data.dataset: streaming transition / trajectory datasets honouring manifests and visible
prefixes."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from nemsim.data.dataset import TrajectoryDataset, TransitionDataset
from nemsim.data.hdf5 import open_trajectories

MANIFEST = {"setting": "vis-50", "train": [104, 101], "val": [102], "test": [100, 103, 105], "unused": [],
            "visible_transitions": 50}


def test_transition_items_follow_manifest_and_prefix(make_file, tiny_scene, decode):
    path = make_file()
    ds = TransitionDataset(path, MANIFEST, "train", visible_transitions=50)
    assert len(ds) == 2 * 50
    x, u, y = ds[0]
    assert x.shape == tiny_scene.state_shape and x.dtype == torch.float32 and u.shape == (14,)
    # rows are case ids 100.. -> seed = row; train [104, 101] keeps manifest order
    assert decode(x) == (4, 0) and decode(y) == (4, 1)
    x, u, y = ds[len(ds) - 1]
    assert decode(x) == (1, 49) and decode(y) == (1, 50)
    assert ds.index(51) == (101, 1)
    with open_trajectories(path) as tf:
        np.testing.assert_allclose(u.numpy(), tf.controls_normalized[1], rtol=1e-6)
    assert len(TransitionDataset(path, MANIFEST, "test")) == 3 * tiny_scene.n_transitions
    assert len(TransitionDataset(path, None)) == 6 * tiny_scene.n_transitions
    with pytest.raises(IndexError):
        ds[len(ds)]
    with pytest.raises(ValueError, match="visible_transitions"):
        TransitionDataset(path, MANIFEST, "train", visible_transitions=0)
    with pytest.raises(ValueError, match="unknown split"):
        TransitionDataset(path, MANIFEST, "training")


def test_refuses_missing_and_unfinished_cases(make_file):
    path = make_file(write=[0, 1, 2])
    with pytest.raises(ValueError, match=r"unfinished .*\[104\]"):
        TransitionDataset(path, MANIFEST, "train")
    with pytest.raises(ValueError, match=r"not in .*\[7\]"):
        TrajectoryDataset(path, {**MANIFEST, "val": [7]}, "val")
    assert len(TrajectoryDataset(path, None)) == 3  # complete rows only


def test_trajectory_items(make_file, tiny_scene, decode):
    path = make_file()
    ds = TrajectoryDataset(path, MANIFEST, "test")
    cid, states, u = ds[1]
    assert cid == 103 and states.shape == (tiny_scene.n_states, *tiny_scene.state_shape)
    assert u.shape == (tiny_scene.n_transitions, 14) and decode(states[42]) == (3, 42)
    assert torch.allclose(u[0], u[-1])


def test_recipe_schedule_controls(make_file):
    path = make_file(n=2, schedule=True)
    ds = TransitionDataset(path, None)
    assert ds[10][1][0] > ds[60][1][0]  # Ar+ flux halves at t = 50
    _, _, u = TrajectoryDataset(path, None)[0]
    assert u[49, 0] > u[50, 0]


def test_lazy_handle_pickles_and_works_in_workers(make_file, decode):
    path = make_file()
    ds = TransitionDataset(path, MANIFEST, "train", visible_transitions=5)
    assert ds._file is None  # nothing open until the first item
    ds[0]
    clone = pickle.loads(pickle.dumps(ds))
    assert clone._file is None and decode(clone[6][0]) == (1, 1)
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2, shuffle=False)
    xs = torch.cat([b[0] for b in loader])
    assert xs.shape[0] == 10 and decode(xs[9]) == (1, 4)


def test_pair_items_stack_the_two_cases_that_share_a_seed(make_file, tiny_scene, decode):
    import h5py

    from nemsim.data.dataset import PairDataset

    path = make_file()  # rows 0..5 written as synthetic seeds 0..5
    with h5py.File(path, "r+") as f:
        f["seeds"][:] = [7, 7, 9, 9, 11, 12]  # two pairs; rows 4 and 5 have seeds of their own
    ds = PairDataset(path, unroll=2)
    n = tiny_scene.n_transitions - 1  # start times per case with two transitions per item
    assert ds.pairs.tolist() == [[0, 1], [2, 3]] and len(ds) == 2 * n
    assert ds.case_ids(1) == (102, 103)
    x, u, y = ds[n + 3]  # pair 1 at t = 3
    assert x.shape == (2, *tiny_scene.state_shape) and u.shape == (2, 2, 14)
    assert y.shape == (2, 2, *tiny_scene.state_shape)
    assert [decode(x[m]) for m in (0, 1)] == [(2, 3), (3, 3)]
    assert [decode(y[m, j]) for m in (0, 1) for j in (0, 1)] == [(2, 4), (2, 5), (3, 4), (3, 5)]
    one = PairDataset(path)  # one transition per item: (2, 14) controls, (2, C, D, H, W) targets
    x1, u1, y1 = one[3]
    assert u1.shape == (2, 14) and decode(y1[1]) == (1, 4)
    # shaped as a quarter-domain model's training items: symmetrized, folded to the quadrant
    shape = {"symmetrize": True, "quarter": True}
    quad = PairDataset(path, unroll=2, **shape)
    items = TransitionDataset(path, None, "train", unroll=2, **shape)
    xq, uq, yq = quad[n + 3]
    for m, row in enumerate((2, 3)):
        xi, ui, yi = items[row * n + 3]
        assert torch.equal(xq[m], xi) and torch.equal(uq[m], ui) and torch.equal(yq[m], yi)
    assert xq.shape[-1] < x.shape[-1]
    ds.close(), one.close(), quad.close(), items.close()

    with h5py.File(path, "r+") as f:
        f["seeds"][:] = [7, 7, 7, 9, 11, 12]
    with pytest.raises(ValueError, match="a pair file pairs two cases"):
        PairDataset(path)
    with h5py.File(path, "r+") as f:
        f["seeds"][:] = [1, 2, 3, 4, 5, 6]
    with pytest.raises(ValueError, match="no two complete cases share"):
        PairDataset(path)
