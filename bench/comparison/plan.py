"""A comparison plan: its YAML file, the choices it defers to earlier runs, and the state of every run.

The plan file (e.g. ``benchmarks/small/compare-45min.plan.yaml``)::

    recipe: compare-45min.train.yaml  # TrainConfig (+ model:) of every run; relative to the plan file
    record: compare-45min             # committed copies of the finished runs; relative to the plan file
    data: data/small.h5               # relative to the working directory, as in every command
    splits: data/splits
    make_data: [COMMAND, ...]         # how to make data and splits (named when they are missing)
    baselines: [deeponet, fno, ...]   # the models `best_baselines(N)` ranks
    sizes: {MODEL: {LABEL: {model config overrides}}}   # "paper" = the registered defaults, always there
    runs:                             # in the order they should run
      - {name: probe-fno-paper-lr5e-4, probe: true, model: fno, size: paper, lr: 5.0e-4, minutes: 15}
      - {name: control-id-fno, model: fno, setting: control-id, minutes: 45, from_probes: true}
      - {name: ood-joint-baseline, models_from: best_baselines(2), setting: ood-joint, minutes: 45}

An entry trains ``model`` at ``size`` with learning rate ``lr`` (default: the recipe's) on ``setting``
(default control-id) for ``minutes`` of wall time; a ``probe`` skips the test. ``from_probes: true`` takes
size and lr from the same model's finished probe with the lowest validation Avg RMSE ("blocked-on-probes"
until all are done). ``models_from: best_baselines(N)`` stands for N entries NAME-1 .. NAME-N: the N
baselines whose control-id full runs reached the lowest validation Avg RMSE ("blocked-on-runs" until those
are done). Choices are made on validation scores only, never on the test.

Run directories (under the runs dir, and the same layout in the record)::

    probes/<name>/             a probe
    full/<setting>/<model>/    a full run: named by its model, so `nemsim bench collect --runs
                               <record>/full/*/*` names every model right without its best.pt

States: ``done`` (summary.json of the plan's budget, and test_metrics.json unless a probe; in the runs dir or
the record), ``partial`` (a last.pt or an earlier summary: ``nemsim train --resume`` continues its budget),
``pending``, ``blocked-on-probes``, ``blocked-on-runs``.
"""

from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from nemsim.data.splits import SETTINGS

RANK_SETTING = "control-id"  # best_baselines(N) ranks the baselines' full runs of this setting
RECORD_FILES = ("config.yaml", "metrics.csv", "test_metrics.json", "summary.json")  # summary.json last: it
# marks a record complete
_NAME = re.compile(r"^[a-z0-9][a-z0-9._-]*$")
_MODELS_FROM = re.compile(r"^best_baselines\((\d+)\)$")
_ENTRY_KEYS = {"name", "model", "setting", "minutes", "lr", "size", "probe", "from_probes", "models_from"}
_PLAN_KEYS = {"recipe", "record", "data", "splits", "make_data", "baselines", "sizes", "runs"}


class PlanError(ValueError):
    """A plan file that cannot be run as written (the CLI prints it as one line, exit code 2)."""


@dataclass(frozen=True)
class Entry:
    """One run of the plan (a ``models_from`` line becomes one Entry per rank)."""

    name: str
    setting: str
    minutes: float  # wall-clock budget of the run
    model: str | None = None  # None: the ``rank``-th strongest baseline
    size: str = "paper"  # a label of the plan's ``sizes`` for the model
    lr: float | None = None  # None: the recipe's
    probe: bool = False  # no test; its validation score chooses size and lr of ``from_probes`` entries
    from_probes: bool = False
    rank: int | None = None  # models_from: 1 = the strongest baseline


