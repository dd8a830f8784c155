"""The command line's error boundary and user-facing defaults.

Every failure on bad input or a damaged file is one line on stderr with exit code 2 and no traceback; an
unexpected exception is one line with exit code 1 and a hint to rerun with --debug, which shows the traceback.
Most cases call ``main(argv)`` in-process; one runs the installed entry point in a subprocess.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nemsim import cli
from nemsim.cli import main

N_CASES = 4


@pytest.fixture(scope="session")
def data_file(tmp_path_factory, tiny_scene, synthetic_states) -> Path:
    """A tiny-scene trajectory file of N_CASES synthetic cases (ids 0..3), no splits next to it."""
    from nemsim.controls import lhs_design
    from nemsim.data.hdf5 import TrajectoryWriter
    from nemsim.rules import compile_rules, load_rules

    path = tmp_path_factory.mktemp("clidata") / "tiny.h5"
    raw = lhs_design(N_CASES, seed=1)
    with TrajectoryWriter(path, scene=tiny_scene, case_ids=range(N_CASES), controls_raw=raw,
                          generator={"kind": "synthetic-test"},
                          rules_sha256=compile_rules(load_rules()).sha256) as w:  # fmt: skip
        for row in range(N_CASES):
            w.write(row, synthetic_states(tiny_scene, 0.02 * (row + 1)), seed=row)
    return path


@pytest.fixture(scope="session")
def damaged(tmp_path_factory, data_file, tiny_checkpoint) -> dict[str, Path]:
    """Damaged copies: .h5 truncated to half and with its middle third zeroed; .pt truncated and garbage."""
    root = tmp_path_factory.mktemp("damaged")
    h5, pt = data_file.read_bytes(), Path(tiny_checkpoint).read_bytes()
    out = {
        "trunc_h5": root / "trunc.h5",
        "zeroed_h5": root / "zeroed.h5",
        "trunc_pt": root / "trunc.pt",
        "garbage_pt": root / "garbage.pt",
    }
    out["trunc_h5"].write_bytes(h5[: len(h5) // 2])
    n = len(h5)
    out["zeroed_h5"].write_bytes(h5[: n // 3] + bytes(n // 3) + h5[2 * (n // 3) :])
    out["trunc_pt"].write_bytes(pt[: len(pt) // 2])
    out["garbage_pt"].write_bytes(b"not a checkpoint\n" * 50)
    return out


def _fails_cleanly(capsys, argv: list[str], code: int = 2) -> str:
    """Run the CLI; assert the exit code, exactly one stderr line and no traceback; return that line."""
    capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's usage errors exit from parse_args
        rc = exc.code
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == code, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


# ---- item 1: output folders are created --------------------------------------------------------------------


def test_design_creates_missing_parent_dirs(tmp_path):
    out = tmp_path / "fresh" / "data" / "design.csv"
    assert main(["design", "--n", "5", "--out", str(out)]) == 0
    assert len(out.read_text().splitlines()) == 6  # header + 5 cases
    npz = tmp_path / "new" / "rules.npz"
    assert main(["rules", "compile", "--out", str(npz)]) == 0 and npz.is_file()


def test_design_log_angles_writes_the_log_m_design(tmp_path, capsys):
    from nemsim.controls import lhs_design, read_controls_csv

    out = tmp_path / "log-angles.csv"
    assert main(["design", "--kind", "lhs-log-angles", "--n", "40", "--seed", "5", "--out", str(out)]) == 0
    np.testing.assert_allclose(read_controls_csv(out), lhs_design(40, 5, log_angles=True), rtol=1e-12)
    assert "ion exponents log m" in capsys.readouterr().out


def test_design_corners_leave_out_the_physics_benchmarks_held_out_corners(tmp_path, capsys):
    from bench.physics import PhysicsConfig, box_corners
    from nemsim.controls import read_controls_csv

    out = tmp_path / "corners.csv"
    assert main(["design", "--kind", "corners", "--n", "50", "--seed", "1", "--out", str(out)]) == 0
    raw = read_controls_csv(out)
    held_out = box_corners(PhysicsConfig.corners, PhysicsConfig.heldout_seed)
    assert raw.shape == (50, 14) and not any(np.array_equal(r, h) for r in raw for h in held_out)
    assert "random box corners" in capsys.readouterr().out
    assert main(["design", "--kind", "corners", "--n", "99999", "--out", str(out)]) == 2
    assert "distinct corners" in capsys.readouterr().err


# ---- item 2: splits of a data file, and manifests that do not fit ------------------------------------------


def test_splits_from_data_file_use_its_case_ids_and_horizon(tmp_path, data_file, tiny_scene):
    out = tmp_path / "splits"
    assert main(["splits", "--data", str(data_file), "--out", str(out)]) == 0
    m = json.loads((out / "control-id.json").read_text())
    assert sorted(m["train"] + m["val"] + m["test"]) == list(range(N_CASES))
    assert m["visible_transitions"] == tiny_scene.n_transitions


def test_default_splits_that_do_not_fit_the_data_file_say_what_to_do(
    tmp_path, capsys, data_file, tiny_checkpoint
):
    data = tmp_path / "tiny.h5"
    shutil.copy(data_file, data)
    design = tmp_path / "design.csv"
    assert main(["design", "--n", "50", "--out", str(design)]) == 0
    assert main(["splits", "--design", str(design), "--out", str(tmp_path / "splits")]) == 0
    for argv in (
        ["evaluate", "--checkpoint", tiny_checkpoint, "--data", data, "--setting", "control-id"],
        [
            "train",
            "--model",
            "nemsim",
            "--data",
            data,
            "--setting",
            "control-id",
            "--out",
            tmp_path / "run",
            "--max-steps",
            "1",
            "--no-progress",
        ],
    ):
        line = _fails_cleanly(capsys, argv)
        assert "does not fit" in line and f"nemsim splits --data {data}" in line


# ---- item 6: values out of range ---------------------------------------------------------------------------


def test_splits_transitions_zero_is_refused(tmp_path, capsys, data_file):
    line = _fails_cleanly(
        capsys, ["splits", "--data", data_file, "--out", tmp_path / "s", "--transitions", "0"]
    )
    assert "--transitions" in line
    assert not (tmp_path / "s").exists()


def test_evaluate_negative_steps_is_refused(capsys, data_file, tiny_checkpoint):
    line = _fails_cleanly(
        capsys,
        [
            "evaluate",
            "--checkpoint",
            tiny_checkpoint,
            "--data",
            data_file,
            "--setting",
            "control-id",
            "--steps",
            "-4",
        ],
    )
    assert "--steps must be in [1," in line


def test_usage_error_is_one_line(capsys):
    line = _fails_cleanly(capsys, ["evaluate", "--checkpoint", "x.pt", "--data", "y.h5", "--setting", "nope"])
    assert "invalid choice" in line and "nemsim evaluate --help" in line


# ---- item 3: damaged files ---------------------------------------------------------------------------------


def test_data_check_reports_a_damaged_file(capsys, damaged):
    line = _fails_cleanly(capsys, ["data", "check", damaged["zeroed_h5"]])
    assert line.startswith("nemsim data check: ") and "damaged" in line


def test_data_check_reports_a_truncated_file(capsys, damaged):
    capsys.readouterr()
    assert main(["data", "check", str(damaged["trunc_h5"])]) == 2
    out, err = capsys.readouterr()
    assert "FAIL" in out and "truncated" in out and "Traceback" not in err


@pytest.mark.parametrize(
    "command", ["train", "evaluate", "generate", "sensitivity", "splits", "counterfactual"]
)
def test_truncated_hdf5_is_one_line(tmp_path, capsys, damaged, tiny_checkpoint, command):
    h5 = tmp_path / "trunc.h5"
    shutil.copy(damaged["trunc_h5"], h5)
    argv = {
        "train": [
            "train",
            "--model",
            "nemsim",
            "--data",
            h5,
            "--setting",
            "control-id",
            "--out",
            tmp_path / "r",
        ],
        "evaluate": ["evaluate", "--checkpoint", tiny_checkpoint, "--data", h5, "--setting", "control-id"],
        "generate": ["generate", "--scene", "tiny", "--n", "1", "--out", h5, "--no-progress"],
        "sensitivity": ["sensitivity", h5],
        "splits": ["splits", "--data", h5, "--out", tmp_path / "s"],
        "counterfactual": ["counterfactual", "--checkpoint", tiny_checkpoint, "--data", h5],
    }[command]
    line = _fails_cleanly(capsys, argv)
    assert str(h5) in line and "truncated" in line
    assert h5.read_bytes() == damaged["trunc_h5"].read_bytes()  # nothing overwritten


@pytest.mark.parametrize("kind", ["trunc_pt", "garbage_pt"])
def test_damaged_checkpoint_is_one_line(capsys, damaged, data_file, kind):
    for argv in (
        ["evaluate", "--checkpoint", damaged[kind], "--data", data_file, "--setting", "control-id"],
        ["stress", "--checkpoint", damaged[kind], "--steps", "2"],
    ):
        line = _fails_cleanly(capsys, argv)
        assert str(damaged[kind]) in line and "not a readable checkpoint" in line


@pytest.mark.parametrize("digest", ["recorded", "absent"])
def test_evaluate_refuses_non_finite_weights(tmp_path, capsys, tiny_checkpoint, data_file, digest):
    """NaN weights (with the weights' digest recorded, or an older checkpoint without one): exit 2 with
    the loader's one-line reason naming the file, never exit 0 with "Avg RMSE nan"."""
    import torch

    ckpt = torch.load(tiny_checkpoint, map_location="cpu", weights_only=True)
    name = next(k for k, t in ckpt["model_state"].items() if t.is_floating_point() and t.numel() > 8)
    ckpt["model_state"][name].view(-1)[:8] = float("nan")
    if digest == "absent":
        ckpt.pop("weights_sha256")
    bad = tmp_path / "poisoned.pt"
    torch.save(ckpt, bad)
    line = _fails_cleanly(capsys, ["evaluate", "--checkpoint", bad, "--data", data_file, "--setting",
                                   "control-id"])  # fmt: skip
    assert "poisoned.pt" in line and "NaN or Inf" in line and "refused" in line


def test_missing_file_is_one_line(tmp_path, capsys):
    line = _fails_cleanly(capsys, ["splits", "--design", tmp_path / "none.csv", "--out", tmp_path / "s"])
    assert "none.csv" in line and "No such file" in line


def test_yaml_syntax_error_names_the_line(tmp_path, capsys):
    bad = tmp_path / "rules.yaml"
    bad.write_text("version: 1\nevents:\n  - name: [unclosed\n    group: both\n")
    line = _fails_cleanly(capsys, ["rules", "check", bad])
    assert f"{bad}: YAML syntax error at line 4" in line


# ---- the boundary: bugs stay visible -----------------------------------------------------------------------


def _buggy(args):
    raise TypeError("unsupported operand")


def test_unexpected_error_is_one_line_with_exit_1_and_debug_shows_it(monkeypatch, capsys):
    from nemsim.cli import data

    monkeypatch.setattr(data, "_cmd_design", _buggy)
    line = _fails_cleanly(capsys, ["design", "--out", "unused.csv"], code=1)
    assert "TypeError: unsupported operand" in line and "--debug" in line
    with pytest.raises(TypeError):
        main(["design", "--out", "unused.csv", "--debug"])
    with pytest.raises(TypeError):
        main(["--debug", "design", "--out", "unused.csv"])


def test_entry_point_prints_no_traceback(damaged, data_file):
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).parents[1]), "OMP_NUM_THREADS": "1"}
    argv = ["evaluate", "--checkpoint", str(damaged["trunc_pt"]), "--data", str(data_file), "--setting",
            "control-id"]
    res = subprocess.run([sys.executable, "-m", "nemsim.cli", *argv], capture_output=True, text=True, env=env,
                         timeout=120)  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr


