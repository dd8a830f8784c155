"""Speed against error (`nemsim bench speed-error`): what a trajectory costs and how far it is from the truth.

On the first N test cases of a split that the data file holds complete (missing ones are listed in
``skipped_case_ids``), every method produces the same 100-step trajectory and is scored against one
**reference**: an independent full-budget simulator run of the case (``default_rng([seed, case_id, 0])``,
another stream than the file's), with the configuration the file records (``SimConfig.from_record``; a file
that records none is refused). Methods:

  * the simulator at particle budgets 1, 1/2, ..., 1/16 (``SimConfig.particle_budget``, seeds
    ``[seed, case_id, k]``). At budget 1 the compared trajectory is the data file's own, so that row **is
    the noise floor**: two equally good simulator runs differ by this much;
  * the **quarter-domain** simulator (``SimConfig.domain`` = "quarter": the scene's lower quadrant between
    mirror walls, the states mirrored to full size) at the same budgets, seeds ``[seed, case_id, k, 1]``
    (another stream: a trailing 0 would not change it), rows "simulator quarter, budget b". The full
    domain is the simulator that made the data and always runs; the quarter is skipped, with the reason in
    ``sim_domains_skipped`` and a note under the table, on a scene it refuses (odd nx or ny: ``tiny``);
  * every surrogate **variant**: each checkpoint under each runtime ``<backend>-<precision>``
    (``nemsim.inference.runtime.compile_model``; ``torch-f32``, PyTorch eager, is the reference), rolled out
    from the case's x_0 with the file's controls.

Errors (``nemsim.evaluation.metrics``): Avg / Final RMSE over t = 1..H and the final-step Chamfer distance;
the error against the data file is kept as ``avg_rmse_vs_data``. Speed, on wall and CPU seconds, against
each simulator side by side (``add_speedups``): the full domain (``speedup``, ``speedup_cpu``,
``batch_speedup``, ``equal_accuracy``) and the quarter domain (the same keys + ``_quarter``; None when it
was not measured):
  (a) ``speedup``: that simulator's full-budget time per trajectory over the variant's (batch 1);
  (b) ``equal_accuracy``: that simulator's time at the variant's Avg RMSE, interpolated in (log error,
      log time) between its budgets (``equal_accuracy_time``), over the variant's time; outside the
      simulator's errors (or with one budget, off its one point) the nearest row bounds it (">=" / "<=").

Timing: batch 1 on ``threads`` threads, methods side by side case by case after one warm-up, so load from
other jobs hits them alike; the median over cases. A surrogate's time on a case is the median of
``SURROGATE_REPEATS`` rollouts, each written into one trajectory buffer per variant, reused (as the
service and any caller rolling out many recipes reuse theirs); one more rollout into a fresh trajectory is
timed beside it (``wall_s_fresh_output``: a fresh multi-100-MB array costs its page faults on `paper`).
Throughput: each variant then rolls out
``throughput_batch`` trajectories in one batch (the simulator does not batch). A variant "keeps the error"
within ``keep_error_rel`` of its checkpoint's ``torch-f32``; the fastest such is ``speed.nemsim_*``, with its
speed-ups against both domains (``speed.speedup``, ``speed.equal_accuracy``, ``speed.*_quarter``).
"""

from __future__ import annotations

import json
import logging
import math
import statistics
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.evaluation.figure import pyplot, save_figure
from nemsim.evaluation.metrics import StepRmse, chamfer_distance, count_params

log = logging.getLogger(__name__)

BACKENDS = ("torch", "openvino")
PRECISIONS = ("f32", "bf16")
RUNTIMES = tuple(f"{b}-{p}" for b in BACKENDS for p in PRECISIONS)
REFERENCE_RUNTIME = "torch-f32"
NOISE_FLOOR_NOTE = "noise floor (two full-budget seeds)"
SURROGATE_REPEATS = 3  # timed rollouts of each surrogate per case (their median)
SIM_DOMAINS = ("full", "quarter")  # SimConfig.domain; "full" made the data sets and is the reference
_DOMAIN_SUFFIX = {"full": "", "quarter": "_quarter"}  # report keys of the speed-ups against each domain


@dataclass(frozen=True)
class SpeedErrorConfig:
    cases: int = 5  # first N test cases of the setting
    budgets: tuple[float, ...] = (1.0, 0.5, 0.25, 0.125, 0.0625)  # particle budgets (1: the noise floor)
    runtimes: tuple[str, ...] = RUNTIMES  # "<backend>-<precision>"; "torch-f32" (the reference) always runs
    threads: int = 1  # torch / OpenVINO threads per rollout
    throughput_batch: int = 16  # batch of the throughput run (0: none)
    seed: int = 1  # entropy of the reference / reruns: default_rng(rerun_seed(seed, case_id, domain, k))
    steps: int | None = None  # transitions per trajectory (default: the scene's horizon, 100)
    keep_error_rel: float = 0.05  # a variant keeps the error if Avg RMSE <= torch-f32 * (1 + this)
    sim_domains: tuple[str, ...] = SIM_DOMAINS  # "full" always runs; "quarter" where the scene allows it


