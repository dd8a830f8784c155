"""``python -m bench.gpu_recipe``: the recipe from nothing in a child process, every printed line stamped,
and a report of its phases and stages from the stages' own files (checked on the CPU, `tiny` scene)."""

from __future__ import annotations

import json

import yaml

from bench.gpu_recipe import main

NET = {"steps_per_call": 10, "domain": "full", "stem": 4, "widths": [4, 4, 4], "latent_channels": 4,
       "context_dim": 4, "readout_width": 4, "decoder_widths": [4, 4]}


def test_the_recipe_runs_from_nothing_and_each_stage_is_reported(tmp_path):
    k10 = {"max_samples": 30, "warmup_samples": 6, "samples_per_epoch": 10, "batch_size": 4, "val_every": 1,
           "in_memory": True, "bf16": False, "rollout_steps": 20, "cuda": {"batch_size": 16}, "model": NET}
    roll = {**k10, "max_samples": 4, "samples_per_epoch": 2, "batch_size": 2, "unroll_steps": 2,
            "unroll_grad": True}
    for name, cfg in (("k10", k10), ("roll", roll)):
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(cfg))
    common = ["--model", "nemsim", "--data", "data/tiny.h5", "--setting", "control-id", "--splits",
              "data/splits"]
    recipe = {"scene": "tiny",
              "data": [["design", "--n", "8", "--seed", "1", "--out", "data/design.csv"],
                       ["generate", "--scene", "tiny", "--n", "8", "--seed", "0", "--out", "data/tiny.h5",
                        "--state-dtype", "float16"],
                       ["splits", "--design", "data/design.csv", "--out", "data/splits"]],
              "stages": [{"name": "k10",
                          "args": [*common, "--config", str(tmp_path / "k10.yaml"), "--no-test"]},
                         {"name": "rollout", "args": [*common, "--config", str(tmp_path / "roll.yaml")]}]}
    (tmp_path / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    out, scratch = tmp_path / "report", tmp_path / "scratch"
    argv = ["--out", str(out), "--recipe", str(tmp_path / "recipe.yaml"), "--scratch", str(scratch),
            "--workers", "1", "--device", "cpu"]
    assert main(argv) == 0
    res = json.loads((out / "recipe.json").read_text())
    assert res["exit"] == 0 and res["wall_s"] > 0
    phases = [p["phase"] for p in res["phases"]]
    assert phases == ["data 1/3 design", "data 2/3 generate", "data 3/3 splits", "stage 1/2 k10",
                      "stage 2/2 rollout"]
    assert all(b["at_s"] >= a["at_s"] for a, b in zip(res["phases"], res["phases"][1:], strict=False))
    first, second = res["stages"]
    assert first["finished"] and (first["batch"], first["steps"], first["items"]) == (4, 8, 32)  # ceil(30/4)
    assert (second["batch"], second["steps"]) == (2, 2) and "test_avg_rmse" not in first
    assert 0 < second["test_avg_rmse"] < 1 and second["items_per_s"] > 0 and first["val_rounds"] >= 1
    text = (out / "recipe.md").read_text()
    assert "**Wall time, data included:" in text and "| k10 | 4 | 8 | 32 |" in text

    (out / "recipe.md").unlink()  # --collect rebuilds the report from the run folder alone
    assert main([*argv, "--collect"]) == 0
    assert json.loads((out / "recipe.json").read_text())["stages"] == res["stages"]
    assert (out / "recipe.md").read_text() == text
