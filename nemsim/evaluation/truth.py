"""The simulator as the truth for benchmarks: cached runs by (controls, seed) and surrogate predictions.

``nemsim stress`` (physical invariants), ``nemsim bench extrapolation`` and ``nemsim bench physics`` judge
a surrogate against the Monte Carlo simulator on the same controls. Simulations dominate their cost, so
every run goes through one :class:`SimTruth` per command: a run is keyed by (raw controls, seed, number
of transitions; scene, rules and simulator configuration), simulated once, and shared by every check
that asks for it.

Choices:
  * Seeds: run (controls, seed) uses ``np.random.default_rng(seed)``; the two seeds of a seed pair (default
    1 and 2, as ``nemsim bench noise``) give the simulator's seed-to-seed differences.
  * Storage: trajectories go to ``.npy`` files in a cache directory (a temporary one unless given), not to
    memory: one ``small`` trajectory is 41 MB and a benchmark runs dozens. With an explicit directory a
    rerun of the same command reuses the finished runs.
  * Parallelism: ``workers`` > 1 runs the missing simulations on a spawn process pool, one core each.
  * Surrogates are called only through ``nemsim.evaluation.rollout.rollout`` (so multi-step models work
    unchanged); any object it accepts works (``forward(x, u)`` or ``precompute``/``step``).
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nemsim.controls import to_normalized
from nemsim.geometry.profile import profile_metrics_batch
from nemsim.scenes import Scene

Run = tuple[np.ndarray, int]  # (raw controls (14,), seed)


def _simulate(scene: Scene, rules: Any, config: Any, raw: np.ndarray, seed: int, steps: int) -> np.ndarray:
    """Worker body: one trajectory (steps + 1, 2, D, H, W) float32."""
    from nemsim.sim import run_trajectory

    res = run_trajectory(scene, rules, raw, np.random.default_rng(seed), config, n_transitions=steps)
    return res.states


class SimTruth:
    """Simulator runs shared by the checks of one command, cached by (controls, seed).

    Args:
        scene, rules: as for ``nemsim.sim.run_trajectory``; config: ``SimConfig`` (None: defaults).
        steps: transitions per run (None: the scene's horizon).
        workers: parallel simulations (1 = in-process).
        cache_dir: where trajectories are kept (None: a temporary directory removed by ``close``).
        progress: a tqdm bar on stderr while simulating.
    """

    def __init__(self, scene: Scene, rules: Any, config: Any = None, *, steps: int | None = None,
                 workers: int = 1, cache_dir: str | Path | None = None, progress: bool = False) -> None:
        from nemsim.sim import SimConfig

        self.scene = scene
        self.rules = rules
        self.config = (config or SimConfig()).resolved(scene)
        self.steps = scene.n_transitions if steps is None else int(steps)
        if not 1 <= self.steps <= scene.n_transitions:
            raise ValueError(f"steps must be in [1, {scene.n_transitions}] (the simulator's horizon on "
                             f"{scene.name!r}), got {steps}")
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self.progress = progress
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        if cache_dir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="nemsim-truth-")
            cache_dir = self._tmp.name
        self.dir = Path(cache_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self._metrics: dict[str, dict[str, np.ndarray]] = {}
        # what else decides a trajectory: a cache directory shared between configurations stays correct
        ident = json.dumps(self.config.to_meta(scene), sort_keys=True, default=str)
        self._ident = f"|{self.steps}|{scene.to_json()}|{getattr(rules, 'sha256', '')}|{ident}"
        self.n_simulated = 0  # runs simulated by this object (cache hits excluded)
        self.sim_wall_s = 0.0

    # --- keys and storage ------------------------------------------------------------------------
    def key(self, raw: np.ndarray, seed: int) -> str:
        raw = np.ascontiguousarray(np.asarray(raw, dtype=np.float64).reshape(14))
        h = hashlib.sha1(raw.tobytes() + f"|{int(seed)}{self._ident}".encode())
        return h.hexdigest()[:20]

    def _path(self, key: str) -> Path:
        return self.dir / f"{key}.npy"

    def has(self, raw: np.ndarray, seed: int) -> bool:
        return self._path(self.key(raw, seed)).is_file()

    def missing(self, runs: Sequence[Run]) -> list[Run]:
        """The runs of ``runs`` not simulated yet, without duplicates (in order)."""
        seen: set[str] = set()
        out = []
        for raw, seed in runs:
            k = self.key(raw, seed)
            if k not in seen and not self._path(k).is_file():
                seen.add(k)
                out.append((np.asarray(raw, dtype=np.float64), int(seed)))
        return out

    # --- simulation ------------------------------------------------------------------------------
    def ensure(self, runs: Sequence[Run], desc: str = "simulate") -> int:
        """Simulate the missing runs of ``runs``; returns how many were simulated."""
        todo = self.missing(runs)
        if not todo:
            return 0
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = tqdm(total=len(todo), unit="run", desc=f"{desc} ({self.scene.name})", dynamic_ncols=True)
        t0 = time.perf_counter()
        try:
            for (raw, seed), states in zip(todo, self._run(todo), strict=True):
                self._store(self.key(raw, seed), states)
                self.n_simulated += 1
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
            self.sim_wall_s += time.perf_counter() - t0
        return len(todo)

    def _run(self, todo: list[Run]) -> Iterator[np.ndarray]:
        if self.workers == 1 or len(todo) == 1:
            for raw, seed in todo:
                yield _simulate(self.scene, self.rules, self.config, raw, seed, self.steps)
            return
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        from nemsim.sim.generate import _worker_init

        with ProcessPoolExecutor(max_workers=self.workers, mp_context=mp.get_context("spawn"),
                                 initializer=_worker_init) as pool:
            futures = [pool.submit(_simulate, self.scene, self.rules, self.config, raw, seed, self.steps)
                       for raw, seed in todo]
            for fut in futures:  # in order: results stay matched to their runs
                yield fut.result()

    def _store(self, key: str, states: np.ndarray) -> None:
        tmp = self.dir / f"{key}.{os.getpid()}.tmp.npy"
        np.save(tmp, np.asarray(states, dtype=np.float32))
        tmp.replace(self._path(key))  # atomic: a half-written file is never taken for a finished run

    def states(self, raw: np.ndarray, seed: int) -> np.ndarray:
        """(steps + 1, 2, D, H, W) float32 trajectory (simulated now if missing)."""
        k = self.key(raw, seed)
        if not self._path(k).is_file():
            self.ensure([(raw, seed)])
        return np.load(self._path(k))

    def metrics(self, raw: np.ndarray, seed: int) -> dict[str, np.ndarray]:
        """Profile metrics of the run, {name: (steps + 1,) nm}."""
        k = self.key(raw, seed)
        if k not in self._metrics:
            self._metrics[k] = profile_metrics_batch(self.states(raw, seed), self.scene)
        return self._metrics[k]

    def close(self) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> SimTruth:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def particle_work(runs: Sequence[Run]) -> float:
    """Simulated particles of ``runs`` in units of one run of the design centre: the sum over runs of the
    total flux (four species) over the centre's. The simulator's primaries scale with the total flux; a
    run also pays a fixed Ψ cost per saved state (a large share of a median ``small`` run)."""
    from nemsim.controls import FLUX_INDICES, from_normalized

    centre = float(from_normalized(np.zeros(14))[list(FLUX_INDICES)].sum())
    return float(sum(np.asarray(raw)[list(FLUX_INDICES)].sum() for raw, _ in runs) / centre)


# --- surrogate side --------------------------------------------------------------------------------


def model_device(model: Any) -> torch.device:
    params = getattr(model, "parameters", None)
    p = next(params(), None) if callable(params) else None
    return p.device if p is not None else torch.device("cpu")


@torch.no_grad()
def predict(model: Any, x0: np.ndarray, raw: np.ndarray, steps: int, batch_size: int = 4
            ) -> Iterator[tuple[int, np.ndarray]]:
    """Rollouts of ``model`` from x0 under constant raw controls, one case at a time.

    Args:
        model: anything ``rollout`` accepts. x0: (2, D, H, W) initial state shared by every case, or
            (N, 2, D, H, W), one per case.
        raw: (N, 14) raw controls (physical units; normalized here, unclipped).
        steps: transitions per rollout. batch_size: cases rolled out together.
    Yields:
        (row, trajectory (steps + 1, 2, D, H, W) float32 numpy).
    """
    from nemsim.evaluation.rollout import rollout

    raw = np.atleast_2d(np.asarray(raw, dtype=np.float64))
    device = model_device(model)
    base = torch.as_tensor(np.asarray(x0), dtype=torch.float32, device=device)  # (2 | N, ...)
    u_all = torch.as_tensor(to_normalized(raw), dtype=torch.float32)  # (N, 14)
    for start in range(0, len(raw), batch_size):
        u = u_all[start : start + batch_size].to(device)
        if base.dim() == 5:  # one initial state per case
            x = base[start : start + len(u)].contiguous()  # (B, 2, D, H, W)
        else:
            x = base[None].expand(len(u), *base.shape).contiguous()  # (B, 2, D, H, W)
        traj = rollout(model, x, u, steps)  # (B, steps + 1, 2, D, H, W)
        arr = traj.float().cpu().numpy()
        for i in range(len(u)):
            yield start + i, arr[i]


def step_rmse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-step RMSE (T,) between two trajectories (T, 2, D, H, W) (normalized SDF units)."""
    from nemsim.evaluation.metrics import rmse_per_step

    return rmse_per_step(a[None], b[None])


def avg_rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Avg RMSE over t = 1..T of two trajectories that share their initial state (index 0)."""
    return float(step_rmse(a[1:], b[1:]).mean())


def final_metrics(m: dict[str, np.ndarray]) -> dict[str, float]:
    return {k: float(v[-1]) for k, v in m.items()}


def compare_case(truth: SimTruth, raw: np.ndarray, pred: np.ndarray, seeds: tuple[int, int]
                 ) -> dict[str, Any]:
    """Surrogate trajectory ``pred`` against the simulator's two seeds of ``raw``.

    Returns (JSON-ready): ``avg_rmse`` (model vs each seed, mean; normalized SDF units), ``floor`` (seed vs
    seed), ``no_change`` (x_0 held for every step vs each seed, mean), ``worse_than_no_change``; final
    profile metrics (nm) of the ``model``, each seed (``sim_a``, ``sim_b``), their mean ``sim``, the
    ``error`` model - sim mean and the ``seed_diff`` |a - b|.
    """
    a, b = truth.states(raw, seeds[0]), truth.states(raw, seeds[1])
    if pred.shape != a.shape:
        raise ValueError(f"prediction shape {pred.shape} != simulated {a.shape}")
    still = np.broadcast_to(a[0], a.shape)
    model_rmse = 0.5 * (avg_rmse(pred, a) + avg_rmse(pred, b))
    no_change = 0.5 * (avg_rmse(still, a) + avg_rmse(still, b))
    fa, fb = final_metrics(truth.metrics(raw, seeds[0])), final_metrics(truth.metrics(raw, seeds[1]))
    fm = final_metrics(profile_metrics_batch(pred, truth.scene))
    sim = {k: 0.5 * (fa[k] + fb[k]) for k in fa}
    return {
        "controls": [float(v) for v in raw],
        "avg_rmse": model_rmse,
        "floor": avg_rmse(a, b),
        "no_change": no_change,
        "worse_than_no_change": bool(model_rmse > no_change * (1.0 + 1e-9)),  # a rounding tie is not worse
        "model": fm,
        "sim_a": fa,
        "sim_b": fb,
        "sim": sim,
        "error": {k: fm[k] - sim[k] for k in fm},
        "seed_diff": {k: abs(fa[k] - fb[k]) for k in fa},
    }


def write_report(rep: dict[str, Any], out_dir: str | Path, name: str,
                 markdown: Callable[[dict[str, Any]], str],
                 plot: Callable[[dict[str, Any], Path], Any]) -> dict[str, str]:
    """``name``.md, .json and .png of a benchmark report in ``out_dir``; returns their paths by kind."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.md").write_text(markdown(rep))
    (out / f"{name}.json").write_text(json.dumps(rep, indent=2))
    plot(rep, out / f"{name}.png")
    return {k: str(out / f"{name}.{k}") for k in ("md", "json", "png")}
