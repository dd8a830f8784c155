"""bench.arde on the tiny scene: the simulator's depth against CD, and the model's slopes beside it (reusing
the simulator's cached results)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import arde


def test_bench_arde_on_tiny(tiny_scene, rules):
    from nemsim.sim.config import SimConfig

    chosen = {"centre": arde.recipes()["centre"]}
    rep = arde.bench_arde(tiny_scene, rules, chosen, cds=(24.0, 48.0), config=SimConfig(domain="full"))
    (row,) = rep["recipes"]
    assert len(row["runs"]) == 2 * len(arde.SEEDS)
    for t in ("5.0", "10.0"):
        assert len(row["slope"][t]["per_seed"]) == len(arde.SEEDS)
        assert np.isfinite(row["slope"][t]["mean"]) and row["slope"][t]["spread"] >= 0
    assert all(x["depth_nm"]["10.0"] >= x["depth_nm"]["5.0"] >= 0 for x in row["runs"])
    text = arde.to_markdown(rep, "python -m bench.arde --scene tiny", "test CPU")
    assert "| centre | 10 |" in text and "slope" in text


def _cached(scene: str) -> dict:
    """A simulator report for the module's CDs at the centre recipe, with made-up depths (slope 0.5)."""
    u = arde.recipes()["centre"]
    runs = [{"cd_nm": cd, "seed": s, "depth_nm": {"5.0": 0.25 * cd, "10.0": 0.5 * cd}, "cpu_s": 0.0,
             "through": False} for cd in arde.CDS_NM for s in arde.SEEDS]
    slope = {t: {"per_seed": [k, k], "mean": k, "spread": 0.0} for t, k in (("5.0", 0.25), ("10.0", 0.5))}
    return {"scene": scene, "mask_nm": arde.MASK_NM, "cds_nm": list(arde.CDS_NM), "seeds": list(arde.SEEDS),
            "domain": "full", "times_s": list(arde.TIMES_S),
            "recipes": [{"recipe": "centre", "controls": [float(v) for v in u], "runs": runs,
                         "slope": slope}]}


def test_checkpoint_adds_model_slopes_from_cached_simulator_results(tmp_path, tiny_checkpoint, monkeypatch,
                                                                    capsys):
    out = tmp_path / "arde"
    out.with_suffix(".json").write_text(json.dumps(_cached("tiny")))

    def no_simulation(*args, **kwargs):
        raise AssertionError("the cached simulator results should have been reused")

    monkeypatch.setattr(arde, "bench_arde", no_simulation)
    arde.main(["--scene", "tiny", "--domain", "full", "--recipes", "centre", "--checkpoint",
               str(tiny_checkpoint), "--out", str(out)])
    rep = json.loads(out.with_suffix(".json").read_text())
    (row,) = rep["model"]["recipes"]
    assert set(row["depth_nm"]) == {str(cd) for cd in arde.CDS_NM}
    for t in ("5.0", "10.0"):
        assert np.isfinite(row["slope"][t])
        assert row["ratio"][t] == pytest.approx(row["slope"][t] / rep["recipes"][0]["slope"][t]["mean"])
    assert rep["model"]["checkpoint_id"] and "model slope" in out.with_suffix(".md").read_text()
    assert "reused" in capsys.readouterr().err


def test_other_holes_are_not_reused():
    cached = _cached("tiny")
    chosen = {"centre": arde.recipes()["centre"]}
    assert arde.same_holes(cached, "tiny", "full", chosen)
    assert not arde.same_holes(cached, "small", "full", chosen)
    assert not arde.same_holes(cached, "tiny", "quarter", chosen)
    assert not arde.same_holes(cached, "tiny", "full", {"centre": chosen["centre"] * 1.1})
    assert not arde.same_holes({"scene": "tiny"}, "tiny", "full", chosen)


def test_trenches_on_their_cross_section_with_a_trench_model(tmp_path, tiny_section_checkpoint):
    """--feature trench: trenches of the same widths simulated on their cross-section, the trench model's
    slopes beside them; a domain that cannot hold a trench is refused."""
    out = tmp_path / "arde"
    arde.main(["--scene", "tiny", "--feature", "trench", "--recipes", "centre", "--checkpoint",
               str(tiny_section_checkpoint), "--out", str(out)])
    rep = json.loads(out.with_suffix(".json").read_text())
    assert rep["feature"] == "trench" and rep["domain"] == "section"
    assert len(rep["recipes"][0]["runs"]) == len(arde.CDS_NM) * len(arde.SEEDS)
    assert np.isfinite(rep["model"]["recipes"][0]["slope"]["10.0"])
    text = out.with_suffix(".md").read_text()
    assert "# ARDE: trench depth" in text and "the same trenches rolled out" in text
    with pytest.raises(SystemExit):
        arde.main(["--scene", "tiny", "--feature", "trench", "--domain", "quarter", "--recipes", "centre"])
