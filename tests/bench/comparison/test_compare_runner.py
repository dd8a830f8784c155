"""`nemsim bench compare` end to end on tiny data: real `nemsim train` subprocesses with a budget of about a
second, the record of finished runs, a rerun that starts nothing, the missing-data refusal, SIGTERM."""

from __future__ import annotations

import json
import os
import signal
import threading
import time

import pytest
import yaml

from bench.comparison.plan import PlanError, plan_status, read_plan
from bench.comparison.runner import RunnerConfig, run_plan
from nemsim.cli import main

TWO_RUNS = (
    "  - {name: probe-fno-small, probe: true, model: fno, size: small, lr: 2.0e-3, minutes: 0.02}\n"
    "  - {name: control-id-nemsim, model: nemsim, minutes: 0.02}\n"
)


def _compare(plan, runs, *extra):
    return main(["bench", "compare", "--plan", str(plan), "--runs-dir", str(runs), "--cores", "0", *extra])


@pytest.mark.slow
def test_a_two_run_plan_completes_and_a_rerun_does_nothing(write_plan, tmp_path, capsys):
    plan, runs = write_plan(TWO_RUNS), tmp_path / "runs"
    assert _compare(plan, runs, "--jobs", "2") == 0
    out = capsys.readouterr().out
    assert out.count("] start ") == 2 and out.count(": done, ") == 2, out
    probe, full = runs / "probes" / "probe-fno-small", runs / "full" / "control-id" / "nemsim"
    for d in (probe, full):
        assert (d / "last.pt").is_file() and (d / "train.log").is_file() and (d / "console.log").is_file()
        assert "--resume: no" in (d / "train.log").read_text()  # started fresh, through --resume
    assert not (probe / "test_metrics.json").exists() and (full / "test_metrics.json").is_file()
    cfg = yaml.safe_load((probe / "config.yaml").read_text())
    assert cfg["lr"] == 2.0e-3 and cfg["max_train_minutes"] == 0.02 and cfg["model"] == {"width": 4}
    assert cfg["batch_size"] == 2  # the recipe's
    record = tmp_path / "record"
    assert (record / "probes" / "probe-fno-small" / "summary.json").is_file()
    assert {p.name for p in (record / "full" / "control-id" / "nemsim").iterdir()} == {
        "config.yaml", "metrics.csv", "summary.json", "test_metrics.json"}  # fmt: skip
    statuses = plan_status(read_plan(plan), runs)
    assert [(s.state, s.recorded) for s in statuses] == [("done", True)] * 2
    # the record alone (no best.pt) makes the results table, the model named by its directory
    res = tmp_path / "results" / "results.json"
    kept = record / "full" / "control-id" / "nemsim"
    assert main(["bench", "collect", "--runs", str(kept), "--out", str(res)]) == 0
    assert list(json.loads(res.read_text())["settings"]["control-id, 0.02 min"]) == ["nemsim"]
    assert all(s.spent_min is not None and s.spent_min >= 0.02 for s in statuses)

    mtime = (full / "last.pt").stat().st_mtime_ns
    assert _compare(plan, runs, "--jobs", "2") == 0
    out = capsys.readouterr().out
    assert "start" not in out and "2 runs: 2 done" in out
    assert (full / "last.pt").stat().st_mtime_ns == mtime
    # a fresh machine: the runs dir is gone, the record says both are done
    assert _compare(plan, tmp_path / "fresh", "--status") == 0
    assert "2 runs: 2 done" in capsys.readouterr().out


def test_missing_data_is_refused_naming_the_commands(write_plan, tmp_path, capsys):
    missing = tmp_path / "no" / "small.h5"
    plan = write_plan(TWO_RUNS, data=missing)
    assert _compare(plan, tmp_path / "runs") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err == (f"nemsim bench compare: {missing} does not exist: make it with `nemsim generate --scene "
                   f"tiny --out {missing}` then `nemsim splits --data {missing}`")  # fmt: skip
    assert not (tmp_path / "runs").exists()
    assert _compare(plan, tmp_path / "runs", "--dry-run") == 0  # shows what would run, writes nothing
    assert "would run probe-fno-small at +0 min" in capsys.readouterr().out
    assert not (tmp_path / "runs").exists()


def test_dry_run_follows_jobs_and_hours(write_plan, tmp_path, capsys):
    plan = write_plan(
        "  - {name: probe-a, probe: true, model: fno, size: small, lr: 2.0e-3, minutes: 15}\n"
        "  - {name: probe-b, probe: true, model: fno, size: small, lr: 5.0e-4, minutes: 15}\n"
        "  - {name: control-id-nemsim, model: nemsim, minutes: 45}\n"
    )
    # one slot, 40 min: probe-a at +0 (17 min with its margin), probe-b at +17, the 60-min run does not fit
    assert _compare(plan, tmp_path / "runs", "--dry-run", "--hours", "0.67") == 0
    out = capsys.readouterr().out
    assert "would run probe-a at +0 min" in out and "would run probe-b at +17 min" in out
    assert "would not start control-id-nemsim" in out
    # two slots, no limit: both probes at once, then the full run on the slot free first
    assert _compare(plan, tmp_path / "runs", "--dry-run", "--jobs", "2") == 0
    out = capsys.readouterr().out
    assert "would run probe-b at +0 min" in out and "would run control-id-nemsim at +17 min" in out