def test_file_in_use_is_one_line(tmp_path, data_file):
    """A second writer on a file another process holds open (h5py's BlockingIOError) is one line, exit 2."""
    import h5py

    h5 = tmp_path / "busy.h5"
    shutil.copy(data_file, h5)
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).parents[1]), "OMP_NUM_THREADS": "1"}
    with h5py.File(h5, "a"):  # holds the HDF5 file lock, as a running `nemsim generate` does
        res = subprocess.run([sys.executable, "-m", "nemsim.cli", "generate", "--scene", "tiny", "--n", "1",
                              "--out", str(h5), "--no-progress"], capture_output=True, text=True, env=env,
                             timeout=120)  # fmt: skip
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "in use" in lines[0] and "Traceback" not in res.stderr


# ---- item 8: defaults never write into committed folders ---------------------------------------------------


def test_default_outputs_are_under_runs(tmp_path, monkeypatch, capsys, data_file, tiny_checkpoint):
    parser = cli.build_parser()
    se = parser.parse_args(["bench", "speed-error", "--data", "x.h5"])
    collect = parser.parse_args(["bench", "collect", "--runs", "r"])
    assert Path(se.out).parts[0] == "runs" and Path(collect.out).parts[0] == "runs"
    monkeypatch.chdir(tmp_path)
    splits = tmp_path / "splits"
    assert main(["splits", "--data", str(data_file), "--out", str(splits)]) == 0
    rc = main(
        [
            "counterfactual",
            "--checkpoint",
            str(tiny_checkpoint),
            "--data",
            str(data_file),
            "--splits",
            str(splits),
            "--max-cases",
            "1",
        ]
    )
    assert rc == 0
    written = list((tmp_path / "runs" / "counterfactual").glob("*/counterfactual.json"))
    assert len(written) == 1
    assert not (Path(tiny_checkpoint).parent / "counterfactual").exists()


