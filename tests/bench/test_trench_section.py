"""bench.trench_section on the tiny scene: a trench's cross-section against its 3-D simulation."""

from __future__ import annotations

import numpy as np


def test_trench_section_on_tiny(tiny_scene, rules):
    from bench.arde import recipes
    from bench.trench_section import METRICS, TIMES_S, bench_section, to_markdown
    from nemsim.geometry.feature import Feature

    scene = Feature("trench", 40.0, 80.0).apply(tiny_scene)
    rep = bench_section(scene, rules, {"centre": recipes()["centre"]}, section_ny=2, extra_timing_runs=0)
    (row,) = rep["recipes"]
    assert len(row["field"]) == 2 * len(TIMES_S)
    assert all(np.isfinite(x["rms_d"]) and x["rms_s"] >= 0 for x in row["field"])
    assert set(row["metrics"]) == set(METRICS)
    assert rep["cpu_s"]["3d"] > 0 and rep["cpu_s"]["section"] > 0 and rep["speedup_cpu"] > 0
    assert rep["feature"]["kind"] == "trench"
    text = to_markdown(rep, "python -m bench.trench_section --scene tiny", "test CPU")
    assert "| centre | 10 | si |" in text and "speed-up" in text