@dataclass(frozen=True)
class Plan:
    path: Path
    recipe: Path
    record: Path
    data: Path
    splits: Path
    make_data: tuple[str, ...]
    baselines: tuple[str, ...]
    sizes: dict[str, dict[str, dict[str, Any]]]
    entries: tuple[Entry, ...]

    def overrides(self, model: str, size: str) -> dict[str, Any]:
        """Model config overrides of ``model`` at ``size`` ("paper": none)."""
        return dict(self.sizes.get(model, {}).get(size, {}))

    def entry(self, name: str) -> Entry:
        for e in self.entries:
            if e.name == name:
                return e
        raise PlanError(f"{self.path}: no run named {name!r}; the runs are {[e.name for e in self.entries]}")


@dataclass(frozen=True)
class Choice:
    """What an entry trains, once known: model, size label and learning rate (None: the recipe's)."""

    model: str
    size: str
    lr: float | None


@dataclass(frozen=True)
class RunStatus:
    entry: Entry
    state: str  # done | partial | pending | blocked-on-probes | blocked-on-runs
    choice: Choice | None = None  # None while blocked
    spent_min: float | None = None  # the run's wall minutes so far (over resumes)
    best_val: float | None = None  # lowest validation Avg RMSE so far
    recorded: bool = False  # done, and its files are in the record


# ---- reading and checking the plan ----------------------------------------------------------------------


def _entry(plan_path: Path, raw: Any, baselines: tuple[str, ...]) -> list[Entry]:
    if not isinstance(raw, dict) or not isinstance(raw.get("name"), str):
        raise PlanError(f"{plan_path}: every run needs a mapping with a name, got {raw!r}")
    name = raw["name"]
    where = f"{plan_path}: run {name!r}"
    unknown = sorted(set(raw) - _ENTRY_KEYS)
    if unknown:
        raise PlanError(f"{where}: unknown keys {unknown}; expected some of {sorted(_ENTRY_KEYS)}")
    if not _NAME.match(name):
        raise PlanError(f"{where}: a name is lower-case letters, digits, '.', '_' and '-'")
    setting = raw.get("setting", RANK_SETTING)
    if setting not in SETTINGS:
        raise PlanError(f"{where}: unknown setting {setting!r}; expected one of {list(SETTINGS)}")
    minutes, lr = raw.get("minutes"), raw.get("lr")
    if not isinstance(minutes, int | float) or isinstance(minutes, bool) or not minutes > 0:
        raise PlanError(f"{where}: minutes must be a number > 0, got {minutes!r}")
    if lr is not None and (not isinstance(lr, int | float) or not lr > 0):
        raise PlanError(f"{where}: lr must be a number > 0, got {lr!r}")
    common = dict(name=name, setting=setting, minutes=float(minutes),
                  lr=None if lr is None else float(lr))  # fmt: skip
    if "models_from" in raw:
        match = _MODELS_FROM.match(str(raw["models_from"]))
        if not match or int(match.group(1)) < 1:
            raise PlanError(f"{where}: models_from must be best_baselines(N), N >= 1; "
                            f"got {raw['models_from']!r}")
        if {"model", "size", "lr", "probe", "from_probes"} & set(raw):
            raise PlanError(f"{where}: models_from takes model, size and lr from the ranked run; remove them")
        if int(match.group(1)) > len(baselines):
            raise PlanError(f"{where}: {raw['models_from']} of {len(baselines)} baselines")
        return [Entry(**{**common, "name": f"{name}-{k}", "lr": None}, rank=k)
                for k in range(1, int(match.group(1)) + 1)]  # fmt: skip
    if not isinstance(raw.get("model"), str):
        raise PlanError(f"{where}: needs a model (or models_from)")
    if raw.get("from_probes") and ({"size", "lr"} & set(raw) or raw.get("probe")):
        raise PlanError(f"{where}: from_probes takes size and lr from the probes; remove size, lr and probe")
    return [Entry(**common, model=raw["model"], size=str(raw.get("size", "paper")),
                  probe=bool(raw.get("probe", False)), from_probes=bool(raw.get("from_probes", False)))]