def budget_label(b: float) -> str:
    """1.0 -> '1', 0.25 -> '1/4', 0.0625 -> '1/16'."""
    f = Fraction(b).limit_denominator(1000)
    return str(f.numerator) if f.denominator == 1 else f"{f.numerator}/{f.denominator}"


def parse_runtime(name: str) -> tuple[str, str]:
    """'openvino-bf16' -> ('openvino', 'bf16'); ValueError naming the choices otherwise."""
    if name not in RUNTIMES:
        raise ValueError(f"unknown runtime {name!r}; expected one of {RUNTIMES}")
    backend, precision = name.split("-")
    return backend, precision


def rerun_seed(seed: int, case_id: int, domain: str, k: int) -> list[int]:
    """``default_rng`` entropy of the simulator run of budget index k (0: budget 1) on ``domain``: [seed,
    case_id, k] on the full domain (k = 0: the reference), [seed, case_id, k, 1] on the quarter (a trailing
    0 would give the full domain's stream: ``SeedSequence`` pads the entropy with zeros)."""
    return [seed, case_id, k] if domain == "full" else [seed, case_id, k, 1]


def sim_label(domain: str, b: float) -> str:
    """('full', 0.25) -> 'simulator, budget 1/4'; ('quarter', 1.0) -> 'simulator quarter, budget 1'."""
    return f"simulator{'' if domain == 'full' else ' ' + domain}, budget {budget_label(b)}"


def equal_accuracy_time(points: Sequence[tuple[float, float]], error: float) -> tuple[float | None, str]:
    """The simulator's time at ``error``, from its measured (Avg RMSE, seconds) points (one per budget).

    Linear interpolation of log(seconds) against log(Avg RMSE) between the points sorted by error.
    Returns (seconds, bound): bound "interpolated" inside the measured errors; "lower" when ``error`` is
    below every point's (the most accurate point's time: the simulator needs at least that); "upper" when
    above every point's (the cheapest such point's time: the simulator needs at most that); (None, "none")
    without usable points (errors or times <= 0 or not finite).
    """
    pts = sorted((e, t) for e, t in points if e > 0 and t > 0 and math.isfinite(e) and math.isfinite(t))
    if not pts or not (error > 0 and math.isfinite(error)):
        return None, "none"
    errs = [e for e, _ in pts]
    if error < errs[0]:
        return pts[0][1], "lower"
    if error > errs[-1]:
        return pts[-1][1], "upper"
    log_t = np.interp(math.log(error), np.log(errs), np.log([t for _, t in pts]))
    return float(math.exp(log_t)), "interpolated"


def _timed(fn):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


class _Scores:
    """Streaming Avg/Final RMSE (vs reference and vs data), final CD and times of one method."""

    def __init__(self) -> None:
        self.vs_ref = StepRmse()
        self.vs_data = StepRmse()
        self.cd: list[float] = []
        self.wall: list[float] = []
        self.cpu: list[float] = []
        self.fresh_wall: list[float] = []  # surrogates: the same rollout into a freshly allocated trajectory

    def add(self, pred, ref, data, scene, case_id: int, steps: int, wall: float, cpu: float, cache) -> None:
        """pred, ref, data: (T+1, 2, D, H, W); step 0 (the shared x_0) is excluded from the RMSE."""
        self.vs_ref.update(pred[None, 1:], ref[None, 1:])
        self.vs_data.update(pred[None, 1:], data[None, 1:])
        self.cd.append(float(chamfer_distance(pred[-1], ref[-1], scene, case_id, steps, cache=cache)))
        self.wall.append(float(wall))
        self.cpu.append(float(cpu))

    def summary(self) -> dict[str, Any]:
        return {
            "wall_s": statistics.median(self.wall),
            "cpu_s": statistics.median(self.cpu),
            "avg_rmse": self.vs_ref.avg(),
            "final_rmse": self.vs_ref.final(),
            "cd": float(np.mean(self.cd)),
            "avg_rmse_vs_data": self.vs_data.avg(),
            "wall_s_fresh_output": statistics.median(self.fresh_wall) if self.fresh_wall else None,
            "wall_s_per_case": self.wall,
            "cpu_s_per_case": self.cpu,
            "cd_per_case": self.cd,
        }


