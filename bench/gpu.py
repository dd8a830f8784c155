"""The GPU measurements in one script: ``python -m bench.gpu --out DIR`` (check: ``--device cpu --quick``).

On the `small` scene with the served checkpoint (``checkpoints/nemsim-small.pt``), its config and weights
built with ``--domain`` (default ``quarter``: the network runs on the lower quadrant of the field,
``nemsim.symmetry``; the full-domain weights load unchanged):
  (a) ``call``: one network call (k states) on the model's input (the quadrant of x_0 for a quarter model),
      eager PyTorch against the CUDA-graph runtime (``nemsim.inference.cuda_graph``: copy in, replay, copy
      out), at batch 1 and 64, ms per call;
  (b) ``rollout``: a 100-step rollout of full fields from the scene's initial state under random in-box
      controls (a quarter model rolls the quadrant): eager ``rollout``, ``rollout`` through the CUDA-graph
      runtime (one replay per call) and the whole rollout as one graph (``CUDAGraphRuntime.rollout``), also
      of the eager kernels (``fuse=False``), and with the runtime's default fused capture (``GRAPH_OPTIONS``:
      ``torch.compile``'s kernels); ms per rollout at batch 1, per trajectory at batch 64;
  (c) ``agreement``: max |Δ| of each graphed result against eager (one call; whole trajectories); the
      fused capture apart (``agreement_reordered``: another float32 order, with the trajectories' RMSE to
      eager);
  (d) ``data``: the ``data:`` commands of the recipe (``--recipe``, default ``configs/nemsim-small.yaml``)
      at reduced size (``--recipe-cases``: the full-domain and the quarter-domain case counts), run
      in-process (``nemsim.cli.main``, ``generate --workers``) into a fresh folder under ``--scratch``, each
      timed; its full-domain trajectory file is the data of (e) unless ``--data`` names one;
  (e) ``train``: the training loop's own step (``nemsim.training.loop``: loss, backward, clip, AdamW;
      ``TrainConfig`` defaults, batch 24, the k-step loss of the served model's form, targets symmetrized,
      items on the model's domain) end to end, with the training set held in memory (``MemoryTransitions``
      on the device, as ``nemsim.training.run`` builds it; its decode time apart) and streamed (DataLoader
      over the HDF5 file, per loader worker count; and the loader alone), each against the same step on
      one batch already on the device; steps per second of each;
  (f) ``recipe``: the recipe's stages on the data of (d), each with ``--max-steps`` from ``--recipe-steps``
      (and a wall cap, ``--max-minutes``), in-process (``nemsim train --recipe``, ``--data-workers
      --workers``): the wall time of each stage (training loop, validation, setup, test), the last stage's
      test Avg RMSE, and an extrapolation of (d) and (f) to the full recipe (the case counts of its data
      commands, the step budgets of its stages' config files).

Timings: ``torch.cuda.synchronize`` before and after each timed repeat; medians (and minima) over repeats;
variants interleaved within a repeat. Every part has a time cap and the whole script a budget
(``--budget-s``; the default fits a 10-minute call with 16 simulator cores); a running data command, and
a stage's setup and test, are not interrupted: no command starts after the data part's cap, and each
stage's training loop stops at its share of the recipe part's. Results are written after every part and
every data command (``gpu.json``, ``gpu.md`` in ``--out``), so a part that fails or runs out of time
leaves the others; the recipe run's data and runs are under ``--scratch``, remade each time. Nothing
heavy is imported at module level: the simulator's worker processes are spawned and re-import this module.
"""

from __future__ import annotations

import argparse
import copy
import csv
import functools
import json
import logging
import math
import os
import platform
import shutil
import statistics
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger("bench.gpu")

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "checkpoints" / "nemsim-small.pt"
RECIPE = ROOT / "configs" / "nemsim-small.yaml"
TOL = 1e-5  # max |Δ| graphed vs eager, fp32
# eager first (the reference); graph_whole_quadrant: a quarter-domain model's states kept on the quadrant
# graph_*: the eager kernels captured (fuse=False, bit for bit); graph_whole_fused: the runtime's default,
# torch.compile's fused kernels captured (on the quadrant for a quarter model)
ROLLOUT_VARIANTS = ("eager", "graph_per_call", "graph_whole", "graph_whole_quadrant", "graph_whole_fused")
GRAPH_OPTIONS = {"fused": {"fuse": True}}  # variant name -> CUDAGraphRuntime options
TOL_REORDERED = 1e-3  # max |Δ| of a fused trajectory vs eager: another float32 order, TF32 as configured
TARGETS = {"rollout_b1_ms": 12.0, "rollout_b64_ms_per_traj": 1.0, "train_ratio": 1.5}  # on one H100
NEEDED = ("numpy", "h5py", "numba", "scipy", "yaml", "pydantic")  # third-party imports of the parts run here
DESIGN_N = 500  # cases of `nemsim design` / `generate` without --n
# part caps (seconds) on the GPU machine; the defaults fit the call's 10 minutes with startup to spare
CAPS = {"call": 35.0, "rollout": 60.0, "data": 150.0, "train": 80.0, "recipe": 150.0}

class Budget:
    """The script's wall-clock budget; each part gets ``min(cap, what is left)``."""

    def __init__(self, total_s: float) -> None:
        self.end = time.perf_counter() + total_s

    def left(self) -> float:
        return self.end - time.perf_counter()

    def cap(self, part_cap_s: float) -> float:
        return max(0.0, min(part_cap_s, self.left()))


def _sync(dev: Any) -> None:
    import torch

    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def time_variants(fns: dict[str, Callable[[], Any]], dev: Any, *, repeats: int, inner: int = 1,
                  cap_s: float = 60.0) -> dict[str, dict[str, Any]]:
    """Seconds per call of each function: ``repeats`` rounds (fewer if ``cap_s`` runs out), each timing
    ``inner`` calls of every variant in turn between two synchronizations. Returns {name: {"median_ms",
    "min_ms", "repeats"}}."""
    times: dict[str, list[float]] = {name: [] for name in fns}
    end = time.perf_counter() + cap_s
    for _ in range(repeats):
        for name, fn in fns.items():
            _sync(dev)
            t0 = time.perf_counter()
            for _ in range(inner):
                fn()
            _sync(dev)
            times[name].append((time.perf_counter() - t0) / inner)
        if time.perf_counter() > end:
            break
    return {name: {"median_ms": 1e3 * statistics.median(t), "min_ms": 1e3 * min(t), "repeats": len(t)}
            for name, t in times.items() if t}  # fmt: skip


def _max_diff(a: Any, b: Any) -> float:
    return float((a.float() - b.float()).abs().max())


