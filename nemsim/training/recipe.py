"""Multi-stage training recipes: stages of `nemsim train` run in order, each warm-started from the last.

A recipe (YAML, read by `nemsim train --recipe FILE --out DIR`)::

    scene: small
    stages:
      - name: k10                      # output: DIR/k10/
        args: [--model, nemsim, --data, data/small.h5, --setting, control-id, --config, FILE.yaml]
      - name: rollout
        args: [...]                    # any `nemsim train` arguments but --out, --resume and --recipe

Stage i > 1 starts from stage i-1's ``best.pt`` (``--init-from``); every stage runs with ``--resume``, so a
stage interrupted part-way continues from its ``last.pt`` and a rerun of the recipe skips the stages that
finished (their ``STAGE_RECORD`` file is written last). The scene is the grid of every stage's data.

An optional ``data`` list names the commands that make the stages' data, run in order before the first
stage (``nemsim design``, ``generate`` or ``splits`` command lines, without the leading ``nemsim``)::

    data:
      - [design, --n, "500", --seed, "42", --out, data/design.csv]
      - [generate, --scene, small, --n, "500", --seed, "0", --out, data/small.h5]

A ``design`` or ``splits`` command whose ``--out`` exists is skipped (both are deterministic); ``generate``
always runs, and resumes: the cases a file holds complete are not simulated again. So one command builds
the model from nothing, and a rerun continues wherever it stopped.
"""

from __future__ import annotations

import gc
import json
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

STAGE_RECORD = "stage.json"  # written into a stage's directory when it has finished
RESERVED = ("--out", "--resume", "--recipe")  # set by the recipe runner, never by a stage
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")

StageState = Literal["done", "partial", "pending"]


@dataclass(frozen=True)
class Stage:
    name: str  # directory under the recipe's output
    args: tuple[str, ...]  # `nemsim train` arguments


DATA_COMMANDS = ("design", "generate", "splits")  # what a recipe's ``data`` list may run


@dataclass(frozen=True)
class Recipe:
    scene: str  # the grid of every stage's data (nemsim.scenes)
    stages: tuple[Stage, ...]
    data: tuple[tuple[str, ...], ...] = ()  # `nemsim` command lines that make the data, in order


def _flag(arg: str) -> str:
    return arg.partition("=")[0]


def _stage(i: int, raw: Any) -> Stage:
    if not isinstance(raw, dict) or set(raw) - {"name", "args"} or "name" not in raw:
        raise ValueError(f"stage {i + 1}: expected a mapping with `name` and `args`, got {raw!r}")
    name = str(raw["name"])
    if not _NAME.fullmatch(name):
        raise ValueError(f"stage {i + 1}: name {name!r} is not a directory name (letters, digits, . _ -)")
    args = raw.get("args") or []
    if not isinstance(args, list) or any(isinstance(a, (dict, list)) or a is None for a in args):
        raise ValueError(f"stage {name}: `args` must be a list of command-line words")
    words = tuple(str(a) for a in args)
    reserved = sorted({_flag(w) for w in words} & set(RESERVED))
    if reserved:
        raise ValueError(f"stage {name}: {', '.join(reserved)} is set by the recipe (each stage writes to "
                         "OUT/<name> and resumes)")
    if i > 0 and "--init-from" in {_flag(w) for w in words}:
        raise ValueError(f"stage {name}: --init-from is the previous stage's best.pt (only the first stage "
                         "may name one)")
    return Stage(name=name, args=words)


def recipe_from_dict(raw: Any) -> Recipe:
    """A Recipe from its YAML mapping; ValueError naming the stage and field when it is malformed."""
    from nemsim.scenes import get_scene

    if not isinstance(raw, dict) or not {"scene", "stages"} <= set(raw) <= {"scene", "stages", "data"}:
        got = sorted(raw) if isinstance(raw, dict) else type(raw).__name__
        raise ValueError(f"a recipe is a mapping with the keys `scene`, `stages` and optionally `data`, "
                         f"got {got}")
    scene = get_scene(str(raw["scene"])).name  # ValueError naming the scenes
    if not isinstance(raw["stages"], list) or not raw["stages"]:
        raise ValueError("`stages` must be a non-empty list")
    stages = tuple(_stage(i, s) for i, s in enumerate(raw["stages"]))
    names = [s.name for s in stages]
    if len(set(names)) != len(names):
        raise ValueError(f"stage names must be unique, got {names}")
    return Recipe(scene=scene, stages=stages, data=tuple(_data_command(i, c)
                                                        for i, c in enumerate(raw.get("data") or [])))


