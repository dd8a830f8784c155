"""Rollout speed of a one-step surrogate at several precisions, side by side (`nemsim bench rollout`).

Each variant rolls out the same ``steps``-step trajectories (batch ``batch``, seeded controls uniform in the
normalized design box, the scene's initial state) ``repeats`` times after one warm-up rollout; reported:
median and min wall seconds per rollout, the median CPU seconds of this process per rollout (all its
threads: on a machine shared with other jobs, wall time grows with their load and CPU time much less), and
max |Δ| of the whole trajectory against fp32 (normalized SDF units), so the fastest precision that keeps the
error is visible. Variants are interleaved (fp32, bf16,
channels_last, fp32, ...) so that load from other processes on the machine hits them alike.

Variants:
  * ``fp32``: the model as loaded (NEMSim: the cached-control fast path of ``rollout``);
  * ``fp32-percall``: the same model called as ``model(x, u_t)`` every step (no control cache), the
    reference for what the cache saves;
  * ``bf16``: ``torch.autocast("cpu", torch.bfloat16)`` around the rollout (the rule side stays fp32);
  * ``channels_last``: a copy of the model and the state in ``torch.channels_last_3d`` memory format;
  * ``fp32-window``: the depth-windowed rollout (``rollout(window=True)``, ``nemsim.model.window``; NEMSim
    only): each call computes the depth slab that can change; the report adds the fraction of voxels
    computed;
  * ``openvino-f32`` / ``openvino-bf16``: the step graph under OpenVINO (``nemsim.inference.runtime``, one
    inference thread; PyTorch if openvino is missing, see the log);
  * ``openvino-int8``: the f32 step graph after NNCF post-training quantization (``nncf.quantize``, preset
    MIXED: symmetric weights, asymmetric activations; fast bias correction), calibrated on the graph's
    inputs over ``INT8_CALIBRATION_ROLLOUTS`` rollouts of controls drawn like the timed ones but from
    another seed (the lever of "int8 where it pays"; needs ``pip install nncf``, not a dependency of the
    product).
"""

from __future__ import annotations

import contextlib
import copy
import statistics
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from nemsim.controls import N_CONTROLS
from nemsim.evaluation.rollout import rollout

VARIANTS = ("fp32", "fp32-percall", "bf16", "channels_last", "fp32-window", "openvino-f32", "openvino-bf16",
            "openvino-int8")
INT8_CALIBRATION_ROLLOUTS = 30  # x 10 calls: 300 calibration samples, NNCF's default subset size


class _PerCall(nn.Module):
    """Hides ``precompute``/``step`` so ``rollout`` calls ``model(x, u_t)`` every step (the model's config
    stays visible, so the rollout projects as it does for the model)."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model
        self.config = getattr(model, "config", None)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.model(x, u)


def _variant(model: nn.Module, x0: torch.Tensor, name: str) -> tuple[Any, torch.Tensor, Any, bool]:
    """(model, x0, context manager factory, depth window on) of one variant."""
    if name == "fp32":
        return model, x0, contextlib.nullcontext, False
    if name == "fp32-percall":
        return _PerCall(model), x0, contextlib.nullcontext, False
    if name == "bf16":
        return model, x0, lambda: torch.autocast("cpu", dtype=torch.bfloat16), False
    if name == "channels_last":
        cl = copy.deepcopy(model).to(memory_format=torch.channels_last_3d)  # type: ignore[call-overload]
        return cl, x0.contiguous(memory_format=torch.channels_last_3d), contextlib.nullcontext, False
    if name == "fp32-window":
        return model, x0, contextlib.nullcontext, True
    if name in ("openvino-f32", "openvino-bf16"):
        from nemsim.inference.runtime import Precision, compile_model

        precision: Precision = "bf16" if name.endswith("bf16") else "f32"
        return compile_model(model, "openvino", precision), x0, contextlib.nullcontext, False
    if name == "openvino-int8":
        return _int8_runtime(model, x0), x0, contextlib.nullcontext, False
    raise ValueError(f"unknown variant {name!r}; expected one of {VARIANTS}")


def _int8_runtime(model: nn.Module, x0: torch.Tensor, seed: int = 1) -> Any:
    """An OpenVINO runtime whose step graph is quantized to int8 by NNCF, calibrated on the inputs of the
    f32 graph's calls over ``INT8_CALIBRATION_ROLLOUTS`` rollouts from x0 (module docstring)."""
    try:
        import nncf
    except ImportError as exc:
        raise ValueError("variant openvino-int8 needs NNCF: pip install nncf") from exc
    from nemsim.inference.runtime import OpenVINORuntime

    samples: list[list[np.ndarray]] = []

    class Recording(OpenVINORuntime):
        def _infer_packed(self, req: Any, x: torch.Tensor, cache: Any, out: torch.Tensor, finish: Any) -> Any:
            samples.append([x.detach().float().numpy().copy(), *(a.copy() for a in cache.inputs)])
            return super()._infer_packed(req, x, cache, out, finish)

    class Int8(OpenVINORuntime):
        def transform(self, ov_model: Any) -> Any:
            return nncf.quantize(ov_model, nncf.Dataset(samples), subset_size=len(samples),
                                 preset=nncf.QuantizationPreset.MIXED)

    if not callable(getattr(model, "predict_packed", None)):
        raise ValueError("variant openvino-int8 needs a model with a packed-residual graph (NEMSim)")
    rec = Recording(model, "f32")
    g = torch.Generator().manual_seed(seed)
    for _ in range(INT8_CALIBRATION_ROLLOUTS):
        rollout(rec, x0[:1], torch.rand(1, N_CONTROLS, generator=g) * 2 - 1, 10 * rec.k, keep=False)  # type: ignore[arg-type]
    return Int8(model, "f32")


