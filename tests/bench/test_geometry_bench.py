"""bench.geometry on the tiny scene: field error against two simulator seeds, ARDE from cached simulator
results, today's geometry, the bottom count, and the checkpoint stamp."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def hole_files(tmp_path_factory, two_seed_files):
    """Two tiny hole files of one design (simulator seeds 1 and 2) and one at the default feature."""
    from nemsim.cli import main

    root = tmp_path_factory.mktemp("geometry")
    files = two_seed_files(root, "hole", "24:48", "40:80")
    files["default"] = root / "default.h5"
    assert main(["generate", "--scene", "tiny", "--n", "1", "--no-progress", "--out",
                 str(files["default"])]) == 0
    return files


def _arde_report() -> dict:
    """bench.arde's simulator report on tiny at the centre recipe, with made-up depths (slope 0.5)."""
    from bench import arde

    runs = [{"cd_nm": cd, "seed": s, "depth_nm": {"5.0": 0.25 * cd, "10.0": 0.5 * cd}, "cpu_s": 0.0,
             "through": False} for cd in arde.CDS_NM for s in arde.SEEDS]
    slope = {t: {"per_seed": [k, k], "mean": k, "spread": 0.0} for t, k in (("5.0", 0.25), ("10.0", 0.5))}
    return {"scene": "tiny", "mask_nm": arde.MASK_NM, "cds_nm": list(arde.CDS_NM), "seeds": list(arde.SEEDS),
            "domain": "full", "times_s": list(arde.TIMES_S),
            "recipes": [{"recipe": "centre", "controls": [float(v) for v in arde.recipes()["centre"]],
                         "runs": runs, "slope": slope}]}


def test_geometry_report_on_tiny(tmp_path, hole_files, tiny_checkpoint):
    from bench import geometry

    arde = tmp_path / "arde.json"
    arde.write_text(json.dumps(_arde_report()))
    out = tmp_path / "geometry"
    assert geometry.main(["--checkpoint", str(tiny_checkpoint), "--baseline", str(tiny_checkpoint),
                          "--test", str(hole_files["a"]), "--test-seed", str(hole_files["b"]),
                          "--default", str(hole_files["default"]), "--arde", str(arde),
                          "--out", str(out)]) == 0
    rep = json.loads(out.with_suffix(".json").read_text())
    field = rep["field"]
    assert len(field["cases"]) == 2 and field["floor"]["avg_rmse"] > 0
    for name in ("model", "baseline"):
        row = field[name]
        assert row["avg_rmse"] == pytest.approx((row["seed_a"]["avg_rmse"] + row["seed_b"]["avg_rmse"]) / 2)
        assert row["ratio_to_floor"] == pytest.approx(row["avg_rmse"] / field["floor"]["avg_rmse"])
        lo, hi = row["ratio_interval_90"]
        assert lo <= row["ratio_to_floor"] <= hi or lo == hi
        assert len(row["per_case"]) == 2
        assert np.isfinite(rep["arde"][name]["recipes"][0]["slope"]["10.0"])
        assert rep["default"][name]["avg_rmse"] > 0
    assert field["model"]["avg_rmse"] == pytest.approx(field["baseline"]["avg_rmse"])  # the same weights
    assert [t["cases"] for t in rep["through"]] == [2, 2, 1]
    assert rep["checkpoint_id"] == rep["models"]["model"]["checkpoint_id"]
    text = out.with_suffix(".md").read_text()
    assert "_Made with checkpoint" in text and "seed-to-seed floor" in text and "model slope" in text


def test_other_designs_are_refused(tmp_path, hole_files, tiny_checkpoint):
    from bench.geometry import field_errors
    from nemsim.inference.checkpoint import load_checkpoint

    loaded = {"model": load_checkpoint(tiny_checkpoint)}
    with pytest.raises(ValueError, match="not the same design"):
        field_errors(loaded, hole_files["a"], hole_files["default"])
