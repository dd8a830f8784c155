"""The GPU measurements in one script: ``python -m bench.gpu --out DIR`` (check: ``--device cpu --quick``).

On the `small` scene with the served checkpoint (``checkpoints/nemsim-small.pt``):
  (a) ``call``: one network call (k states), eager PyTorch against the CUDA-graph runtime
      (``nemsim.inference.cuda_graph``: copy in, replay, copy out), at batch 1 and 64, ms per call;
  (b) ``rollout``: a 100-step rollout from the scene's initial state under random in-box controls: eager
      ``rollout``, ``rollout`` through the CUDA-graph runtime (one replay per call) and the whole rollout
      as one graph (``CUDAGraphRuntime.rollout``); ms per rollout at batch 1, per trajectory at batch 64;
  (c) ``agreement``: max |Δ| of each graphed result against eager (one call; whole trajectories);
  (d) ``train``: the training loop's own step (``nemsim.training.loop``: DataLoader over the HDF5 file,
      loss, backward, clip, AdamW; ``TrainConfig`` defaults, batch 24, the k-step loss of the served
      model's form) end to end, against the same step on one batch already on the device; with ``--data``
      absent, ``--cases`` `small` cases are generated first (``nemsim.sim.generate``, ``--workers``
      processes) into ``--scratch``, and the generation's wall time is reported too.

Timings: ``torch.cuda.synchronize`` before and after each timed repeat; medians (and minima) over repeats;
variants interleaved within a repeat. Every part has a time cap and the whole script a budget
(``--budget-s``); results are written after every part (``gpu.json``, ``gpu.md`` in ``--out``), so a part
that fails or runs out of time leaves the others. Nothing heavy is imported at module level: the
simulator's worker processes are spawned and re-import this module.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
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
TOL = 1e-5  # max |Δ| graphed vs eager, fp32
TARGETS = {"rollout_b1_ms": 12.0, "rollout_b64_ms_per_traj": 1.0, "train_ratio": 1.5}  # on one H100
NEEDED = ("numpy", "h5py", "numba", "scipy", "yaml", "pydantic")  # third-party imports of the parts run here


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


def graph_runtime(model: Any, dev: Any) -> tuple[Any, str | None]:
    """(CUDAGraphRuntime, None), or (None, why not) on a device without CUDA graphs."""
    from nemsim.inference.cuda_graph import CUDAGraphRuntime, CUDAUnavailable

    if dev.type != "cuda":
        return None, f"device {dev}: CUDA graphs need a CUDA device"
    try:
        return CUDAGraphRuntime(model, device=dev), None
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
    out: dict[str, Any] = {"steps": steps, **({"graphed_unavailable": why} if why else {})}
    for b in batches:
        out[f"b{b}"] = _rollouts_at(eager, graphed, x0, dev, b, steps, repeats, cap_s / len(batches))
        log.info("rollout, batch %d: %s", b, _brief(out[f"b{b}"]))
        if dev.type == "cuda":
            torch.cuda.empty_cache()
    if graphed is not None:
        out["graphed_runtime"] = graphed.describe()
    return out


def _rollouts_at(eager: Any, graphed: Any, x0: Any, dev: Any, b: int, steps: int, repeats: int,
                 cap_s: float) -> dict[str, Any]:
    import torch

    from nemsim.evaluation.rollout import rollout

    x, u = _inputs(x0, b, dev)
    fns: dict[str, Callable[[], Any]] = {"eager": lambda: rollout(eager, x, u, steps)}
    if graphed is not None:
        fns["graph_per_call"] = lambda: rollout(graphed, x, u, steps)
        fns["graph_whole"] = lambda: graphed.rollout(x, u, steps)
    row: dict[str, Any] = {}
    with torch.no_grad():
        trajs = {}
        for name, fn in fns.items():  # warm-up (and the captures), and the trajectories compared
            t0 = time.perf_counter()
            trajs[name] = fn()
            _sync(dev)
            row[f"{name}_first_s"] = time.perf_counter() - t0
        for name in fns:
            if name != "eager":
                row[f"{name}_max_abs_diff"] = _max_diff(trajs[name], trajs["eager"])
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


class _OutOfTime(Exception):
    pass


def training_data(args: argparse.Namespace, cap_s: float) -> dict[str, Any]:
    """The HDF5 file to train from: ``--data``, or ``--cases`` `small` cases generated into ``--scratch``
    (resumed if already there), stopped after ``cap_s`` with the cases finished by then."""
    if args.data:
        return {"path": str(args.data), "generated": False}
    from nemsim.controls import lhs_design
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.scenes import get_scene
    from nemsim.sim.generate import generate_dataset

    path = Path(args.scratch) / f"small-{args.cases}.h5"
    path.parent.mkdir(parents=True, exist_ok=True)
    end = time.perf_counter() + cap_s

    def deadline(row: int, meta: dict) -> None:
        if time.perf_counter() > end:
            raise _OutOfTime(f"generation stopped after {cap_s:.0f} s")

    t0 = time.perf_counter()
    info: dict[str, Any] = {"path": str(path), "generated": True, "cases": args.cases,
                            "workers": args.workers}
    try:
        report = generate_dataset(path, get_scene("small"), compile_rules(load_rules()),
                                  lhs_design()[: args.cases], list(range(args.cases)), seed=0,
                                  workers=args.workers, progress=False, state_dtype="float16",
                                  on_case=deadline)  # fmt: skip
        info.update(written=report["written"], skipped=report["skipped"])
    except _OutOfTime as exc:
        info["stopped"] = str(exc)
    info["wall_s"] = time.perf_counter() - t0
    log.info("training data: %s", info)
    return info


def bench_train(args: argparse.Namespace, data_path: str, dev: Any, cap_s: float) -> dict[str, Any]:
    """(d) the training loop's step end to end from the HDF5 file (per DataLoader worker count; and the
    loader alone) against the same step on a batch already on the device."""
    from nemsim.data.dataset import TransitionDataset
    from nemsim.evaluation.rollout import steps_per_call
    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.training.config import TrainConfig
    from nemsim.training.loop import Clock, ModelMeta, TrainData, _Run

    loaded = load_checkpoint(args.checkpoint, device="cpu")
    k = steps_per_call(loaded.model)
    train_set = TransitionDataset(data_path, None, "train", unroll=k)
    if len(train_set) < args.train_batch:
        raise ValueError(f"{data_path} holds {len(train_set)} training items (complete cases: "
                         f"{len(train_set.rows)}); a batch needs {args.train_batch}")
    meta = ModelMeta(loaded.name, loaded.config, loaded.scene, loaded.rules)
    steps = args.train_steps
    out: dict[str, Any] = {"cases": len(train_set.rows), "items": len(train_set), "steps_timed": steps,
                           "steps_per_call": k}  # fmt: skip
    end = time.perf_counter() + cap_s
    run = None
    for workers in args.loader_workers:
        if time.perf_counter() > end:
            out[f"workers{workers}"] = {"skipped": "time cap"}
            continue
        cfg = TrainConfig(batch_size=args.train_batch, num_workers=workers, device=str(dev), progress=False,
                          batches_per_epoch=steps, warmup_steps=1, seed=0)  # fmt: skip
        model = load_checkpoint(args.checkpoint, device="cpu").model
        run = _Run(cfg, model, TrainData(train=train_set, val=[]), Path(args.scratch) / "run", meta, Clock())
        run.start()
        run.train_epoch(0)  # warm-up: workers start, kernels are selected
        c0 = time.process_time()
        row = run.train_epoch(1)
        res = {"e2e_step_ms": 1e3 * row["epoch_seconds"] / steps,
               "main_cpu_s_per_step": (time.process_time() - c0) / steps,
               "loader_only_ms_per_batch": _loader_ms(run.loader, steps, end)}  # fmt: skip
        out[f"workers{workers}"] = res
        out["bf16"], out["batch"] = cfg.bf16, cfg.batch_size
        log.info("train, %d loader workers: %s", workers, res)
    if run is not None:
        out["in_memory_step_ms"] = _in_memory_step_ms(run, dev, steps, max(end - time.perf_counter(), 1.0))
        for key, val in out.items():
            if key.startswith("workers") and "e2e_step_ms" in val:
                val["ratio_to_in_memory"] = val["e2e_step_ms"] / out["in_memory_step_ms"]
        log.info("train, in memory: %.1f ms/step", out["in_memory_step_ms"])
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


def write_report(out_dir: Path, results: dict[str, Any]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "gpu.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
    (out_dir / "gpu.md").write_text(markdown(results))


def _ms(row: dict[str, Any] | None, key: str, field: str = "median_ms") -> str:
    v = (row or {}).get(key)
    return f"{v[field]:.3f}" if isinstance(v, dict) and field in v else "-"


def markdown(res: dict[str, Any]) -> str:
    env = res.get("environment", {})
    lines = [f"# GPU measurements ({env.get('gpu', env.get('device', '?'))})", "",
             f"`python -m bench.gpu {' '.join(res.get('argv', []))}`; torch {env.get('torch')}, CUDA "
             f"{env.get('torch_cuda')}, {env.get('cpu_count')} CPU cores; the `small` served checkpoint; "
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
            for name in ("eager", "graph_per_call", "graph_whole"):
                if name in row:
                    t = row[name]
                    diff = row.get(f"{name}_max_abs_diff", "-" if name != "eager" else "ref")
                    lines.append(f"| {key[1:]} | {name} | {t['median_ms']:.2f} | {t['per_traj_ms']:.3f} | "
                                 f"{t['traj_per_s']:.0f} | {diff} |")
        lines.append("")
    if "agreement" in res:
        lines += ["## Agreement", "", f"max abs diff graphed vs eager: {res['agreement']}", ""]
    if "targets" in res:
        lines += ["## Targets", "", "| target | value | met |", "|---|---:|---|"]
        lines += [f"| {k} | {v['value']:.3g} (<= {v['target']}) | {v['met']} |"
                  for k, v in res["targets"].items()]
        lines.append("")
    data, train = res.get("data", {}), res.get("train", {})
    if data or train:
        lines += ["## Training step", "", f"data: {json.dumps(data, default=str)}", ""]
        for key, val in train.items():
            if key.startswith("workers"):
                lines.append(f"- end to end, {key[7:]} loader workers: {json.dumps(val)}")
        for key in ("in_memory_step_ms", "loader_only_ms_per_batch", "bf16", "batch", "cases"):
            if key in train:
                lines.append(f"- {key}: {train[key]}")
        lines.append("")
    for part in ("call", "rollout"):
        row = res.get(part, {})
        why = row.get("graphed_unavailable") or row.get("graphed_runtime", {}).get("fallback_reason")
        if why:
            lines += [f"{part}: no CUDA graph ({why})", ""]
    errors = {k: v["error"] for k, v in res.items() if isinstance(v, dict) and "error" in v}
    if errors:
        lines += ["## Errors", ""] + [f"- {k}: {v.splitlines()[-1] if v else v}" for k, v in errors.items()]
    return "\n".join(lines) + "\n"


def summarize(res: dict[str, Any]) -> None:
    """The agreement figure and the issue's targets, from the parts that ran."""
    diffs = {}
    for part in ("call", "rollout"):
        for key, row in res.get(part, {}).items():
            if isinstance(row, dict):
                diffs.update({f"{part}_{key}_{k}": v for k, v in row.items() if k.endswith("max_abs_diff")})
    if diffs:
        res["agreement"] = {"max": max(diffs.values()), "tolerance": TOL, "agree": max(diffs.values()) < TOL,
                            "each": diffs}  # fmt: skip
    targets: dict[str, Any] = {}
    roll = res.get("rollout", {})
    best_b1 = [roll.get("b1", {}).get(n, {}).get("median_ms") for n in ("graph_per_call", "graph_whole")]
    best_b64 = [roll.get("b64", {}).get(n, {}).get("per_traj_ms") for n in ("graph_per_call", "graph_whole")]
    if any(v is not None for v in best_b1):
        targets["rollout_b1_ms"] = min(v for v in best_b1 if v is not None)
    if any(v is not None for v in best_b64):
        targets["rollout_b64_ms_per_traj"] = min(v for v in best_b64 if v is not None)
    ratios = [v.get("ratio_to_in_memory") for k, v in res.get("train", {}).items()
              if k.startswith("workers") and isinstance(v, dict)]  # fmt: skip
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


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m bench.gpu", description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, type=Path, help="folder for gpu.json and gpu.md")
    p.add_argument("--device", default="cuda", help="cuda (default), cuda:N or cpu (a check of the script)")
    p.add_argument("--checkpoint", type=Path, default=CHECKPOINT)
    p.add_argument("--data", default=None, help="a `small` trajectory .h5 to train from (default: generate)")
    p.add_argument("--scratch", default="/tmp/nemsim-bench-gpu", help="generated data and the training run")
    p.add_argument("--cases", type=int, default=32, help="`small` cases to generate without --data")
    p.add_argument("--workers", type=int, default=16, help="simulator processes for the generation")
    p.add_argument("--budget-s", type=float, default=300.0, help="wall-clock budget of the whole script")
    p.add_argument("--quick", action="store_true", help="few repeats, small batches (a check of the script)")
    p.add_argument("--skip", default="", help="comma-separated parts to skip: call,rollout,train")
    args = p.parse_args(argv)
    q = args.quick
    args.batches = (1, 2) if q else (1, 64)
    args.steps = 20 if q else 100
    args.call_repeats, args.rollout_repeats = (2, 2) if q else (30, 10)
    args.train_steps, args.train_batch = (2, 4) if q else (15, 24)
    args.loader_workers = (0,) if q else (0, 8)
    if q and args.cases == 32:
        args.cases = 2
    if q and args.workers == 16:
        args.workers = 1
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

    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.sim import initial_state

    dev = torch.device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        log.error("--device %s, but torch sees no CUDA device; use --device cpu to check the script", dev)
        return 2
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    results: dict[str, Any] = {"argv": list(argv if argv is not None else sys.argv[1:]),
                               "environment": environment(dev),
                               "checkpoint": Path(args.checkpoint).name}  # fmt: skip
    loaded = load_checkpoint(args.checkpoint, device=dev)
    model, scene = loaded.model, loaded.scene
    x0 = torch.as_tensor(initial_state(scene), dtype=torch.float32)  # (2, D, H, W)
    results["model"] = {"name": loaded.name, "steps_per_call": int(loaded.config.get("steps_per_call", 1)),
                        "scene": scene.name, "state": list(scene.state_shape)}  # fmt: skip
    write_report(args.out, results)
    caps = {"call": 35.0, "rollout": 60.0, "data": 110.0, "train": 80.0}
    if "call" not in skip:
        _part(results, "call", args.out, lambda: bench_calls(
            model, x0, dev, args.batches, args.call_repeats, budget.cap(caps["call"])))
    if "rollout" not in skip:
        _part(results, "rollout", args.out, lambda: bench_rollouts(
            model, x0, dev, args.batches, args.steps, args.rollout_repeats, budget.cap(caps["rollout"])))
    if "train" not in skip:
        del model, loaded
        if dev.type == "cuda":
            torch.cuda.empty_cache()
        _part(results, "data", args.out, lambda: training_data(args, budget.cap(caps["data"])))
        data = results["data"]
        if "path" in data and budget.left() > 20:
            _part(results, "train", args.out, lambda: bench_train(args, data["path"], dev,
                                                                  budget.cap(caps["train"])))
    results["seconds"] = args.budget_s - budget.left()
    write_report(args.out, results)
    log.info("wrote %s and %s (%.0f s)", args.out / "gpu.json", args.out / "gpu.md", results["seconds"])
    return 0


def _importable(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


if __name__ == "__main__":
    raise SystemExit(main())