def environment(dev: Any) -> dict[str, Any]:
    """Versions, device and machine."""
    import torch

    env: dict[str, Any] = {"python": platform.python_version(), "torch": torch.__version__,
                           "torch_cuda": torch.version.cuda, "cpu_count": os.cpu_count(),
                           "device": str(dev), "platform": platform.platform()}  # fmt: skip
    if dev.type == "cuda":
        props = torch.cuda.get_device_properties(dev)
        env.update(gpu=props.name, gpu_memory_gib=round(props.total_memory / 2**30, 1),
                   cudnn=torch.backends.cudnn.version(),
                   tf32_matmul=torch.backends.cuda.matmul.allow_tf32,
                   tf32_cudnn=torch.backends.cudnn.allow_tf32)  # fmt: skip
    return env


def graph_runtime(model: Any, dev: Any, **options: Any) -> tuple[Any, str | None]:
    """(CUDAGraphRuntime with ``options``, None), or (None, why not) on a device without CUDA graphs."""
    from nemsim.inference.cuda_graph import CUDAGraphRuntime, CUDAUnavailable

    if dev.type != "cuda":
        return None, f"device {dev}: CUDA graphs need a CUDA device"
    try:
        return CUDAGraphRuntime(model, device=dev, **{"fuse": False, **options}), None
    except CUDAUnavailable as exc:
        return None, str(exc)


def _inputs(x0: Any, batch: int, dev: Any, seed: int = 0) -> tuple[Any, Any]:
    """x0 (2, D, H, W) repeated to (B, 2, D, H, W) on dev; u (B, 14): uniform in the normalized design box."""
    import torch

    g = torch.Generator().manual_seed(seed + batch)
    u = torch.rand(batch, 14, generator=g) * 2 - 1  # (B, 14)
    return x0[None].repeat(batch, 1, 1, 1, 1).to(dev), u.to(dev)


def bench_calls(model: Any, x0: Any, dev: Any, batches: Sequence[int], repeats: int,
                cap_s: float) -> dict[str, Any]:
    """(a) one network call, eager against graphed (and their max |Δ|), per batch size."""
    from nemsim.inference.runtime import TorchRuntime

    eager = TorchRuntime(model)
    graphed, why = graph_runtime(model, dev)
    out: dict[str, Any] = {"graphed_unavailable": why} if why else {}
    for b in batches:
        out[f"b{b}"] = _calls_at(eager, graphed, x0, dev, b, repeats, cap_s / len(batches))
        log.info("call, batch %d: %s", b, _brief(out[f"b{b}"]))
    if graphed is not None:
        out["graphed_runtime"] = graphed.describe()  # backend "torch" here: a capture failed (and why)
    return out


def _calls_at(eager: Any, graphed: Any, x0: Any, dev: Any, b: int, repeats: int,
              cap_s: float) -> dict[str, Any]:
    import torch

    x, u = _inputs(x0, b, dev)
    row: dict[str, Any] = {}
    with torch.no_grad():
        ecache = eager.precompute(u)
        ref = eager.predict(x, ecache)  # (B, k, 2, D, H, W)
        fns: dict[str, Callable[[], Any]] = {"eager": lambda: eager.predict(x, ecache)}
        if graphed is not None:
            gcache = graphed.precompute(u)
            dst = torch.empty_like(ref)
            t0 = time.perf_counter()
            graphed.predict_into(x, gcache, dst)  # captures this batch size's graph
            _sync(dev)
            row["capture_s"] = time.perf_counter() - t0
            row["max_abs_diff"] = _max_diff(dst, ref)
            fns["graphed"] = lambda: graphed.predict_into(x, gcache, dst)
        for fn in fns.values():  # warm-up
            fn()
        row.update(time_variants(fns, dev, repeats=repeats, inner=10 if b == 1 else 3, cap_s=cap_s))
    return row


def bench_rollouts(model: Any, x0: Any, dev: Any, batches: Sequence[int], steps: int, repeats: int,
                   cap_s: float) -> dict[str, Any]:
    """(b) and (c): ``steps``-step rollouts, eager / one replay per call / one replay per rollout."""
    import torch

    from nemsim.inference.runtime import TorchRuntime

    eager = TorchRuntime(model)
    graphed, why = graph_runtime(model, dev)
    options = {n: graph_runtime(model, dev, **kw)[0] for n, kw in GRAPH_OPTIONS.items()} if graphed else {}
    out: dict[str, Any] = {"steps": steps, **({"graphed_unavailable": why} if why else {})}
    for b in batches:
        out[f"b{b}"] = _rollouts_at(eager, graphed, options, x0, dev, b, steps, repeats, cap_s / len(batches))
        log.info("rollout, batch %d: %s", b, _brief(out[f"b{b}"]))
        if dev.type == "cuda":
            torch.cuda.empty_cache()
    if graphed is not None:
        out["graphed_runtime"] = graphed.describe()
        out["option_runtimes"] = {name: rt.describe() for name, rt in options.items()}
    return out


def _rollouts_at(eager: Any, graphed: Any, options: dict[str, Any], x0: Any, dev: Any, b: int, steps: int,
                 repeats: int, cap_s: float) -> dict[str, Any]:
    import torch

    from nemsim.evaluation.rollout import rollout
    from nemsim.symmetry import fold, quarter_model_size, symmetrize

    x, u = _inputs(x0, b, dev)
    fns: dict[str, Callable[[], Any]] = {"eager": lambda: rollout(eager, x, u, steps)}
    if graphed is not None:
        fns["graph_per_call"] = lambda: rollout(graphed, x, u, steps)
        fns["graph_whole"] = lambda: graphed.rollout(x, u, steps)
        xo = x  # the options' input: the quadrant for a quarter model
        if quarter_model_size(graphed) is not None:  # the states left on the quadrant (the service's path)
            xq = xo = fold(symmetrize(x)).contiguous()
            fns["graph_whole_quadrant"] = lambda: graphed.rollout(xq, u, steps)
        for name, rt in options.items():
            fns[f"graph_whole_{name}"] = functools.partial(rt.rollout, xo, u, steps)
    row: dict[str, Any] = {}
    with torch.no_grad():
        trajs = {}
        for name, fn in fns.items():  # warm-up (and the captures)
            t0 = time.perf_counter()
            fn()
            _sync(dev)
            row[f"{name}_first_s"] = time.perf_counter() - t0
        for name, fn in fns.items():  # the trajectories compared: replays, as they are timed
            trajs[name] = fn()
            _sync(dev)
        for name in [n for n in fns if n != "eager"]:
            option = name.removeprefix("graph_whole_") in options
            got, want = trajs[name], trajs["eager"]
            if got.shape != want.shape:  # on the quadrant: after x_0 (the quadrant holds its symmetric mean)
                got, want = got[:, 1:], fold(want)[:, 1:]
            row[f"{name}_{'reordered_' if option else ''}max_abs_diff"] = _max_diff(got, want)
            if option:  # what another float32 order does to the score: RMSE of the two trajectories
                row[f"{name}_rmse_to_eager"] = float((got.float() - want.float()).pow(2).mean().sqrt())
        del trajs
        timed = time_variants(fns, dev, repeats=repeats, cap_s=cap_s)
    for t in timed.values():
        t["per_traj_ms"] = t["median_ms"] / b
        t["traj_per_s"] = 1e3 * b / t["median_ms"]
    row.update(timed)
    return row


