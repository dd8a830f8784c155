"""The benchmark's results file (`nemsim bench collect`): ``benchmarks/<scene>/results.json`` and its table.

Format::

    {"settings": {table: {model: {"avg_rmse", "final_rmse", "cd", "params", "rollout_s", "budget_min",
                                  "steps", "final_train_loss", "train_wall_s", "train_cpu_s"}}},
     "budget": {table: {"train_minutes", "max_steps", "batch_size"}},
     "curves": {table: {model: {"wall_min", "cpu_min", "steps", "val_avg_rmse"}}},
     "noise_floor": {"avg_rmse", "cd"},
     "speed": {"simulator_s", "nemsim_s", ...}}

Sources: each training run directory's ``test_metrics.json`` (written by ``nemsim train``: EvalResult fields
plus ``setting``; ``rollout_s`` = its ``rollout_seconds_per_case``, batch 1), the model name from the run's
``best.pt`` (``model_name``; the directory name when there is no checkpoint), the training summary from
``summary.json`` (the run's end; else best.pt's, written at the best validation) and the validation curve
from ``metrics.csv``. Test scores are on the test split; ``steps``, ``final_train_loss`` (mean of the last
step losses), ``train_wall_s`` / ``train_cpu_s`` (the whole run: training, validation and checkpoints, over
every resume) describe the training run. A run trained on a budget is filed under its own table
"<setting>, <M> min" (wall clock, ``max_train_minutes``) and/or "<setting>, <S> steps x batch <B>"
(``max_steps``), so equal-budget comparisons sit in one table; ``budget`` says what every model of a table
was given. ``curves`` holds each run's validation Avg RMSE at every validation against the run's cumulative
wall (and CPU) minutes when the validated weights were reached; ``write_results`` draws them as
``budget_curve.png`` next to results.json, one panel per table. The noise floor and the speed from the JSON
of ``nemsim bench speed-error`` (its ``noise_floor`` and ``speed`` blocks; ``nemsim_s`` is NEMSim's fastest
precision that keeps its fp32 error). Extra keys (``n_cases``, ``run``, ``scene``,
``speed.nemsim_precision``) are informational. Two runs for the same (table, model) are refused.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from nemsim.evaluation.figure import pyplot, save_figure

MODEL_KEYS = ("avg_rmse", "final_rmse", "cd", "params", "rollout_s", "budget_min", "steps",
              "final_train_loss", "train_wall_s", "train_cpu_s")
FIGURE = "budget_curve.png"  # written next to results.json
TABLE_BEGIN = "<!-- results-table:begin (nemsim bench collect) -->"
TABLE_END = "<!-- results-table:end -->"


def _run_info(run_dir: Path) -> tuple[str, dict[str, Any]]:
    """(model name, training summary): the name from the run's best.pt (the directory name without one; a
    multi-step model's name gets " (k=N)"), the summary from summary.json (written at the run's end), else
    best.pt's, else {}."""
    name, summary = run_dir.name, {}
    ckpt = run_dir / "best.pt"
    if ckpt.is_file():
        from nemsim.inference.checkpoint import read_checkpoint

        c = read_checkpoint(ckpt)
        name, summary = str(c.get("model_name") or run_dir.name), dict(c.get("summary") or {})
        k = (c.get("model_config") or {}).get("steps_per_call", 1)
        if k and k > 1:  # a multi-step model is its own row (the steps_per_call comparison)
            name = f"{name} (k={k})"
    end = run_dir / "summary.json"
    if end.is_file():
        summary = json.loads(end.read_text())
    return name, summary


def setting_key(setting: str, summary: dict[str, Any]) -> str:
    """A budget run is its own table: "<setting>, <M> min" for a wall budget (train_config.max_train_minutes),
    "<setting>, <S> steps x batch <B>" for a step budget (max_steps), both suffixes when both are set."""
    tc = summary.get("train_config") or {}
    parts = [setting]
    if tc.get("max_train_minutes") is not None:
        parts.append(f"{tc['max_train_minutes']:g} min")
    if tc.get("max_steps") is not None:
        parts.append(f"{tc['max_steps']} steps x batch {tc.get('batch_size')}")
    return ", ".join(parts)


