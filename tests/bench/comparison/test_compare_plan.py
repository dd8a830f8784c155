"""The comparison plan: parsing and its errors, the shipped plan's sizes, the state of every run, and the
choices deferred to probes (lowest validation Avg RMSE) and to the ranking of the baselines."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
import torch

from bench.comparison.plan import Choice, PlanError, format_status, plan_status, read_plan, record_run
from nemsim.cli import main
from nemsim.training.loop import CSV_FIELDS

ROOT = Path(__file__).resolve().parents[3]
SHIPPED = ROOT / "benchmarks" / "small" / "compare-45min.plan.yaml"


def _run(d: Path, vals=(), budget: float | None = None, wall_s: float = 60.0, test: bool = True,
         last_wall_s: float | None = None) -> Path:
    """A run directory as `nemsim train` leaves it: metrics.csv with these validation scores; summary.json
    (a finished run of ``budget`` minutes) and test_metrics.json if ``budget``; last.pt if ``last_wall_s``."""
    d.mkdir(parents=True)
    with (d / "metrics.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        for i, v in enumerate(vals):
            w.writerow({"epoch": i + 1, "step": 2 * (i + 1), "val_avg_rmse": v})
    if budget is not None:
        (d / "summary.json").write_text(json.dumps({"budget_minutes": budget, "wall_s": wall_s,
                                                    "select_metric": "avg_rmse", "best_val": min(vals)}))
        if test:
            (d / "test_metrics.json").write_text(json.dumps({"avg_rmse": 0.5, "setting": "control-id"}))
    if last_wall_s is not None:
        state = {"format_version": 1, "model_state": {}, "train_state": {"wall_s": last_wall_s}}
        torch.save(state, d / "last.pt")
    return d


def test_the_shipped_plan(rules):
    """35 runs: 20 probes (5 core-hours), 15 full runs; every baseline's matched size within 10 % of NEMSim's
    parameter count on `small`, its paper size the registered default."""
    from nemsim.evaluation.metrics import count_params
    from nemsim.registry import build_model
    from nemsim.scenes import SMALL

    plan = read_plan(SHIPPED)
    probes = [e for e in plan.entries if e.probe]
    full = [e for e in plan.entries if not e.probe]
    assert len(probes) == 20 and len(full) == 15
    assert sum(e.minutes for e in probes) / 60 == 5.0 and {e.minutes for e in full} == {45.0}
    assert {e.model for e in probes} == set(plan.baselines) == {"deeponet", "fno", "cno", "uno", "convlstm"}
    assert sorted({e.setting for e in full}) == ["control-id", "ood-joint", "vis-50"]
    assert plan.recipe.name == "compare-45min.train.yaml" and str(plan.data) == "data/small.h5"
    nemsim = count_params(build_model("nemsim", SMALL, rules))
    for model in plan.baselines:
        n = count_params(build_model(model, SMALL, rules, plan.overrides(model, "matched")))
        assert abs(n / nemsim - 1) < 0.1, (model, n, nemsim)


@pytest.mark.parametrize("runs, sizes, message", [
    ("  - {name: a, model: fno, minutes: 1, colour: red}\n", None, "unknown keys ['colour']"),
    ("  - {name: a, model: nope, minutes: 1}\n", None, "unknown model 'nope'"),
    ("  - {name: a, model: fno, minutes: 0}\n", None, "minutes must be a number > 0"),
    ("  - {name: a, model: fno, minutes: 1, setting: ood-x}\n", None, "unknown setting 'ood-x'"),
    ("  - {name: A b, model: fno, minutes: 1}\n", None, "lower-case"),
    ("  - {name: a, model: fno, minutes: 1, size: huge}\n", None, "no size 'huge' for fno"),
    ("  - {name: a, model: fno, minutes: 1}\n  - {name: a, model: cno, minutes: 1}\n", None,
     "repeats run 'a'"),
    ("  - {name: a, model: fno, minutes: 1}\n  - {name: b, model: fno, minutes: 1}\n", None,
     "repeats run 'a'"),
    ("  - {name: a, model: fno, minutes: 1, from_probes: true}\n", None, "no probe of fno"),
    ("  - {name: a, model: fno, minutes: 1, from_probes: true, lr: 0.1}\n", None, "remove size, lr"),
    ("  - {name: a, models_from: best_of(2), minutes: 1}\n", None, "best_baselines(N)"),
    ("  - {name: a, models_from: best_baselines(3), minutes: 1}\n", None, "best_baselines(3) of 2 baselines"),
    ("  - {name: a, models_from: best_baselines(1), setting: vis-50, minutes: 1}\n", None,
     "ranks one control-id full run per baseline; fno has 0"),
    ("  - {name: a, model: fno, minutes: 1}\n", "{fno: {small: {depth: 3}}}",
     "sizes.fno.small: unknown config key"),
])  # fmt: skip
def test_plan_errors_name_the_run(write_plan, runs, sizes, message):
    plan = write_plan(runs, sizes=sizes) if sizes else write_plan(runs)
    with pytest.raises(PlanError) as err:
        read_plan(plan)
    assert message in str(err.value) and str(plan) in str(err.value)


def test_plan_error_is_one_line_on_the_command_line(write_plan, capsys):
    plan = write_plan("  - {name: a, model: nope, minutes: 1}\n")
    assert main(["bench", "compare", "--plan", str(plan), "--status"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "unknown model 'nope'" in err and "Traceback" not in err


def test_status_of_done_partial_pending_and_blocked_runs(write_plan, tmp_path):
    plan = read_plan(write_plan(
        "  - {name: p-small, probe: true, model: fno, size: small, lr: 1.0e-3, minutes: 1}\n"
        "  - {name: p-paper, probe: true, model: fno, lr: 1.0e-3, minutes: 1}\n"
        "  - {name: control-id-fno, model: fno, minutes: 1, from_probes: true}\n"
        "  - {name: control-id-cno, model: cno, minutes: 1}\n"
        "  - {name: ood-joint-nemsim, model: nemsim, setting: ood-joint, minutes: 2}\n"
    ))  # fmt: skip
    runs = tmp_path / "runs"
    _run(plan.record / "probes" / "p-small", [0.2, 0.1, 0.15], budget=1, wall_s=61.0, test=False)
    _run(runs / "probes" / "p-paper", [0.3], last_wall_s=30.0)
    # a finished run of another budget is partial: --resume goes on to the plan's budget
    _run(runs / "full" / "ood-joint" / "nemsim", [0.4], budget=1, wall_s=60.0)
    by = {s.entry.name: s for s in plan_status(plan, runs)}
    assert by["p-small"].state == "done" and by["p-small"].recorded
    assert by["p-small"].spent_min == pytest.approx(61 / 60) and by["p-small"].best_val == 0.1
    assert by["p-paper"].state == "partial" and by["p-paper"].spent_min == 0.5
    assert by["p-paper"].best_val == 0.3
    assert by["control-id-fno"].state == "blocked-on-probes" and by["control-id-fno"].choice is None
    assert by["control-id-cno"].state == "pending"
    assert by["control-id-cno"].choice == Choice("cno", "paper", None)
    assert by["ood-joint-nemsim"].state == "partial" and by["ood-joint-nemsim"].spent_min == 1.0
    table = format_status(list(by.values()))
    assert "control-id-fno" in table and "blocked-on-probes" in table
    assert table.splitlines()[-1] == ("5 runs: 1 done, 2 partial, 1 blocked-on-probes, 1 pending; "
                                      "0.0 of 0.1 core-hours of budget spent")  # fmt: skip


def test_a_full_run_takes_the_probe_with_the_lowest_validation_score(write_plan, tmp_path):
    plan = read_plan(write_plan(
        "  - {name: p1, probe: true, model: fno, size: small, lr: 1.0e-3, minutes: 1}\n"
        "  - {name: p2, probe: true, model: fno, size: paper, lr: 2.0e-3, minutes: 1}\n"
        "  - {name: p3, probe: true, model: fno, size: small, lr: 4.0e-3, minutes: 1}\n"
        "  - {name: control-id-fno, model: fno, minutes: 1, from_probes: true}\n"
    ))  # fmt: skip
    runs = tmp_path / "runs"
    _run(runs / "probes" / "p1", [0.3, 0.08], budget=1, test=False)
    _run(runs / "probes" / "p2", [0.05, 0.09], budget=1, test=False)  # best early, worse at the end
    _run(runs / "probes" / "p3", [math.nan, 0.07], budget=1, test=False)  # a diverged validation is ignored
    (full,) = [s for s in plan_status(plan, runs) if s.entry.name == "control-id-fno"]
    assert full.state == "pending" and full.choice == Choice("fno", "paper", 2.0e-3)
    _run(runs / "full" / "control-id" / "fno", [0.04], budget=1)
    (full,) = [s for s in plan_status(plan, runs) if s.entry.name == "control-id-fno"]
    assert full.state == "done" and not full.recorded
    kept = record_run(full, runs, plan.record)
    assert kept == plan.record / "full" / "control-id" / "fno"
    assert sorted(p.name for p in kept.iterdir()) == ["metrics.csv", "summary.json", "test_metrics.json"]
    (full,) = [s for s in plan_status(plan, runs) if s.entry.name == "control-id-fno"]
    assert full.recorded and record_run(full, runs, plan.record) is None


def test_best_baselines_are_ranked_by_their_control_id_runs(write_plan, tmp_path):
    plan = read_plan(write_plan(
        "  - {name: control-id-fno, model: fno, size: small, lr: 1.0e-3, minutes: 1}\n"
        "  - {name: control-id-cno, model: cno, minutes: 1}\n"
        "  - {name: vis-50-baseline, models_from: best_baselines(2), setting: vis-50, minutes: 1}\n"
    ))  # fmt: skip
    runs = tmp_path / "runs"
    _run(runs / "full" / "control-id" / "fno", [0.2], budget=1)
    states = {s.entry.name: s for s in plan_status(plan, runs)}
    assert [states[f"vis-50-baseline-{k}"].state for k in (1, 2)] == ["blocked-on-runs"] * 2
    _run(runs / "full" / "control-id" / "cno", [0.1], budget=1)
    states = {s.entry.name: s for s in plan_status(plan, runs)}
    assert states["vis-50-baseline-1"].choice == Choice("cno", "paper", None)
    assert states["vis-50-baseline-2"].choice == Choice("fno", "small", 1.0e-3)
    assert states["vis-50-baseline-1"].state == "pending"
