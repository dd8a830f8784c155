"""Which precision a runtime computes in on this machine: ``resolve_precision("auto")`` and ``machine``.

bfloat16 pays only where the hardware computes in it: a CUDA GPU, or a CPU with AVX-512 BF16 or AMX
(``CPU_BF16_FLAGS``). Elsewhere it is emulated: PyTorch's autocast on any such CPU
(benchmarks/small/README.md), OpenVINO's CPU plugin on one with AVX-512; without AVX-512 the plugin drops a
bf16 hint and runs the float32 graph (``OpenVINORuntime.describe``: ``inference_precision``). So ``"auto"``
(the service's default) is bf16 where the hardware computes in it and f32 elsewhere, and says so;
``"f32"`` or ``"bf16"`` given explicitly is taken as is. The speed of each precision per CPU is measured by
``nemsim bench rollout`` and ``nemsim bench speed-error``.
"""

from __future__ import annotations

import platform
from pathlib import Path
from typing import Literal

Precision = Literal["f32", "bf16"]
PRECISIONS: tuple[str, ...] = ("f32", "bf16")
PRECISION_CHOICES: tuple[str, ...] = ("auto", *PRECISIONS)  # "auto": ``default_precision`` of the device
CPU_BF16_FLAGS = ("avx512_bf16", "amx_bf16")  # /proc/cpuinfo flags of CPUs that compute in bfloat16


def cpu_info() -> dict[str, str]:
    """Each /proc/cpuinfo field's first value ("model name", "flags", ...); {} where there is none."""
    info = Path("/proc/cpuinfo")
    if not info.is_file():
        return {}
    out: dict[str, str] = {}
    for line in info.read_text(errors="replace").splitlines():
        key, sep, value = line.partition(":")
        if sep:
            out.setdefault(key.strip(), value.strip())
    return out


def cpu_flags() -> set[str]:
    """The instruction-set flags of this machine's first CPU (empty where /proc/cpuinfo has none)."""
    return set(cpu_info().get("flags", "").split())


def native_bf16(device_type: str) -> bool:
    """Whether bfloat16 autocast is the faster training forward on ``device_type``: a CUDA GPU, or a CPU
    with AVX-512 BF16 or AMX. A CPU without them emulates bfloat16 arithmetic, several times slower than
    float32 (benchmarks/small/README.md)."""
    return device_type == "cuda" or bool(cpu_flags() & set(CPU_BF16_FLAGS))


def default_precision(device_type: str = "cpu") -> Precision:
    """"bf16" on a device that computes in bfloat16 (``native_bf16``), else "f32"."""
    return "bf16" if native_bf16(device_type) else "f32"


def resolve_precision(precision: str, device_type: str = "cpu") -> Precision:
    """``"auto"`` -> ``default_precision(device_type)``; "f32" and "bf16" are checked and kept."""
    if precision not in PRECISION_CHOICES:
        raise ValueError(f"unknown precision {precision!r}; expected one of {list(PRECISION_CHOICES)}")
    return default_precision(device_type) if precision == "auto" else precision  # type: ignore[return-value]


def cpu_name() -> str:
    """The CPU's model name from /proc/cpuinfo; the bare architecture where there is none."""
    return cpu_info().get("model name") or platform.processor() or platform.machine()


def machine() -> dict[str, str | list[str]]:
    """What decides the default precision here: {"cpu": model name, "bf16_flags": the CPU's flags among
    ``CPU_BF16_FLAGS`` (empty: no bfloat16 arithmetic), "default_precision": the CPU's}."""
    flags = cpu_flags()
    return {"cpu": cpu_name(), "bf16_flags": [f for f in CPU_BF16_FLAGS if f in flags],
            "default_precision": default_precision("cpu")}  # fmt: skip
