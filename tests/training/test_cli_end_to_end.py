"""Tiny train -> evaluate end to end through the CLI, `nemsim models`, and a 2-process DDP run."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import h5py
import pytest

from nemsim.cli import main

STEPS = 4  # as in tests/training/conftest.py


def _train_args(tiny_data, out, *extra):
    splits = tiny_data.parent / "splits"
    return ["train", "--model", "test-standin", "--data", str(tiny_data), "--setting", "control-id",
            "--out", str(out), "--splits", str(splits), "--epochs", "2", "--rollout-steps", str(STEPS),
            "--no-progress", *extra]


@pytest.mark.slow
def test_train_then_evaluate(tmp_path, tiny_data, tiny_scene, capsys):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("warmup_epochs: 1\nval_every: 1\nbatch_size: 4\nmodel:\n  width: 3\n")
    out = tmp_path / "run"
    assert main(_train_args(tiny_data, out, "--config", str(cfg))) == 0
    for name in ("best.pt", "last.pt", "metrics.csv", "train.log", "test_metrics.json"):
        assert (out / name).is_file(), name
    assert "epoch 2" in (out / "train.log").read_text()

    capsys.readouterr()
    js, h5 = tmp_path / "eval.json", tmp_path / "roll.h5"
    rc = main(["evaluate", "--checkpoint", str(out / "best.pt"), "--data", str(tiny_data), "--setting",
               "control-id", "--splits", str(tiny_data.parent / "splits"), "--json", str(js),
               "--save-rollouts", str(h5), "--steps", str(STEPS), "--batch-size", "2"])
    assert rc == 0
    printed = capsys.readouterr().out
    for word in ("Avg RMSE", "Final RMSE", "CD", "Params", "Rollout"):
        assert word in printed
    result = json.loads(js.read_text())
    for key in ("avg_rmse", "final_rmse", "cd", "params", "rollout_seconds", "rmse_per_step"):
        assert key in result
    assert len(result["rmse_per_step"]) == STEPS and result["params"] > 0 and result["cd"] >= 0
    assert result["final_rmse"] == pytest.approx(result["rmse_per_step"][-1])
    assert js.with_suffix(".png").is_file()
    with h5py.File(h5) as f:
        assert f["pred"].shape == (2, STEPS + 1, *tiny_scene.state_shape)
        assert list(f["case_ids"][:]) == [4, 5]
    # mismatched scene: a checkpoint is refused by name
    from nemsim.inference.checkpoint import read_checkpoint, write_checkpoint_dict
    from nemsim.scenes import SMALL

    ck = read_checkpoint(out / "best.pt")
    ck["scene"] = SMALL.to_json()
    write_checkpoint_dict(tmp_path / "wrong.pt", ck)
    rc = main(["evaluate", "--checkpoint", str(tmp_path / "wrong.pt"), "--data", str(tiny_data),
               "--setting", "control-id", "--splits", str(tiny_data.parent / "splits")])
    assert rc == 2 and "scene" in capsys.readouterr().err


def test_resume_flag_continues(tmp_path, tiny_data):
    out = tmp_path / "run"
    assert main(_train_args(tiny_data, out, "--no-test")) == 0
    args = _train_args(tiny_data, out, "--no-test", "--resume")
    args[args.index("--epochs") + 1] = "3"
    assert main(args) == 0
    assert "resumed from" in (out / "train.log").read_text()


def test_wall_budget_run_then_collect(tmp_path, tiny_data):
    """`nemsim train --max-minutes` (0.06 ms: spent by the first step) validates, tests and writes the
    summary; `nemsim bench collect` files it under its budget table with the run's steps, time and curve."""
    import csv

    out = tmp_path / "run"
    args = _train_args(tiny_data, out, "--max-minutes", "0.000001")
    args[args.index("--epochs") + 1] = "3"
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["budget_spent"] and summary["steps"] == 1 and summary["budget_minutes"] == 1e-6
    assert summary["wall_s"] >= summary["val_wall_s"] > 0 and summary["cpu_s"] > 0
    assert "wall budget of 1e-06 minutes spent at step 1" in (out / "train.log").read_text()
    (row,) = list(csv.DictReader((out / "metrics.csv").open()))
    assert row["step"] == "1" and row["val_avg_rmse"] and 0 < float(row["wall_s"]) < summary["wall_s"]
    res_path = tmp_path / "results" / "results.json"
    assert main(["bench", "collect", "--runs", str(out), "--out", str(res_path)]) == 0
    res = json.loads(res_path.read_text())
    entry = res["settings"]["control-id, 1e-06 min"]["test-standin"]
    assert entry["steps"] == 1 and entry["train_wall_s"] == summary["wall_s"] and entry["budget_min"] == 1e-6
    assert entry["avg_rmse"] == json.loads((out / "test_metrics.json").read_text())["avg_rmse"]
    assert res["curves"]["control-id, 1e-06 min"]["test-standin"]["wall_min"] == [float(row["wall_s"]) / 60]
    assert (res_path.parent / "budget_curve.png").stat().st_size > 0


