"""Which precision a runtime computes in on this machine: ``resolve_precision("auto")`` and ``machine``.

bfloat16 pays only where the hardware computes in it: a CUDA GPU, or a CPU with AVX-512 BF16 or AMX
(``nemsim.training.config.CPU_BF16_FLAGS``). Elsewhere it is emulated: PyTorch's autocast on any such CPU
(benchmarks/small/README.md), OpenVINO's CPU plugin on one with AVX-512; without AVX-512 the plugin drops a
bf16 hint and runs the float32 graph (``OpenVINORuntime.describe``: ``inference_precision``). So ``"auto"``
(the service's default) is bf16 where the hardware computes in it and f32 elsewhere, and says so;
``"f32"`` or ``"bf16"`` given explicitly is taken as is. The speed of each precision per CPU is measured by
``nemsim bench rollout`` and ``nemsim bench speed-error``.
"""

from __future__ import annotations

import platform
from typing import Literal

from nemsim.training import config as train_config

Precision = Literal["f32", "bf16"]
PRECISIONS: tuple[str, ...] = ("f32", "bf16")
PRECISION_CHOICES: tuple[str, ...] = ("auto", *PRECISIONS)  # "auto": ``default_precision`` of the device


def default_precision(device_type: str = "cpu") -> Precision:
    """"bf16" on a device that computes in bfloat16 (``native_bf16``), else "f32"."""
    return "bf16" if train_config.native_bf16(device_type) else "f32"


def resolve_precision(precision: str, device_type: str = "cpu") -> Precision:
    """``"auto"`` -> ``default_precision(device_type)``; "f32" and "bf16" are checked and kept."""
    if precision not in PRECISION_CHOICES:
        raise ValueError(f"unknown precision {precision!r}; expected one of {list(PRECISION_CHOICES)}")
    return default_precision(device_type) if precision == "auto" else precision  # type: ignore[return-value]


def cpu_name() -> str:
    """The CPU's model name from /proc/cpuinfo; the bare architecture where there is none."""
    return train_config.cpu_info().get("model name") or platform.processor() or platform.machine()


def machine() -> dict[str, str | list[str]]:
    """What decides the default precision here: {"cpu": model name, "bf16_flags": the CPU's flags among
    ``CPU_BF16_FLAGS`` (empty: no bfloat16 arithmetic), "default_precision": the CPU's}."""
    flags = train_config.cpu_flags()
    return {"cpu": cpu_name(), "bf16_flags": [f for f in train_config.CPU_BF16_FLAGS if f in flags],
            "default_precision": default_precision("cpu")}  # fmt: skip