def test_a_started_run_keeps_its_configuration(write_plan, tmp_path):
    runs = tmp_path / "runs"
    plan = read_plan(write_plan(TWO_RUNS))
    d = runs / "probes" / "probe-fno-small"
    d.mkdir(parents=True)
    (d / "config.yaml").write_text("lr: 0.5\n")
    (d / "last.pt").write_bytes(b"")
    lines: list[str] = []
    failed = run_plan(plan, RunnerConfig(runs_dir=runs, cores=(0,), only=("probe-fno-small",)), lines.append)
    assert failed == 1 and "the run started with other" in "\n".join(lines)
    with pytest.raises(PlanError, match="no run named 'nope'"):
        run_plan(plan, RunnerConfig(runs_dir=runs, only=("nope",)), lines.append)


def _processes_mentioning(text: str) -> list[int]:
    """Pids of live processes whose command line contains ``text``."""
    pids = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            cmdline = open(f"/proc/{pid}/cmdline", "rb").read().decode(errors="replace")
        except OSError:
            continue
        if text in cmdline:
            pids.append(int(pid))
    return pids


@pytest.mark.slow
@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc to find the children")
def test_sigterm_stops_the_runs_and_a_rerun_resumes_them(write_plan, tmp_path):
    """SIGTERM to the runner stops its child (state partial: its last.pt is kept) and ends in
    KeyboardInterrupt (the CLI's exit 130); the rerun resumes the same budget from last.pt and finishes.
    The budget (0.3 min) is long against the first checkpoint (2 steps) so that on a loaded machine the
    child is still running when the signal arrives."""
    plan = read_plan(write_plan("  - {name: control-id-nemsim, model: nemsim, minutes: 0.3}\n"))
    runs = tmp_path / "runs"
    out = runs / "full" / "control-id" / "nemsim"

    def terminate_once_checkpointed() -> None:
        end = time.monotonic() + 60
        while not (out / "last.pt").is_file() and time.monotonic() < end:
            time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGTERM)

    # SIGINT ignored, as another caller in the process may leave it: the children must not inherit that
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=terminate_once_checkpointed, daemon=True).start()
    lines: list[str] = []
    cfg = RunnerConfig(runs_dir=runs, cores=(0,), poll_s=0.05)
    try:
        with pytest.raises(KeyboardInterrupt):
            run_plan(plan, cfg, lines.append)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert any("stopped control-id-nemsim" in ln for ln in lines)
    assert _processes_mentioning(str(out)) == []
    (status,) = plan_status(plan, runs)
    spent_before = status.spent_min or 0
    assert status.state == "partial" and 0 < spent_before < 0.3

    assert run_plan(plan, cfg, lines.append) == 0
    (status,) = plan_status(plan, runs)
    assert status.state == "done" and status.recorded and status.spent_min > spent_before  # resumed
    assert "resumed from" in (out / "train.log").read_text()
    # it ended by its budget, or (on an idle, fast core) by its last epoch before the budget was spent
    from nemsim.training.config import TrainConfig

    summary = json.loads((out / "summary.json").read_text())
    assert summary["budget_spent"] or summary["epochs"] == TrainConfig().max_epochs


def test_one_runner_at_a_time_per_runs_dir(write_plan, tmp_path):
    import fcntl

    from bench.comparison.runner import LOCK

    runs = tmp_path / "runs"
    runs.mkdir()
    plan = read_plan(write_plan(TWO_RUNS))
    with (runs / LOCK).open("w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(PlanError, match="another `nemsim bench compare` is running in"):
            run_plan(plan, RunnerConfig(runs_dir=runs, cores=(0,)), print)
    assert not (runs / "probes").exists()


def test_a_training_key_added_since_a_run_started_keeps_its_default():
    """A started run's config.yaml written before a TrainConfig field existed (here ``ema_decay``) still
    matches the plan when the plan gives the field's default, and not when it gives another value."""
    from dataclasses import asdict

    from bench.comparison.runner import config_changes
    from nemsim.training.config import TrainConfig

    now = {**asdict(TrainConfig(lr=2e-3)), "model": {"width": 10}}
    stored = {k: v for k, v in now.items() if k != "ema_decay"}
    assert config_changes(stored, now) == []
    assert config_changes(stored, {**now, "ema_decay": 0.999}) == ["ema_decay"]
    assert config_changes({**stored, "lr": 5e-4}, now) == ["lr"]
