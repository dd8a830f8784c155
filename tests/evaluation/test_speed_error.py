"""`nemsim bench speed-error` and `nemsim bench collect` on a 3-case `tiny` data file, untrained checkpoint.

One simulator-generated data file (3 design cases, full tiny horizon, ~2 s) and one untrained NEMSim
checkpoint are shared by the module; the bench runs once (1 case) through the CLI: ~7 s in all.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def rules():
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    return compile_rules(load_rules())


@pytest.fixture(scope="module")
def tiny_sim_data(tmp_path_factory, tiny_scene, rules):
    """data.h5 (3 simulated cases) with splits/control-id.json (all three in test) next to it."""
    from nemsim.controls import lhs_design
    from nemsim.sim.generate import generate_dataset

    root = tmp_path_factory.mktemp("speed_error")
    path = root / "data.h5"
    generate_dataset(path, tiny_scene, rules, lhs_design()[:3], [0, 1, 2], seed=0, workers=1, progress=False)
    (root / "splits").mkdir()
    manifest = {"setting": "control-id", "train": [], "val": [], "test": [2, 0, 1], "unused": [],
                "visible_transitions": tiny_scene.n_transitions}  # fmt: skip
    (root / "splits" / "control-id.json").write_text(json.dumps(manifest))
    return path


@pytest.fixture(scope="module")
def speed_error_out(tmp_path_factory, tiny_sim_data, tiny_checkpoint):
    from nemsim.cli import main

    out = tmp_path_factory.mktemp("bench")
    rc = main(["bench", "speed-error", "--data", str(tiny_sim_data), "--setting", "control-id",
               "--checkpoints", str(tiny_checkpoint), "--cases", "1", "--out", str(out)])  # fmt: skip
    assert rc == 0
    return out


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def test_speed_error_report(speed_error_out):
    rep = json.loads((speed_error_out / "speed_error.json").read_text())
    assert rep["scene"] == "tiny" and rep["setting"] == "control-id" and rep["steps"] == 100
    assert rep["case_ids"] == [2]  # first test case in manifest order
    rows = rep["rows"]
    sims = [r for r in rows if r["kind"] == "simulator"]
    models = [r for r in rows if r["kind"] == "model"]
    assert [r["budget"] for r in sims] == [1.0, 0.25, 0.0625]
    assert [r["precision"] for r in models] == ["fp32", "bf16"] and {r["model"] for r in models} == {"nemsim"}
    for r in rows:
        for key in ("wall_s", "cpu_s", "avg_rmse", "final_rmse", "cd", "avg_rmse_vs_data", "speedup"):
            assert _finite(r[key]) and r[key] >= 0, (r["label"], key, r[key])
        assert r["wall_s"] > 0
    # exactly one noise-floor row: the full-budget simulator, compared with a second full-budget seed
    floor = [r for r in rows if r["noise_floor"]]
    assert len(floor) == 1 and floor[0]["kind"] == "simulator" and floor[0]["budget"] == 1.0
    assert floor[0]["avg_rmse"] > 0  # the reference is an independent run, not the data file
    assert floor[0]["avg_rmse_vs_data"] == 0.0  # that row *is* the data file's trajectory
    assert rep["noise_floor"] == {k: floor[0][k] for k in ("avg_rmse", "final_rmse", "cd")}
    assert rep["speed"]["simulator_s"] == floor[0]["wall_s"]
    assert _finite(rep["speed"]["nemsim_s"]) and rep["speed"]["nemsim_precision"] in ("fp32", "bf16")
    assert sum(r["fastest"] for r in models) == 1 and models[0]["keeps_error"] is True
    assert models[0]["params"] > 0
    # the untrained model is far from the simulator; lower budgets are noisier, not better, than the floor
    assert models[0]["avg_rmse"] > floor[0]["avg_rmse"]


def test_speed_error_table_and_plot(speed_error_out):
    md = (speed_error_out / "speed_error.md").read_text()
    assert "| method |" in md and "noise floor (two full-budget seeds)" in md
    assert "**simulator, budget 1**" in md
    for label in ("simulator, budget 1/4", "simulator, budget 1/16", "nemsim fp32", "nemsim bf16"):
        assert label in md
    png = (speed_error_out / "speed_error.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_collect_builds_results_json_and_readme(tmp_path, speed_error_out):
    from nemsim.cli import main

    runs = []
    for name, setting, avg in (("nemsim", "control-id", 0.01), ("fno", "control-id", 0.03),
                               ("nemsim-vis", "vis-50", 0.02)):  # fmt: skip
        d = tmp_path / name
        d.mkdir()
        (d / "test_metrics.json").write_text(json.dumps({
            "avg_rmse": avg, "final_rmse": 2 * avg, "cd": 0.5, "params": 250_000, "rollout_seconds": 1.0,
            "rollout_seconds_per_case": 0.2, "n_cases": 10, "steps": 100, "setting": setting,
        }))  # fmt: skip
        runs.append(str(d))
    readme = tmp_path / "README.md"
    readme.write_text("# Benchmarks\n\nhand-written intro\n")
    out = tmp_path / "results.json"
    se = str(speed_error_out / "speed_error.json")
    rc = main(["bench", "collect", "--runs", *runs, "--speed-error", se, "--out", str(out),
               "--readme", str(readme)])  # fmt: skip
    assert rc == 0
    res = json.loads(out.read_text())
    assert set(res["settings"]) == {"control-id", "vis-50"}
    assert set(res["settings"]["control-id"]) == {"nemsim", "fno"}  # no best.pt: the run directory's name
    for m in res["settings"]["control-id"].values():
        assert {"avg_rmse", "final_rmse", "cd", "params", "rollout_s"} <= set(m)
    assert res["settings"]["control-id"]["nemsim"]["rollout_s"] == 0.2
    assert _finite(res["noise_floor"]["avg_rmse"]) and _finite(res["noise_floor"]["cd"])
    assert _finite(res["speed"]["simulator_s"]) and _finite(res["speed"]["nemsim_s"])
    text = readme.read_text()
    assert text.startswith("# Benchmarks\n\nhand-written intro") and "### control-id" in text
    assert text.index("| nemsim |") < text.index("| fno |")  # sorted by Avg RMSE
    # a second collect replaces the table instead of appending another one
    assert main(["bench", "collect", "--runs", *runs, "--out", str(out), "--readme", str(readme)]) == 0
    assert readme.read_text().count("### control-id") == 1
    # the same (setting, model) twice is refused with exit code 2
    assert main(["bench", "collect", "--runs", runs[0], runs[0], "--out", str(out)]) == 2


def test_step_budget_runs_get_their_own_table():
    from nemsim.evaluation.results import setting_key

    assert setting_key("control-id", {}) == "control-id"
    assert setting_key("control-id", {"train_config": {"max_steps": None, "batch_size": 24}}) == "control-id"
    assert setting_key("control-id", {"train_config": {"max_steps": 250, "batch_size": 24}}) == \
        "control-id, 250 steps x batch 24"
