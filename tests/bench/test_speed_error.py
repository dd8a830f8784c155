"""`nemsim bench speed-error` and `nemsim bench collect` on a 3-case `tiny` data file, untrained checkpoint.

One simulator-generated data file (3 design cases, full tiny horizon) and one untrained NEMSim
checkpoint are shared by the module; the bench runs once (1 case, runtimes torch-f32, torch-bf16 and, when
openvino is installed, openvino-f32; throughput batch 2) through the CLI. `tiny` is odd (13 x 13), so there
the quarter-domain simulator is skipped with a note; the quarter rows and the side-by-side speed-ups run on
a one-case `small` file of 2 simulated transitions (the rest of the horizon repeats the last state) for 2
steps. The equal-accuracy interpolation and the speed-ups against both domains are checked against
hand-computed numbers. `nemsim evaluate --runtime` is scored on the same file.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from nemsim.inference.runtime import openvino_available

torch.set_num_threads(1)



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
               "--checkpoints", str(tiny_checkpoint), "--cases", "1", "--runtimes", ",".join(RUNTIMES),
               "--batch", "2", "--out", str(out)])  # fmt: skip
    assert rc == 0
    return out


RUNTIMES = ["torch-f32", "torch-bf16"] + (["openvino-f32"] if openvino_available() else [])


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def test_speed_error_report(speed_error_out):
    rep = json.loads((speed_error_out / "speed_error.json").read_text())
    assert rep["scene"] == "tiny" and rep["setting"] == "control-id" and rep["steps"] == 100
    assert rep["case_ids"] == [2]  # first test case in manifest order
    assert rep["threads"] == 1 and rep["throughput_batch"] == 2
    rows = rep["rows"]
    sims = [r for r in rows if r["kind"] == "simulator"]
    models = [r for r in rows if r["kind"] == "model"]
    assert [r["budget"] for r in sims] == [1.0, 0.5, 0.25, 0.125, 0.0625]
    # tiny is 13 x 13: the quarter domain is refused, so skipped with its reason; no quarter figures
    assert {r["domain"] for r in sims} == {"full"} and rep["sim_domains"] == ["full"]
    assert list(rep["sim_domains_skipped"]) == ["quarter"] and "even nx and ny" in rep["sim_domains_skipped"][
        "quarter"]  # fmt: skip
    assert rep["config"]["sim_domains"] == ["full", "quarter"]  # the default asked for both
    for r in rows:
        assert r["speedup_quarter"] is r["speedup_cpu_quarter"] is r["equal_accuracy_quarter"] is None
    assert rep["speed"]["simulator_quarter_s"] is None and rep["speed"]["equal_accuracy_quarter"] is None
    assert [r["runtime"] for r in models] == RUNTIMES and {r["model"] for r in models} == {"nemsim"}
    assert [r["backend"] for r in models] == [r.split("-")[0] for r in RUNTIMES]  # no fallback happened
    for r in rows:
        for key in ("wall_s", "cpu_s", "avg_rmse", "final_rmse", "cd", "avg_rmse_vs_data", "speedup",
                    "speedup_cpu", "batch_wall_s", "batch_speedup"):  # fmt: skip
            assert _finite(r[key]) and r[key] >= 0, (r["label"], key, r[key])
        assert r["wall_s"] > 0
        eq = r["equal_accuracy"]
        assert eq["bound"] in ("interpolated", "lower", "upper")
        assert _finite(eq["simulator_wall_s"]) and _finite(eq["speedup_wall"]) and _finite(eq["speedup_cpu"])
        assert eq["speedup_wall"] == pytest.approx(eq["simulator_wall_s"] / r["wall_s"])
    # the simulator does not batch: its per-trajectory time at the throughput batch is the batch-1 time
    assert all(r["batch_wall_s"] == r["wall_s"] for r in sims)
    # exactly one noise-floor row: the full-budget simulator, compared with a second full-budget seed
    floor = [r for r in rows if r["noise_floor"]]
    assert len(floor) == 1 and floor[0]["kind"] == "simulator" and floor[0]["budget"] == 1.0
    assert floor[0]["avg_rmse"] > 0  # the reference is an independent run, not the data file
    assert floor[0]["avg_rmse_vs_data"] == 0.0  # that row *is* the data file's trajectory
    assert floor[0]["speedup"] == 1.0
    assert rep["noise_floor"] == {k: floor[0][k] for k in ("avg_rmse", "final_rmse", "cd")}
    assert rep["speed"]["simulator_s"] == floor[0]["wall_s"]
    best = next(r for r in models if r["fastest"])
    assert rep["speed"]["nemsim_s"] == best["wall_s"] and rep["speed"]["nemsim_runtime"] == best["runtime"]
    assert rep["speed"]["equal_accuracy"]["speedup"] == best["equal_accuracy"]["speedup_wall"]
    assert sum(r["fastest"] for r in models) == 1 and models[0]["keeps_error"] is True
    assert models[0]["params"] > 0
    for r in models:  # timed into a reused buffer; the fresh-allocation time beside it
        assert _finite(r["wall_s_fresh_output"]) and r["wall_s_fresh_output"] > 0
    assert all(r["wall_s_fresh_output"] is None for r in sims)
    # the untrained model is far from the simulator: worse than every budget, so the equal-accuracy time is
    # the cheapest budget's, an upper bound
    assert models[0]["avg_rmse"] > max(r["avg_rmse"] for r in sims)
    cheapest = max(sims, key=lambda r: r["avg_rmse"])
    assert models[0]["equal_accuracy"]["bound"] == "upper"
    assert models[0]["equal_accuracy"]["simulator_wall_s"] == cheapest["wall_s"]


def test_speed_error_table_and_plot(speed_error_out):
    md = (speed_error_out / "speed_error.md").read_text()
    assert "| method |" in md and "noise floor (two full-budget seeds)" in md
    assert "**simulator, budget 1**" in md and "speed-up at equal accuracy" in md and "batch 2" in md
    for label in ("simulator, budget 1/2", "simulator, budget 1/8", "simulator, budget 1/16",
                  *(f"nemsim {r}" for r in RUNTIMES)):  # fmt: skip
        assert label in md
    assert "<=" in md  # the untrained model's equal-accuracy speed-up is a bound
    assert "freshly allocated trajectory" in md and "nemsim torch-f32 " in md.split("freshly allocated")[1]
    assert "The quarter-domain simulator was not measured (skipped): domain 'quarter'" in md
    assert "simulator quarter" not in md and "### Speed-ups against" not in md
    png = (speed_error_out / "speed_error.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_equal_accuracy_interpolates_log_log():
    from bench.speed_error import equal_accuracy_time

    # (Avg RMSE, seconds) of budgets 1, 1/4, 1/16; listed unsorted
    pts = [(0.04, 1.0), (0.01, 4.0), (0.02, 2.0)]
    # between 0.01 and 0.02: log t = log 4 + (log e - log 0.01) / (log 0.02 - log 0.01) * (log 2 - log 4);
    # e = 0.01 * sqrt(2) is half-way in log: t = sqrt(4 * 2) = 2.828...
    t, bound = equal_accuracy_time(pts, 0.01 * 2**0.5)
    assert bound == "interpolated" and t == pytest.approx(8**0.5)
    # e = 0.03: fraction log(1.5)/log(2) = 0.585 of the way from 2 s to 1 s: t = 2 * 0.5**0.585 = 1.3333
    t, _ = equal_accuracy_time(pts, 0.03)
    assert t == pytest.approx(2 * 0.5 ** (math.log(1.5) / math.log(2)), rel=1e-12)
    assert t == pytest.approx(4 / 3)  # the points lie on t = 0.04 / e, which log-log interpolation keeps
    assert equal_accuracy_time(pts, 0.02) == (pytest.approx(2.0), "interpolated")
    # outside the measured errors: bounds, never extrapolated
    assert equal_accuracy_time(pts, 0.005) == (4.0, "lower")
    assert equal_accuracy_time(pts, 0.08) == (1.0, "upper")
    assert equal_accuracy_time([], 0.02) == (None, "none")
    assert equal_accuracy_time(pts, float("nan")) == (None, "none")


def _sim_row(domain: str, budget: float, wall: float, err: float) -> dict:
    return {"kind": "simulator", "domain": domain, "budget": budget, "wall_s": wall, "cpu_s": wall / 2,
            "avg_rmse": err, "batch_wall_s": None}  # fmt: skip


def test_speedups_against_both_domains_side_by_side():
    """``add_speedups`` on a synthetic report: each domain's budget-1 time over the row's, and equal
    accuracy along each domain's own curve; a single quarter budget is one point (>= / <= off it)."""
    from bench.speed_error import add_speedups, format_markdown

    model = {"kind": "model", "domain": None, "budget": None, "wall_s": 0.5, "cpu_s": 0.25, "avg_rmse": 0.02,
             "batch_wall_s": 0.1}  # fmt: skip
    full = [_sim_row("full", 1.0, 8.0, 0.01), _sim_row("full", 0.25, 2.0, 0.04)]
    quarter = [_sim_row("quarter", 1.0, 3.0, 0.012)]
    rows = [*full, *quarter, model]
    add_speedups(rows)
    assert model["speedup"] == 16.0 and model["speedup_cpu"] == 16.0 and model["batch_speedup"] == 80.0
    assert model["speedup_quarter"] == 6.0 and model["speedup_cpu_quarter"] == 6.0
    assert model["batch_speedup_quarter"] == pytest.approx(30.0)
    # full curve: 0.02 is half-way in log between 0.01 (8 s) and 0.04 (2 s): 4 s, 8x the model's 0.5 s
    eq = model["equal_accuracy"]
    assert eq["bound"] == "interpolated" and eq["simulator_wall_s"] == pytest.approx(4.0)
    assert eq["speedup_wall"] == pytest.approx(8.0) and eq["speedup_cpu"] == pytest.approx(8.0)
    # one quarter point, more accurate than the model: the quarter needs at most its budget-1 time
    eq_q = model["equal_accuracy_quarter"]
    assert eq_q == {"simulator_wall_s": 3.0, "speedup_wall": 6.0, "simulator_cpu_s": 1.5, "speedup_cpu": 6.0,
                    "bound": "upper"}  # fmt: skip
    # a model more accurate than the quarter's one point: at least that time
    better = {**model, "avg_rmse": 0.011}
    add_speedups([*full, *quarter, better])
    assert better["equal_accuracy_quarter"]["bound"] == "lower"
    assert better["equal_accuracy_quarter"]["speedup_wall"] == 6.0
    # the simulator rows against each other: the quarter's budget 1 is 8 / 3 x the full domain's speed
    assert quarter[0]["speedup"] == pytest.approx(8 / 3) and quarter[0]["speedup_quarter"] == 1.0
    # no quarter rows (a report of the full domain only, or one from before the domain key): None throughout
    legacy = [{k: v for k, v in r.items() if k != "domain"} for r in full] + [dict(model)]
    add_speedups(legacy)
    assert legacy[-1]["speedup"] == 16.0 and legacy[-1]["equal_accuracy"]["bound"] == "interpolated"
    assert legacy[-1]["speedup_quarter"] is legacy[-1]["equal_accuracy_quarter"] is None
    # the side-by-side table: ">=" / "<=" marks per domain
    rep = {"scene": "s", "setting": "x", "case_ids": [0], "steps": 2, "throughput_batch": 4,
           "noise_floor": {"avg_rmse": 0.01, "cd": 0.1},
           "rows": [{**r, "label": r.get("label", "m"), "note": "", "noise_floor": False, "final_rmse": 0.0,
                     "cd": 0.0, "avg_rmse_vs_data": 0.0} for r in rows]}  # fmt: skip
    md = format_markdown(rep)
    assert "| m | 0.0200 | 16x (16x) | 6x (6x) | 8x (8x) | <=6x (<=6x) | 80x | 30x |" in md


