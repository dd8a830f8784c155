"""Inverse design (`POST /design` jobs) and profile-metric intervals for the service.

A design job runs in a child process of the job queue (`service.jobs.run_child`, task `design` of
`service.sim_child`), as a simulator job's simulator does: the search's gradients and its batched rollouts
take hundreds of MB, which the server's resident memory would keep (its budget is 1 GB); cancelling kills
the search at once; the child computes at the server's priority. The server writes the served weights
into the job's folder in checkpoint form (`write_weights`) with what it derived from them (initial state,
simulator configuration, calibration, model id); the child loads them with the weights-only loader
(`nemsim.inference.checkpoint`), runs `nemsim.analysis.inverse.search` in PyTorch (gradients; the fast
runtime serves rollouts only), then the verification's or the simulator-corrected rounds' simulator runs
in the same process (`service.sim_child.design_in_child`, beside what a simulator job runs), and writes the
result as JSON. Progress goes to the job as the child reports it. Intervals come from the checkpoint's
calibration file (`nemsim.analysis.intervals`), read once per model.

A design's result reports `simulator_calls` (every simulator run it made: verification, corrected rounds)
and, when the repository holds a committed `nemsim bench design-cost` result for the served checkpoint
(`benchmarks/<scene>/design_cost/results.json` stamped with its checkpoint id), `expected_calls_to_target`:
that benchmark's simulator calls per target reached with the surrogate-guided design (its `design`
strategy: every call it spent on the reachable targets, independent confirmation runs included, over the
targets it reached), read once per model. Calls per hit rather than the median: it stays finite when
fewer than half the targets are reached, and it is what a design costs on average when a miss is retried.
It is one figure for every design, not an estimate for the query at hand, and `expected_calls_basis` says
so (how many targets it averages, where it comes from). Another checkpoint, or an installation without the
benchmarks, has none: both fields are then absent.

Every rollout also says how far its recipe lies from the training data and what error the committed
extrapolation benchmark of the served checkpoint (`benchmarks/<scene>/extrapolation/extrapolation.json`,
stamped with its checkpoint id) measured there, with a verdict ok / warn / reject (`rollout_trust`,
`nemsim.analysis.trust`); without that benchmark the verdict follows the region alone and says so. The
feature etched is judged beside the controls: outside the geometry the checkpoint was trained on
(`nemsim.inference.range_check.geometry_outside`) the verdict is `reject` whatever the controls' region, the
reason names the feature and the trained range, and `controls_level` keeps the controls' own verdict.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nemsim.analysis.intervals import Calibration, Support, calibration_for
from nemsim.analysis.inverse import (
    InverseSpec,
    RefineConfig,
)
from nemsim.analysis.trust import assess, place
from service.jobs import ChildFailed, Job, run_child
from service.sim_child import MODEL_FILE, RESULT_FILE

_calibrations: dict[str, Calibration | None] = {}
_results: dict[tuple[str, str], dict[str, Any] | None] = {}  # committed benchmark results (`_committed`)
_supports: dict[str, Support] = {}
_lock = threading.Lock()
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"  # the repository's committed results
DESIGN_LABEL = "design"  # the strategy of `nemsim bench design-cost` that `POST /design` runs


def calibration(served: Any) -> Calibration | None:
    """The calibration stored next to the served checkpoint (None: none, or one of another file)."""
    with _lock:
        if served.model_id not in _calibrations:
            path = getattr(served.predictor.loaded, "path", None)
            _calibrations[served.model_id] = calibration_for(path) if path is not None else None
        return _calibrations[served.model_id]


def expected_calls_to_target(served: Any, benchmarks: Path = BENCHMARKS) -> tuple[float, str] | None:
    """The committed design-cost benchmark's simulator calls per target reached, for the served checkpoint,
    and a line that says what that figure is (module docstring); None when there is no result for it."""
    rep = _committed(served, benchmarks, "design_cost/results.json")
    summary = rep.get("summary", {}).get(DESIGN_LABEL) if rep else None
    value = summary.get("calls_per_hit") if isinstance(summary, dict) else None
    if not isinstance(summary, dict) or not isinstance(value, int | float) or isinstance(value, bool):
        return None
    basis = (
        f"the benchmark's average over {summary.get('reachable', '?')} held-out reachable targets "
        f"(nemsim bench design-cost, benchmarks/{served.predictor.scene.name}/design_cost), the same "
        "figure for every design: not an estimate for this one"
    )
    return float(value), basis


def rollout_trust(served: Any, raw: np.ndarray, normalized: np.ndarray, feature: Any = None,
                  benchmarks: Path = BENCHMARKS) -> dict[str, Any]:
    """Where the recipe (T, 14) physical / normalized lies and the error measured there, and whether
    `feature` (as built; None: the model's own) lies in the trained geometry (module docstring)."""
    out = _controls_trust(served, raw, normalized, benchmarks)
    return with_geometry_trust(out, served.predictor, feature)


def with_geometry_trust(trust: dict[str, Any], predictor: Any, feature: Any = None) -> dict[str, Any]:
    """`trust` with its `geometry` entry (the feature, inside the trained ranges?, those ranges); outside
    them the level is `reject` (module docstring)."""
    feature = predictor.case(None).feature if feature is None else feature
    out = dict(trust)
    out["geometry"], outside = _geometry_entry(predictor, feature)
    if outside is not None:
        out["controls_level"] = out.get("level")
        out["level"] = "reject"
        out["reason"] = f"{outside}; controls: {out.get('reason')}"
    return out


def _controls_trust(served: Any, raw: np.ndarray, normalized: np.ndarray, benchmarks: Path) -> dict[str, Any]:
    """The controls' part of `rollout_trust` (`nemsim.analysis.trust`)."""
    cal = calibration(served)
    with _lock:
        if served.model_id not in _supports:
            _supports[served.model_id] = Support.from_record(cal.support if cal is not None else None)
        support = _supports[served.model_id]
    rep = _committed(served, benchmarks, "extrapolation/extrapolation.json")
    summary = rep.get("summary") if rep else None
    bench = None
    if isinstance(summary, dict) and isinstance(summary.get("groups"), dict):
        scene = served.predictor.scene.name
        bench = {**summary, "source": f"benchmarks/{scene}/extrapolation (nemsim bench extrapolation, "
                                      f"model {served.model_id})"}
    return assess(place(normalized, raw, support), bench)


def _committed(served: Any, benchmarks: Path, name: str) -> dict[str, Any] | None:
    """The committed benchmark result ``benchmarks/<scene>/<name>`` when it is stamped with the served
    checkpoint's id, else None; read once per (model, file)."""
    scene = getattr(served.predictor.scene, "name", None)
    path = benchmarks / str(scene) / name
    key = (served.model_id, str(path))
    with _lock:
        if key not in _results:
            try:
                rep = json.loads(path.read_text())
            except (OSError, ValueError):
                rep = None
            cid = served.model_id.rpartition("@")[2]
            _results[key] = rep if isinstance(rep, dict) and rep.get("checkpoint_id") == cid else None
        return _results[key]


def with_call_counts(result: dict[str, Any], served: Any) -> dict[str, Any]:
    """The design result with ``simulator_calls`` and, when the benchmark has a figure for the served
    checkpoint, ``expected_calls_to_target`` and ``expected_calls_basis``."""
    out = dict(result)
    if "simulator_calls" not in out:
        out["simulator_calls"] = len((out.get("verification") or {}).get("recipes") or [])
    expected = expected_calls_to_target(served)
    if expected is not None:
        out["expected_calls_to_target"], out["expected_calls_basis"] = expected
    return out


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
    case: Any = None,
) -> dict[str, Any]:
    """The work of a design job: search, then (with verify) simulate the top recipes; with ``refine`` the
    simulator-corrected design (``nemsim.analysis.inverse.refine``) instead. All of it in a child process
    (`service.sim_child.design_in_child`), which gets the served weights and what the server derived from
    them. ``case``: the predictor's FeatureCase the recipe is searched for (None: the model's own feature);
    outside the trained geometry every recipe is marked ``ood``."""
    predictor = served.predictor
    case = case or predictor.case(None)
    inputs = {
        "spec": spec,
        "seed": int(seed),
        "verify": bool(verify),
        "verify_top": int(verify_top),
        "sim_seed": int(sim_seed),
        "sim_max_work": float(sim_max_work),
        "refine": refine,
        "x0": np.asarray(case.x0, dtype=np.float32),  # (2, D, H, W)
        "scene": case.scene,  # the per-case scene: metrics, targets' ranges, simulator runs
        "sim_config": predictor.simulator_config(case.scene),
        "calibration": calibration(served),
        "model_id": served.model_id,
        "threads": torch.get_num_threads(),  # the server's: the search computes as it would in the server
    }
    try:
        result = run_child(
            job,
            "design",
            inputs,
            lambda job_dir: json.loads((job_dir / RESULT_FILE).read_text()),
            what="the design",
            write=lambda job_dir: write_weights(predictor.loaded, job_dir / MODEL_FILE),
        )
    except ChildFailed as exc:  # the job's message: the search's own, as if it ran here
        raise RuntimeError(exc.detail or exc.kind or str(exc)) from None
    return with_geometry(with_call_counts(result, served), predictor, case.feature)


def with_geometry(result: dict[str, Any], predictor: Any, feature: Any) -> dict[str, Any]:
    """A design result with its `geometry` (feature, inside the trained ranges?, the ranges, why not);
    outside them every recipe is `ood`."""
    out = dict(result)
    entry, outside = _geometry_entry(predictor, feature)
    out["geometry"] = entry if outside is None else {**entry, "reason": outside}
    if outside is not None:
        out["recipes"] = [{**rec, "ood": True} for rec in out.get("recipes") or []]
    return out


def _geometry_entry(predictor: Any, feature: Any) -> tuple[dict[str, Any], str | None]:
    """(the `geometry` entry of an answer: the feature, inside the trained ranges?, those ranges; why it lies
    outside them, None inside)."""
    outside = predictor.geometry_outside(feature)
    entry = {"feature": feature.to_dict(), "inside": outside is None,
             "trained": predictor.geometry.as_dict()["kinds"]}
    return entry, outside


def write_weights(loaded: Any, path: Path) -> None:
    """The served model as a checkpoint file (`nemsim.inference.checkpoint`'s format, weights verified at
    load): a checkpoint replaced on disk while the server runs does not change what a design job uses."""
    torch.save({**loaded.raw, "model_state": loaded.model.state_dict()}, path)
