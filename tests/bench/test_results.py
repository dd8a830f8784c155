"""`nemsim bench collect` on hand-written run directories: per-setting budget tables, the budget fields taken
from each run's summary.json, the validation curves from metrics.csv and their figure."""

from __future__ import annotations

import csv
import json

from bench.results import setting_key
from nemsim.cli import main
from nemsim.training.loop import CSV_FIELDS

BUDGET = {"max_train_minutes": 45.0, "max_steps": None, "batch_size": 24}


def _run_dir(root, name, setting, avg, train_config, summary=None, rows=()):
    """A run directory as `nemsim train` leaves it: test_metrics.json, summary.json, metrics.csv."""
    d = root / name
    d.mkdir(parents=True)
    (d / "test_metrics.json").write_text(json.dumps({
        "avg_rmse": avg, "final_rmse": 2 * avg, "cd": 0.5, "params": 250_000, "rollout_seconds": 1.0,
        "rollout_seconds_per_case": 0.2, "n_cases": 10, "steps": 100, "setting": setting,
    }))  # fmt: skip
    if summary is not None:
        (d / "summary.json").write_text(json.dumps({**summary, "train_config": train_config}))
    with (d / "metrics.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        for row in rows:
            w.writerow({k: row.get(k, "") for k in CSV_FIELDS})
    return str(d)


def _summary(steps, wall_s, cpu_s, loss):
    return {"steps": steps, "wall_s": wall_s, "cpu_s": cpu_s, "final_train_loss": loss,
            "budget_minutes": 45.0, "budget_spent": True}


def test_setting_key_names_the_budget():
    assert setting_key("ood-joint", {"train_config": BUDGET}) == "ood-joint, 45 min"
    assert setting_key("vis-50", {"train_config": {**BUDGET, "max_train_minutes": 7.5}}) == "vis-50, 7.5 min"
    both = {"train_config": {**BUDGET, "max_steps": 150}}
    assert setting_key("control-id", both) == "control-id, 45 min, 150 steps x batch 24"


def test_collect_budget_tables_fields_and_curve(tmp_path, capsys):
    rows_nemsim = [  # validated at 10 and 30 min; the epoch row at 20 min has no validation
        {"epoch": 1, "step": 100, "train_loss": 0.02, "val_avg_rmse": 0.05, "wall_s": 600.0, "cpu_s": 590.0},
        {"epoch": 2, "step": 200, "train_loss": 0.01, "wall_s": 1200.0, "cpu_s": 1180.0},
        {"epoch": 3, "step": 300, "train_loss": 0.008, "val_avg_rmse": 0.03, "wall_s": 1800.0,
         "cpu_s": 1770.0},
    ]
    rows_fno = [{"epoch": 1, "step": 40, "train_loss": 0.05, "val_avg_rmse": 0.09, "wall_s": 2700.0,
                 "cpu_s": 2650.0}]  # fmt: skip
    runs = [
        _run_dir(tmp_path / "cid", "nemsim", "control-id", 0.02, BUDGET,
                 _summary(310, 2760.0, 2700.0, 0.0075), rows_nemsim),
        _run_dir(tmp_path / "cid", "fno", "control-id", 0.06, BUDGET, _summary(41, 2790.0, 2750.0, 0.04),
                 rows_fno),
        _run_dir(tmp_path / "vis", "nemsim", "vis-50", 0.03, BUDGET, _summary(305, 2750.0, 2690.0, 0.009),
                 rows_nemsim[:1]),
        # a run from before summary.json and wall times: its own (unbudgeted) table, no curve
        _run_dir(tmp_path / "old", "deeponet", "control-id", 0.05, {}, None,
                 [{"epoch": 1, "step": 10, "train_loss": 0.1, "val_avg_rmse": 0.2}]),
    ]
    speed = tmp_path / "speed_error.json"
    fastest = {"simulator_s": 3.0, "nemsim_s": 0.5, "nemsim_runtime": "openvino-bf16",
               "nemsim_checkpoint": "checkpoints/x.pt", "equal_accuracy": {"speedup": 4.0, "bound": "lower"}}
    speed.write_text(json.dumps({"noise_floor": {"avg_rmse": 0.01, "cd": 0.2}, "case_ids": [1, 2],
                                 "setting": "control-id", "scene": "small", "speed": fastest}))  # fmt: skip
    out = tmp_path / "bench" / "results.json"
    assert main(["bench", "collect", "--runs", *runs, "--speed-error", str(speed), "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert set(res["settings"]) == {"control-id, 45 min", "vis-50, 45 min", "control-id"}
    table = res["settings"]["control-id, 45 min"]
    assert set(table) == {"nemsim", "fno"}
    keys = ("avg_rmse", "budget_min", "steps", "final_train_loss", "train_wall_s", "train_cpu_s")
    assert [table["nemsim"][k] for k in keys] == [0.02, 45.0, 310, 0.0075, 2760.0, 2700.0]
    assert table["fno"]["steps"] == 41 and res["settings"]["vis-50, 45 min"]["nemsim"]["steps"] == 305
    old = res["settings"]["control-id"]["deeponet"]
    assert old["steps"] == 10 and old["budget_min"] is None and old["train_wall_s"] is None  # metrics.csv
    none = {"train_minutes": None, "max_steps": None, "batch_size": None}
    assert res["budget"]["control-id, 45 min"] == {**none, "train_minutes": 45.0}
    assert res["budget"]["control-id"] == none
    # curves: validated rows only, wall minutes when the validated weights were reached
    curve = res["curves"]["control-id, 45 min"]["nemsim"]
    assert curve == {"wall_min": [10.0, 30.0], "cpu_min": [590 / 60, 1770 / 60], "steps": [100, 300],
                     "val_avg_rmse": [0.05, 0.03]}  # fmt: skip
    assert res["curves"]["control-id, 45 min"]["fno"]["wall_min"] == [45.0]
    assert "control-id" not in res["curves"]  # no wall times recorded
    figure = out.parent / "budget_curve.png"
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and figure.stat().st_size > 10_000
    text = (out.parent / "README.md").read_text()
    assert "| train steps | train wall min | train CPU min | final train loss |" in text
    assert "| nemsim | 0.0200 | 0.0400 | 0.500 | 0.250 | 0.2 | 2.00 | 310 | 46.0 | 45.0 | 7.500e-03 |" in text
    assert "](budget_curve.png)" in text
    assert ("(`nemsim bench speed-error`, x.pt, openvino-bf16, batch 1): simulator 3 s per trajectory, "
            "NEMSim 0.5 s, 6.0x faster; at equal accuracy (the simulator's time at NEMSim's error) "
            ">= 4.0x.") in text
    assert text.index("### control-id, 45 min") < text.index("| nemsim | 0.0200") < text.index("| fno |")
    assert "budget_curve.png" in capsys.readouterr().out


def test_collect_without_curves_writes_no_figure(tmp_path, capsys):
    run = _run_dir(tmp_path, "cno", "control-id", 0.1, {}, None, [])
    out = tmp_path / "results.json"
    assert main(["bench", "collect", "--runs", run, "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["curves"] == {} and res["settings"]["control-id"]["cno"]["steps"] is None
    assert not (tmp_path / "budget_curve.png").exists()
    assert "no budget_curve.png" in capsys.readouterr().out.replace(str(tmp_path) + "/", "")



def test_collect_names_multistep_models_apart(tmp_path):
    """Runs of one model differing in steps_per_call are separate rows ("nemsim (k=5)"), not refused."""
    import torch

    runs = []
    for k in (1, 5):
        summary = _summary(100, 60.0, 59.0, 0.01)
        d = _run_dir(tmp_path, f"k{k}", "control-id", 0.02 + 0.01 * k, BUDGET, summary)
        torch.save({"format_version": 1, "model_name": "nemsim", "model_config": {"steps_per_call": k},
                    "model_state": {}},
                   f"{d}/best.pt")
        runs.append(d)
    out = tmp_path / "results.json"
    assert main(["bench", "collect", "--runs", *runs, "--out", str(out)]) == 0
    table = json.loads(out.read_text())["settings"]["control-id, 45 min"]
    assert set(table) == {"nemsim", "nemsim (k=5)"}
    assert table["nemsim (k=5)"]["avg_rmse"] == 0.07