@pytest.fixture(scope="module")
def small_sim_data(tmp_path_factory, rules):
    """A one-case `small` data file (even 26 x 26: the quarter runs) with a real full-domain generator
    record: 2 simulated transitions, the rest of the horizon the last state repeated (the bench reads 2)."""
    import numpy as np

    from nemsim.controls import lhs_design
    from nemsim.data.hdf5 import TrajectoryWriter
    from nemsim.scenes import SMALL
    from nemsim.sim import SimConfig, run_trajectory
    from nemsim.sim.generate import generator_meta

    cfg = SimConfig().resolved(SMALL)
    u = np.asarray(lhs_design()[0], dtype=np.float64)
    states = run_trajectory(SMALL, rules, u, np.random.default_rng(0), cfg, n_transitions=2).states
    states = np.concatenate([states, np.repeat(states[-1:], SMALL.n_states - len(states), axis=0)])
    root = tmp_path_factory.mktemp("speed_error_small")
    path = root / "data.h5"
    writer = TrajectoryWriter(path, scene=SMALL, case_ids=[0], controls_raw=u[None],
                              generator=generator_meta(SMALL, cfg, 0), rules_sha256=rules.sha256)  # fmt: skip
    writer.write(0, states, seed=0)
    writer.close()
    (root / "splits").mkdir()
    manifest = {"setting": "control-id", "train": [], "val": [], "test": [0], "unused": [],
                "visible_transitions": SMALL.n_transitions}  # fmt: skip
    (root / "splits" / "control-id.json").write_text(json.dumps(manifest))
    return path


