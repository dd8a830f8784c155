"""bench.gpu, the one script run on a borrowed GPU machine: its recipe rewriting and extrapolation, and the
whole script end to end on the CPU at its smallest sizes (``--device cpu --quick``), every part."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from bench.gpu import RECIPE, ROOT, generate_extrapolation, main, reduced_recipe


def _numbers(tree, path=""):
    """(path, value) of every number in a JSON tree."""
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _numbers(v, f"{path}.{k}")
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            yield from _numbers(v, f"{path}[{i}]")
    elif isinstance(tree, (int, float)) and not isinstance(tree, bool):
        yield path, tree


def test_reduced_recipe_rewrites_sizes_paths_and_budgets(tmp_path):
    raw = yaml.safe_load(RECIPE.read_text())
    new, counts = reduced_recipe(raw, tmp_path, (8, 6), (5, 3), max_minutes=1.5,
                                 sim_set=["particle_budget=0.5"])
    commands = {(c[0], Path(c[c.index("--out") + 1]).name): c for c in new["data"]}
    design, extra = commands["design", "design.csv"], commands["design", "design-extra.csv"]
    full, quarter = commands["generate", "small.h5"], commands["generate", "small-quarter.h5"]
    assert design[design.index("--n") + 1] == "8" and extra[extra.index("--n") + 1] == "6"
    assert full[full.index("--n") + 1] == "8" and "--n" not in quarter  # its --controls CSV has 6 rows
    assert quarter[quarter.index("--controls") + 1] == str(tmp_path / "data" / "design-extra.csv")
    for cmd in (full, quarter):
        assert cmd[-2:] == ["--set", "particle_budget=0.5"]
    assert all(Path(c[c.index("--out") + 1]).is_relative_to(tmp_path) for c in new["data"])
    assert [(c["command"], c["cases"], c["full_cases"]) for c in counts] == [
        ("design", 8, 500), ("generate", 8, 500), ("splits", None, None), ("design", 6, 1500),
        ("generate", 6, 1500)]
    for stage, steps in zip(new["stages"], ("5", "3"), strict=True):
        args = stage["args"]
        assert args[args.index("--max-steps") + 1] == steps and args[args.index("--max-minutes") + 1] == "1.5"
        config = Path(args[args.index("--config") + 1])
        assert config.is_absolute() and config.is_relative_to(ROOT) and config.is_file()
        assert Path(args[args.index("--data") + 1]) == tmp_path / "data" / "small.h5"
    assert raw["data"][0][2] == "500"  # the recipe read is left as it was
    with pytest.raises(ValueError, match="2 stages"):
        reduced_recipe(raw, tmp_path, (8, 6), (5,))


def test_generate_extrapolation_counts_startup_once():
    # 8 cases on 4 workers: each worker's first case compiled (10 s more); 2 cases per worker
    ext = generate_extrapolation(30.0, 8, 400, 4, [12, 12, 12, 12, 2, 2, 2, 2])
    assert ext["scaled_s"] == pytest.approx(30.0 * 100 / 2)
    assert ext["case_s"] == 2 and ext["startup_s"] == pytest.approx(26.0)
    assert ext["per_case_s"] == pytest.approx(26.0 + 100 * 2)
    assert "per_case_s" not in generate_extrapolation(30.0, 4, 400, 4, [12, 12, 12, 12])  # no warm case


@pytest.mark.slow
def test_quick_check_on_cpu_runs_every_part(tmp_path):
    out = tmp_path / "out"
    argv = ["--out", str(out), "--device", "cpu", "--quick", "--scratch", str(tmp_path / "scratch"),
            "--recipe-cases", "4,1", "--recipe-steps", "2,1", "--sim-set", "particle_budget=0.05"]
    assert main(argv) == 0
    res = json.loads((out / "gpu.json").read_text())
    md = (out / "gpu.md").read_text()
    errors = {k: v["error"] for k, v in res.items() if isinstance(v, dict) and "error" in v}
    assert not errors, errors
    assert set(res["part_seconds"]) == {"call", "rollout", "data", "train", "recipe"}
    assert res["model"]["domain"] == "quarter" and "**quarter** domain" in md
    assert res["model"]["call_input"][-2:] == [14, 14]  # the quadrant of the 28 x 28 field
    for part, field in (("call", "median_ms"), ("rollout", "per_traj_ms")):
        for batch in ("b1", "b2"):
            assert res[part][batch]["eager"][field] > 0
    train = res["train"]
    assert train["domain"] == "quarter" and train["device_step_ms"] > 0
    for name in ("memory", "streamed_w0"):
        assert train[name]["e2e_step_ms"] > 0 and train[name]["steps_per_s"] > 0
    assert train["memory"]["decode_s"] > 0 and train["streamed_w0"]["loader_only_ms_per_batch"] > 0
    ratios = [train[n]["ratio_to_device"] for n in ("memory", "streamed_w0")]
    assert res["targets"]["train_ratio"]["value"] == min(ratios)

    data = res["data"]
    assert data.get("complete"), data.get("stopped")
    assert [c["command"] for c in data["commands"]] == ["design", "generate", "splits", "design", "generate"]
    for c in data["commands"]:
        assert c["exit"] == 0 and c["wall_s"] >= 0
        if c["command"] == "generate":
            assert c["wall_s"] > 0 and c["extrapolation"]["scaled_s"] > c["wall_s"]
    recipe = res["recipe"]
    assert recipe["exit"] == 0, md
    assert [(s["name"], s["steps"]) for s in recipe["stages"]] == [("k10", 2), ("rollout", 1)]
    for s in recipe["stages"]:
        assert s["wall_s"] > 0 and s["loop_s"] > 0 and s["steps_per_s"] > 0
        assert s["full_steps"] in (12000, 3000) and s["extrapolated_s"] > s["wall_s"]
    assert recipe["test_stage"] == "rollout" and recipe["test_avg_rmse"] > 0
    assert recipe["extrapolation"]["total_s"] > recipe["extrapolation"]["data_s"] > 0
    assert "Extrapolation, not a measurement" in md
    bad = [(p, v) for p, v in _numbers(res) if not math.isfinite(v) or v < 0]
    assert not bad, bad