def _brief(row: dict[str, Any]) -> str:
    parts = []
    for k, v in row.items():
        if isinstance(v, dict) and "median_ms" in v:
            parts.append(f"{k} {v['median_ms']:.3f} ms")
        elif isinstance(v, float):
            parts.append(f"{k} {v:.3g}")
    return ", ".join(parts)


def domain_model(loaded: Any, domain: str, dev: Any) -> tuple[Any, dict[str, Any]]:
    """(model, its config): the checkpoint's model rebuilt with ``domain`` ("full" or "quarter"), its weights
    loaded unchanged (the shapes do not depend on the domain), in eval mode on ``dev``."""
    from nemsim.registry import build_model

    config = {**loaded.config, "domain": domain, "full_size": 0}  # a quarter model: the size of the scene
    model = build_model(loaded.name, loaded.scene, loaded.rules, config)
    model.load_state_dict(loaded.model.state_dict())
    return model.to(dev).eval(), config


def model_input(x0: Any, domain: str) -> Any:
    """What one network call takes: x0 (2, D, H, W), or for a quarter model the quadrant of its symmetric
    mean (as ``rollout`` feeds it)."""
    from nemsim.symmetry import fold, symmetrize

    return fold(symmetrize(x0)).contiguous() if domain == "quarter" else x0


class _OutOfTime(Exception):
    pass


# ---- (d) the recipe's data, at reduced size ------------------------------------------------------------


def _value(words: Sequence[str], flag: str) -> str | None:
    """The value of ``flag`` in a command line (``--flag V`` or ``--flag=V``), None when absent."""
    for i, w in enumerate(words):
        if w == flag and i + 1 < len(words):
            return words[i + 1]
        if w.startswith(flag + "="):
            return w.partition("=")[2]
    return None


def _with(words: list[str], flag: str, value: str) -> list[str]:
    """``words`` with ``flag`` set to ``value`` (replaced where given, else appended)."""
    out = [w for w in words if not w.startswith(flag + "=")]
    if flag in out:
        out[out.index(flag) + 1] = value
        return out
    return [*out, flag, value]


def _relocated(word: str, work: Path) -> str:
    """A recipe word with its paths made absolute: ``data/...`` into ``work``, a repository file (a stage's
    --config) under the repository root; other words unchanged."""
    if word.startswith("data/"):
        return str(work / word)
    if "/" in word and not word.startswith("-") and (ROOT / word).exists():
        return str(ROOT / word)
    return word


def reduced_recipe(raw: dict[str, Any], work: Path, cases: tuple[int, int], steps: Sequence[int],
                   max_minutes: float | None = None,
                   sim_set: Sequence[str] = ()) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The recipe ``raw`` (its YAML mapping) at reduced size in ``work``, and per data command its reduced and
    full case counts ({"command", "cases", "full_cases"}; None for commands without cases).

    Data commands: ``data/...`` paths into ``work``; ``--n`` of the full-domain design and generate set to
    ``cases[0]``, of the quarter-domain ones (a generate with ``--sim-domain quarter`` and the design whose
    CSV it takes as ``--controls``) to ``cases[1]``; each generate gets ``--set KEY=VALUE`` of ``sim_set``.
    Stages: paths absolute, ``--max-steps`` of ``steps`` (one per stage) and, if given, ``--max-minutes``."""
    raw = copy.deepcopy(raw)
    data = [[str(w) for w in cmd] for cmd in raw.get("data") or []]
    quarter_csv = {_value(c, "--controls") for c in data
                   if c[0] == "generate" and _value(c, "--sim-domain") == "quarter"}  # fmt: skip
    design_n = {_value(c, "--out"): int(_value(c, "--n") or DESIGN_N) for c in data if c[0] == "design"}
    new_data, counts = [], []
    for cmd in data:
        quarter = _value(cmd, "--sim-domain") == "quarter" if cmd[0] == "generate" else (
            cmd[0] == "design" and _value(cmd, "--out") in quarter_csv)
        n = cases[1] if quarter else cases[0]
        full: int | None = None
        if cmd[0] == "design":
            full, cmd = int(_value(cmd, "--n") or DESIGN_N), _with(cmd, "--n", str(n))
        elif cmd[0] == "generate":
            given, controls = _value(cmd, "--n"), _value(cmd, "--controls")
            full = int(given) if given else design_n.get(controls, DESIGN_N) if controls else DESIGN_N
            if given or not controls:  # a --controls file of the reduced design holds n rows already
                cmd = _with(cmd, "--n", str(n))
            cmd += [w for kv in sim_set for w in ("--set", kv)]
        counts.append({"command": cmd[0], "quarter": quarter, "cases": n if full else None,
                       "full_cases": full})
        new_data.append([_relocated(w, work) for w in cmd])
    stages = raw["stages"]
    if len(steps) != len(stages):
        raise ValueError(f"--recipe-steps gives {len(steps)} step budgets for {len(stages)} stages")
    for stage, s in zip(stages, steps, strict=True):
        args = [_relocated(str(w), work) for w in stage.get("args") or []] + ["--max-steps", str(s)]
        stage["args"] = args + (["--max-minutes", f"{max_minutes:.4g}"] if max_minutes else [])
    if new_data:
        raw["data"] = new_data
    return raw, counts


def _cli(nemsim: Callable[[list[str]], int], argv: list[str]) -> tuple[int, str]:
    """(exit code, the end of what it wrote to stderr) of one in-process `nemsim` command; its stderr is
    passed on too (a failing command says why there, in one line)."""
    import contextlib
    import io

    buf = io.StringIO()
    try:
        with contextlib.redirect_stderr(buf):
            code = nemsim(argv)
    finally:
        sys.stderr.write(buf.getvalue())
    return code, buf.getvalue()[-2000:]


def recipe_dir(args: argparse.Namespace) -> Path:
    nf, nq = args.recipe_cases
    return Path(args.scratch) / f"recipe-{nf}-{nq}"


def _case_seconds(path: str | Path) -> list[float]:
    """The simulator's wall seconds of every complete case of a trajectory file (its case metadata)."""
    from nemsim.data.hdf5 import open_trajectories

    with open_trajectories(path) as tf:
        return [float(tf.case_meta(r).get("wall_s", math.nan)) for r in range(len(tf.case_ids))
                if tf.complete[r]]  # fmt: skip