@pytest.fixture(scope="module")
def small_checkpoint(tmp_path_factory, rules):
    """An untrained NEMSim checkpoint on `small`."""
    import dataclasses

    from nemsim.inference.checkpoint import save_checkpoint
    from nemsim.registry import build_model, model_config
    from nemsim.scenes import SMALL

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ckpt_small") / "small_nemsim.pt"
    save_checkpoint(path, build_model("nemsim", SMALL, rules), model_name="nemsim",
                    model_config=dataclasses.asdict(model_config("nemsim", SMALL)), scene=SMALL, rules=rules,
                    summary={"note": "untrained, for tests"}, metrics={})  # fmt: skip
    return path


def test_quarter_domain_rows_and_side_by_side_speedups(tmp_path, small_sim_data, small_checkpoint):
    """On `small` the quarter-domain simulator is timed and scored at every budget against the same
    full-domain reference, on its own seeds, and every variant reports its speed-ups against both."""
    from nemsim.cli import main

    assert main(["bench", "speed-error", "--data", str(small_sim_data), "--checkpoints",
                 str(small_checkpoint), "--cases", "1", "--steps", "2", "--budgets", "1,0.5", "--runtimes",
                 "torch-f32", "--batch", "2", "--out", str(tmp_path)]) == 0  # fmt: skip
    rep = json.loads((tmp_path / "speed_error.json").read_text())
    assert rep["sim_domains"] == ["full", "quarter"] and rep["sim_domains_skipped"] == {}
    rows = rep["rows"]
    sims = [(r["domain"], r["budget"], r["label"]) for r in rows if r["kind"] == "simulator"]
    assert sims == [("full", 1.0, "simulator, budget 1"), ("full", 0.5, "simulator, budget 1/2"),
                    ("quarter", 1.0, "simulator quarter, budget 1"),
                    ("quarter", 0.5, "simulator quarter, budget 1/2")]  # fmt: skip
    q1 = next(r for r in rows if r["label"] == "simulator quarter, budget 1")
    assert not q1["noise_floor"] and q1["avg_rmse"] > 0 and q1["avg_rmse_vs_data"] > 0  # its own stream
    assert q1["speedup_quarter"] == 1.0
    model = next(r for r in rows if r["kind"] == "model")
    assert model["speedup_quarter"] == pytest.approx(q1["wall_s"] / model["wall_s"])
    assert model["speedup_cpu_quarter"] == pytest.approx(q1["cpu_s"] / model["cpu_s"])
    assert model["batch_speedup_quarter"] == pytest.approx(q1["wall_s"] / model["batch_wall_s"])
    eq_q = model["equal_accuracy_quarter"]
    assert eq_q["bound"] in ("interpolated", "lower", "upper") and _finite(eq_q["speedup_wall"])
    sp = rep["speed"]
    assert sp["simulator_quarter_s"] == q1["wall_s"] and sp["speedup_quarter"] == model["speedup_quarter"]
    assert sp["equal_accuracy_quarter"]["speedup"] == eq_q["speedup_wall"]
    md = (tmp_path / "speed_error.md").read_text()
    assert "| simulator quarter, budget 1/2 |" in md and "### Speed-ups against the full-domain and the " \
        "quarter-domain simulator" in md and "Quarter-domain simulator at budget 1 against the same" in md
    assert "not measured" not in md