def _data_command(i: int, raw: Any) -> tuple[str, ...]:
    if not isinstance(raw, list) or not raw or any(isinstance(a, (dict, list)) or a is None for a in raw):
        raise ValueError(f"data command {i + 1}: expected a list of command-line words, got {raw!r}")
    words = tuple(str(a) for a in raw)
    if words[0] not in DATA_COMMANDS:
        raise ValueError(f"data command {i + 1}: `{words[0]}` is not one of {', '.join(DATA_COMMANDS)}")
    if "--out" not in words:
        raise ValueError(f"data command {i + 1} ({words[0]}): needs --out")
    return words


def run_recipe_data(recipe: Recipe, run_command: Callable[[list[str]], int],
                    echo: Callable[[str], None]) -> None:
    """Run the recipe's data commands in order (module docstring): ``run_command(words)`` runs one `nemsim`
    command line and returns its exit code; a non-zero code stops the recipe (RuntimeError)."""
    n = len(recipe.data)
    for i, words in enumerate(recipe.data):
        out = Path(words[words.index("--out") + 1])
        head = f"data {i + 1}/{n} {words[0]} -> {out}"
        if words[0] != "generate" and out.exists():
            echo(f"{head}: exists, skipped")
            continue
        echo(f"{head}: running")
        t0 = time.monotonic()
        code = run_command(list(words))
        if code != 0:
            raise RuntimeError(f"{head}: `nemsim {' '.join(words)}` exited with {code}")
        echo(f"{head}: done in {(time.monotonic() - t0) / 60:.1f} min")


def stage_state(out: Path) -> StageState:
    """done: the stage finished (its record exists); partial: it has a last.pt to resume; else pending."""
    if (out / STAGE_RECORD).is_file():
        return "done"
    return "partial" if (out / "last.pt").is_file() else "pending"


RunStage = Callable[[Stage, Path, Path | None], dict[str, Any]]  # (stage, its output, warm start) -> summary


def run_recipe(recipe: Recipe, out: Path, run_stage: RunStage, echo: Callable[[str], None]) -> list[Path]:
    """Run the recipe's stages in order into ``out/<name>``; the stages' best.pt paths.

    ``run_stage(stage, stage_out, init_from)`` trains one stage with resume on (``init_from`` is the previous
    stage's best.pt, None for the first) and returns its training summary; ``echo`` gets one progress line
    per stage as it starts and as it ends.
    """
    bests: list[Path] = []
    n = len(recipe.stages)
    for i, stage in enumerate(recipe.stages):
        stage_out, prev = out / stage.name, (bests[-1] if bests else None)
        head = f"stage {i + 1}/{n} {stage.name}"
        state = stage_state(stage_out)
        if state == "done":
            echo(f"{head}: done, skipped ({stage_out / STAGE_RECORD})")
            bests.append(stage_out / "best.pt")
            continue
        start = "resuming from its last.pt" if state == "partial" else "starting"
        warm = f", warm start from {prev}" if prev is not None else ""
        echo(f"{head}: {start}{warm} -> {stage_out}")
        t0 = time.monotonic()
        summary = run_stage(stage, stage_out, prev)
        # the stage's training set (tens of GB when held in memory) sits in reference cycles of its training
        # loop: free it now, not whenever a collection happens, or the next stage's decodes beside it
        gc.collect()
        minutes = (time.monotonic() - t0) / 60
        record = {"stage": stage.name, "args": list(stage.args),
                  "init_from": None if prev is None else str(prev), "summary": summary}
        (stage_out / STAGE_RECORD).write_text(json.dumps(record, indent=2, default=str) + "\n")
        echo(f"{head}: done in {minutes:.1f} min, best {summary.get('select_metric')} "
             f"{summary.get('best_val', float('nan')):.5g} at epoch {summary.get('best_epoch')} "
             f"-> {stage_out / 'best.pt'}")
        bests.append(stage_out / "best.pt")
    return bests
