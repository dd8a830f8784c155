"""The CPU name benchmarks print (bench.machine)."""

from __future__ import annotations

import os
import platform
from pathlib import Path

from bench.machine import cpu_name


def test_cpu_name_names_the_model_and_the_bf16_features():
    name = cpu_name()
    if Path("/proc/cpuinfo").is_file():
        model = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                     if line.startswith("model name"))
        assert name.startswith(model) and f"{os.cpu_count()} logical CPUs" in name
        assert "avx512_bf16" in name or "amx" in name or "no AVX-512 BF16, no AMX" in name
    else:
        assert name in (platform.processor(), platform.machine())
