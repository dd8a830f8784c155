"""Shared fixtures. Tests run on CPU, on the `tiny` scene, in seconds."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Keep numba/torch from oversubscribing the 2-core CI machine.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")


@pytest.fixture(scope="session")
def tiny_scene():
    from nemsim.scenes import TINY

    return TINY


@pytest.fixture(scope="session")
def rules():
    """The compiled Event Rules Library (rules/cl_si.yaml), shared by every test."""
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    return compile_rules(load_rules())


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory, tiny_scene, rules):
    """An untrained NEMSim checkpoint on `tiny`, written with the real save_checkpoint (full model config,
    as ``nemsim train`` stores it)."""
    import dataclasses

    import torch

    from nemsim.inference.checkpoint import save_checkpoint
    from nemsim.registry import build_model, model_config

    torch.manual_seed(0)
    model = build_model("nemsim", tiny_scene, rules)
    path = tmp_path_factory.mktemp("ckpt") / "tiny_nemsim.pt"
    save_checkpoint(
        path,
        model,
        model_name="nemsim",
        model_config=dataclasses.asdict(model_config("nemsim", tiny_scene)),
        scene=tiny_scene,
        rules=rules,
        summary={"note": "untrained, for tests"},
        metrics={"avg_rmse": 0.5},
    )
    return path


@pytest.fixture(scope="session")
def tiny_section_checkpoint(tmp_path_factory, tiny_scene, rules):
    """An untrained cross-section (trench) checkpoint on `tiny`: ``domain = "section"``, five states per call,
    its trained geometry recorded as trenches of CD 32-48 nm under 48-80 nm of mask."""
    import dataclasses

    import torch

    from nemsim.inference.checkpoint import save_checkpoint
    from nemsim.registry import build_model, model_config

    torch.manual_seed(0)
    overrides = {"domain": "section", "steps_per_call": 5}
    model = build_model("nemsim", tiny_scene, rules, overrides)
    path = tmp_path_factory.mktemp("ckpt") / "tiny_trench.pt"
    save_checkpoint(path, model, model_name="nemsim",
                    model_config=dataclasses.asdict(model_config("nemsim", tiny_scene, overrides)),
                    scene=tiny_scene, rules=rules,
                    summary={"note": "untrained, for tests",
                             "geometry": {"trench": {"cd_nm": [32, 48], "mask_nm": [48, 80]}}},
                    metrics={"avg_rmse": 0.5})
    return path


def _synthetic_states(scene, rate: float):
    """(T, 2, D, H, W) float32 in [-1, 1]: a fixed mask slab and a Si plane that moves down at ``rate``."""
    import numpy as np

    C, D, H, W = scene.state_shape
    depth = np.arange(D, dtype=np.float32)[:, None, None]
    out = np.empty((scene.n_states, C, D, H, W), dtype=np.float32)
    for t in range(scene.n_states):
        out[t, 0] = np.clip((np.abs(depth - scene.resist_top + 3) - 3) / scene.d_max_vox, -1, 1)
        out[t, 1] = np.clip((depth - scene.si_top + rate * t) / scene.d_max_vox, -1, 1)
    return out


@pytest.fixture(scope="session")
def synthetic_states():
    """states(scene, rate) -> the synthetic trajectory states the tests write into data files."""
    return _synthetic_states


def hole_state(scene, radius_vox, depth_vox, *, mask_top=None, bow=0.0, bow_depth=None):
    """Analytic SDF state of the geometry and training tests: (2, D, H, W) normalized state: Si slab
    with a flat-bottom cylindrical hole of ``radius_vox``
    and ``depth_vox`` below the initial Si top, under a resist layer (top at ``mask_top``, native z).
    ``bow`` widens the hole by that many voxels in a band around native z = ``bow_depth``."""
    import numpy as np

    d, h, w = scene.field_shape
    z = np.arange(d, dtype=np.float64)[:, None, None] - 1.0  # native coordinates
    y = np.arange(h, dtype=np.float64)[None, :, None] - 1.0
    x = np.arange(w, dtype=np.float64)[None, None, :] - 1.0
    cx, cy = scene.opening_centre
    r = np.hypot(x - cx, y - cy)
    s_top = scene.si_top - 0.5
    floor = s_top - depth_vox
    radius = radius_vox + (bow * (np.abs(z - bow_depth) <= 1.0) if bow_depth is not None else 0.0)
    si = np.maximum(z - s_top, np.minimum(radius - r, z - floor))
    m_top = scene.resist_top - 0.5 if mask_top is None else mask_top
    mask = np.maximum(np.maximum(z - m_top, s_top - z), scene.opening_radius_vox - r)
    st = np.stack([np.broadcast_to(mask, (d, h, w)), np.broadcast_to(si, (d, h, w))])
    return np.clip(st / scene.d_max_vox, -1.0, 1.0).astype(np.float32)


@pytest.fixture
def make_hole():
    return hole_state


class Stops:
    """For the tests that stop a running command: Linux /proc views of its processes, and how many cases
    its trajectory file has finished."""

    @staticmethod
    def alive(pid: int) -> bool:
        """Whether ``pid`` runs (a zombie does not)."""
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            return False
        return stat.rsplit(")", 1)[1].split()[0] != "Z"

    @staticmethod
    def children(pid: int) -> set[int]:
        """Pids of the live direct children of ``pid``."""
        out = set()
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] != "Z":
                out.add(int(entry.name))
        return out

    @staticmethod
    def cases_written(path: Path) -> int:
        """Finished cases of a trajectory file being written (0 while it cannot be read yet)."""
        import h5py

        if not path.exists():
            return 0
        try:
            with h5py.File(path, "r", locking=False) as f:
                return int(f["complete"][()].sum())
        except (OSError, KeyError):
            return 0


@pytest.fixture
def stops():
    return Stops
