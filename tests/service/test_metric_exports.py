"""The served model's metrics are measurements, in every form the service gives them (POST /rollout JSON,
metrics.csv, trajectory.h5): a width the hole has not reached the row of is null / an empty cell / NaN,
never a stand-in number, and a jump of the neck width is labelled by a change of `neck_depth`, the row the
neck is measured on (`nemsim.geometry.profile`). Checked on rollouts of the shipped checkpoint."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
# normalized controls of a recipe whose hole bulges faintly: the neck moves to another row at steps 30, 35
BULGING = [0.76, 0.02, -0.31, 0.99, -0.37, -0.63, 0.76, 0.62, 0.34, 0.92, 0.85, 0.5, 0.72, -0.51]
WIDTHS = ("top_width", "bottom_width", "neck_width", "bowing", "neck_depth")


@pytest.fixture(scope="module")
def shipped():
    """(served model of checkpoints/nemsim-small.pt, a client of the app serving it)."""
    from fastapi.testclient import TestClient

    from service.config import Settings
    from service.deps import get_served_model
    from service.main import create_app
    from service.served_model import ServedModel

    served = ServedModel.from_checkpoint(
        ROOT / "checkpoints" / "nemsim-small.pt", runtime_backend="torch", runtime_precision="f32"
    )
    app = create_app(Settings(warmup_steps=0, rate_limit_per_minute=0), served=served)
    app.dependency_overrides[get_served_model] = lambda: served
    with TestClient(app) as client:
        yield served, client


@pytest.fixture(scope="module", params=["default", "bulging"])
def rollout(request, shipped) -> dict:
    """A 40-step rollout of the shipped model: the default controls, or the bulging recipe."""
    served, client = shipped
    body: dict[str, Any] = {"steps": 40, "controls": {}}  # every control its default
    if request.param == "bulging":
        body = {"steps": 40, "controls_normalized": BULGING}
    r = client.post("/rollout", json=body)
    assert r.status_code == 200, r.text
    return {**r.json(), "case": request.param, "voxel_nm": served.scene.voxel_nm}


def test_undefined_metrics_are_null_empty_and_nan(shipped, rollout):
    """Widths are undefined exactly until their row is sidewall, h_b = max(0.1 depth, 1 voxel) above the
    floor (top and bottom width: the top Si row, 0.5 voxel deep; neck, bowing, neck_depth: the first
    reference row, 2.5 voxels deep), and the exports agree with the JSON cell for cell."""
    _, client = shipped
    metrics, vox = rollout["metrics"], rollout["voxel_nm"]
    depth = np.array(metrics["etch_depth"]) / vox  # voxels, defined at every step
    sidewall = depth - np.maximum(0.1 * depth, 1.0)
    for name in WIDTHS:
        row = 0.5 if name in ("top_width", "bottom_width") else 2.5
        undefined = [v is None for v in metrics[name]]
        assert undefined == (sidewall < row).tolist(), name
        assert undefined[0] and not undefined[-1], name
        assert all(v > 0 for v in metrics[name] if v is not None and name != "bowing"), name

    text = client.get(f"/rollouts/{rollout['id']}/metrics.csv").text
    assert any(line.startswith("# empty cell: not defined") for line in text.splitlines())
    table = list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))
    h5 = client.get(f"/rollouts/{rollout['id']}/trajectory.h5").content
    with h5py.File(io.BytesIO(h5), "r") as f:
        stored = {name: (f[f"metrics/{name}"][()], dict(f[f"metrics/{name}"].attrs)) for name in metrics}
    for name, values in metrics.items():
        cells = [row[f"{name} [nm]"] for row in table]
        assert [c == "" for c in cells] == [v is None for v in values], name
        assert [float(c) for c in cells if c] == pytest.approx([v for v in values if v is not None], rel=1e-5)
        array, attrs = stored[name]
        assert np.isnan(array).tolist() == [v is None for v in values], name
        assert attrs["unit"] == "nm" and attrs["nan"].startswith("not defined"), attrs


def test_no_unexplained_jump(rollout):
    """Between defined steps every metric changes by at most one voxel per step, except the neck width
    where `neck_depth` says the neck moved to another row; the bulging recipe has such moves."""
    metrics, vox = rollout["metrics"], rollout["voxel_nm"]
    labelled = 0
    for name, values in metrics.items():
        if name == "neck_depth":
            continue
        for k in range(1, len(values)):
            a, b = values[k - 1], values[k]
            if a is None or b is None or abs(b - a) <= vox:
                continue
            moved = name == "neck_width" and metrics["neck_depth"][k] != metrics["neck_depth"][k - 1]
            assert moved, f"{name} jumps from {a:.1f} to {b:.1f} nm at step {k} ({rollout['case']})"
            labelled += 1
    assert labelled > 0 if rollout["case"] == "bulging" else labelled == 0
