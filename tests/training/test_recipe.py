"""`nemsim train --recipe`: stages run in order, each warm-started from the previous best.pt, skipped once
finished and resumed when interrupted; malformed recipes are one line, exit 2."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest
import torch
import yaml

from nemsim.cli import main
from nemsim.training.recipe import STAGE_RECORD, recipe_from_dict

ROOT = Path(__file__).parents[2]
STEPS = 4  # as in tests/training/conftest.py


def _stage_args(tiny_data: Path) -> list[str]:
    return ["--model", "test-standin", "--data", str(tiny_data), "--setting", "control-id", "--splits",
            str(tiny_data.parent / "splits"), "--epochs", "1", "--rollout-steps", str(STEPS), "--no-test"]


def _recipe(tmp_path: Path, tiny_data: Path, scene: str = "tiny", **extra: list[str]) -> Path:
    stages = [{"name": "first", "args": _stage_args(tiny_data) + extra.get("first", [])},
              {"name": "second", "args": _stage_args(tiny_data) + extra.get("second", [])}]
    path = tmp_path / f"recipe-{len(list(tmp_path.glob('recipe-*.yaml')))}.yaml"
    path.write_text(yaml.safe_dump({"scene": scene, "stages": stages}))
    return path


def test_stages_run_in_order_warm_started_then_skip_or_resume(tmp_path, tiny_data, capsys):
    recipe, out = _recipe(tmp_path, tiny_data), tmp_path / "runs"
    assert main(["train", "--recipe", str(recipe), "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    first, second = out / "first", out / "second"
    assert "stage 1/2 first: starting ->" in printed
    assert f"stage 2/2 second: starting, warm start from {first / 'best.pt'}" in printed
    assert printed.count("done in") == 2
    for stage in (first, second):
        assert (stage / "best.pt").is_file() and (stage / STAGE_RECORD).is_file()
    assert f"initialized from {first / 'best.pt'}" in (second / "train.log").read_text()
    assert "initialized from" not in (first / "train.log").read_text()  # each stage logs to its own file
    assert json.loads((second / STAGE_RECORD).read_text())["init_from"] == str(first / "best.pt")

    before = (second / "best.pt").stat().st_mtime_ns
    assert main(["train", "--recipe", str(recipe), "--out", str(out), "--no-progress"]) == 0
    assert capsys.readouterr().out.count("done, skipped") == 2
    assert (second / "best.pt").stat().st_mtime_ns == before

    (second / STAGE_RECORD).unlink()  # as if killed after its last checkpoint
    assert main(["train", "--recipe", str(recipe), "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "stage 1/2 first: done, skipped" in printed
    assert "stage 2/2 second: resuming from its last.pt" in printed
    assert "resumed from" in (second / "train.log").read_text() and (second / STAGE_RECORD).is_file()


def test_the_stages_share_one_decode_and_drop_what_they_no_longer_use(tmp_path, tiny_data, tiny_manifest,
                                                                      monkeypatch):
    """Stages run in one process: a second stage on the same cases reuses the first stage's decoded states
    (training and validation), and a decode of other cases drops the least recently used one before it is
    made, so two training sets of a recipe never coexist (13.9 GB for the union recipe on `small`)."""
    import gc
    import weakref

    import nemsim.training.run as run
    from nemsim.data.dataset import TransitionDataset, decoded_states

    config = tmp_path / "memory.train.yaml"
    config.write_text("in_memory: true\n")
    made, seen = run._memory_sets, []

    def memory_sets(sets, val, cfg):
        out = made(sets, val, cfg)
        seen.append((out[0].states, out[1].states))
        return out

    monkeypatch.setattr(run, "_memory_sets", memory_sets)
    memory = ["--config", str(config)]
    recipe = _recipe(tmp_path, tiny_data, first=memory, second=memory)
    assert main(["train", "--recipe", str(recipe), "--out", str(tmp_path / "runs"), "--no-progress"]) == 0
    (train_a, val_a), (train_b, val_b) = seen
    assert train_a is train_b and val_a is val_b  # decoded once
    seen.clear()
    del train_a, train_b, val_b

    gc.disable()  # freed by reference counts alone, as when no collection runs between stages
    try:
        ref = weakref.ref(val_a)
        del val_a
        other = TransitionDataset(tiny_data, tiny_manifest, "train", symmetrize=True)
        other_b = TransitionDataset(tiny_data, tiny_manifest, "test")
        decoded_states([other], torch.device("cpu"))
        decoded_states([other_b], torch.device("cpu"))  # two other decodes: the recipe's are gone
        assert ref() is None
    finally:
        gc.enable()


def test_malformed_recipes_are_one_line_exit_2(tmp_path, tiny_data, capsys):
    out = str(tmp_path / "runs")
    cases = [
        (["--recipe", str(_recipe(tmp_path, tiny_data)), "--out", out, "--epochs", "3"],
         "beside it give only --out, --device, --no-progress, --data-workers (got --epochs)"),
        (["--recipe", str(_recipe(tmp_path, tiny_data))], "needs --out"),
        (["--recipe", str(_recipe(tmp_path, tiny_data, second=["--out", "x"])), "--out", out],
         "--out is set by the recipe"),
        (["--recipe", str(_recipe(tmp_path, tiny_data, second=["--init-from", "x.pt"])), "--out", out],
         "only the first stage"),
        (["--recipe", str(_recipe(tmp_path, tiny_data, scene="small")), "--out", out], "on scene 'tiny'"),
        (["--recipe", str(_recipe(tmp_path, tiny_data, first=["--no-such-flag"])), "--out", out],
         "stage first: unrecognized arguments: --no-such-flag"),
    ]
    for argv, words in cases:
        capsys.readouterr()
        assert main(["train", *argv]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (argv, err)
    assert not (tmp_path / "runs").exists()  # nothing ran
    assert main(["train", "--model", "test-standin", "--out", out]) == 2
    assert "required: --data, --setting" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["nemsim-small.yaml", "nemsim-paper.yaml", "nemsim-small-k20.yaml"])
def test_shipped_recipes_parse(name):
    """The committed recipe (the served model, from nothing) is a valid recipe whose data commands and stage
    arguments parse, and whose config files and warm start exist."""
    from nemsim.cli import build_parser
    from nemsim.cli.train import add_train_arguments

    recipe = recipe_from_dict(yaml.safe_load((ROOT / "configs" / name).read_text()))
    assert recipe.data, "a recipe names the commands that make its data"
    for words in recipe.data:
        build_parser().parse_args(list(words))
    for stage in recipe.stages:
        parser = argparse.ArgumentParser()
        add_train_arguments(parser)
        args = parser.parse_args([*stage.args, "--out", "unused"])
        assert args.config is None or (ROOT / args.config).is_file(), (stage.name, args.config)
        assert args.init_from is None or (ROOT / args.init_from).is_file(), (stage.name, args.init_from)


def test_recipe_data_commands_run_in_order_and_resume(tmp_path):
    """A recipe's ``data`` list: design/splits whose --out exists are skipped, generate always runs (it
    resumes by itself), a failing command stops the recipe with its name; malformed lists are refused."""
    from nemsim.training.recipe import run_recipe_data

    have = tmp_path / "design.csv"
    have.write_text("x\n")
    raw = {"scene": "tiny", "stages": [{"name": "a", "args": []}],
           "data": [["design", "--n", "4", "--out", str(have)],
                    ["generate", "--scene", "tiny", "--controls", str(have), "--out", str(tmp_path / "t.h5")],
                    ["splits", "--design", str(have), "--out", str(tmp_path / "splits")]]}
    recipe = recipe_from_dict(raw)
    ran, lines = [], []
    run_recipe_data(recipe, lambda words: ran.append(words[0]) or 0, lines.append)
    assert ran == ["generate", "splits"]
    assert "exists, skipped" in lines[0] and "generate" in lines[1]
    with pytest.raises(RuntimeError, match="exited with 3"):
        run_recipe_data(recipe, lambda words: 3, lines.append)
    for bad, words in (([["train", "--out", "x"]], "not one of"),
                       ([["generate", "--scene", "tiny"]], "--out"),
                       (["generate"], "list of command-line words")):
        with pytest.raises(ValueError, match=words):
            recipe_from_dict({**raw, "data": bad})


def test_a_terminated_recipe_stops_its_data_command(tmp_path, stops):
    """SIGTERM to `nemsim train --recipe` while a data command runs: the command (here `generate`) stops
    too, keeping its finished cases, and the recipe exits 130; nothing outlives it."""
    import os
    import signal
    import subprocess
    import sys
    import time

    import h5py

    out = tmp_path / "g.h5"
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(yaml.safe_dump({
        "scene": "tiny", "stages": [{"name": "a", "args": []}],
        "data": [["generate", "--scene", "tiny", "--n", "40", "--no-progress", "--out", str(out)]],
    }))
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "nemsim.cli", "train", "--recipe", str(recipe), "--out",
                             str(tmp_path / "run")], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    child = None
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:  # wait for the command's first written case
            kids = stops.children(proc.pid)
            child = min(kids) if kids else child
            if child is not None and stops.cases_written(out) >= 1:
                break
            time.sleep(0.2)
        assert proc.poll() is None and child is not None, "the recipe finished before it could be stopped"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        if child is not None and stops.alive(child):
            os.kill(child, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert not stops.alive(child), "the data command outlived the recipe"
    with h5py.File(out, "r") as f:
        assert 1 <= int(f["complete"][()].sum()) < 40