def generate_extrapolation(wall_s: float, cases: int, full: int, workers: int,
                           case_s: Sequence[float]) -> dict[str, Any]:
    """The wall time of a generate of ``full`` cases from one of ``cases`` that took ``wall_s`` on ``workers``
    processes. ``scaled``: ``wall_s`` times the ratio of cases per worker (the per-process start-up and
    numba compile scaled too: an upper bound). ``per_case``: the start-up (``wall_s`` less the measured
    cases' share) once, plus the full cases per worker at the median seconds of the cases that did not
    compile (the fastest ``cases - workers``; a worker's first case compiles the kernels)."""
    w = max(1, min(workers, cases))
    per_worker, full_per_worker = math.ceil(cases / w), math.ceil(full / max(1, workers))
    out: dict[str, Any] = {"scaled_s": wall_s * full_per_worker / per_worker}
    warm = sorted(s for s in case_s if math.isfinite(s))[: max(0, len(case_s) - w)]
    if warm:
        per_case = statistics.median(warm)
        startup = max(0.0, wall_s - per_worker * per_case)
        out.update(case_s=per_case, startup_s=startup, per_case_s=startup + full_per_worker * per_case)
    return out


def recipe_data(args: argparse.Namespace, cap_s: float, progress: Callable[[dict[str, Any]], None],
                only_full: bool = False) -> dict[str, Any]:
    """(d) The recipe's data commands at reduced size (``reduced_recipe``), in order, each timed, in a fresh
    folder; ``only_full``: only the full-domain generate (the data of (e) when the recipe part is skipped).
    A command is not started after ``cap_s``; ``progress`` gets the figures after each command."""
    import yaml

    from nemsim.cli import main as nemsim
    from nemsim.training.recipe import recipe_from_dict, run_recipe_data

    work = recipe_dir(args)
    if work.exists():  # fresh: the times are those of the commands run now
        shutil.rmtree(work)
    work.mkdir(parents=True)
    raw, counts = reduced_recipe(yaml.safe_load(Path(args.recipe).read_text()), work, args.recipe_cases,
                                 args.recipe_steps, sim_set=args.sim_set)  # fmt: skip
    if only_full:
        keep = [i for i, c in enumerate(counts) if c["command"] == "generate" and not c["quarter"]][:1]
        raw["data"], counts = [raw["data"][i] for i in keep], [counts[i] for i in keep]
    (work / "recipe.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
    recipe = recipe_from_dict(raw)
    out: dict[str, Any] = {"work": str(work), "recipe": str(args.recipe), "workers": args.workers,
                           "sim_set": list(args.sim_set), "commands": []}  # fmt: skip
    full_h5 = [cmd for cmd, c in zip(raw["data"], counts, strict=True)
               if c["command"] == "generate" and not c["quarter"]]  # fmt: skip
    if full_h5:
        out["path"] = _value(full_h5[0], "--out")
    end = time.perf_counter() + cap_s
    rows = iter(counts)

    def run(words: list[str]) -> int:
        count = next(rows)
        if time.perf_counter() > end:
            raise _OutOfTime(f"stopped before `{words[0]}`: the part's {cap_s:.0f} s are spent")
        extra = ["--workers", str(args.workers), "--no-progress"] if words[0] == "generate" else []
        t0 = time.perf_counter()
        code, err = _cli(nemsim, [*words, *extra])
        row = {**count, "out": Path(_value(words, "--out") or "").name, "wall_s": time.perf_counter() - t0,
               "exit": code, **({"stderr": err} if code else {})}  # fmt: skip
        if words[0] == "generate" and code == 0:
            row["extrapolation"] = generate_extrapolation(
                row["wall_s"], count["cases"], count["full_cases"], args.workers,
                _case_seconds(_value(words, "--out") or ""))
        out["commands"].append(row)
        log.info("data: %s", row)
        progress(out)
        return code

    try:
        run_recipe_data(recipe, run, echo=lambda line: log.info("recipe %s", line))
        out["complete"] = True
    except (_OutOfTime, RuntimeError) as exc:  # a command not started, or one that failed (its exit code)
        out["stopped"] = str(exc)
    out["wall_s"] = sum(r["wall_s"] for r in out["commands"])
    return out


# ---- (e) the training step ------------------------------------------------------------------------------


def bench_train(args: argparse.Namespace, data_path: str, dev: Any, cap_s: float) -> dict[str, Any]:
    """(e) the training loop's step end to end, the training set in memory and streamed from the HDF5 file
    (per DataLoader worker count; and the loader alone), against the same step on a batch already on the
    device. The in-memory variant runs first (the pipeline the recipe trains with)."""
    from nemsim.data.dataset import MemoryTransitions, TransitionDataset
    from nemsim.evaluation.rollout import steps_per_call
    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.training.config import TrainConfig
    from nemsim.training.loop import Clock, ModelMeta, TrainData, _Run

    loaded = load_checkpoint(args.checkpoint, device="cpu")
    k = steps_per_call(loaded.model)
    quarter = args.domain == "quarter"

    def dataset() -> Any:
        return TransitionDataset(data_path, None, "train", unroll=k, symmetrize=True, quarter=quarter)

    probe = dataset()
    if len(probe) < args.train_batch:
        raise ValueError(f"{data_path} holds {len(probe)} training items (complete cases: "
                         f"{len(probe.rows)}); a batch needs {args.train_batch}")
    steps = args.train_steps
    out: dict[str, Any] = {"domain": args.domain, "cases": len(probe.rows), "items": len(probe),
                           "steps_timed": steps, "steps_per_call": k}  # fmt: skip
    probe.close()
    end = time.perf_counter() + cap_s
    device_step: float | None = None
    variants = [("memory", None)] + [(f"streamed_w{w}", w) for w in args.loader_workers]
    for name, workers in variants:
        if time.perf_counter() > end:
            out[name] = {"skipped": "time cap"}
            continue
        cfg = TrainConfig(batch_size=args.train_batch, num_workers=workers or 0, device=str(dev),
                          progress=False, batches_per_epoch=steps, warmup_steps=1, seed=0,
                          symmetrize_targets=True, in_memory=workers is None)  # fmt: skip
        res: dict[str, Any] = {}
        if workers is None:
            t0 = time.perf_counter()
            train_set = MemoryTransitions([dataset()], device=dev)
            _sync(dev)
            res.update(decode_s=time.perf_counter() - t0, held_on=str(train_set.device),
                       gib=round(train_set.states.numel() * 2 / 2**30, 3))
        else:
            train_set = dataset()
        model, mconfig = domain_model(loaded, args.domain, "cpu")
        meta = ModelMeta(loaded.name, mconfig, loaded.scene, loaded.rules)
        run = _Run(cfg, model, TrainData(train=train_set, val=[]), Path(args.scratch) / "run", meta, Clock())
        run.start()
        run.train_epoch(0)  # warm-up: workers start, kernels are selected
        c0 = time.process_time()
        row = run.train_epoch(1)
        res.update(e2e_step_ms=1e3 * row["epoch_seconds"] / steps,
                   main_cpu_s_per_step=(time.process_time() - c0) / steps)
        res["steps_per_s"] = 1e3 / res["e2e_step_ms"]
        if workers is not None:
            res["loader_only_ms_per_batch"] = _loader_ms(run.loader, steps, end)
        if device_step is None:
            device_step = _in_memory_step_ms(run, dev, steps, max(end - time.perf_counter(), 1.0))
            out["device_step_ms"], out["device_steps_per_s"] = device_step, 1e3 / device_step
            log.info("train, one batch on the device: %.1f ms/step", device_step)
        res["ratio_to_device"] = res["e2e_step_ms"] / device_step
        out[name] = res
        out["bf16"], out["batch"] = cfg.bf16, cfg.batch_size
        log.info("train, %s: %s", name, res)
        del run, model, train_set
        if dev.type == "cuda":
            import torch

            torch.cuda.empty_cache()
    return out


def _loader_ms(loader: Any, batches: int, end: float) -> float:
    """ms per batch of the training DataLoader alone (reading, decoding, collating; no model)."""
    it = iter(loader)
    t0, n = time.perf_counter(), 0
    for _ in range(batches):
        next(it)
        n += 1
        if time.perf_counter() > end:
            break
    return 1e3 * (time.perf_counter() - t0) / n


def _in_memory_step_ms(run: Any, dev: Any, steps: int, cap_s: float) -> float:
    """The loop's step (loss, backward, clip, AdamW, reading the loss) on one batch already on ``dev``."""
    import torch

    x, u, y = (t.to(dev) for t in next(iter(run.loader)))
    params = list(run.model.parameters())

    def step() -> None:
        loss = run.loss(x, u, y)
        run.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, run.cfg.grad_clip)
        run.optimizer.step()
        float(loss.detach())  # the loop reads every step's loss

    run.train_model.train()
    step()
    return time_variants({"step": step}, dev, repeats=steps, cap_s=cap_s)["step"]["median_ms"]