def test_bad_runtime_is_one_line_exit_2(tmp_path, tiny_sim_data, capsys):
    from nemsim.cli import main

    rc = main(["bench", "speed-error", "--data", str(tiny_sim_data), "--runtimes", "onnx-f32",
               "--out", str(tmp_path)])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "unknown runtime 'onnx-f32'" in err and "openvino-bf16" in err
    assert len(err.splitlines()) == 1


def _edited_copy(src, dst, *, unfinished: list[int], generator: dict | None = None):
    """A copy of a data file with the rows of ``unfinished`` case ids flagged unfinished (a file still being
    generated) and, if given, another ``generator`` record."""
    import shutil

    import h5py
    import numpy as np

    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        ids = [int(c) for c in np.asarray(f["case_ids"])]
        for c in unfinished:
            f["complete"][ids.index(c)] = 0
        if generator is not None:
            f.attrs["generator"] = json.dumps(generator)
    return dst


def test_incomplete_file_uses_the_complete_test_cases_and_its_recorded_simulator(tmp_path, tiny_sim_data,
                                                                                  capsys):
    """A file still being generated: the bench passes over the unfinished test case and says so; the reruns
    use the simulator configuration the file records (here the mirror reflection of files made before the
    specular lobe), not today's defaults; too few complete cases, or no record, is one line and exit 2."""
    from nemsim.cli import main
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.sim import SimConfig

    with open_trajectories(tiny_sim_data) as tf:
        generator = dict(tf.generator)
    mirror = {k: v for k, v in generator["config"].items() if k != "ion_reflect_spread_deg"}
    assert SimConfig.from_meta(mirror).ion_reflect_spread_deg == 0 != SimConfig().ion_reflect_spread_deg
    data = _edited_copy(tiny_sim_data, tmp_path / "partial.h5", unfinished=[2],
                        generator={**generator, "config": mirror})
    (tmp_path / "splits").symlink_to(tiny_sim_data.parent / "splits")  # test cases [2, 0, 1]
    base = ["bench", "speed-error", "--data", str(data), "--budgets", "1", "--steps", "2", "--batch", "0"]
    assert main([*base, "--cases", "1", "--out", str(tmp_path / "out")]) == 0
    rep = json.loads((tmp_path / "out" / "speed_error.json").read_text())
    assert rep["case_ids"] == [0] and rep["skipped_case_ids"] == [2]
    assert "Test cases [2] are not complete" in (tmp_path / "out" / "speed_error.md").read_text()
    used = SimConfig.from_meta(rep["reference"]["sim_config"])
    with open_trajectories(data) as tf:
        assert used == SimConfig.from_record(tf.generator).resolved(tf.scene)
    assert used.ion_reflect_spread_deg == 0.0
    capsys.readouterr()

    assert main([*base, "--cases", "3", "--out", str(tmp_path / "out3")]) == 2
    err = capsys.readouterr().err.strip()
    assert "holds 2 complete test cases" in err and "[2]" in err and "--cases <= 2" in err
    assert len(err.splitlines()) == 1

    bare = _edited_copy(tiny_sim_data, tmp_path / "bare.h5", unfinished=[], generator={"kind": "test"})
    base[base.index(str(data))] = str(bare)
    assert main([*base, "--cases", "1", "--out", str(tmp_path / "out4")]) == 2
    assert "records no simulator configuration" in capsys.readouterr().err


