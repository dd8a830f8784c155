"""Extrapolation benchmark (bench.extrapolation) on `tiny`."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from bench.extrapolation import ExtrapolationConfig, box_distance, recipes, run_extrapolation
from nemsim.controls import CONTROL_INDEX, FLUX_INDICES, PHYS_MIN, to_normalized

torch.set_num_threads(1)


def test_recipes_leave_the_box_one_control_at_a_time():
    cases, skipped = recipes(ExtrapolationConfig(distances=(1.5, 2.0), corners=2, in_box=3))
    by = {c["name"]: c for c in cases}
    centre = by["centre"]["raw"]
    assert by["centre"]["distance"] == pytest.approx(-1.0)
    assert all(-1.0 <= c["distance"] <= 0.0 for c in cases if c["kind"] == "in-box")
    assert [c["distance"] for c in cases if c["kind"] == "corner"] == pytest.approx([0.0, 0.0])
    axis = [c for c in cases if c["kind"] == "axis"]
    for c in axis:
        moved = np.flatnonzero(~np.isclose(c["raw"], centre, rtol=1e-12, atol=0))
        assert len(moved) == 1, c["name"]
        assert np.all(c["raw"] >= PHYS_MIN)
        d = float(c["name"].rsplit("-", 1)[1])
        if not c["name"].startswith("angle_"):  # integer exponents are rounded
            assert abs(to_normalized(c["raw"])[moved[0]]) == pytest.approx(d, rel=1e-9)
            assert c["distance"] == pytest.approx(d - 1.0, rel=1e-9)
    # 14 controls x 2 sides x 2 distances, minus the physically impossible low sides
    assert len(axis) + len(skipped) == 56
    names = {k["name"] for k in skipped}
    assert "energy_mean_ar_plus-low-2" in names and "angle_cl_plus-low-1.5" in names
    assert "flux_ar_plus-low-2" not in names  # fluxes move in log space: always admissible
    assert by["zero-all-fluxes"]["raw"][list(FLUX_INDICES)].tolist() == [0.0] * 4
    assert by["isotropic-m1"]["raw"][CONTROL_INDEX["angle_ar_plus"]] == 1.0
    assert by["needle-m10000"]["raw"][CONTROL_INDEX["angle_cl_plus"]] == 10_000.0
    assert box_distance(by["zero-all-fluxes"]["raw"]) > 3.0
    with pytest.raises(ValueError, match="distances"):
        ExtrapolationConfig(distances=(0.5,))


STEPS = 2  # simulated transitions of the shared `truth` fixture (conftest.py)


@pytest.fixture(scope="module")
def report(truth, x0, stubs):
    cfg = ExtrapolationConfig(distances=(2.0,), corners=1, in_box=1)
    return run_extrapolation(stubs.NoChange(), truth, x0, cfg)


def test_report_groups_and_reference(report):
    s = report["summary"]
    assert set(s["groups"]) == {"in-box", "corner", "axis 2", "zero-flux", "angle"}
    assert s["groups"]["in-box"]["ratio_to_in_box"] == pytest.approx(1.0)
    assert s["in_box_avg_rmse"] == pytest.approx(np.mean([r["avg_rmse"] for r in report["cases"]
                                                           if r["kind"] == "in-box"]))
    # a no-change model is exact where nothing happens: zero fluxes leave the simulated state unchanged
    zero = next(r for r in report["cases"] if r["name"] == "zero-all-fluxes")
    assert zero["avg_rmse"] == pytest.approx(0.0, abs=1e-7) and zero["floor"] == pytest.approx(0.0, abs=1e-7)
    # ... and off by the whole etch where the simulator etches fastest
    hot = next(r for r in report["cases"] if r["name"] == "flux_ar_plus-high-2")
    assert hot["error"]["etch_depth"] < 0 and hot["avg_rmse"] > hot["floor"]
    json.dumps(report)


def test_cli_bench_extrapolation(tiny_checkpoint, tmp_path, capsys):
    from nemsim.cli import main

    out = tmp_path / "ex"
    rc = main(["bench", "extrapolation", "--checkpoint", str(tiny_checkpoint), "--sim-steps", "1",
               "--distances", "2", "--corners", "0", "--in-box", "0", "--no-progress", "--out", str(out)])
    assert rc == 0
    assert "planned: " in capsys.readouterr().out
    rep = json.loads((out / "extrapolation.json").read_text())
    assert rep["summary"]["in_box_avg_rmse"] is not None  # the design centre is always the in-box reference
    assert (out / "extrapolation.png").stat().st_size > 1000
    assert "| axis 2 |" in (out / "extrapolation.md").read_text()
    assert main(["bench", "extrapolation", "--checkpoint", str(tiny_checkpoint), "--distances", "0.5"]) == 2
    assert main(["bench", "extrapolation", "--checkpoint", str(tiny_checkpoint), "--distances", "x"]) == 2