# ---- (f) the recipe's stages ----------------------------------------------------------------------------


def bench_recipe(args: argparse.Namespace, data: dict[str, Any], dev: Any, cap_s: float) -> dict[str, Any]:
    """(f) The recipe's stages at reduced size on the data of (d), in-process through `nemsim train --recipe`
    (its data commands find their outputs and are skipped or resume at once); each stage's training loop
    is capped at ``cap_s`` / stages (``--max-minutes``). The figures of each stage come from what it
    writes (``stage_figures``)."""
    import yaml

    from nemsim.cli import main as nemsim

    work = Path(data["work"])
    raw = yaml.safe_load(Path(args.recipe).read_text())
    minutes = max(cap_s / len(raw["stages"]) / 60.0, 0.05)
    raw, counts = reduced_recipe(raw, work, args.recipe_cases, args.recipe_steps, max_minutes=minutes,
                                 sim_set=args.sim_set)
    path = work / "recipe.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    runs = work / "runs"
    if runs.exists():
        shutil.rmtree(runs)
    argv = ["train", "--recipe", str(path), "--out", str(runs), "--device", str(dev), "--data-workers",
            str(args.workers), "--no-progress"]  # fmt: skip
    t0 = time.time()  # the stages' files carry file-system times
    code, err = _cli(nemsim, argv)
    out: dict[str, Any] = {"exit": code, "wall_s": time.time() - t0, "max_minutes_per_stage": minutes,
                           "stages": [], **({"stderr": err} if code else {})}  # fmt: skip
    full = {c["quarter"]: c["full_cases"] for c in counts if c["command"] == "generate"}
    start = t0
    for stage in raw["stages"]:
        folder = runs / stage["name"]
        if not (folder / "stage.json").is_file():
            out["stages"].append({"name": stage["name"], "finished": False})
            break
        done = (folder / "stage.json").stat().st_mtime
        row = stage_figures(stage, folder, done - start, full.get(False, DESIGN_N), full.get(True, 0))
        out["stages"].append(row)
        log.info("recipe, stage %s: %s", stage["name"], row)
        start = done
        if (folder / "test_metrics.json").is_file():
            out["test_avg_rmse"] = json.loads((folder / "test_metrics.json").read_text())["avg_rmse"]
            out["test_stage"] = stage["name"]
    stages = out["stages"]
    if stages and all("extrapolated_s" in s for s in stages) and len(stages) == len(raw["stages"]):
        gen = [c.get("extrapolation", {}) for c in data.get("commands", [])]
        data_s = sum(e.get("per_case_s", e.get("scaled_s", 0.0)) for e in gen) + sum(
            c["wall_s"] for c in data.get("commands", []) if "extrapolation" not in c)
        out["extrapolation"] = {"data_s": data_s, "stages_s": sum(s["extrapolated_s"] for s in stages),
                                "total_s": data_s + sum(s["extrapolated_s"] for s in stages),
                                "workers": args.workers}  # fmt: skip
    return out


def stage_figures(stage: dict[str, Any], folder: Path, wall_s: float, full_cases: int,
                  full_extra: int) -> dict[str, Any]:
    """One finished stage: its wall time split into the training loop (of which validation), the test of
    best.pt and the rest (setup: data decode, model build), and their extrapolation to the stage's budget
    in its config file (``max_steps``) on the full data (``full_cases`` cases of the main file, of which the
    control-id split's shares, and ``full_extra`` of --extra-data): steps by the step time, validation by
    rounds (an epoch of ``batches_per_epoch`` steps) times cases, the test by cases, an in-memory setup by
    training cases."""
    args = [str(w) for w in stage["args"]]
    summary = json.loads((folder / "stage.json").read_text())["summary"]
    steps, loop, val = int(summary["steps"]), float(summary["wall_s"]), float(summary["val_wall_s"])
    test = folder / "test_metrics.json"
    test_s = test.stat().st_mtime - (folder / "summary.json").stat().st_mtime if test.is_file() else 0.0
    row: dict[str, Any] = {"name": stage["name"], "finished": True, "wall_s": wall_s, "steps": steps,
                           "loop_s": loop, "val_s": val, "test_s": test_s,
                           "setup_s": max(0.0, wall_s - loop - test_s),
                           "steps_per_s": steps / max(loop - val, 1e-9),
                           "batch": summary["train_config"]["batch_size"],
                           "device_type": str(summary["train_config"]["device"]).split(":")[0]}  # fmt: skip
    row["items_per_s"] = row["steps_per_s"] * row["batch"]
    try:
        row.update(_stage_extrapolation(args, folder, row, full_cases, full_extra))
    except Exception as exc:  # noqa: BLE001 -- the measured figures stand without it
        row["extrapolation_error"] = f"{type(exc).__name__}: {exc}"
    return row