def test_models_lists_params(tmp_path, capsys):
    js = tmp_path / "models.json"
    assert main(["models", "--scene", "tiny", "--json", str(js)]) == 0
    table = json.loads(js.read_text())
    assert "nemsim" in table and "test-standin" in table
    assert all(isinstance(v["params"], int) and v["params"] > 0 for v in table.values())


def test_bad_input_exit_2(tmp_path, tiny_data, capsys):
    args = _train_args(tiny_data, tmp_path / "x")
    args[args.index("--model") + 1] = "no-such-model"
    assert main(args) == 2
    assert "no-such-model" in capsys.readouterr().err
    # a bad budget or config value is a one-line error too, not a traceback
    assert main(_train_args(tiny_data, tmp_path / "y") + ["--max-steps", "0"]) == 2
    assert "max_steps" in capsys.readouterr().err
    assert main(_train_args(tiny_data, tmp_path / "y") + ["--max-minutes", "0"]) == 2
    err = capsys.readouterr().err
    assert "max_train_minutes must be None or > 0" in err and len(err.strip().splitlines()) == 1
    bad = tmp_path / "bad.yaml"
    bad.write_text("unroll_steps: 0\n")
    assert main(_train_args(tiny_data, tmp_path / "z") + ["--config", str(bad)]) == 2
    assert "unroll_steps" in capsys.readouterr().err


def _worker_errors(stderr: str) -> str:
    """A failed torchrun's message: the workers' own error lines (an abort's "terminate called ... what():"
    comes long before torchrun's summary, which a plain tail of stderr shows alone), then the tail."""
    lines = [ln for ln in stderr.splitlines()
             if any(key in ln for key in ("terminate", "what()", "Error", "Traceback", "Signal"))]
    return "\n".join(lines[-40:]) + "\n--- tail ---\n" + stderr[-3000:]


@pytest.mark.slow
def test_torchrun_ddp_two_processes(tmp_path, tiny_data):
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "nemsim.train", "--model", "nemsim", "--data", str(tiny_data), "--setting",
           "control-id", "--out", str(out), "--splits", str(tiny_data.parent / "splits"), "--epochs", "1",
           "--rollout-steps", "2", "--no-progress", "--no-test"]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, _worker_errors(res.stderr)
    assert (out / "last.pt").is_file() and (out / "best.pt").is_file()
    log = (out / "train.log").read_text()
    assert "2 ranks" in log
    # a wall budget (0.06 ms) spent at the first step: both ranks stop together (rank 0's clock decides)
    # and the run validates; a rank stopping alone would hang the other in its next all-reduce
    budget = [*cmd[:cmd.index("--out") + 1], str(tmp_path / "ddp-budget"), *cmd[cmd.index("--out") + 2:]]
    budget[budget.index("--epochs") + 1] = "3"
    res = subprocess.run([*budget, "--max-minutes", "0.000001"], env=env, capture_output=True, text=True,
                         timeout=180)
    assert res.returncode == 0, _worker_errors(res.stderr)
    summary = json.loads((tmp_path / "ddp-budget" / "summary.json").read_text())
    assert summary["budget_spent"] and summary["steps"] == 1 and summary["best_epoch"] == 1