# ---- item 7: `make test` prints its count ------------------------------------------------------------------


def test_make_test_runs_pytest_with_a_single_quiet_flag():
    import tomllib

    root = Path(__file__).parents[1]
    recipe = [ln for ln in (root / "Makefile").read_text().splitlines() if "-m pytest" in ln]
    addopts = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"].get(
        "addopts", ""
    )
    quiet = sum(tok.count("q") for tok in (recipe[0] + " " + addopts).split() if tok.startswith("-q"))
    assert len(recipe) == 1 and quiet == 1  # -qq hides the "N passed, M skipped" line


def test_design_pairs_write_a_seed_id_column_and_need_an_even_n(tmp_path, capsys):
    from nemsim.controls import read_controls_csv, read_seed_ids

    out = tmp_path / "pairs.csv"
    assert main(["design", "--kind", "pairs", "--n", "14", "--seed", "3", "--out", str(out)]) == 0
    assert read_controls_csv(out).shape == (14, 14)
    np.testing.assert_array_equal(read_seed_ids(out), np.repeat(np.arange(0, 14, 2), 2))
    assert "7 sweep pairs" in capsys.readouterr().out
    assert main(["design", "--kind", "pairs", "--n", "7", "--out", str(out)]) == 2
    assert "even --n" in capsys.readouterr().err