@dataclass
class _Bench:
    """What the measurements of one ``run_speed_error`` share: data, simulator, predictors, scores."""

    tf: Any  # the open TrajectoryFile
    scene: Any
    rules: Any
    tables: Any  # the simulator's event tables
    sim_cfgs: dict[tuple[str, float], Any]  # (domain, particle budget) -> resolved SimConfig (full, 1 first)
    steps: int
    variants: dict[tuple[str, str], Any]  # (model label, runtime) -> predictor
    seed: int
    scores: dict[Any, _Scores] = field(default_factory=dict)
    cd_cache: dict = field(default_factory=dict)
    # per variant: the (1, T+1, 2, D, H, W) trajectory its rollouts are written into, reused from case to
    # case as the service and a caller rolling out many recipes reuse theirs (zero-filled: its pages mapped
    # before any timing)
    outputs: dict[tuple[str, str], Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        keys = [("sim", d, b) for d, b in self.sim_cfgs] + list(self.variants)
        self.scores = {k: _Scores() for k in keys}

    def controls_of(self, row: int) -> tuple[np.ndarray, Any]:
        """(14,) or (T, 14) raw controls; (1, T, 14) normalized tensor."""
        import torch

        sched = self.tf.controls_raw_schedule
        raw = sched[row] if sched is not None else self.tf.controls_raw[row]
        u = self.tf.controls_normalized_schedule(row)[: self.steps]
        return np.asarray(raw), torch.as_tensor(u, dtype=torch.float32)[None]

    def simulate(self, raw: np.ndarray, sim: tuple[str, float], rng_key: int | list[int],
                 n: int | None = None) -> Any:
        """A simulator trajectory of ``steps`` (or ``n``) transitions; ``sim``: (domain, particle budget)."""
        from nemsim.sim import run_trajectory

        rng = np.random.default_rng(rng_key)
        return run_trajectory(self.scene, self.rules, raw, rng, self.sim_cfgs[sim], tables=self.tables,
                              n_transitions=self.steps if n is None else n)  # fmt: skip

    def warm_up(self, row: int, nb: int) -> None:
        """JIT kernels, first-call allocations and graph compilation of every variant."""
        import torch

        from nemsim.evaluation.rollout import rollout

        raw0, u0 = self.controls_of(row)
        x00 = torch.as_tensor(np.asarray(self.tf.states[row, 0], dtype=np.float32))[None]
        for sim in self.sim_cfgs:
            self.simulate(raw0, sim, 0, n=1)
        for key, pred in self.variants.items():
            self.outputs[key] = torch.zeros((1, self.steps + 1, *x00.shape[1:]))
            rollout(pred, x00, u0, min(2, self.steps))
            if nb:
                rollout(pred, x00.expand(nb, -1, -1, -1, -1), u0.expand(nb, -1, -1), 1, keep=False)

    def measure_case(self, case_id: int, row: int) -> tuple[Any, Any]:
        """Time and score every method on one case; returns its (x0 (1, 2, D, H, W), u (1, T, 14))."""
        import torch

        from nemsim.evaluation.rollout import rollout

        scene, steps, cd_cache = self.scene, self.steps, self.cd_cache
        raw, u = self.controls_of(row)
        data_states = np.asarray(self.tf.states[row, : steps + 1], dtype=np.float32)  # (T+1, 2, D, H, W)
        ref_key = rerun_seed(self.seed, case_id, "full", 0)
        ref_res, wall, cpu = _timed(lambda: self.simulate(raw, ("full", 1.0), ref_key))
        ref = ref_res.states
        if np.array_equal(ref, data_states):
            raise ValueError(f"case {case_id}: the reference rerun equals the data file's trajectory; "
                             "choose another --seed")  # fmt: skip
        # budget 1: the data file's trajectory is the second full-budget seed (noise floor)
        self.scores[("sim", "full", 1.0)].add(data_states, ref, data_states, scene, case_id, steps, wall, cpu,
                                              cd_cache)  # fmt: skip
        budgets = list(dict.fromkeys(b for _, b in self.sim_cfgs))  # budget index k: the seeds' third word
        for domain, b in list(self.sim_cfgs)[1:]:
            entropy = rerun_seed(self.seed, case_id, domain, budgets.index(b))
            res, wall, cpu = _timed(lambda d=domain, b=b, e=entropy: self.simulate(raw, (d, b), e))
            self.scores[("sim", domain, b)].add(res.states, ref, data_states, scene, case_id, steps, wall,
                                                cpu, cd_cache)  # fmt: skip
        x0 = torch.as_tensor(data_states[0])[None]  # (1, 2, D, H, W)
        for key, pred in self.variants.items():
            buf = self.outputs[key]
            # the median of a few repeats: the first rollout after a simulator run meets cold caches
            runs = [_timed(lambda pred=pred, buf=buf: rollout(pred, x0, u, steps, out=buf))
                    for _ in range(SURROGATE_REPEATS)]
            out = runs[-1][0]
            wall, cpu = statistics.median(r[1] for r in runs), statistics.median(r[2] for r in runs)
            fresh, fresh_wall, _ = _timed(lambda pred=pred: rollout(pred, x0, u, steps))
            if not torch.equal(fresh, out):
                raise RuntimeError(f"{key}: the rollout into a reused buffer differs from a fresh one")
            del fresh
            out = out[0].float().numpy()  # (T+1, 2, D, H, W)
            self.scores[key].add(out, ref, data_states, scene, case_id, steps, wall, cpu, cd_cache)
            self.scores[key].fresh_wall.append(fresh_wall)
        log.info("case %d done", case_id)
        return x0, u


def _check_config(config: SpeedErrorConfig) -> tuple[list[str], list[float], list[str]]:
    """(runtimes, budgets, simulator domains) to measure, the references first; ValueError on a bad config."""
    runtimes = [REFERENCE_RUNTIME] + [r for r in dict.fromkeys(config.runtimes) if r != REFERENCE_RUNTIME]
    for r in runtimes:
        parse_runtime(r)  # validates the name
    budgets = [1.0] + [float(b) for b in dict.fromkeys(config.budgets) if float(b) != 1.0]
    domains = ["full"] + [d for d in dict.fromkeys(config.sim_domains) if d != "full"]
    for d in domains:
        if d not in SIM_DOMAINS:
            raise ValueError(f"unknown simulator domain {d!r}; expected one of {SIM_DOMAINS}")
    if config.cases < 1:
        raise ValueError(f"cases must be >= 1, got {config.cases}")
    if config.threads < 1 or config.throughput_batch < 0:
        raise ValueError(f"threads must be >= 1 and throughput_batch >= 0, got {config.threads}, "
                         f"{config.throughput_batch}")  # fmt: skip
    return runtimes, budgets, domains


def _sim_configs(base_cfg: Any, scene: Any, budgets: list[float], domains: list[str],
                 data: str | Path) -> tuple[dict[tuple[str, float], Any], dict[str, str]]:
    """({(domain, budget): resolved SimConfig}, {skipped domain: why}): the file's configuration on each
    domain the scene allows at each budget, the full domain (the file's) first."""
    if base_cfg.domain != "full":
        raise ValueError(f"{data} was made on the {base_cfg.domain!r} domain; the bench compares against the "
                         "full-domain simulator the data sets are made with")  # fmt: skip
    skipped: dict[str, str] = {}
    kept = []
    for d in domains:
        try:
            replace(base_cfg, domain=d).check_scene(scene)
        except ValueError as exc:
            skipped[d] = str(exc)
            log.warning("simulator domain %r skipped: %s", d, exc)
            continue
        kept.append(d)
    return {(d, b): replace(base_cfg, domain=d, particle_budget=b).resolved(scene)
            for d in kept for b in budgets}, skipped  # fmt: skip


def _test_rows(tf: Any, manifest: dict, cases: int,
               data: str | Path) -> tuple[list[int], list[int], list[int]]:
    """(case ids, file rows) of the first ``cases`` test cases the file holds complete, and the test cases
    passed over on the way (absent or unfinished: a file still being generated); ValueError if the file
    holds fewer than ``cases`` complete test cases."""
    from nemsim.data.splits import complete_cases

    all_ids = [int(c) for c in manifest.get("test", [])]
    if not all_ids:
        raise ValueError(f"setting {manifest.get('setting')!r} has no test cases")
    kept, dropped = complete_cases({"test": all_ids}, tf.case_ids, tf.complete)
    if len(kept["test"]) < cases:
        raise ValueError(f"{data} holds {len(kept['test'])} complete test cases of setting "
                         f"{manifest.get('setting')!r} ({len(dropped['test'])} of {len(all_ids)} absent or "
                         f"unfinished, e.g. {dropped['test'][:5]}); use --cases <= {len(kept['test'])} or "
                         "finish generation")  # fmt: skip
    test_ids = kept["test"][:cases]
    skipped = [c for c in all_ids[: all_ids.index(test_ids[-1])] if c in set(dropped["test"])]
    return test_ids, [tf.row_of(c) for c in test_ids], skipped


def _load_models(checkpoints: Sequence[str | Path], scene: Any, runtimes: list[str],
                 threads: int) -> tuple[list[tuple[str, Any, Path]], dict[tuple[str, str], Any]]:
    """([(label, LoadedModel, path)], {(label, runtime): predictor}) of the checkpoints."""
    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.inference.runtime import compile_model

    models: list[tuple[str, Any, Path]] = []  # (label, LoadedModel, path)
    for path in checkpoints:
        loaded = load_checkpoint(path, scene=scene)
        label = loaded.name
        if any(label == m[0] for m in models):
            label = f"{loaded.name} ({Path(path).stem})"
        models.append((label, loaded, Path(path)))
    variants: dict[tuple[str, str], Any] = {}  # (model label, runtime) -> predictor
    for label, loaded, _ in models:
        for rt in runtimes:
            backend, precision = parse_runtime(rt)
            variants[(label, rt)] = compile_model(loaded.model, backend, precision, threads)  # type: ignore[arg-type]
    return models, variants


def run_speed_error(
    data: str | Path,
    checkpoints: Sequence[str | Path],
    manifest: dict,
    config: SpeedErrorConfig = SpeedErrorConfig(),
) -> dict[str, Any]:
    """Measure every method on the first ``config.cases`` test cases of ``manifest`` (module docstring).

    Args:
        data: HDF5 trajectory file (``nemsim generate``); its ``generator`` constants configure the reruns.
        checkpoints: ``.pt`` files (any registered model); their scene must be the data file's.
        manifest: split manifest of the setting (``{"setting", "test": [case ids], ...}``).
    Returns:
        JSON-able report: ``rows`` (one per method: label, kind, domain (simulator rows), budget / runtime,
        backend, precision, wall_s, cpu_s, avg_rmse, final_rmse, cd, avg_rmse_vs_data, speedup, speedup_cpu,
        batch_speedup, equal_accuracy {...} and the same four + ``_quarter`` against the quarter domain,
        batch_wall_s / batch_cpu_s per trajectory at the throughput batch, noise_floor, keeps_error, fastest),
        plus ``sim_domains`` (measured), ``sim_domains_skipped`` {domain: why}, ``noise_floor`` {avg_rmse,
        final_rmse, cd} and ``speed`` (simulators and fastest NEMSim figures).
    """
    import torch

    from nemsim.data.hdf5 import open_trajectories
    from nemsim.evaluation.rollout import rollout
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.sim import SimConfig
    from nemsim.sim.events import build_event_tables

    runtimes, budgets, domains = _check_config(config)

    tf = open_trajectories(data)
    try:
        scene = tf.scene
        steps = scene.n_transitions if config.steps is None else int(config.steps)
        if not 1 <= steps <= tf.n_states - 1:
            raise ValueError(f"steps must be in [1, {tf.n_states - 1}], got {steps}")
        test_ids, rows, skipped = _test_rows(tf, manifest, config.cases, data)
        if skipped:
            log.warning("test cases %s are not complete in %s: measured on the next ones", skipped, data)

        rules = compile_rules(load_rules())
        tf.warn_if_other_rules(rules.sha256)
        base_cfg = SimConfig.from_record(tf.generator)
        if base_cfg is None:
            raise ValueError(f"{data} records no simulator configuration (its `generator` attribute): the "
                             "reference and budget reruns must use the configuration the file was made with")
        sim_cfgs, domains_skipped = _sim_configs(base_cfg, scene, budgets, domains, data)
        tables = build_event_tables(rules, base_cfg.resolved(scene))

        models, variants = _load_models(checkpoints, scene, runtimes, config.threads)

        bench = _Bench(tf, scene, rules, tables, sim_cfgs, steps, variants, config.seed)
        nb = config.throughput_batch
        bench.warm_up(rows[0], nb)
        inputs = [bench.measure_case(case_id, row) for case_id, row in zip(test_ids, rows, strict=True)]
        scores = bench.scores
        data_seeds = [int(tf.seeds[r]) for r in rows]
    finally:
        tf.close()

    batch_times: dict[tuple[str, str], tuple[float, float]] = {}  # per trajectory (wall, cpu)
    if nb:
        xb = torch.cat([inputs[i % len(inputs)][0] for i in range(nb)])  # (nb, 2, D, H, W)
        ub = torch.cat([inputs[i % len(inputs)][1] for i in range(nb)])  # (nb, T, 14)
        for key, pred in variants.items():
            _, wall, cpu = _timed(lambda pred=pred: rollout(pred, xb, ub, steps, keep=False))
            batch_times[key] = (wall / nb, cpu / nb)

    report_rows, fastest = _report_rows(list(sim_cfgs), models, runtimes, variants, scores, batch_times,
                                        config)  # fmt: skip
    sim_full = report_rows[0]
    nemsim_rows = [r for r in report_rows if r["kind"] == "model" and r["fastest"]
                   and r["model"].split(" (")[0] == "nemsim"]  # fmt: skip
    best = nemsim_rows[0] if nemsim_rows else None
    return {
        "scene": scene.name,
        "data": str(data),
        "setting": manifest.get("setting"),
        "case_ids": test_ids,
        "skipped_case_ids": skipped,
        "steps": steps,
        "threads": config.threads,
        "torch_threads": torch.get_num_threads(),
        "throughput_batch": nb,
        "config": asdict(config),
        "sim_domains": list(dict.fromkeys(d for d, _ in sim_cfgs)),
        "sim_domains_skipped": domains_skipped,
        "reference": {
            "what": "independent full-budget simulator run per case",
            "rng": f"numpy default_rng([{config.seed}, case_id, 0]); budget-b reruns [seed, case_id, k] "
                   "(k: the budget's index), on the quarter domain [seed, case_id, k, 1]",
            "data_seeds": data_seeds,
            "sim_config": sim_cfgs[("full", 1.0)].to_meta(scene),
        },
        "rows": report_rows,
        "fastest_keeping_error": fastest,
        "noise_floor": {k: sim_full[k] for k in ("avg_rmse", "final_rmse", "cd")},
        "speed": _speed(report_rows, best),
    }


def _report_rows(sims: list[tuple[str, float]], models: list[tuple[str, Any, Path]], runtimes: list[str],
                 variants: dict[tuple[str, str], Any], scores: dict[Any, _Scores],
                 batch_times: dict[tuple[str, str], tuple[float, float]],
                 config: SpeedErrorConfig) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """(rows of the report, the full-budget full-domain simulator first; fastest runtime keeping the error
    per model)."""
    nb = config.throughput_batch
    report_rows: list[dict[str, Any]] = []
    for domain, b in sims:
        s = scores[("sim", domain, b)].summary()
        floor = domain == "full" and b == 1.0
        report_rows.append({
            "label": sim_label(domain, b), "kind": "simulator", "model": "simulator", "domain": domain,
            "budget": b, "runtime": None, "backend": None, "precision": None, "params": None,
            "noise_floor": floor, "note": NOISE_FLOOR_NOTE if floor else "", **s,
            "batch_wall_s": s["wall_s"] if nb else None, "batch_cpu_s": s["cpu_s"] if nb else None,
        })  # fmt: skip
    fastest: dict[str, str] = {}
    for label, loaded, path in models:
        group = []
        for rt in runtimes:
            pred = variants[(label, rt)]
            s = scores[(label, rt)].summary()
            backend, precision = parse_runtime(rt)
            note = f"ran on torch: {pred.fallback_reason}" if pred.backend != backend else ""
            bw, bc = batch_times.get((label, rt), (None, None))
            group.append({"label": f"{label} {rt}", "kind": "model", "model": label, "checkpoint": str(path),
                          "domain": None, "budget": None, "runtime": rt, "backend": pred.backend,
                          "precision": precision, "threads": config.threads,
                          "params": int(count_params(loaded.model)), "noise_floor": False, "note": note, **s,
                          "batch_wall_s": bw, "batch_cpu_s": bc})  # fmt: skip
        ref_err = group[0]["avg_rmse"]
        for r in group:
            r["keeps_error"] = bool(r["avg_rmse"] <= ref_err * (1.0 + config.keep_error_rel))
        best = min((r for r in group if r["keeps_error"]), key=lambda r: r["wall_s"])
        best["fastest"] = True
        fastest[label] = best["runtime"]
        report_rows.extend(group)
    for r in report_rows:
        r.setdefault("keeps_error", None)
        r.setdefault("fastest", False)
    add_speedups(report_rows)
    return report_rows, fastest


def _equal_accuracy(curve: list[dict[str, Any]], r: dict[str, Any]) -> dict[str, Any]:
    """``equal_accuracy`` of row ``r`` against the simulator rows ``curve`` (one domain, its budgets)."""
    eq: dict[str, Any] = {}
    for clock in ("wall", "cpu"):
        t, bound = equal_accuracy_time([(s["avg_rmse"], s[f"{clock}_s"]) for s in curve], r["avg_rmse"])
        eq[f"simulator_{clock}_s"] = t
        eq[f"speedup_{clock}"] = t / max(r[f"{clock}_s"], 1e-12) if t is not None else None
        eq["bound"] = bound
    return eq


def add_speedups(rows: list[dict[str, Any]]) -> None:
    """Fill in every row's speed-ups against each simulator domain (module docstring), in place.

    Per domain (key suffix ``_DOMAIN_SUFFIX``: "" for the full domain, "_quarter"), from the simulator rows
    of that ``domain`` (a row without one is the full domain's): ``speedup`` / ``speedup_cpu`` (its budget-1
    row's wall / CPU seconds over the row's), ``batch_speedup`` (over the row's ``batch_wall_s``) and
    ``equal_accuracy`` {simulator_wall_s, speedup_wall, simulator_cpu_s, speedup_cpu, bound} against its
    budgets' (Avg RMSE, seconds) curve; None throughout for a domain without rows.
    """
    for domain, suffix in _DOMAIN_SUFFIX.items():
        curve = [r for r in rows if r["kind"] == "simulator" and (r.get("domain") or "full") == domain]
        base = next((r for r in curve if r["budget"] == 1.0), None)
        for r in rows:
            if base is None:
                r.update({f"speedup{suffix}": None, f"speedup_cpu{suffix}": None,
                          f"batch_speedup{suffix}": None, f"equal_accuracy{suffix}": None})  # fmt: skip
                continue
            r[f"speedup{suffix}"] = base["wall_s"] / max(r["wall_s"], 1e-12)
            r[f"speedup_cpu{suffix}"] = base["cpu_s"] / max(r["cpu_s"], 1e-12)
            bw = r.get("batch_wall_s")
            r[f"batch_speedup{suffix}"] = base["wall_s"] / bw if bw else None
            r[f"equal_accuracy{suffix}"] = _equal_accuracy(curve, r)


def _speed(rows: list[dict[str, Any]], best: dict[str, Any] | None) -> dict[str, Any]:
    """The report's ``speed`` block: the simulators (full domain; quarter, None if not measured) against the
    fastest NEMSim runtime keeping the error."""
    sim_full = rows[0]
    sim_q = next((r for r in rows if r.get("domain") == "quarter" and r["budget"] == 1.0), None)

    def eq(key: str) -> dict[str, Any] | None:
        e = best.get(key) if best else None
        if not e:
            return None
        return {"simulator_s": e["simulator_wall_s"], "speedup": e["speedup_wall"], "bound": e["bound"]}

    return {
        "simulator_s": sim_full["wall_s"],
        "simulator_cpu_s": sim_full["cpu_s"],
        "nemsim_s": best["wall_s"] if best else None,
        "nemsim_cpu_s": best["cpu_s"] if best else None,
        "nemsim_checkpoint": best["checkpoint"] if best else None,
        "nemsim_runtime": best["runtime"] if best else None,
        "nemsim_precision": best["precision"] if best else None,
        "nemsim_avg_rmse": best["avg_rmse"] if best else None,
        "speedup": best["speedup"] if best else None,
        "nemsim_batch_s": best["batch_wall_s"] if best else None,
        "batch_speedup": best["batch_speedup"] if best else None,
        "equal_accuracy": eq("equal_accuracy"),
        "simulator_quarter_s": sim_q["wall_s"] if sim_q else None,
        "simulator_quarter_cpu_s": sim_q["cpu_s"] if sim_q else None,
        "speedup_quarter": best["speedup_quarter"] if best else None,
        "batch_speedup_quarter": best["batch_speedup_quarter"] if best else None,
        "equal_accuracy_quarter": eq("equal_accuracy_quarter"),
    }


def _fmt(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


_BOUND_MARK = {"interpolated": "", "lower": ">=", "upper": "<=", "none": ""}


def _eq_cell(r: dict[str, Any], clock: str, key: str = "equal_accuracy") -> str:
    eq = r.get(key) or {}
    v = eq.get(f"speedup_{clock}")
    if v is None:
        return "-"
    return f"{_BOUND_MARK.get(str(eq.get('bound')), '')}{v:.3g}x"


def format_markdown(report: dict[str, Any]) -> str:
    """The report as a Markdown table (one row per method; the noise floor and fastest variants marked),
    then, with the quarter domain measured, the surrogates' speed-ups against both simulators side by side."""
    nb = report.get("throughput_batch") or 0
    lines = [
        f"## Speed against error: {report['scene']}, {report['setting']}, {len(report['case_ids'])} test "
        f"cases, {report['steps']} steps",
        "",
        "Errors are against an independent full-budget simulator run of each case (not the data file). "
        f"Times: median over cases, one trajectory, batch 1, {report.get('threads', 1)} thread(s), the "
        f"surrogates' the median of {SURROGATE_REPEATS} rollouts per case, each into a trajectory buffer "
        "reused from case to case (as the service does; a fresh trajectory per rollout: below the tables); "
        "speed-ups against the full-budget, full-domain simulator (the one that made the data; wall, CPU in "
        "brackets), and at equal accuracy: its time interpolated log-log at the method's Avg RMSE between "
        "its budgets (>= / <=: the error lies outside the simulator's measured range, the figure is a bound)."
        + (f" Batch {nb}: wall seconds per trajectory of one batch-{nb} rollout (the simulator does not "
           "batch: its batch-1 time)." if nb else "")
        + (" \"simulator quarter\": the quarter-domain simulator (the lower quadrant between mirror walls, "
           "states mirrored to full size), scored against the same reference."
           if _has_quarter(report) else ""),  # fmt: skip
        "",
        "| method | s / traj | CPU s | speed-up | speed-up at equal accuracy | "
        + (f"s / traj at batch {nb} | speed-up at batch {nb} | " if nb else "")
        + "Avg RMSE | Final RMSE | CD (vox) | Avg RMSE vs data | note |",
        "|---|---:|---:|---:|---:|" + ("---:|---:|" if nb else "") + "---:|---:|---:|---:|---|",
    ]
    for r in report["rows"]:
        note = r["note"]
        if r.get("fastest"):
            note = "; ".join(x for x in ("fastest variant keeping the error", note) if x)
        elif r.get("keeps_error") is False:
            note = "; ".join(x for x in ("loses accuracy vs torch-f32", note) if x)
        label = f"**{r['label']}**" if r["noise_floor"] else r["label"]
        batch = (f"{_fmt(r.get('batch_wall_s'), '.3g')} | "
                 f"{_fmt(r.get('batch_speedup'), '.3g')}x | ") if nb else ""  # fmt: skip
        lines.append(
            f"| {label} | {_fmt(r['wall_s'], '.3g')} | {_fmt(r['cpu_s'], '.3g')} | "
            f"{_fmt(r['speedup'], '.3g')}x ({_fmt(r.get('speedup_cpu'), '.3g')}x) | "
            f"{_eq_cell(r, 'wall')} ({_eq_cell(r, 'cpu')}) | {batch}"
            f"{_fmt(r['avg_rmse'], '.4f')} | {_fmt(r['final_rmse'], '.4f')} | {_fmt(r['cd'], '.3f')} | "
            f"{_fmt(r['avg_rmse_vs_data'], '.4f')} | {note} |"
        )
    lines += _side_by_side(report)
    sim_wall = report["rows"][0]["wall_s"]
    fresh = [(r["label"], r["wall_s_fresh_output"]) for r in report["rows"]
             if r["kind"] == "model" and r.get("wall_s_fresh_output")]
    if fresh:
        lines += ["", "Each surrogate rollout into a freshly allocated trajectory instead (its pages mapped "
                  "on first write; the same states), s / traj and speed-up against the full-domain "
                  "simulator: " + "; ".join(f"{label} {_fmt(w, '.3g')} s ({_fmt(sim_wall / w, '.3g')}x)"
                                            for label, w in fresh) + "."]  # fmt: skip
    if report.get("skipped_case_ids"):
        lines += ["", f"Test cases {report['skipped_case_ids']} are not complete in the data file and were "
                  "passed over."]  # fmt: skip
    for domain, why in (report.get("sim_domains_skipped") or {}).items():
        lines += ["", f"The {domain}-domain simulator was not measured (skipped): {why}"]
    nf = report["noise_floor"]
    lines += ["", f"Noise floor (simulator vs itself, two seeds): Avg RMSE {nf['avg_rmse']:.4f}, "
              f"CD {nf['cd']:.3f} vox."]  # fmt: skip
    q = _quarter_full_budget(report)
    if q is not None:
        lines[-1] += (f" Quarter-domain simulator at budget 1 against the same reference: Avg RMSE "
                      f"{q['avg_rmse']:.4f}, CD {q['cd']:.3f} vox, {_fmt(q['speedup'], '.3g')}x the full "
                      f"domain's speed ({_fmt(q.get('speedup_cpu'), '.3g')}x CPU).")  # fmt: skip
    return "\n".join(lines) + "\n"


def _has_quarter(report: dict[str, Any]) -> bool:
    return any(r.get("domain") == "quarter" for r in report["rows"])


def _quarter_full_budget(report: dict[str, Any]) -> dict[str, Any] | None:
    return next((r for r in report["rows"] if r.get("domain") == "quarter" and r["budget"] == 1.0), None)


def _side_by_side(report: dict[str, Any]) -> list[str]:
    """Table lines: each surrogate variant's speed-ups against the full- and the quarter-domain simulator
    (budget 1; at equal accuracy: along each one's budgets), side by side; none without quarter rows."""
    models = [r for r in report["rows"] if r["kind"] == "model"]
    if not models or _quarter_full_budget(report) is None:
        return []
    nb = report.get("throughput_batch") or 0
    eq_q = "equal_accuracy_quarter"
    lines = [
        "",
        "### Speed-ups against the full-domain and the quarter-domain simulator",
        "",
        "Against each simulator at budget 1 (wall; CPU in brackets), at equal accuracy along each one's "
        "budgets" + (f", and per trajectory at batch {nb}" if nb else "") + ".",
        "",
        "| method | Avg RMSE | speed-up vs full | vs quarter | at equal accuracy vs full | vs quarter | "
        + (f"at batch {nb} vs full | vs quarter |" if nb else ""),
        "|---|---:|---:|---:|---:|---:|" + ("---:|---:|" if nb else ""),
    ]
    for r in models:
        batch = (f" {_fmt(r.get('batch_speedup'), '.3g')}x | {_fmt(r.get('batch_speedup_quarter'), '.3g')}x |"
                 if nb else "")  # fmt: skip
        lines.append(
            f"| {r['label']} | {_fmt(r['avg_rmse'], '.4f')} | "
            f"{_fmt(r['speedup'], '.3g')}x ({_fmt(r.get('speedup_cpu'), '.3g')}x) | "
            f"{_fmt(r.get('speedup_quarter'), '.3g')}x ({_fmt(r.get('speedup_cpu_quarter'), '.3g')}x) | "
            f"{_eq_cell(r, 'wall')} ({_eq_cell(r, 'cpu')}) | "
            f"{_eq_cell(r, 'wall', eq_q)} ({_eq_cell(r, 'cpu', eq_q)}) |" + batch
        )
    return lines


def plot_speed_error(report: dict[str, Any], path: str | Path) -> Path:
    """Log-log PNG: wall seconds per trajectory (x) against Avg RMSE (y), one line per simulator domain
    along its budgets; the noise floor marked; hollow markers: the same variant's per-trajectory time at the
    throughput batch."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    tiny = 1e-12
    sim = [r for r in report["rows"] if r["kind"] == "simulator"]
    for domain, style, color in (("full", "o-", "k"), ("quarter", "s--", "tab:gray")):
        curve = [r for r in sim if (r.get("domain") or "full") == domain]
        if not curve:
            continue
        ax.plot([max(r["wall_s"], tiny) for r in curve], [max(r["avg_rmse"], tiny) for r in curve], style,
                color=color, label=f"simulator, {domain} domain (particle budget)")  # fmt: skip
        for r in curve:
            ax.annotate(f"{'budget' if domain == 'full' else domain} {budget_label(r['budget'])}",
                        (max(r["wall_s"], tiny), max(r["avg_rmse"], tiny)), textcoords="offset points",
                        xytext=(6, 4) if domain == "full" else (6, -10), fontsize=8, color=color)  # fmt: skip
    markers = {"torch-f32": "s", "torch-bf16": "D", "openvino-f32": "^", "openvino-bf16": "v"}
    models = sorted({r["model"] for r in report["rows"] if r["kind"] == "model"})
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    nb = report.get("throughput_batch") or 0
    for i, m in enumerate(models):
        for r in (r for r in report["rows"] if r["model"] == m):
            mk, color = markers.get(r.get("runtime"), "o"), colors[i % len(colors)]
            y = max(r["avg_rmse"], tiny)
            ax.plot(max(r["wall_s"], tiny), y, mk, color=color, label=r["label"], ms=8)
            if r.get("batch_wall_s"):
                ax.plot(max(r["batch_wall_s"], tiny), y, mk, color=color, mfc="none", ms=8)
    nf = report["noise_floor"]["avg_rmse"]
    ax.axhline(max(nf, tiny), color="tab:red", ls="--", lw=1.2, label=f"noise floor (Avg RMSE {nf:.4f})")
    floor = next(r for r in sim if r["noise_floor"])
    ax.plot(max(floor["wall_s"], tiny), max(nf, tiny), "*", color="tab:red", ms=16, zorder=5)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per trajectory (s, median; hollow: per trajectory at batch "
                  f"{nb})" if nb else "wall time per trajectory (s, median)")  # fmt: skip
    ax.set_ylabel("Avg RMSE vs independent full-budget run")
    ax.set_title(f"speed vs error: {report['scene']} {report['setting']}, {len(report['case_ids'])} cases")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return save_figure(fig, path, dpi=120)


def write_speed_error(report: dict[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """speed_error.json, speed_error.md and speed_error.png in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "speed_error.json", "md": out / "speed_error.md", "png": out / "speed_error.png"}
    paths["json"].write_text(json.dumps(report, indent=2))
    paths["md"].write_text(format_markdown(report))
    plot_speed_error(report, paths["png"])
    return paths