def test_default_out_is_not_the_committed_results():
    from nemsim.cli import build_parser

    args = build_parser().parse_args(["bench", "speed-error", "--data", "x.h5"])
    assert args.out == "runs/speed-error" and args.batch == 16 and args.threads == 1
    assert args.budgets == "1,0.5,0.25,0.125,0.0625" and args.sim_domains == "full,quarter"


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
    eq = res["speed"]["equal_accuracy"]  # DESIGN.md: the simulator's time at the surrogate's error, the ratio
    assert set(eq) == {"simulator_s", "speedup", "bound"} and res["speed"]["nemsim_runtime"]
    text = readme.read_text()
    assert text.startswith("# Benchmarks\n\nhand-written intro") and "### control-id" in text
    assert text.index("| nemsim |") < text.index("| fno |")  # sorted by Avg RMSE
    # a second collect replaces the table instead of appending another one
    assert main(["bench", "collect", "--runs", *runs, "--out", str(out), "--readme", str(readme)]) == 0
    assert readme.read_text().count("### control-id") == 1
    # the same (setting, model) twice is refused with exit code 2
    assert main(["bench", "collect", "--runs", runs[0], runs[0], "--out", str(out)]) == 2


def test_step_budget_runs_get_their_own_table():
    from bench.results import setting_key

    assert setting_key("control-id", {}) == "control-id"
    assert setting_key("control-id", {"train_config": {"max_steps": None, "batch_size": 24}}) == "control-id"
    assert setting_key("control-id", {"train_config": {"max_steps": 250, "batch_size": 24}}) == \
        "control-id, 250 steps x batch 24"


