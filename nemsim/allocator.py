"""glibc allocator settings for the `nemsim` process (training, rollouts, the service).

Why: PyTorch on CPU allocates and frees the same large activation and gradient buffers every step. With
glibc's defaults, blocks above the (dynamic, at most 32 MiB) mmap threshold are mapped and unmapped on every
allocation and the heap top is trimmed back to the kernel, so every step pays page faults and zeroing of
fresh pages: a `nemsim train` step of the `small` scene spent about half its CPU time in the kernel. Keeping
large blocks on the heap and never trimming it makes the memory reused instead (`nemsim bench allocator`
measures it). The cost is that the resident size stays at the process's high-water mark.

How: the settings are environment variables that glibc reads once, at process start, so the console script
re-executes itself once with them set (``reexec_tuned``) before any work is done. Values the user has set
are kept; ``NEMSIM_ALLOCATOR=default`` turns the re-execution off. Other C libraries ignore the variables.
`nemsim serve` keeps glibc's defaults: a server runs indefinitely and its resident size is bounded by its
settings, which a heap that never shrinks would undo (`benchmarks/service/README.md`: the 2-minute soak peaked
higher with the settings, for a few percent more throughput).
"""

from __future__ import annotations

import os
import sys

# glibc tunables (malloc(3), mallopt(3)): large blocks from the heap, never trimmed, the heap grown in 1 GiB
TUNED = {
    "MALLOC_MMAP_THRESHOLD_": str(16 << 30),
    "MALLOC_TRIM_THRESHOLD_": str(16 << 30),
    "MALLOC_TOP_PAD_": str(1 << 30),
}
OPT_OUT = "NEMSIM_ALLOCATOR"  # "default": keep glibc's defaults
EXEMPT_COMMANDS = ("serve",)  # long-running: resident size matters more than speed (module docstring)


def tuned_environ(environ: dict[str, str]) -> dict[str, str] | None:
    """The environment to re-execute with, or None when nothing needs to change (already tuned, opted out,
    or not Linux)."""
    if not sys.platform.startswith("linux") or environ.get(OPT_OUT, "") in ("default", "tuned"):
        return None
    missing = {k: v for k, v in TUNED.items() if k not in environ}
    if not missing:
        return None
    return {**environ, **missing, OPT_OUT: environ.get(OPT_OUT, "tuned")}


def reexec_tuned(argv: list[str] | None = None) -> None:
    """Replace this process by ``python -m nemsim.cli ARGS`` with the tuned allocator (no return), unless
    ``tuned_environ`` says nothing needs to change or the command is exempt (then return at once)."""
    args = sys.argv[1:] if argv is None else argv
    command = next((a for a in args if not a.startswith("-")), None)
    env = tuned_environ(dict(os.environ))
    if env is None or command in EXEMPT_COMMANDS:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, "-m", "nemsim.cli", *args], env)


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


def bench(checkpoint: str, batch: int = 24, steps: int = 4, rounds: int = 2) -> list[dict[str, object]]:
    """``train_step_cost`` in fresh processes with glibc's default allocator and with ``TUNED``, alternated
    ``rounds`` times (so a busy machine affects both alike). One row per process."""
    import json
    import subprocess

    code = ("import json, sys; from nemsim.allocator import train_step_cost; "
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
