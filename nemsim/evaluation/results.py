"""The benchmark's results file (`nemsim bench collect`): ``benchmarks/<scene>/results.json`` and its table.

Format (issue 7)::

    {"settings": {setting: {model: {"avg_rmse", "final_rmse", "cd", "params", "rollout_s"}}},
     "noise_floor": {"avg_rmse", "cd"},
     "speed": {"simulator_s", "nemsim_s"}}

Sources: each training run directory's ``test_metrics.json`` (written by ``nemsim train``: EvalResult fields
plus ``setting``; ``rollout_s`` = its ``rollout_seconds_per_case``, batch 1) and the model name from the run's
``best.pt`` (``model_name``; the directory name when there is no checkpoint). A run trained on a step budget
(``max_steps`` in the ``train_config`` stored in best.pt) is filed under its own setting key
"<setting>, <S> steps x batch <B>" so equal-budget comparisons sit in one table. The noise floor and the speed
from the JSON of ``nemsim bench speed-error`` (its ``noise_floor`` and ``speed`` blocks; ``nemsim_s`` is
NEMSim's fastest precision that keeps its fp32 error). Extra keys (``n_cases``, ``run``, ``scene``,
``speed.nemsim_precision``) are informational. Two runs for the same (setting, model) are refused.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

MODEL_KEYS = ("avg_rmse", "final_rmse", "cd", "params", "rollout_s")
TABLE_BEGIN = "<!-- results-table:begin (nemsim bench collect) -->"
TABLE_END = "<!-- results-table:end -->"


def _run_info(run_dir: Path) -> tuple[str, dict[str, Any]]:
    """(model name, training summary) from the run's best.pt; (directory name, {}) without one."""
    ckpt = run_dir / "best.pt"
    if ckpt.is_file():
        from nemsim.checkpoint import read_checkpoint

        c = read_checkpoint(ckpt)
        return str(c.get("model_name") or run_dir.name), dict(c.get("summary") or {})
    return run_dir.name, {}


def setting_key(setting: str, summary: dict[str, Any]) -> str:
    """A step-budget run (train_config.max_steps set) is its own table: "<setting>, <S> steps x batch <B>"."""
    tc = summary.get("train_config") or {}
    if tc.get("max_steps") is None:
        return setting
    return f"{setting}, {tc['max_steps']} steps x batch {tc.get('batch_size')}"


def collect_results(run_dirs: Sequence[str | Path], speed_error: str | Path | dict | None = None) -> dict:
    """Assemble the results dict (module docstring) from training runs and a speed-error report.

    Raises ValueError naming the directory when a run has no ``test_metrics.json`` or repeats a
    (setting, model) pair.
    """
    settings: dict[str, dict[str, dict[str, Any]]] = {}
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
        settings.setdefault(setting, {})[model] = {
            "avg_rmse": m.get("avg_rmse"),
            "final_rmse": m.get("final_rmse"),
            "cd": m.get("cd"),
            "params": m.get("params"),
            "rollout_s": m.get("rollout_seconds_per_case"),
            "n_cases": m.get("n_cases"),
            "run": str(d),
        }
    out: dict[str, Any] = {
        "settings": settings,
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
        out["scene"] = rep.get("scene")
    return out


# copied from a speed-error report into results.json
SPEED_KEYS = ("simulator_s", "simulator_cpu_s", "nemsim_s", "nemsim_cpu_s", "nemsim_runtime",
              "nemsim_precision", "speedup", "equal_accuracy")


def _f(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


def _by_error(item: tuple[str, dict]) -> tuple[bool, float]:
    """Sort key: Avg RMSE ascending, missing values last."""
    return item[1].get("avg_rmse") is None, item[1].get("avg_rmse") or 0.0


def results_markdown(results: dict) -> str:
    """One table per setting (models sorted by Avg RMSE), then the noise floor and the speed."""
    lines = [TABLE_BEGIN, ""]
    nf = results.get("noise_floor") or {}
    for setting, models in sorted(results["settings"].items()):
        lines += [
            f"### {setting}",
            "",
            "| model | Avg RMSE | Final RMSE | CD (vox) | Params (M) | rollout s / case | "
            "Avg RMSE / noise floor |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        order = sorted(models.items(), key=_by_error)
        for name, m in order:
            avg = m.get("avg_rmse")
            ratio = avg / nf["avg_rmse"] if avg is not None and nf.get("avg_rmse") else None
            params = m["params"] / 1e6 if m.get("params") is not None else None
            lines.append(
                f"| {name} | {_f(avg, '.4f')} | {_f(m.get('final_rmse'), '.4f')} | "
                f"{_f(m.get('cd'), '.3f')} | "
                f"{_f(params, '.3f')} | {_f(m.get('rollout_s'), '.3g')} | {_f(ratio, '.2f')} |"
            )
        lines.append("")
    lines.append(f"Noise floor (simulator vs itself, two seeds): Avg RMSE {_f(nf.get('avg_rmse'), '.4f')}, "
                 f"CD {_f(nf.get('cd'), '.3f')} vox.")  # fmt: skip
    sp = results.get("speed") or {}
    if sp.get("simulator_s") is not None and sp.get("nemsim_s"):
        lines.append(
            f"Speed: simulator {sp['simulator_s']:.3g} s per trajectory, NEMSim {sp['nemsim_s']:.3g} s "
            f"({sp.get('nemsim_precision') or 'fp32'}), {sp['simulator_s'] / sp['nemsim_s']:.1f}x faster."
        )
    lines += ["", TABLE_END]
    return "\n".join(lines) + "\n"


def write_results(results: dict, out: str | Path, readme: str | Path | None = None) -> tuple[Path, Path]:
    """Write ``results.json`` and the table into ``readme`` (default: README.md next to it).

    An existing README keeps its text: only the part between the table markers is replaced (appended
    when the markers are absent).
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    readme = Path(readme) if readme is not None else out.parent / "README.md"
    table = results_markdown(results)
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
    return out, readme