def _stage_extrapolation(args: list[str], folder: Path, row: dict[str, Any], full_cases: int,
                         full_extra: int) -> dict[str, Any]:
    """The extrapolation of ``stage_figures`` (its docstring) from the stage's files and arguments."""
    from nemsim.data.splits import CONTROL_ID_FRACTIONS
    from nemsim.training.config import TrainConfig, read_config_file

    steps, loop, val, test_s = row["steps"], row["loop_s"], row["val_s"], row["test_s"]
    with open(folder / "metrics.csv", newline="") as f:
        rounds = sum(1 for r in csv.DictReader(f) if r.get("val_avg_rmse"))
    config = _value(args, "--config")
    cfg = (read_config_file(config)[0] if config else TrainConfig()).resolved(row.get("device_type", "cuda"))
    if cfg.max_steps is None:
        return {}
    manifest = json.loads((Path(_value(args, "--splits") or "") / f"{_value(args, '--setting')}.json")
                          .read_text())  # fmt: skip
    n_train, n_val, n_test = (len(manifest[s]) for s in ("train", "val", "test"))
    extra = sum(_complete_cases(p) for i, p in enumerate(args) if i and args[i - 1] == "--extra-data")
    f_train, f_val, _ = CONTROL_ID_FRACTIONS
    full_train, full_val = round(f_train * full_cases), round(f_val * full_cases)
    full_test = full_cases - full_train - full_val
    vcases, full_vcases = _capped(n_val, cfg.val_cases), _capped(full_val, cfg.val_cases)
    tcases, full_tcases = _capped(n_test, cfg.test_cases), _capped(full_test, cfg.test_cases)
    per_epoch = cfg.batches_per_epoch
    full_rounds = (math.ceil(math.ceil(cfg.max_steps / per_epoch) / cfg.val_every) if per_epoch
                   else rounds * cfg.max_steps / max(steps, 1))  # fmt: skip
    setup_scale = (full_train + full_extra) / max(n_train + extra, 1) if cfg.in_memory else 1.0
    parts = {"steps_s": (loop - val) / max(steps, 1) * cfg.max_steps,
             "val_s": val / max(rounds * vcases, 1) * full_rounds * full_vcases,
             "test_s": test_s / max(tcases, 1) * full_tcases if test_s else 0.0,
             "setup_s": row["setup_s"] * setup_scale}  # fmt: skip
    return {"full_steps": cfg.max_steps, "val_rounds": rounds, "val_cases": vcases,
            "full_val_rounds": full_rounds, "full_val_cases": full_vcases,
            "test_cases": tcases if test_s else 0, "full_test_cases": full_tcases if test_s else 0,
            "full_parts_s": parts,
            "extrapolated_s": sum(parts.values())}  # fmt: skip


def _capped(n: int, cap: int | None) -> int:
    return n if cap is None else min(n, cap)


def _complete_cases(path: str) -> int:
    from nemsim.data.hdf5 import open_trajectories

    with open_trajectories(path) as tf:
        return int(tf.complete.sum())


# ---- report ---------------------------------------------------------------------------------------------