def _budget(summary: dict[str, Any]) -> dict[str, Any]:
    """What a table's runs were given (the parts of ``setting_key``)."""
    tc = summary.get("train_config") or {}
    steps = tc.get("max_steps")
    return {"train_minutes": tc.get("max_train_minutes"), "max_steps": steps,
            "batch_size": tc.get("batch_size") if steps is not None else None}


def _float(text: str | None) -> float | None:
    return float(text) if text not in (None, "") else None


def read_metrics(run_dir: str | Path) -> list[dict[str, str]]:
    """The rows of a run's metrics.csv (one per epoch, see nemsim.training.loop); [] without the file."""
    path = Path(run_dir) / "metrics.csv"
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def validation_curve(rows: list[dict[str, str]]) -> dict[str, list[float]]:
    """Per validation of metrics.csv ``rows``: the run's cumulative wall and CPU minutes and optimizer steps
    when the validated weights were reached, and the validation Avg RMSE. Rows without a validation, or
    written before the loop recorded wall time, are left out."""
    curve: dict[str, list[float]] = {"wall_min": [], "cpu_min": [], "steps": [], "val_avg_rmse": []}
    for row in rows:
        wall, val, cpu = _float(row.get("wall_s")), _float(row.get("val_avg_rmse")), _float(row.get("cpu_s"))
        if wall is None or val is None:
            continue
        curve["wall_min"].append(wall / 60)
        curve["cpu_min"].append(cpu / 60 if cpu is not None else math.nan)
        curve["steps"].append(int(row["step"]))
        curve["val_avg_rmse"].append(val)
    return curve


def collect_results(run_dirs: Sequence[str | Path], speed_error: str | Path | dict | None = None) -> dict:
    """Assemble the results dict (module docstring) from training runs and a speed-error report.

    Raises ValueError naming the directory when a run has no ``test_metrics.json`` or repeats a
    (setting, model) pair.
    """
    settings: dict[str, dict[str, dict[str, Any]]] = {}
    budgets: dict[str, dict[str, Any]] = {}
    curves: dict[str, dict[str, dict[str, list[float]]]] = {}
    sources: dict[tuple[str, str], str] = {}
    for d in map(Path, run_dirs):
        f = d / "test_metrics.json"
        if not f.is_file():
            raise ValueError(f"{d}: no test_metrics.json (run `nemsim train` without --no-test, or "
                             "`nemsim evaluate`, first)")  # fmt: skip
        m = json.loads(f.read_text())
        setting = m.get("setting")
        if not setting:
            raise ValueError(f"{f}: no 'setting' key")
        model, summary = _run_info(d)
        setting = setting_key(setting, summary)
        key = (setting, model)
        if key in sources:
            raise ValueError(f"two runs for setting {setting!r}, model {model!r}: {sources[key]} and {d}")
        sources[key] = str(d)
        rows = read_metrics(d)
        curve = validation_curve(rows)
        budgets[setting] = _budget(summary)
        settings.setdefault(setting, {})[model] = {
            "avg_rmse": m.get("avg_rmse"),
            "final_rmse": m.get("final_rmse"),
            "cd": m.get("cd"),
            "params": m.get("params"),
            "rollout_s": m.get("rollout_seconds_per_case"),
            "budget_min": budgets[setting]["train_minutes"],
            "steps": summary.get("steps", int(rows[-1]["step"]) if rows else None),
            "final_train_loss": summary.get("final_train_loss"),
            "train_wall_s": summary.get("wall_s"),
            "train_cpu_s": summary.get("cpu_s"),
            "n_cases": m.get("n_cases"),
            "run": str(d),
        }
        if curve["val_avg_rmse"]:
            curves.setdefault(setting, {})[model] = curve
    out: dict[str, Any] = {
        "settings": settings,
        "budget": budgets,
        "curves": curves,
        "noise_floor": {"avg_rmse": None, "cd": None},
        "speed": {"simulator_s": None, "nemsim_s": None},
    }
    if speed_error is not None:
        rep = speed_error if isinstance(speed_error, dict) else json.loads(Path(speed_error).read_text())
        if "noise_floor" not in rep or "speed" not in rep:
            raise ValueError(f"{speed_error}: not a `nemsim bench speed-error` report "
                             "(no noise_floor / speed)")  # fmt: skip
        nf = rep["noise_floor"]
        out["noise_floor"] = {
            "avg_rmse": nf.get("avg_rmse"),
            "cd": nf.get("cd"),
            "n_cases": len(rep.get("case_ids", [])),
            "setting": rep.get("setting"),
        }
        out["speed"] = {k: rep["speed"].get(k) for k in SPEED_KEYS}
        if out["speed"]["nemsim_checkpoint"] is None:  # a report from before the key: its fastest row's
            out["speed"]["nemsim_checkpoint"] = next(
                (r.get("checkpoint") for r in rep.get("rows", [])
                 if r.get("fastest") and r.get("wall_s") == rep["speed"].get("nemsim_s")), None)  # fmt: skip
        out["scene"] = rep.get("scene")
    return out


