"""The recipe from nothing, end to end, measured: ``python -m bench.gpu_recipe --out DIR``.

Runs ``nemsim train --recipe RECIPE --out SCRATCH/runs --data-workers N`` in a child process from an empty
scratch folder (data included: the recipe's data commands write under SCRATCH) and stamps every line it
prints with the seconds since the start. ``DIR/recipe.json`` and ``DIR/recipe.md`` are rewritten after
every line (a run cut short leaves what it reached) and completed at the end with each stage's figures
from its own files (``stage.json``, ``metrics.csv``, ``test_metrics.json``): batch, steps, items seen,
training-loop and validation seconds, training items per second, the best validation and the test Avg
RMSE. ``--collect`` rebuilds the report of a run folder without running anything.

Meant for a GPU machine (``--device cuda``); ``--device cpu`` with a small recipe checks the script. Nothing
heavy is imported here: the recipe runs in its own process.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "configs" / "nemsim-small.yaml"
DONE = re.compile(r"\b(data \d+/\d+ \w+|stage \d+/\d+ [\w.-]+)\b.*: done in ([\d.]+) min")


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m bench.gpu_recipe", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path, help="folder for recipe.json and recipe.md")
    p.add_argument("--recipe", type=Path, default=RECIPE,
                   help="the recipe (default configs/nemsim-small.yaml)")
    p.add_argument("--scratch", type=Path, default=Path("/tmp/nemsim-recipe"),
                   help="where the recipe runs (its data/ and runs/); emptied first unless --resume")
    p.add_argument("--workers", type=int, default=os.cpu_count(), help="simulator workers (--data-workers)")
    p.add_argument("--device", default="cuda", help="the training device (cuda, cpu)")
    p.add_argument("--resume", action="store_true", help="continue a run in --scratch (the recipe resumes)")
    p.add_argument("--collect", action="store_true", help="only rebuild the report of the run in --scratch")
    return p.parse_args(argv)


def environment(device: str) -> dict[str, Any]:
    """Versions, device and machine (``bench.gpu.environment``; the bare machine without torch)."""
    try:
        import torch
    except ImportError:
        return {"python": platform.python_version(), "cpu_count": os.cpu_count(), "device": device}
    from bench.gpu import environment as of_device

    return of_device(torch.device(device))


def stage_rows(runs: Path, recipe: dict[str, Any]) -> list[dict[str, Any]]:
    """Each stage's figures from its own files (the finished ones, and how far an unfinished one got)."""
    rows = []
    for stage in recipe["stages"]:
        folder = runs / stage["name"]
        row: dict[str, Any] = {"name": stage["name"], "finished": (folder / "stage.json").is_file()}
        summary_file = folder / "summary.json"
        if row["finished"]:
            summary = json.loads((folder / "stage.json").read_text())["summary"]
        elif summary_file.is_file():
            summary = json.loads(summary_file.read_text())
        else:
            row["started"] = folder.is_dir()
            rows.append(row)
            continue
        tc = summary["train_config"]
        steps, wall, val = int(summary["steps"]), float(summary["wall_s"]), float(summary["val_wall_s"])
        row.update(batch=tc["batch_size"], steps=steps, items=steps * tc["batch_size"], lr=tc["lr"],
                   loop_s=wall, val_s=val, items_per_s=steps * tc["batch_size"] / max(wall - val, 1e-9),
                   best_val_avg_rmse=summary["best_val"], best_epoch=summary["best_epoch"],
                   stopped_early=summary["stopped_early"])
        with open(folder / "metrics.csv", newline="") as f:
            row["val_rounds"] = sum(1 for r in csv.DictReader(f) if r.get("val_avg_rmse"))
        test = folder / "test_metrics.json"
        if test.is_file():
            metrics = json.loads(test.read_text())
            row.update(test_avg_rmse=metrics["avg_rmse"], test_final_rmse=metrics["final_rmse"],
                       test_cases=metrics.get("n_cases"))
        rows.append(row)
    return rows