# ---- the CLI package: its version, the commands plugged in from service/ and bench/ ----------------------


@pytest.mark.parametrize(("flags", "runtime", "named"), [("avx2 fma", "f32", "no bf16 arithmetic"),
                                                         ("avx2 avx512_bf16", "bf16", "avx512_bf16")])
def test_version_prints_the_version_and_the_served_runtime(capsys, monkeypatch, flags, runtime, named):
    from importlib.metadata import version

    from nemsim.inference import precision

    monkeypatch.setattr(precision, "cpu_info", lambda: {"model name": "Some CPU 9000", "flags": flags})
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    first, second = capsys.readouterr().out.strip().splitlines()
    assert exc.value.code == 0 and first == f"nemsim {version('nemsim')}"
    assert second.startswith(f"served runtime openvino-{runtime} on Some CPU 9000 ({named};")


def test_help_lists_the_commands_of_the_library_and_of_the_plugins():
    text = cli.build_parser().format_help()
    for name, words in {"train": "train a model", "serve": "serve a checkpoint", "bench": "benchmarks",
                        "stress": "hard-case stability"}.items():
        assert f"    {name:<14}{words}" in text, name


def test_a_plugin_that_fails_to_import_leaves_the_rest_working(monkeypatch, tmp_path, capsys):
    from importlib import metadata

    real = metadata.entry_points
    broken = metadata.EntryPoint("serve", "no_such_package_here.cli:register", "nemsim.cli")
    monkeypatch.setattr(metadata, "entry_points",
                        lambda group: [broken, *(e for e in real(group=group) if e.name != "serve")])
    line = _fails_cleanly(capsys, ["serve", "--checkpoint", "x.pt"])
    assert "`nemsim serve` is not available" in line and "pip install 'nemsim[service]'" in line
    assert main(["design", "--n", "3", "--out", str(tmp_path / "d.csv")]) == 0
    assert cli.build_parser().parse_args(["bench", "collect", "--runs", "r"]).bench == "collect"
    _fails_cleanly(capsys, ["design", "--out", "x.csv", "--no-such-flag"])


def test_evaluate_runtimes_are_the_inference_runtimes():
    from nemsim.cli.evaluate import RUNTIMES
    from nemsim.inference.runtime import BACKENDS, PRECISIONS

    assert set(RUNTIMES) == {f"{b}-{p}" for b in BACKENDS for p in PRECISIONS}  # every runtime


def test_the_library_imports_neither_the_service_nor_the_bench():
    import ast

    root = Path(cli.__file__).parents[1]
    found = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and not node.level else [])
            found += [f"{path.relative_to(root.parent)}: {n}" for n in names
                      if n.split(".")[0] in ("service", "bench")]
    assert not found, found


def test_evaluate_cuda_runtime_needs_a_cuda_device(tmp_path, capsys):
    args = ["evaluate", "--checkpoint", str(tmp_path / "x.pt"), "--data", str(tmp_path / "x.h5"), "--setting",
            "control-id", "--runtime", "cuda-f32"]
    assert cli.main(args) == 2
    assert "runs on a CUDA device; give --device cuda" in capsys.readouterr().err
    assert cli.main([*args[:-1], "openvino-f32", "--device", "cuda"]) == 2
    assert "runs on the CPU only" in capsys.readouterr().err