def _check(plan: Plan) -> None:
    """Models registered, sizes known and buildable, names and run directories unique, dependencies met."""
    from nemsim.registry import available_models, model_config

    models = available_models()
    for m in plan.baselines:
        if m not in models:
            raise PlanError(f"{plan.path}: baseline {m!r} is not a registered model; "
                            f"expected one of {models}")
    for model, sizes in plan.sizes.items():
        for size, overrides in sizes.items():
            try:
                model_config(model, None, overrides)
            except (ValueError, TypeError) as exc:
                raise PlanError(f"{plan.path}: sizes.{model}.{size}: {exc}") from None
    seen: dict[str, str] = {}
    for e in plan.entries:
        where = f"{plan.path}: run {e.name!r}"
        if e.model is not None and e.model not in models:
            raise PlanError(f"{where}: unknown model {e.model!r}; expected one of {models}")
        if e.model is not None and e.size != "paper" and e.size not in plan.sizes.get(e.model, {}):
            raise PlanError(f"{where}: no size {e.size!r} for {e.model} under sizes:")
        if e.from_probes and not any(p.probe and p.model == e.model for p in plan.entries):
            raise PlanError(f"{where}: from_probes, but the plan has no probe of {e.model}")
        key = f"probe {e.name}" if e.probe else f"{e.setting}/{e.model or f'rank {e.rank}'}"
        if e.name in seen.values() or key in seen:
            raise PlanError(f"{where}: repeats run {seen.get(key, e.name)!r} (name, or setting and model)")
        seen[key] = e.name
    if any(e.rank is not None for e in plan.entries):
        for m in plan.baselines:
            if len(_rank_entries(plan, m)) != 1:
                raise PlanError(f"{plan.path}: best_baselines(N) ranks one {RANK_SETTING} full run per "
                                f"baseline; {m} has {len(_rank_entries(plan, m))}")
        ranked = {e.setting for e in plan.entries if e.rank is not None}
        for e in plan.entries:
            if e.setting in ranked and e.model in plan.baselines and not e.probe:
                raise PlanError(f"{plan.path}: run {e.name!r}: {e.setting} takes its baselines from "
                                "best_baselines(N); a fixed baseline there could repeat one")


def read_plan(path: str | Path) -> Plan:
    """Parse and check a plan file; raises PlanError naming the file and the run."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise PlanError(f"plan file {path} does not exist")
    raw = yaml.safe_load(path.read_text()) or {}
    if not isinstance(raw, dict):
        raise PlanError(f"{path}: expected a mapping, got {type(raw).__name__}")
    unknown = sorted(set(raw) - _PLAN_KEYS)
    missing = sorted({"recipe", "record", "data", "splits", "runs"} - set(raw))
    if unknown or missing:
        raise PlanError(f"{path}: unknown keys {unknown}, missing keys {missing}")
    if not isinstance(raw["runs"], list) or not raw["runs"]:
        raise PlanError(f"{path}: runs must be a non-empty list")
    sizes = raw.get("sizes") or {}
    if not all(isinstance(s, dict) and all(isinstance(o, dict) for o in s.values()) for s in sizes.values()):
        raise PlanError(f"{path}: sizes must map MODEL: {{LABEL: {{overrides}}}}")
    baselines = tuple(raw.get("baselines") or ())
    entries = tuple(e for r in raw["runs"] for e in _entry(path, r, baselines))
    recipe = path.parent / str(raw["recipe"])
    if not recipe.is_file():
        raise PlanError(f"{path}: recipe {recipe} does not exist")
    plan = Plan(path=path, recipe=recipe, record=path.parent / str(raw["record"]),
                data=Path(str(raw["data"])), splits=Path(str(raw["splits"])),
                make_data=tuple(str(c) for c in raw.get("make_data") or ()), baselines=baselines,
                sizes={str(m): dict(s) for m, s in sizes.items()}, entries=entries)
    _check(plan)
    return plan


def _rank_entries(plan: Plan, model: str) -> list[Entry]:
    return [e for e in plan.entries
            if e.model == model and e.setting == RANK_SETTING and not e.probe and e.rank is None]  # fmt: skip


# ---- the configuration a run trains with ----------------------------------------------------------------


def run_config(plan: Plan, entry: Entry, choice: Choice) -> dict[str, Any]:
    """The merged ``nemsim train --config``: the recipe, the entry's budget and lr, the size's overrides."""
    from nemsim.training.config import read_config_file

    cfg, model = read_config_file(plan.recipe)
    changes: dict[str, Any] = {"max_train_minutes": entry.minutes, "progress": False}
    if choice.lr is not None:
        changes["lr"] = choice.lr
    try:
        cfg = cfg.replace(**changes)
    except ValueError as exc:
        raise PlanError(f"{plan.path}: run {entry.name!r}: {exc}") from None
    merged = json.loads(json.dumps(asdict(cfg)))  # tuples as lists: plain YAML
    merged["model"] = json.loads(json.dumps({**model, **plan.overrides(choice.model, choice.size)}))
    return merged


def config_text(plan: Plan, entry: Entry, choice: Choice) -> str:
    import yaml

    lr = choice.lr if choice.lr is not None else "of the recipe"
    head = (f"# {entry.name}: {choice.model} ({choice.size}), {entry.setting}, {entry.minutes:g} min, "
            f"lr {lr}; written by `nemsim bench compare` from {plan.path.name} and "
            f"{plan.recipe.name}\n")  # fmt: skip
    return head + yaml.safe_dump(run_config(plan, entry, choice), sort_keys=False)


# ---- where every run stands -------------------------------------------------------------------------------


def run_dir(root: Path, entry: Entry, choice: Choice | None) -> Path | None:
    """The entry's directory under ``root`` (runs dir or record); None while its model is unknown."""
    if entry.probe:
        return root / "probes" / entry.name
    return None if choice is None else root / "full" / entry.setting / choice.model