def test_evaluate_runtime_scores_the_compiled_graph(tmp_path, tiny_sim_data, tiny_checkpoint, capsys):
    """`nemsim evaluate --runtime` rolls out through the compiled runtime the service uses and records which
    ran: OpenVINO f32 agrees with PyTorch f32 (the same graph), bf16 is close, and a GPU device is refused."""
    from nemsim.cli import main

    args = ["evaluate", "--checkpoint", str(tiny_checkpoint), "--data", str(tiny_sim_data), "--setting",
            "control-id", "--no-cd", "--batch-size", "2"]  # fmt: skip
    scores = {}
    for rt in RUNTIMES:
        js = tmp_path / f"{rt}.json"
        assert main([*args, "--runtime", rt, "--json", str(js)]) == 0
        result = json.loads(js.read_text())
        assert result["runtime"] == rt and result["n_cases"] == 3
        assert f"{rt})" in capsys.readouterr().out
        scores[rt] = result["avg_rmse"]
    assert scores["torch-bf16"] == pytest.approx(scores["torch-f32"], rel=0.05)
    if "openvino-f32" in scores:
        assert scores["openvino-f32"] == pytest.approx(scores["torch-f32"], rel=1e-4)
    assert main([*args, "--runtime", "openvino-f32", "--device", "cuda"]) == 2
    assert "CPU only" in capsys.readouterr().err
