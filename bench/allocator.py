"""CPU seconds per training step with glibc's default allocator against the settings `nemsim` runs with.

The settings and why they help are in ``nemsim.cli.allocator``; this measures them in fresh processes
(`nemsim bench allocator`), since glibc reads them only at process start.
"""

from __future__ import annotations

import os
import sys

from nemsim.cli.allocator import OPT_OUT, TUNED


def train_step_cost(checkpoint: str, batch: int, steps: int) -> dict[str, float]:
    """Per-step wall, user and system CPU seconds of ``steps`` optimizer steps (after one warm-up step) of the
    checkpoint's model on random states at ``batch``, bf16 autocast as in training, one thread."""
    import resource
    import time

    import torch

    from nemsim.inference.checkpoint import load_checkpoint

    torch.set_num_threads(1)
    loaded = load_checkpoint(checkpoint)
    model, scene = loaded.model, loaded.scene
    k = int(getattr(getattr(model, "config", None), "steps_per_call", 1))
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(batch, *scene.state_shape, generator=gen) * 2 - 1  # (B, 2, D, H, W)
    u = torch.rand(batch, 14, generator=gen) * 2 - 1  # (B, 14)
    y = torch.rand(batch, k, *scene.state_shape, generator=gen)  # (B, k, 2, D, H, W)
    opt = torch.optim.AdamW(model.parameters(), 1e-6)

    def step() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = model(x, u, all_steps=True) if k > 1 else model(x, u)[:, None]
        loss = ((out.float() - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    step()
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    for _ in range(steps):
        step()
    r1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    return {"wall_s": (t1 - t0) / steps, "user_s": (r1.ru_utime - r0.ru_utime) / steps,
            "sys_s": (r1.ru_stime - r0.ru_stime) / steps}


def compare_allocators(checkpoint: str, batch: int = 24, steps: int = 4,
                       rounds: int = 2) -> list[dict[str, object]]:
    """``train_step_cost`` in fresh processes with glibc's default allocator and with ``TUNED``, alternated
    ``rounds`` times (so a busy machine affects both alike). One row per process."""
    import json
    import subprocess

    code = ("import json, sys; from bench.allocator import train_step_cost; "
            "print(json.dumps(train_step_cost(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))))")
    base = {k: v for k, v in os.environ.items() if k not in TUNED}
    rows: list[dict[str, object]] = []
    for r in range(rounds):
        for name, env in (("default", {**base, OPT_OUT: "default"}), ("tuned", {**base, **TUNED})):
            env["OMP_NUM_THREADS"] = "1"
            out = subprocess.run([sys.executable, "-c", code, checkpoint, str(batch), str(steps)], env=env,
                                 capture_output=True, text=True, check=True)
            rows.append({"allocator": name, "round": r, **json.loads(out.stdout.strip().splitlines()[-1])})
    return rows
