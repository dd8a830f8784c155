"""What CPU a benchmark ran on, for its report: figures differ between machines (AMX or not, AVX-512 BF16 or
not), so every timed result names the CPU it came from."""

from __future__ import annotations

import os
import platform
from pathlib import Path

from nemsim.training.config import cpu_flags

# instruction-set extensions that change the speed of bf16 inference and training
_FLAGS = ("avx512_bf16", "amx_bf16", "amx_tile")


def cpu_name() -> str:
    """e.g. "<model name> (2 logical CPUs; avx512_bf16)"; the bare architecture without /proc/cpuinfo."""
    info = Path("/proc/cpuinfo")
    if not info.is_file():
        return platform.processor() or platform.machine()
    model = ""
    for line in info.read_text(errors="replace").splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name":
            model = value.strip()
            break
    flags = cpu_flags()
    present = [f for f in _FLAGS if f in flags] or ["no AVX-512 BF16, no AMX"]
    return f"{model or platform.machine()} ({os.cpu_count()} logical CPUs; {', '.join(present)})"