def bench_rollout(
    model: nn.Module,
    x0: np.ndarray | torch.Tensor,
    *,
    steps: int = 100,
    batch: int = 1,
    repeats: int = 5,
    variants: Sequence[str] = VARIANTS,
    seed: int = 0,
    arms: Mapping[str, nn.Module] | None = None,
) -> dict[str, Any]:
    """Time ``steps``-step rollouts of ``model`` from x0 (2, D, H, W) for each variant (CPU).

    Returns {"steps", "batch", "repeats", "threads", "variants": {name: {"median_s", "min_s", "times_s",
    "cpu_median_s", "cpu_times_s", "max_abs_diff_vs_fp32"}}}; ``max_abs_diff_vs_fp32`` is max
    |x̂ - x̂_fp32| over the whole trajectory. ``arms``: other architectures (name -> untrained model, e.g.
    the checkpoint's configuration with more states per call), each timed as variant ``arm:<name>`` through
    OpenVINO f32 beside the others: the speed of a candidate before it is trained; its error is None.
    """
    if steps < 1 or batch < 1 or repeats < 1:
        raise ValueError(f"steps, batch and repeats must be >= 1, got {steps}, {batch}, {repeats}")
    variants = list(variants)
    if "fp32" not in variants:
        variants.insert(0, "fp32")
    model = model.eval()
    x = torch.as_tensor(np.asarray(x0), dtype=torch.float32)[None].repeat(batch, 1, 1, 1, 1)  # (B,2,D,H,W)
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(batch, N_CONTROLS, generator=g) * 2 - 1  # (B, 14) normalized
    setups = {name: _variant(model, x, name) for name in variants}
    for arm, arm_model in (arms or {}).items():
        from nemsim.inference.runtime import compile_model

        variants.append(f"arm:{arm}")
        setups[f"arm:{arm}"] = (compile_model(arm_model.eval(), "openvino", "f32"), x, contextlib.nullcontext,
                                False)
    times: dict[str, list[float]] = {name: [] for name in variants}
    cpu_times: dict[str, list[float]] = {name: [] for name in variants}
    trajs: dict[str, torch.Tensor] = {}
    window_stats: dict[str, dict[str, Any]] = {}
    with torch.inference_mode():
        for name, (m, xv, ctx, win) in setups.items():  # warm-up, and the trajectory for the error figure
            with ctx():
                stats: dict[str, Any] = {}
                trajs[name] = rollout(m, xv, u, steps, window=win, stats=stats).float().contiguous()
                if win:
                    window_stats[name] = stats
        for _ in range(repeats):
            for name, (m, xv, ctx, win) in setups.items():
                with ctx():
                    t0, c0 = time.perf_counter(), time.process_time()
                    rollout(m, xv, u, steps, window=win)
                    times[name].append(time.perf_counter() - t0)
                    cpu_times[name].append(time.process_time() - c0)
    ref = trajs["fp32"]
    return {
        "steps": steps,
        "batch": batch,
        "repeats": repeats,
        "threads": torch.get_num_threads(),
        "variants": {
            name: {
                "median_s": statistics.median(times[name]),
                "min_s": min(times[name]),
                "times_s": times[name],
                "cpu_median_s": statistics.median(cpu_times[name]),
                "cpu_times_s": cpu_times[name],
                "max_abs_diff_vs_fp32": (None if name.startswith("arm:")
                                         else float((trajs[name] - ref).abs().max())),
                **({"fraction_computed": window_stats[name]["fraction_computed"]} if name in window_stats
                   else {}),
            }
            for name in variants
        },
    }


def format_bench(report: dict[str, Any]) -> str:
    lines = [
        f"{report['steps']}-step rollout, batch {report['batch']}, {report['repeats']} repeats, "
        f"{report['threads']} thread(s):",
        f"  {'variant':14s} {'median s':>9s} {'min s':>8s} {'CPU s':>8s} {'max|Δ| vs fp32':>15s}",
    ]
    for name, v in report["variants"].items():
        frac = f"  ({v['fraction_computed']:.2f} of the voxels computed)" if "fraction_computed" in v else ""
        err = "untrained" if v["max_abs_diff_vs_fp32"] is None else f"{v['max_abs_diff_vs_fp32']:.2e}"
        lines.append(
            f"  {name:14s} {v['median_s']:9.3f} {v['min_s']:8.3f} {v['cpu_median_s']:8.3f} {err:>15s}{frac}"
        )
    return "\n".join(lines)
