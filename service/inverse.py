"""Inverse design (`POST /design` jobs) and profile-metric intervals for the service.

The search is `nemsim.analysis.inverse.search` on the loaded model (PyTorch: gradients; the fast runtime
serves rollouts only); verification runs the simulator for the top recipes in child processes, the same
way simulator jobs do (`service.jobs.run_simulator`), inside the design job (the job queue's worker is
busy with the design itself, so a nested job could never start). Intervals come from the checkpoint's
calibration file (`nemsim.analysis.intervals`), read once per model.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import torch

from nemsim.analysis.intervals import Calibration, Support, calibration_for
from nemsim.analysis.inverse import (
    InverseContext,
    InverseSpec,
    RefineConfig,
    SearchCancelled,
    SimulationSkipped,
    refine_with_simulator,
    search,
    simulated_metrics,
    verify_recipes,
)
from nemsim.controls import CONTROL_NAMES
from service.job_processes import SimulatorChildren
from service.jobs import Job, JobCancelled, run_simulator

SEARCH_SHARE = 0.6  # progress share of the search when the job also verifies

_calibrations: dict[str, Calibration | None] = {}
_lock = threading.Lock()


def calibration(served: Any) -> Calibration | None:
    """The calibration stored next to the served checkpoint (None: none, or one of another file)."""
    with _lock:
        if served.model_id not in _calibrations:
            path = getattr(served.predictor.loaded, "path", None)
            _calibrations[served.model_id] = calibration_for(path) if path is not None else None
        return _calibrations[served.model_id]


def rollout_intervals(served: Any, metrics: dict[str, list[float | None]]) -> dict[str, Any]:
    """Per-step conformal intervals of a rollout's metrics, or why there are none."""
    cal = calibration(served)
    if cal is None:
        return {
            "available": False,
            "reason": "no calibration file for the served checkpoint "
            "(`nemsim calibrate` writes <checkpoint stem>.calibration.json)",
        }
    steps = len(next(iter(metrics.values()))) - 1
    out: dict[str, Any] = {
        "available": True,
        "levels": list(cal.levels),
        "method": cal.calibration.get("method"),
        "calibrated_on": f"{cal.calibration.get('cases')} {cal.calibration.get('split')} cases",
        "by_level": {f"{lv:g}": cal.intervals(metrics, lv) for lv in cal.levels},
    }
    if steps > cal.steps:
        out["warning"] = (
            f"steps past {cal.steps} reuse the last calibrated step's interval widths (not calibrated there)"
        )
    return out


class _Share:
    """A job seen by `run_simulator` whose progress maps into [base, base + span] of the real job."""

    def __init__(self, job: Job, base: float, span: float) -> None:
        self._job, self._base, self._span = job, base, span

    @property
    def cancelled(self) -> bool:
        return self._job.cancelled

    @property
    def children(self) -> SimulatorChildren | None:
        return self._job.children  # the queue's: its folder, and stopped with it

    @property
    def progress(self) -> float:
        return self._job.progress

    @progress.setter
    def progress(self, value: float) -> None:
        self._job.progress = self._base + self._span * float(value)


def design_work(
    job: Job,
    served: Any,
    spec: InverseSpec,
    *,
    seed: int,
    verify: bool,
    verify_top: int,
    sim_seed: int,
    sim_max_work: float,
    refine: RefineConfig | None = None,
) -> dict[str, Any]:
    """The work of a design job: search, then (with verify) simulate the top recipes; with ``refine`` the
    simulator-corrected design (``nemsim.analysis.inverse.refine``) instead."""
    from nemsim.evaluation.truth import particle_work

    predictor = served.predictor
    cal = calibration(served)
    ctx = InverseContext(
        model=predictor.model,
        scene=predictor.scene,
        x0=torch.from_numpy(np.asarray(predictor.x0, dtype=np.float32)),
        calibration=cal,
        support=Support.from_record(cal.support if cal else None),
        model_id=served.model_id,
        loaded=predictor.loaded,
    )
    if refine is not None:
        return _refined(
            job, predictor, ctx, spec, refine, seed=seed, sim_seed=sim_seed, sim_max_work=sim_max_work
        )
    share = SEARCH_SHARE if verify else 0.98

    def progress(f: float, _msg: str) -> None:
        job.progress = share * f

    try:
        result = search(ctx, spec, seed=seed, on_progress=progress, should_stop=lambda: job.cancelled)
    except SearchCancelled:
        raise JobCancelled from None
    if verify:
        top = min(verify_top, len(result["recipes"]))
        span = (0.98 - share) / max(top, 1)
        skipped = []
        for i, rec in enumerate(result["recipes"][:top]):
            raw = np.array([rec["controls"][n] for n in CONTROL_NAMES], dtype=np.float64)
            work = particle_work([(raw, 0)])
            if work > sim_max_work:
                skipped.append(
                    f"recipe {i + 1}: {work:.3g}x the work of a design-centre run (server limit "
                    f"{sim_max_work:g}x)"
                )
        counter = {"i": 0}

        def simulate(raw: np.ndarray, steps: int) -> np.ndarray:
            sub = _Share(job, share + span * counter["i"], span)
            counter["i"] += 1
            schedule = np.repeat(raw[None], steps, axis=0)  # (T, 14)
            states = run_simulator(
                sub, predictor.scene, predictor.sim_config, schedule, sim_seed, share=1.0  # type: ignore[arg-type]
            )
            return states.astype(np.float32)

        if skipped:
            result["verification"] = {"seed": sim_seed, "recipes": [], "skipped": skipped}
        else:
            result["verification"] = {
                "seed": sim_seed,
                "recipes": verify_recipes(result, spec, predictor.scene, simulate, top),
            }
    return result


def _refined(
    job: Job,
    predictor: Any,
    ctx: InverseContext,
    spec: InverseSpec,
    refine: RefineConfig,
    *,
    seed: int,
    sim_seed: int,
    sim_max_work: float,
) -> dict[str, Any]:
    """The simulator-corrected design in a job: every simulator run in a child process, as for simulator
    jobs; a recipe beyond the server's work limit is skipped (reported), not simulated."""
    from nemsim.evaluation.truth import particle_work

    def simulate(raw: np.ndarray, steps: int) -> np.ndarray:
        work = particle_work([(raw, 0)])
        if work > sim_max_work:
            raise SimulationSkipped(
                f"{work:.3g}x the work of a design-centre run (server limit {sim_max_work:g}x)"
            )
        schedule = np.repeat(raw[None], steps, axis=0)  # (T, 14)
        hold = _Share(job, job.progress, 0.0)  # the design's progress stands still while it simulates
        states = run_simulator(
            hold, predictor.scene, predictor.sim_config, schedule, sim_seed, share=1.0  # type: ignore[arg-type]
        )
        return states.astype(np.float32)

    def progress(f: float, _msg: str) -> None:
        job.progress = 0.98 * f

    try:
        return refine_with_simulator(
            ctx,
            spec,
            simulated_metrics(simulate, predictor.scene),
            refine=refine,
            seed=seed,
            sim_seed=sim_seed,
            on_progress=progress,
            should_stop=lambda: job.cancelled,
        )
    except SearchCancelled:
        raise JobCancelled from None