def test_fraction_uses_data_efficiency_subset(tmp_path, tiny_data):
    out = tmp_path / "frac"
    args = _train_args(tiny_data, out, "--no-test", "--fraction", "0.5")
    args[args.index("--epochs") + 1] = "1"
    assert main(args) == 0
    log = (out / "train.log").read_text()
    assert "train / 1 val" in log and "3 train /" not in log  # fewer than the 3 training cases
    assert main([*args[:-2], "--fraction", "0.3"]) == 2  # not one of the subsets


def test_extra_data_adds_training_cases(tmp_path, tiny_data, capsys):
    import shutil

    extra = tmp_path / "extra.h5"
    shutil.copy(tiny_data, extra)  # same scene, rules and generator: all 6 complete cases are added
    out = tmp_path / "extra-run"
    args = _train_args(tiny_data, out, "--no-test", "--extra-data", str(extra))
    args[args.index("--epochs") + 1] = "1"
    assert main(args) == 0
    log = (out / "train.log").read_text()
    assert f"{extra} (6 cases)" in log
    assert "training test-standin: 45 transitions" in log  # (3 train + 6 extra cases) x 5 visible

    with h5py.File(extra, "r+") as f:  # another simulator configuration is refused, in one line
        f.attrs["generator"] = json.dumps({"config": {"voxel_nm": 2.0}})
    assert main(_train_args(tiny_data, tmp_path / "bad", "--no-test", "--extra-data", str(extra))) == 2
    assert "simulator configuration differs" in capsys.readouterr().err
    assert main(_train_args(tiny_data, tmp_path / "bad", "--extra-data", str(tmp_path / "none.h5"))) == 2
    assert "does not exist" in capsys.readouterr().err


def test_further_data_may_differ_from_the_main_file_in_domain_and_random_numbers_only(tmp_path, tiny_data):
    import shutil

    from nemsim.data.hdf5 import open_trajectories
    from nemsim.training.run import TrainInputError, _check_like_data

    files = {}
    for name, config in (("main", {"voxel_nm": 8.0, "domain": "full", "rng_mode": "stream"}),
                         ("crn", {"voxel_nm": 8.0, "domain": "quarter", "rng_mode": "counter"}),
                         ("other", {"voxel_nm": 4.0, "domain": "full", "rng_mode": "stream"})):
        files[name] = tmp_path / f"{name}.h5"
        shutil.copy(tiny_data, files[name])
        with h5py.File(files[name], "r+") as f:
            f.attrs["generator"] = json.dumps({"config": config})
    with open_trajectories(files["main"]) as tf:
        _check_like_data(files["crn"], tf, "--pair-data")  # quarter domain, common random numbers: accepted
        with pytest.raises(TrainInputError, match="simulator configuration differs"):
            _check_like_data(files["other"], tf, "--pair-data")


def test_pair_data_joins_every_batch_and_is_required_by_its_weight(tmp_path, tiny_data, capsys):
    import shutil

    pairs = tmp_path / "pairs.h5"
    shutil.copy(tiny_data, pairs)
    with h5py.File(pairs, "r+") as f:
        f["seeds"][:] = [0, 0, 2, 2, 4, 5]  # cases (0, 1) and (2, 3) are sweep pairs
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("pair_loss_weight: 1.0\npairs_per_step: 2\n")
    out = tmp_path / "pair-run"
    args = _train_args(tiny_data, out, "--no-test", "--config", str(cfg), "--pair-data", str(pairs))
    args[args.index("--epochs") + 1] = "1"
    assert main(args) == 0
    log = (out / "train.log").read_text()
    assert f"sweep pairs: {pairs} (2 pairs), 2 per step, pair_loss_weight 1" in log
    assert main(_train_args(tiny_data, tmp_path / "bad", "--no-test", "--config", str(cfg))) == 2
    assert "need --pair-data" in capsys.readouterr().err
    assert main(_train_args(tiny_data, tmp_path / "bad", "--pair-data", str(tiny_data))) == 2
    assert "no two complete cases share a simulator seed" in capsys.readouterr().err