def best_val(d: Path) -> float | None:
    """Lowest validation Avg RMSE of a run directory: metrics.csv, else summary.json; None without one."""
    vals = []
    if (d / "metrics.csv").is_file():
        with (d / "metrics.csv").open(newline="") as f:
            vals = [float(r["val_avg_rmse"]) for r in csv.DictReader(f) if r.get("val_avg_rmse")]
    vals = [v for v in vals if math.isfinite(v)]
    if vals:
        return min(vals)
    summary = _json(d / "summary.json")
    if summary.get("select_metric") == "avg_rmse" and isinstance(summary.get("best_val"), int | float):
        return float(summary["best_val"]) if math.isfinite(summary["best_val"]) else None
    return None


def _json(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {}


def finished(d: Path, entry: Entry) -> dict[str, Any] | None:
    """The summary of ``d`` if the run there is done: trained to the entry's budget (or stopped early), and
    tested unless it is a probe."""
    summary = _json(d / "summary.json")
    budget = summary.get("budget_minutes")
    if not summary or not (summary.get("stopped_early") or (budget is not None and
                                                            math.isclose(budget, entry.minutes))):
        return None
    if not entry.probe and not (d / "test_metrics.json").is_file():
        return None
    return summary


def _last_wall_s(d: Path) -> float | None:
    """The run's wall seconds stored in last.pt (over resumes); None when unreadable."""
    try:
        from nemsim.inference.checkpoint import read_checkpoint

        return float(read_checkpoint(d / "last.pt").get("train_state", {}).get("wall_s"))
    except (OSError, ValueError, TypeError, RuntimeError, EOFError):
        return None


def measure(entry: Entry, choice: Choice, runs_dir: Path, record: Path) -> RunStatus:
    """Status of an entry whose choice is known, from the record and the runs dir."""
    scratch, kept = run_dir(runs_dir, entry, choice), run_dir(record, entry, choice)
    assert scratch is not None and kept is not None  # the choice is known
    for d, recorded in ((kept, True), (scratch, False)):
        summary = finished(d, entry)
        if summary is not None:
            return RunStatus(entry, "done", choice, summary.get("wall_s", 0.0) / 60, best_val(d), recorded)
    if (scratch / "last.pt").is_file() or (scratch / "summary.json").is_file():
        wall = _last_wall_s(scratch) if (scratch / "last.pt").is_file() else None
        if wall is None:
            wall = _json(scratch / "summary.json").get("wall_s")
        return RunStatus(entry, "partial", choice, None if wall is None else wall / 60, best_val(scratch))
    return RunStatus(entry, "pending", choice)


def _score(s: RunStatus) -> float:
    return s.best_val if s.best_val is not None and math.isfinite(s.best_val) else math.inf


def plan_status(plan: Plan, runs_dir: str | Path) -> list[RunStatus]:
    """The status of every entry, in plan order; choices deferred to probes or the ranking resolved when the
    runs they depend on are done (ties: the earlier entry wins)."""
    runs_dir = Path(runs_dir)
    out: dict[str, RunStatus] = {}
    fixed = [e for e in plan.entries if not e.from_probes and e.rank is None]
    for e in fixed:
        assert e.model is not None
        out[e.name] = measure(e, Choice(e.model, e.size, e.lr), runs_dir, plan.record)
    for e in plan.entries:
        if not e.from_probes:
            continue
        probes = [out[p.name] for p in plan.entries if p.probe and p.model == e.model]
        if all(p.state == "done" for p in probes):
            best = min(probes, key=_score)
            assert best.choice is not None
            out[e.name] = measure(e, Choice(best.choice.model, best.choice.size, best.choice.lr), runs_dir,
                                  plan.record)
        else:
            out[e.name] = RunStatus(e, "blocked-on-probes")
    ranked = [out[r.name] for m in plan.baselines for r in _rank_entries(plan, m)]
    ranked_done = all(r.state == "done" for r in ranked)
    order = sorted(ranked, key=_score)
    for e in plan.entries:
        if e.rank is None:
            continue
        if ranked_done and order[e.rank - 1].choice is not None:
            source = order[e.rank - 1].choice
            assert source is not None
            out[e.name] = measure(e, source, runs_dir, plan.record)
        else:
            out[e.name] = RunStatus(e, "blocked-on-runs")
    return [out[e.name] for e in plan.entries]


def record_run(status: RunStatus, runs_dir: Path, record: Path) -> Path | None:
    """Copy a done run's small files (RECORD_FILES) from the runs dir into the record; its record dir, or
    None when there is nothing to copy (already recorded, or not done in the runs dir)."""
    import shutil

    src = run_dir(runs_dir, status.entry, status.choice)
    dst = run_dir(record, status.entry, status.choice)
    if status.state != "done" or status.recorded or src is None or dst is None or not src.is_dir():
        return None
    dst.mkdir(parents=True, exist_ok=True)
    for name in RECORD_FILES:
        if (src / name).is_file():
            shutil.copyfile(src / name, dst / name)
    return dst


# ---- the table ------------------------------------------------------------------------------------------


def _fmt(v: float | None, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def format_status(statuses: list[RunStatus]) -> str:
    """A fixed-width table, one line per entry, and a line of totals (core-hours planned and spent)."""
    rows = [("name", "model", "size", "lr", "setting", "min spent/budget", "best val Avg RMSE", "state")]
    for s in statuses:
        e, c = s.entry, s.choice
        model = c.model if c else (e.model or f"best_baselines #{e.rank}")
        size = c.size if c else "?"
        lr = ("recipe" if c.lr is None else f"{c.lr:g}") if c else "?"
        state = s.state + ("" if s.state != "done" or s.recorded else " (not in the record)")
        rows.append((e.name, model, size, lr, e.setting, f"{_fmt(s.spent_min, '.1f')}/{e.minutes:g}",
                     _fmt(s.best_val, ".5f"), state))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    counts = {k: sum(s.state == k for s in statuses) for k in dict.fromkeys(s.state for s in statuses)}
    planned = sum(s.entry.minutes for s in statuses) / 60
    spent = sum(min(s.spent_min or 0.0, s.entry.minutes) for s in statuses) / 60
    lines.append(f"{len(statuses)} runs: " + ", ".join(f"{n} {k}" for k, n in counts.items())
                 + f"; {spent:.1f} of {planned:.1f} core-hours of budget spent")  # fmt: skip
    return "\n".join(lines)

