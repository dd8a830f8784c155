"""Training records the geometry it saw: the summary's ``geometry``, per kind, read back by the
inference side (``checkpoint_geometry``)."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np

STEPS = 4  # as in tests/training/conftest.py


def _with_geometry(src, dst, rows: np.ndarray):
    """A copy of ``src`` (and its splits/) whose cases carry the hole features ``rows`` (N, 2) [cd, mask]."""
    dst.mkdir()
    shutil.copy(src, dst / src.name)
    shutil.copytree(src.parent / "splits", dst / "splits")
    with h5py.File(dst / src.name, "r+") as f:
        f.create_dataset("geometry", data=rows)
        f.attrs["feature_kind"] = "hole"
    return dst / src.name


def test_a_file_without_geometry_records_the_scene_feature(tiny_data, tiny_scene):
    from nemsim.geometry.feature import Feature
    from nemsim.training.run import trained_geometry

    own = Feature.of(tiny_scene)
    assert trained_geometry([(tiny_data, [0, 1, 2])]) == {
        own.kind: {"cd_nm": [own.cd_nm] * 2, "mask_nm": [own.mask_nm] * 2}}


def test_ranges_span_the_training_cases_only(tmp_path, tiny_data):
    from nemsim.training.run import trained_geometry

    rows = np.array([[30.0, 40.0], [40.0, 56.0], [36.0, 48.0], [20.0, 64.0], [60.0, 32.0], [50.0, 40.0]])
    data = _with_geometry(tiny_data, tmp_path / "geo", rows)
    assert trained_geometry([(data, [0, 1, 2])]) == {"hole": {"cd_nm": [30.0, 40.0], "mask_nm": [40.0, 56.0]}}
    # an extra file trains on all its complete cases
    assert trained_geometry([(data, None)]) == {"hole": {"cd_nm": [20.0, 60.0], "mask_nm": [32.0, 64.0]}}


def test_the_checkpoint_carries_the_trained_geometry(tmp_path, tiny_data):
    from nemsim.cli import main
    from nemsim.inference.checkpoint import checkpoint_geometry, read_checkpoint

    rows = np.array([[30.0, 40.0], [40.0, 56.0], [36.0, 48.0], [20.0, 64.0], [60.0, 32.0], [50.0, 40.0]])
    data = _with_geometry(tiny_data, tmp_path / "geo", rows)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"warmup_epochs": 0, "val_every": 1, "batch_size": 3, "bf16": False,
                               "model": {"stem": 4, "widths": [4, 6, 6], "latent_channels": 6,
                                         "context_dim": 8, "readout_width": 6, "decoder_widths": [6, 6]}}))
    out = tmp_path / "run"
    assert main(["train", "--model", "nemsim", "--data", str(data), "--setting", "control-id",
                 "--epochs", "1", "--rollout-steps", str(STEPS), "--config", str(cfg), "--no-progress",
                 "--no-test", "--out", str(out)]) == 0
    ckpt = read_checkpoint(out / "best.pt")
    assert ckpt["summary"]["geometry"] == {"hole": {"cd_nm": [30.0, 40.0], "mask_nm": [40.0, 56.0]}}
    trained = checkpoint_geometry(ckpt)
    assert trained.kinds == ("hole",)
    assert trained.as_dict()["kinds"]["hole"] == {"cd_nm": [30.0, 40.0], "mask_nm": [40.0, 56.0]}