# copied from a speed-error report into results.json
SPEED_KEYS = ("simulator_s", "simulator_cpu_s", "nemsim_s", "nemsim_cpu_s", "nemsim_checkpoint",
              "nemsim_runtime", "nemsim_precision", "speedup", "equal_accuracy")
_BOUND_WORD = {"lower": ">= ", "upper": "<= "}  # equal_accuracy.bound -> how the figure reads


def _f(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


def _by_error(item: tuple[str, dict]) -> tuple[bool, float]:
    """Sort key: Avg RMSE ascending, missing values last."""
    return item[1].get("avg_rmse") is None, item[1].get("avg_rmse") or 0.0


def _minutes(seconds: Any) -> float | None:
    return seconds / 60 if isinstance(seconds, (int, float)) else None


def results_markdown(results: dict, figure: str | None = None) -> str:
    """One table per setting (models sorted by test Avg RMSE, with each run's training steps, wall and CPU
    minutes and final training loss), then the curve figure (``figure``: its path relative to the Markdown
    file, if written), the noise floor and the speed."""
    lines = [TABLE_BEGIN, ""]
    nf = results.get("noise_floor") or {}
    for setting, models in sorted(results["settings"].items()):
        lines += [
            f"### {setting}",
            "",
            "| model | Avg RMSE | Final RMSE | CD (vox) | Params (M) | rollout s / case | "
            "Avg RMSE / noise floor | train steps | train wall min | train CPU min | final train loss |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        order = sorted(models.items(), key=_by_error)
        for name, m in order:
            avg = m.get("avg_rmse")
            ratio = avg / nf["avg_rmse"] if avg is not None and nf.get("avg_rmse") else None
            params = m["params"] / 1e6 if m.get("params") is not None else None
            lines.append(
                f"| {name} | {_f(avg, '.4f')} | {_f(m.get('final_rmse'), '.4f')} | "
                f"{_f(m.get('cd'), '.3f')} | "
                f"{_f(params, '.3f')} | {_f(m.get('rollout_s'), '.3g')} | {_f(ratio, '.2f')} | "
                f"{_f(m.get('steps'), 'd')} | {_f(_minutes(m.get('train_wall_s')), '.1f')} | "
                f"{_f(_minutes(m.get('train_cpu_s')), '.1f')} | {_f(m.get('final_train_loss'), '.3e')} |"
            )
        lines.append("")
    if figure is not None:
        lines += [f"![validation Avg RMSE against training wall time, per table]({figure})", ""]
    lines.append(f"Noise floor (simulator vs itself, two seeds): Avg RMSE {_f(nf.get('avg_rmse'), '.4f')}, "
                 f"CD {_f(nf.get('cd'), '.3f')} vox.")  # fmt: skip
    sp = results.get("speed") or {}
    if sp.get("simulator_s") is not None and sp.get("nemsim_s"):
        source = ["`nemsim bench speed-error`"]
        if sp.get("nemsim_checkpoint"):
            source.append(Path(sp["nemsim_checkpoint"]).name)
        if sp.get("nemsim_runtime"):
            source.append(sp["nemsim_runtime"])
        eq = sp.get("equal_accuracy") or {}
        at_eq = ""
        if eq.get("speedup"):
            at_eq = (f"; at equal accuracy (the simulator's time at NEMSim's error) "
                     f"{_BOUND_WORD.get(str(eq.get('bound')), '')}{eq['speedup']:.1f}x")
        lines.append(
            f"Speed ({', '.join(source)}, batch 1): simulator "
            f"{sp['simulator_s']:.3g} s per trajectory, NEMSim {sp['nemsim_s']:.3g} s, "
            f"{sp['simulator_s'] / sp['nemsim_s']:.1f}x faster{at_eq}."
        )
    lines += ["", TABLE_END]
    return "\n".join(lines) + "\n"


def plot_budget_curves(results: dict, path: str | Path) -> Path:
    """PNG of ``results["curves"]``: one panel per table, validation Avg RMSE (log) against the run's
    cumulative wall minutes, one line per model; a dashed line at a table's wall budget."""
    plt = pyplot()

    tables = sorted(results["curves"])
    models = sorted({m for t in tables for m in results["curves"][t]})
    palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    color = {m: palette[i % len(palette)] for i, m in enumerate(models)}  # one colour per model everywhere
    fig, axes = plt.subplots(1, len(tables), figsize=(5.5 * len(tables), 4.2), squeeze=False)
    for ax, table in zip(axes[0], tables, strict=True):
        for model, c in sorted(results["curves"][table].items()):
            ax.plot(c["wall_min"], c["val_avg_rmse"], "o-", ms=3, color=color[model], label=model)
        minutes = (results.get("budget", {}).get(table) or {}).get("train_minutes")
        if minutes is not None:
            ax.axvline(minutes, color="k", ls="--", lw=1, label=f"budget {minutes:g} min")
        ax.set_xlim(left=0)
        ax.set_yscale("log")
        ax.set_xlabel("run wall time (min: training + validation, over resumes)")
        ax.set_ylabel("validation Avg RMSE")
        ax.set_title(table)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


def write_results(results: dict, out: str | Path, readme: str | Path | None = None) -> dict[str, Path]:
    """Write ``results.json``, ``budget_curve.png`` next to it (when any run has a validation curve) and the
    table into ``readme`` (default: README.md next to it); returns their paths ("json", "readme", "figure").

    An existing README keeps its text: only the part between the table markers is replaced (appended
    when the markers are absent).
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    readme = Path(readme) if readme is not None else out.parent / "README.md"
    paths = {"json": out, "readme": readme}
    figure = None
    if results.get("curves"):
        paths["figure"] = plot_budget_curves(results, out.parent / FIGURE)
        figure = os.path.relpath(paths["figure"].resolve(), readme.resolve().parent)
    table = results_markdown(results, figure)
    if readme.is_file():
        text = readme.read_text()
        if TABLE_BEGIN in text and TABLE_END in text:
            head, rest = text.split(TABLE_BEGIN, 1)
            tail = rest.split(TABLE_END, 1)[1]
            text = head + table.rstrip("\n") + tail
        else:
            text = text.rstrip("\n") + "\n\n" + table
    else:
        text = f"# Benchmark results\n\nGenerated by `nemsim bench collect`.\n\n{table}"
    readme.write_text(text)
    return paths
