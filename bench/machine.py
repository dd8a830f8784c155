"""What CPU a benchmark ran on, for its report: figures differ between machines (AMX or not, AVX-512 BF16 or
not), so every timed result names the CPU it came from."""

from __future__ import annotations

import os

from nemsim.inference.precision import CPU_BF16_FLAGS, cpu_info

# instruction-set extensions that change the speed of bf16 inference and training
_FLAGS = (*CPU_BF16_FLAGS, "amx_tile")


def cpu_name() -> str:
    """e.g. "<model name> (2 logical CPUs; avx512_bf16)"; the bare architecture without /proc/cpuinfo."""
    from nemsim.inference.precision import cpu_name as model_name

    info = cpu_info()
    if not info:
        return model_name()
    flags = set(info.get("flags", "").split())
    present = [f for f in _FLAGS if f in flags] or ["no AVX-512 BF16, no AMX"]
    return f"{model_name()} ({os.cpu_count()} logical CPUs; {', '.join(present)})"