def write_report(out_dir: Path, results: dict[str, Any]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "gpu.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
    (out_dir / "gpu.md").write_text(markdown(results))


def _ms(row: dict[str, Any] | None, key: str, field: str = "median_ms") -> str:
    v = (row or {}).get(key)
    return f"{v[field]:.3f}" if isinstance(v, dict) and field in v else "-"


def _f(v: Any, fmt: str = ".3g") -> str:
    return format(v, fmt) if isinstance(v, (int, float)) and not isinstance(v, bool) else "-"


def markdown(res: dict[str, Any]) -> str:
    env, model = res.get("environment", {}), res.get("model", {})
    lines = [f"# GPU measurements ({env.get('gpu', env.get('device', '?'))})", "",
             f"`python -m bench.gpu {' '.join(res.get('argv', []))}`; torch {env.get('torch')}, CUDA "
             f"{env.get('torch_cuda')}, {env.get('cpu_count')} CPU cores; the `small` served checkpoint on "
             f"the **{model.get('domain', '?')}** domain (call input {model.get('call_input', '?')}); "
             "medians over repeats (synchronized).", ""]  # fmt: skip
    calls = res.get("call", {})
    if calls:
        lines += ["## Network call (k states), ms", "", "| batch | eager | graphed | max abs diff |",
                  "|---:|---:|---:|---:|"]
        for key, row in calls.items():
            if key.startswith("b") and isinstance(row, dict):
                lines.append(f"| {key[1:]} | {_ms(row, 'eager')} | {_ms(row, 'graphed')} | "
                             f"{row.get('max_abs_diff', '-')} |")
        lines.append("")
    roll = res.get("rollout", {})
    if roll:
        lines += [f"## {roll.get('steps')}-step rollout", "",
                  "| batch | variant | ms per rollout | ms per trajectory | trajectories/s | max abs diff |",
                  "|---:|---|---:|---:|---:|---:|"]  # fmt: skip
        for key, row in roll.items():
            if not (key.startswith("b") and isinstance(row, dict)):
                continue
            for name in ROLLOUT_VARIANTS:
                if name in row:
                    t = row[name]
                    diff = row.get(f"{name}_max_abs_diff", row.get(f"{name}_reordered_max_abs_diff",
                                                                    "-" if name != "eager" else "ref"))
                    lines.append(f"| {key[1:]} | {name} | {t['median_ms']:.2f} | {t['per_traj_ms']:.3f} | "
                                 f"{t['traj_per_s']:.0f} | {diff} |")
        lines.append("")
    if "agreement" in res:
        lines += ["## Agreement", "", f"max abs diff graphed vs eager: {res['agreement']}", ""]
    if "agreement_reordered" in res:
        rmse = {f"b{key[1:]} {k.removesuffix('_rmse_to_eager')}": f"{v:.2e}" for key, row in roll.items()
                if key.startswith("b") and isinstance(row, dict)
                for k, v in row.items() if k.endswith("_rmse_to_eager")}  # fmt: skip
        lines += [f"fused (another float32 order) vs eager: {res['agreement_reordered']}; trajectory "
                  f"RMSE to eager: {rmse}", ""]
    if "targets" in res:
        lines += ["## Targets", "", "| target | value | met |", "|---|---:|---|"]
        lines += [f"| {k} | {v['value']:.3g} (<= {v['target']}) | {v['met']} |"
                  for k, v in res["targets"].items()]
        lines.append("")
    lines += _train_md(res.get("train", {}))
    lines += _recipe_md(res.get("data", {}), res.get("recipe", {}))
    for part in ("call", "rollout"):
        row = res.get(part, {})
        why = row.get("graphed_unavailable") or row.get("graphed_runtime", {}).get("fallback_reason")
        if why:
            lines += [f"{part}: no CUDA graph ({why})", ""]
    errors = {k: v["error"] for k, v in res.items() if isinstance(v, dict) and "error" in v}
    if errors:
        lines += ["## Errors", ""] + [f"- {k}: {v.splitlines()[-1] if v else v}" for k, v in errors.items()]
    return "\n".join(lines) + "\n"


def _train_md(train: dict[str, Any]) -> list[str]:
    if not train or "error" in train:
        return []
    lines = ["## Training step", "",
             f"{train.get('cases')} cases ({train.get('items')} items), batch {train.get('batch')}, bf16 "
             f"{train.get('bf16')}, {train.get('steps_timed')} steps timed, domain {train.get('domain')}; "
             f"one batch already on the device: {_f(train.get('device_step_ms'), '.2f')} ms/step "
             f"({_f(train.get('device_steps_per_s'), '.1f')} steps/s).", "",
             "| pipeline | ms/step end to end | steps/s | ratio to on-device | loader alone, ms/batch | "
             "decode, s |", "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for key, row in train.items():
        if not (isinstance(row, dict) and (key == "memory" or key.startswith("streamed_w"))):
            continue
        what = (f"in memory ({row.get('held_on', '?')}, {row.get('gib', '?')} GiB)" if key == "memory"
                else f"streamed, {key.removeprefix('streamed_w')} loader workers")  # fmt: skip
        if "skipped" in row:
            lines.append(f"| {what} | skipped: {row['skipped']} | | | | |")
            continue
        lines.append(f"| {what} | {_f(row.get('e2e_step_ms'), '.2f')} | {_f(row.get('steps_per_s'), '.1f')} "
                     f"| {_f(row.get('ratio_to_device'), '.2f')} | "
                     f"{_f(row.get('loader_only_ms_per_batch'), '.1f')} | {_f(row.get('decode_s'), '.2f')} |")
    return lines + [""]


def _recipe_md(data: dict[str, Any], recipe: dict[str, Any]) -> list[str]:
    if not data.get("commands") and not recipe.get("stages"):
        return []
    sim_set = f", simulator overrides {', '.join(data['sim_set'])}" if data.get("sim_set") else ""
    lines = [f"## Recipe at reduced size ({Path(str(data.get('recipe', RECIPE))).name}, "
             f"{data.get('workers')} simulator workers{sim_set})", ""]
    if data.get("commands"):
        lines += ["| data command | cases | wall s | full cases | full, s (scaled per worker) | "
                  "full, s (start-up + per case) |", "|---|---:|---:|---:|---:|---:|"]
        for c in data["commands"]:
            e = c.get("extrapolation", {})
            what = f"{c['command']} {c.get('out', '')}" + (" (quarter)" if c.get("quarter") else "")
            lines.append(f"| {what} | {c.get('cases') or '-'} | {c['wall_s']:.1f} | "
                         f"{c.get('full_cases') or '-'} | {_f(e.get('scaled_s'), '.0f')} | "
                         f"{_f(e.get('per_case_s'), '.0f')} |")
        if data.get("stopped"):
            why = [c["stderr"].strip().splitlines()[-1] for c in data["commands"]
                   if c.get("stderr", "").strip()]  # fmt: skip
            lines.append(f"\ndata stopped: {data['stopped']}" + (f" ({why[-1]})" if why else ""))
        lines.append("")
    if recipe.get("stages"):
        lines += ["| stage | steps | wall s | loop s | of which val s | test s | setup s | steps/s | "
                  "full steps | full, s (extrapolated) |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for s in recipe["stages"]:
            if not s.get("finished"):
                lines.append(f"| {s['name']} | not finished | | | | | | | | |")
                continue
            lines.append(f"| {s['name']} | {s['steps']} | {s['wall_s']:.1f} | {s['loop_s']:.1f} | "
                         f"{s['val_s']:.1f} | {s['test_s']:.1f} | {s['setup_s']:.1f} | "
                         f"{s['steps_per_s']:.2f} | {s.get('full_steps', '-')} | "
                         f"{_f(s.get('extrapolated_s'), '.0f')} |")
        lines.append("")
        if "test_avg_rmse" in recipe:
            lines.append(f"Test Avg RMSE of stage {recipe.get('test_stage')} (after the reduced budgets): "
                         f"{recipe['test_avg_rmse']:.5f}")
        if recipe.get("exit"):
            why = (recipe.get("stderr") or "").strip().splitlines()[-1:] or [""]
            lines.append(f"`nemsim train --recipe` exited with {recipe['exit']}: {why[0]}")
        lines.append("")
    ext = recipe.get("extrapolation")
    if ext:
        lines += [f"**Extrapolation, not a measurement**: the full recipe on this machine with "
                  f"{ext['workers']} simulator workers would take about {ext['total_s'] / 60:.0f} min: data "
                  f"{ext['data_s'] / 60:.1f} min (each generate's start-up once plus its full cases per "
                  f"worker at the measured seconds per case), stages {ext['stages_s'] / 60:.1f} min (step "
                  "time times the config files' max_steps, validation by rounds and cases, the test by "
                  "cases, the in-memory decode by training cases).", ""]  # fmt: skip
    return lines


def summarize(res: dict[str, Any]) -> None:
    """The agreement figure and the issue's targets, from the parts that ran."""
    diffs = {}
    for part in ("call", "rollout"):
        for key, row in res.get(part, {}).items():
            if isinstance(row, dict):
                diffs.update({f"{part}_{key}_{k}": v for k, v in row.items() if k.endswith("max_abs_diff")})
    exact = {k: v for k, v in diffs.items() if "_reordered_" not in k}
    reordered = {k: v for k, v in diffs.items() if "_reordered_" in k}
    if exact:
        res["agreement"] = {"max": max(exact.values()), "tolerance": TOL, "agree": max(exact.values()) < TOL,
                            "each": exact}  # fmt: skip
    if reordered:
        res["agreement_reordered"] = {"max": max(reordered.values()), "tolerance": TOL_REORDERED,
                                      "agree": max(reordered.values()) < TOL_REORDERED,
                                      "each": reordered}  # fmt: skip
    targets: dict[str, Any] = {}
    roll = res.get("rollout", {})
    best_b1 = [roll.get("b1", {}).get(n, {}).get("median_ms") for n in ROLLOUT_VARIANTS[1:]]
    best_b64 = [roll.get("b64", {}).get(n, {}).get("per_traj_ms") for n in ROLLOUT_VARIANTS[1:]]
    if any(v is not None for v in best_b1):
        targets["rollout_b1_ms"] = min(v for v in best_b1 if v is not None)
    if any(v is not None for v in best_b64):
        targets["rollout_b64_ms_per_traj"] = min(v for v in best_b64 if v is not None)
    ratios = [v.get("ratio_to_device") for v in res.get("train", {}).values() if isinstance(v, dict)]
    if any(r is not None for r in ratios):
        targets["train_ratio"] = min(r for r in ratios if r is not None)
    res["targets"] = {k: {"value": v, "target": TARGETS[k], "met": v <= TARGETS[k]}
                      for k, v in targets.items()}


def _part(results: dict[str, Any], name: str, out_dir: Path, fn: Callable[[], dict[str, Any]]) -> None:
    """Run one part; its error (with traceback) is recorded instead of ending the script."""
    t0 = time.perf_counter()
    try:
        results[name] = fn()
    except Exception:  # noqa: BLE001 -- one failing part must not lose the others' figures
        results[name] = {"error": traceback.format_exc(limit=8)}
        log.error("part %s failed:\n%s", name, results[name]["error"])
    results.setdefault("part_seconds", {})[name] = time.perf_counter() - t0
    summarize(results)
    write_report(out_dir, results)


def _pair(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m bench.gpu", description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, type=Path, help="folder for gpu.json and gpu.md")
    p.add_argument("--device", default="cuda", help="cuda (default), cuda:N or cpu (a check of the script)")
    p.add_argument("--checkpoint", type=Path, default=CHECKPOINT)
    p.add_argument("--domain", choices=("full", "quarter"), default="quarter",
                   help="the domain the checkpoint's model is built with for call, rollout and train "
                        "(default quarter)")
    p.add_argument("--data", default=None,
                   help="a `small` trajectory .h5 for the train part (default: the recipe's full-domain "
                        "data)")
    p.add_argument("--scratch", default="/tmp/nemsim-bench-gpu", help="the recipe's data and runs")
    p.add_argument("--recipe", type=Path, default=RECIPE, help="the recipe of the data and recipe parts")
    p.add_argument("--recipe-cases", type=_pair, default=None, metavar="N_FULL,N_QUARTER",
                   help="cases of the recipe's full- and quarter-domain data (default 32,64; --quick 4,4)")
    p.add_argument("--recipe-steps", type=_pair, default=None, metavar="S1,S2",
                   help="--max-steps of each recipe stage (default 200,20; --quick 2,1)")
    p.add_argument("--workers", type=int, default=None,
                   help="simulator processes of the data commands (default 16; --quick 1)")
    p.add_argument("--sim-set", action="append", default=[], metavar="KEY=VALUE",
                   help="a simulator override added to the recipe's generate commands (repeatable; e.g. "
                        "particle_budget=0.05 for a quicker check: the data times are then not the recipe's)")
    p.add_argument("--budget-s", type=float, default=480.0, help="wall-clock budget of the whole script")
    p.add_argument("--quick", action="store_true", help="few repeats, small sizes (a check of the script)")
    p.add_argument("--skip", default="", help="comma-separated parts to skip: call,rollout,train,recipe")
    args = p.parse_args(argv)
    q = args.quick
    args.batches = (1, 2) if q else (1, 64)
    args.steps = 20 if q else 100
    args.call_repeats, args.rollout_repeats = (2, 2) if q else (30, 10)
    args.train_steps, args.train_batch = (2, 4) if q else (15, 24)
    args.loader_workers = (0,) if q else (0, 8)
    if args.recipe_cases is None:
        args.recipe_cases = (4, 4) if q else (32, 64)
    if args.recipe_steps is None:
        args.recipe_steps = (2, 1) if q else (200, 20)
    if args.workers is None:
        args.workers = 1 if q else 16
    if len(args.recipe_cases) != 2:
        p.error(f"--recipe-cases takes two counts (full, quarter), got {args.recipe_cases}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    args = parse_args(argv)
    budget = Budget(args.budget_s)
    missing = [m for m in NEEDED if not _importable(m)]
    if missing:
        log.error("missing python packages %s: install them (pydantic, pyyaml, ...) first", missing)
        return 2
    import torch

    dev = torch.device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        log.error("--device %s, but torch sees no CUDA device; use --device cpu to check the script", dev)
        return 2
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    results: dict[str, Any] = {"argv": list(argv if argv is not None else sys.argv[1:]),
                               "environment": environment(dev),
                               "checkpoint": Path(args.checkpoint).name}  # fmt: skip
    try:
        inference_parts(args, dev, skip, budget, results)
    except Exception:  # noqa: BLE001 -- the model could not be built: the data, train and recipe parts still run
        results["model"] = {"error": traceback.format_exc(limit=8)}
        log.error("the model for call and rollout:\n%s", results["model"]["error"])
        write_report(args.out, results)
    if dev.type == "cuda":
        torch.cuda.empty_cache()
    want_data = "recipe" not in skip or ("train" not in skip and not args.data)
    if want_data and budget.left() > 30:
        def progress(figures: dict[str, Any]) -> None:
            results["data"] = figures
            write_report(args.out, results)

        _part(results, "data", args.out, lambda: recipe_data(args, budget.cap(CAPS["data"]), progress,
                                                             only_full="recipe" in skip))
    data = results.get("data", {})
    train_path = args.data or data.get("path")
    if "train" not in skip and train_path and budget.left() > 20:
        _part(results, "train", args.out,
              lambda: bench_train(args, train_path, dev, budget.cap(CAPS["train"])))
    if "recipe" not in skip and data.get("complete") and budget.left() > 30:
        _part(results, "recipe", args.out,
              lambda: bench_recipe(args, data, dev, budget.cap(CAPS["recipe"])))
    results["seconds"] = args.budget_s - budget.left()
    write_report(args.out, results)
    log.info("wrote %s and %s (%.0f s)", args.out / "gpu.json", args.out / "gpu.md", results["seconds"])
    return 0


def inference_parts(args: argparse.Namespace, dev: Any, skip: set[str], budget: Budget,
                    results: dict[str, Any]) -> None:
    """The model (``domain_model``) and the parts that call it: (a) call, (b) rollout."""
    import torch

    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.sim import initial_state

    loaded = load_checkpoint(args.checkpoint, device="cpu")
    model, _ = domain_model(loaded, args.domain, dev)
    scene = loaded.scene
    x0 = torch.as_tensor(initial_state(scene), dtype=torch.float32)  # (2, D, H, W)
    x_in = model_input(x0, args.domain)
    results["model"] = {"name": loaded.name, "steps_per_call": int(loaded.config.get("steps_per_call", 1)),
                        "scene": scene.name, "state": list(scene.state_shape), "domain": args.domain,
                        "call_input": list(x_in.shape)}  # fmt: skip
    write_report(args.out, results)
    if "call" not in skip:
        _part(results, "call", args.out, lambda: bench_calls(
            model, x_in, dev, args.batches, args.call_repeats, budget.cap(CAPS["call"])))
    if "rollout" not in skip:
        _part(results, "rollout", args.out, lambda: bench_rollouts(
            model, x0, dev, args.batches, args.steps, args.rollout_repeats, budget.cap(CAPS["rollout"])))


def _importable(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


if __name__ == "__main__":
    raise SystemExit(main())