def markdown(res: dict[str, Any]) -> str:
    env = res.get("environment", {})
    lines = [f"# The recipe from nothing ({env.get('gpu', env.get('device', '?'))})", "",
             f"`{res.get('command', '')}`; {env.get('cpu_count')} CPU cores, torch {env.get('torch')}, CUDA "
             f"{env.get('torch_cuda')}; recipe `{res.get('recipe')}`.", "",
             f"**Wall time, data included: {res.get('wall_s', 0) / 60:.1f} min** "
             f"({'finished, exit ' + str(res['exit']) if 'exit' in res else 'still running when written'}).",
             "", "| phase | wall min (its own line) | at min |", "|---|---:|---:|"]  # fmt: skip
    for phase in res.get("phases", []):
        lines.append(f"| {phase['phase']} | {phase['minutes']:.2f} | {phase['at_s'] / 60:.2f} |")
    lines += ["", "| stage | batch | steps | items | lr | loop s | of which validation s | items/s "
              "| val rounds | best val Avg RMSE | test Avg RMSE |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in res.get("stages", []):
        if "steps" not in s:
            state = "running when written (its epochs: the log below)" if s.get("started") else "not started"
            lines.append(f"| {s['name']} | {state} | | | | | | | | | |")
            continue
        test = f"{s['test_avg_rmse']:.5f}" if "test_avg_rmse" in s else "-"
        lines.append(f"| {s['name']}{'' if s['finished'] else ' (unfinished)'} | {s['batch']} | {s['steps']} "
                     f"| {s['items']} | {s['lr']:.3g} | {s['loop_s']:.1f} | {s['val_s']:.1f} | "
                     f"{s['items_per_s']:.1f} | {s['val_rounds']} | {s['best_val_avg_rmse']:.5f} | {test} |")
    if "exit" not in res and res.get("log_tail"):
        lines += ["", "The last lines the run printed (seconds since its start):", "", "```",
                  *res["log_tail"][-20:], "```"]
    return "\n".join(lines) + "\n"


def write(out: Path, res: dict[str, Any]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "recipe.json").write_text(json.dumps(res, indent=2, default=str) + "\n")
    (out / "recipe.md").write_text(markdown(res))


def main(argv: Sequence[str] | None = None) -> int:
    import yaml

    args = parse_args(argv)
    recipe_path = args.recipe.resolve()
    recipe = yaml.safe_load(recipe_path.read_text())
    runs = args.scratch / "runs"
    cmd = [sys.executable, "-m", "nemsim.cli", "train", "--recipe", str(recipe_path), "--out", str(runs),
           "--device", args.device, "--data-workers", str(args.workers), "--no-progress"]  # fmt: skip
    res: dict[str, Any] = {"command": " ".join(["nemsim", *cmd[3:]]), "recipe": str(args.recipe),
                           "environment": environment(args.device), "phases": [], "log_tail": []}  # fmt: skip
    report = args.out / "recipe.json"
    if args.collect:
        if report.is_file():
            res = json.loads(report.read_text())
        res["stages"] = stage_rows(runs, recipe)
        write(args.out, res)
        return 0
    if args.scratch.exists() and not args.resume:
        shutil.rmtree(args.scratch)
    args.scratch.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    _link_configs(args.scratch)
    t0 = time.perf_counter()
    # the recipe's data paths are relative: it runs in the scratch folder, its configs found from the root
    proc = subprocess.Popen(cmd, cwd=args.scratch, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, bufsize=1)
    assert proc.stdout is not None
    for line in proc.stdout:
        at = time.perf_counter() - t0
        sys.stdout.write(f"[{at:7.1f} s] {line}")
        sys.stdout.flush()
        res["log_tail"] = (res["log_tail"] + [f"{at:.1f} {line.rstrip()}"])[-40:]
        m = DONE.search(line)
        if m:
            res["phases"].append({"phase": m.group(1), "minutes": float(m.group(2)), "at_s": at})
        res["wall_s"] = at
        write(args.out, res)
    res["exit"] = proc.wait()
    res["wall_s"] = time.perf_counter() - t0
    res["stages"] = stage_rows(runs, recipe)
    write(args.out, res)
    return int(res["exit"])


def _link_configs(scratch: Path) -> None:
    """The recipe names its stage configs relative to the repository root (configs/...)."""
    link = scratch / "configs"
    if not link.exists():
        link.symlink_to(ROOT / "configs")


if __name__ == "__main__":
    raise SystemExit(main())
