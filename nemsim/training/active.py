"""Active learning: simulate next where the current model is most likely wrong, fine-tune, repeat.

One round (``run_learning`` runs R of them): propose candidate recipes over the admissible region, score
each by an acquisition computed from the current model, choose a diverse batch among the best, simulate
it (``generate_dataset``: resumable, process pool or Ray), fine-tune the model on every case so far (its
training data plus all rounds' cases) from its current weights, and start the next round from the result.

Region (unit coordinates xi, eq:supp_ood_unit_coordinate: 0..1 across the design box of each control,
xi = (u + 1) / 2 of the normalized control u), ``propose``:
  interior  a Latin hypercube (``lhs_unit``);
  face      a Latin-hypercube point with one control (in turn) on a face of the box, xi_j in {0, 1};
  corner    distinct random corners (``corner_design``), never the physics benchmark's held-out ones;
  band      a Latin-hypercube point with 1..``band_controls`` controls past an edge by up to ``band_width``
            (0.25: the explorer's sliders reach a quarter of each range beyond either edge, normalized
            |u| <= 1.5, the extrapolation benchmark's first distance; the service answers there with a
            warning). Only directions that stay admissible are drawn (no neutral exponent below 0; an ion
            exponent at most down to 0), and exponents are rounded away from the box so they stay outside.
Inside the box unit coordinates map to physical units exactly as ``nemsim design`` maps them (``from_unit``).

Acquisitions (``ACQUISITIONS``), one number per recipe, larger = simulate sooner:
  distance    unit-space distance to the nearest recipe the model was trained on (no model call);
  ensemble    RMS spread between the model's trajectory and those of ``members`` copies with every weight
              tensor perturbed by Gaussian noise of ``weight_noise`` times its RMS (a cheap stand-in for a
              deep ensemble: NEMSim has no dropout, and training M models costs M times a training run);
  jitter      RMS spread of the trajectories under ``members`` control perturbations of ``control_noise``
              (normalized units, the box half-width is 1): the local steepness of the learned response;
  checkpoint  RMS difference from the trajectory of the model this one was trained from (its predecessor:
              a two-member committee that costs no training; in the loop, round 1 compares with the
              predecessor the caller names and round r > 1 with round r - 1's starting model);
  change      the RMS change the model predicts (x̂_t - x_0): errors grow with how much is etched.
Spreads compare states every ``every`` steps (normalized SDF units, like the Avg RMSE). A calibrated
interval (``nemsim.analysis.intervals``) is no acquisition: its split-conformal offsets depend on the step
only, so every recipe gets the same width.

Which one: ``measure_acquisitions`` computes each on held-out simulated cases and its Spearman rank
correlation with the model's actual rollout error there (Avg RMSE against the simulator, and the final
depth error); `nemsim learn measure` prints the table. ``DEFAULT_ACQUISITION`` is the one with the highest
correlation over the whole region (interior test cases, held-out corners, points past the box) for the
served model, compared with the full-domain model it was retrained from. The others measure mostly how
much happens (the perturbed-weight spread follows the predicted change), which ranks the interior well
but keeps no memory of where the model has been taught.

Batch (``select_batch``): among the ``pool_factor`` x batch best candidates, start from the best and add,
one at a time, the candidate with the largest score x unit-space distance to those chosen (scores rescaled to
(0, 1]): a k-center weighted by the acquisition, so a batch is not eight copies of one corner, yet it keeps
to high scores. Plain k-center (equal weights) would pick only the pool's corners: corners lie farthest
apart. Recipes past the box compete like the others: a trajectory file holds any admissible controls.

Baseline: acquisition "lhs" replaces a round's candidates and scores by a fresh Latin hypercube of the batch
size (``nemsim design --n B --seed S``) and keeps everything else (simulation, fine-tuning, files): the
control arm of a learning curve, active against Latin hypercube at the same budget.

Files (``out``): ``learn.json`` (the options; a rerun with other options is refused) and per round
``round-NN/``: ``candidates.csv`` (every candidate, its kind and scores), ``batch.csv`` (the chosen
recipes in `nemsim design`'s format: ``nemsim generate --controls batch.csv --seed S`` rebuilds
``data.h5``), ``data.h5``, ``train/`` (a `nemsim train` run directory) and ``round.json``, the round's
state (selected, simulated, trained). A stopped run resumes where it stopped: rerun the same command.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nemsim.controls import (
    CONTROL_NAMES,
    HIGH,
    INT_INDICES,
    IS_LOG,
    LOW,
    N_CONTROLS,
    PHYS_MAX,
    PHYS_MIN,
    corner_design,
    from_normalized,
    from_unit,
    heldout_corners,
    lhs_design,
    lhs_unit,
    to_normalized,
    write_controls_csv,
)
from nemsim.training.config import TrainConfig

log = logging.getLogger(__name__)

KINDS = ("interior", "face", "corner", "band")
BAND_WIDTH = 0.25  # unit coordinates past an edge: the explorer's sliders (module docstring)
ACQUISITIONS = ("distance", "ensemble", "jitter", "checkpoint", "change")
MODEL_ACQUISITIONS = ("ensemble", "jitter", "checkpoint", "change")  # those that roll the model out
Acquisition = Literal["distance", "ensemble", "jitter", "checkpoint", "change", "lhs"]
BASELINES = (
    "lhs",
)  # no acquisition: each round's batch is a fresh Latin hypercube (a learning curve's control)
DEFAULT_ACQUISITION: Acquisition = "checkpoint"  # the best measured (module docstring, "Which one")
STATUSES = ("selected", "simulated", "trained")  # a round's phases, in order


# --- the region ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ProposalConfig:
    """How many candidates of each kind (module docstring) and their seed."""

    interior: int = 256  # Latin-hypercube points inside the box
    faces: int = 128  # points with one control on a face of the box
    corners: int = 64  # distinct corners of the box
    band: int = 128  # points with some controls past the box
    band_width: float = BAND_WIDTH  # how far past an edge, unit coordinates (fraction of the range)
    band_controls: int = 3  # at most this many controls past the box per band point
    seed: int = 0

    def __post_init__(self) -> None:
        counts = (self.interior, self.faces, self.corners, self.band)
        if min(counts) < 0 or sum(counts) < 1:
            raise ValueError(f"candidate counts must be >= 0 with at least one candidate, got {counts}")
        if not 0.0 < self.band_width <= 1.0:
            raise ValueError(f"band_width must be in (0, 1] (unit coordinates), got {self.band_width}")
        if not 1 <= self.band_controls <= N_CONTROLS:
            raise ValueError(f"band_controls must be in 1..{N_CONTROLS}, got {self.band_controls}")


@dataclass(frozen=True)
class Candidates:
    """Candidate recipes: raw (N, 14) admissible physical controls, whole exponents; kind (N,) of KINDS."""

    raw: np.ndarray
    kind: np.ndarray

    def __len__(self) -> int:
        return len(self.raw)

    @property
    def unit(self) -> np.ndarray:
        """(N, 14) unit coordinates of the recipes (outside [0, 1] past the box)."""
        return to_unit(self.raw)

    def counts(self) -> dict[str, int]:
        return {k: int(np.count_nonzero(self.kind == k)) for k in KINDS}


def to_unit(raw: np.ndarray) -> np.ndarray:
    """Raw controls (..., 14) -> unit coordinates xi = (u + 1) / 2 (eq:supp_ood_unit_coordinate)."""
    return (np.asarray(to_normalized(np.asarray(raw, dtype=np.float64))) + 1.0) * 0.5


def from_unit_extended(xi: np.ndarray) -> np.ndarray:
    """Unit coordinates (N, 14), possibly past the box -> admissible raw controls (N, 14).

    Inside [0, 1]: ``from_unit`` (the design's mapping). Outside: the inverse normalization, exponents rounded
    away from the box (so a point past an edge stays past it), then clamped at the physical minimum.
    """
    xi = np.asarray(xi, dtype=np.float64)
    inside = from_unit(np.clip(xi, 0.0, 1.0))
    beyond = np.asarray(from_normalized(2.0 * xi - 1.0))
    ints = list(INT_INDICES)
    beyond[:, ints] = np.where(xi[:, ints] > 1.0, np.ceil(beyond[:, ints]), np.floor(beyond[:, ints]))
    raw = np.where((xi < 0.0) | (xi > 1.0), beyond, inside)
    return np.clip(raw, PHYS_MIN, PHYS_MAX)


def band_room() -> np.ndarray:
    """(14, 2) how far each control may go past its (low, high) edge, unit coordinates, and stay admissible
    (inf for the log-scaled fluxes, which never reach zero)."""
    span = HIGH - LOW
    low = np.where(IS_LOG, np.inf, (LOW - PHYS_MIN) / span)
    high = np.where(IS_LOG | np.isinf(PHYS_MAX), np.inf, (PHYS_MAX - HIGH) / span)
    return np.stack([low, high], axis=1)


def _seed(seed: int, part: int) -> int:
    return int(np.random.SeedSequence([int(seed), part]).generate_state(1, np.uint32)[0])


def _band_points(n: int, cfg: ProposalConfig) -> np.ndarray:
    """(n, 14) unit coordinates: Latin-hypercube points with 1..band_controls admissible controls past an
    edge by a uniform fraction (0, 1] of the band (or of the admissible room, if smaller)."""
    xi = lhs_unit(n, _seed(cfg.seed, 4))
    rng = np.random.default_rng(_seed(cfg.seed, 5))
    room = np.minimum(band_room(), cfg.band_width)  # (14, 2)
    movable = np.flatnonzero(room.max(axis=1) > 0)
    for i in range(n):
        k = int(rng.integers(1, min(cfg.band_controls, len(movable)) + 1))
        for j in rng.choice(movable, size=k, replace=False):
            sides = np.flatnonzero(room[j] > 0)
            side = int(rng.choice(sides))
            d = (1.0 - rng.random()) * room[j, side]  # in (0, room]
            xi[i, j] = 1.0 + d if side else -d
    return xi


def propose(cfg: ProposalConfig) -> Candidates:
    """Candidates over the whole admissible region (module docstring), in the order interior, faces,
    corners, band; the same ``cfg`` gives the same candidates."""
    parts: list[np.ndarray] = []
    kinds: list[str] = []
    if cfg.interior:
        parts.append(from_unit(lhs_unit(cfg.interior, _seed(cfg.seed, 1))))
        kinds += ["interior"] * cfg.interior
    if cfg.faces:
        xi = lhs_unit(cfg.faces, _seed(cfg.seed, 2))
        side = np.random.default_rng(_seed(cfg.seed, 3)).integers(0, 2, cfg.faces)
        xi[np.arange(cfg.faces), np.arange(cfg.faces) % N_CONTROLS] = side  # every control in turn
        parts.append(from_unit(xi))
        kinds += ["face"] * cfg.faces
    if cfg.corners:
        parts.append(corner_design(cfg.corners, _seed(cfg.seed, 6), exclude=heldout_corners()))
        kinds += ["corner"] * cfg.corners
    if cfg.band:
        parts.append(from_unit_extended(_band_points(cfg.band, cfg)))
        kinds += ["band"] * cfg.band
    return Candidates(raw=np.concatenate(parts), kind=np.array(kinds))


# --- acquisitions ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScoreConfig:
    """How the model-based acquisitions are computed (module docstring)."""

    members: int = 4  # perturbed models (ensemble) or control perturbations (jitter)
    weight_noise: float = 0.05  # ensemble: std of each weight's perturbation / the RMS of its tensor
    control_noise: float = 0.1  # jitter: std of the control perturbation, normalized units
    every: int = 10  # compare trajectories every this many steps (and at the last)
    steps: int | None = None  # rollout length (None: the scene's horizon)
    batch_size: int = 8  # recipes rolled out together
    seed: int = 0

    def __post_init__(self) -> None:
        if self.members < 1 or self.every < 1 or self.batch_size < 1:
            raise ValueError(
                f"members, every and batch_size must be >= 1, got {self.members}, "
                f"{self.every}, {self.batch_size}"
            )
        if not (self.weight_noise > 0 and self.control_noise > 0):
            raise ValueError("weight_noise and control_noise must be > 0")


def check_acquisitions(names: Sequence[str]) -> list[str]:
    """``names`` without repeats; ValueError naming an unknown one and the choices."""
    bad = [n for n in names if n not in ACQUISITIONS]
    if bad or not names:
        got = f"unknown acquisition {bad[0]!r}" if bad else "no acquisition given"
        raise ValueError(f"{got}; expected some of {list(ACQUISITIONS)}")
    return list(dict.fromkeys(names))


def nearest_distance(unit: np.ndarray, reference: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(N,) Euclidean distance of each point of ``unit`` (N, 14) to its nearest point of ``reference``."""
    ref = np.asarray(reference, dtype=np.float64)
    if len(ref) == 0:
        raise ValueError("no reference points: the model's training recipes are needed for 'distance'")
    out = np.empty(len(unit))
    for s in range(0, len(unit), chunk):
        d = np.linalg.norm(unit[s : s + chunk, None, :] - ref[None], axis=-1)  # (chunk, M)
        out[s : s + chunk] = d.min(axis=1)
    return out


def perturbed_models(model: Any, n: int, rel: float, seed: int) -> list[Any]:
    """``n`` copies of ``model`` with every parameter tensor p moved by rel * RMS(p) * N(0, 1)."""
    import copy

    import torch

    gen = torch.Generator().manual_seed(int(seed))
    out = []
    for _ in range(n):
        twin = copy.deepcopy(model).eval()
        with torch.no_grad():
            for p in twin.parameters():
                noise = torch.randn(p.shape, generator=gen, dtype=p.dtype).to(p.device)
                p.add_(rel * p.detach().pow(2).mean().sqrt() * noise)
        out.append(twin)
    return out


def _signature(model: Any, x0: Any, u: Any, steps: int, every: int) -> Any:
    """(B, S, 2, D, H, W): the states of a rollout at steps every, 2 every, ... and the last."""
    import torch

    from nemsim.evaluation.rollout import rollout

    picks: list[torch.Tensor] = []

    def grab(t: int, x: torch.Tensor) -> None:
        if t % every == 0 or t == steps:
            picks.append(x.detach().clone())

    rollout(model, x0, u, steps, keep=False, on_step=grab)
    return torch.stack(picks, dim=1)


def _rms(a: Any, b: Any) -> Any:
    return (a - b).pow(2).flatten(1).mean(dim=1).sqrt()  # (B,)


def score_candidates(
    model: Any,
    x0: np.ndarray,
    raw: np.ndarray,
    names: Sequence[str],
    cfg: ScoreConfig,
    steps: int,
    *,
    train_unit: np.ndarray | None = None,
    second: Any = None,
    progress: bool = False,
) -> dict[str, np.ndarray]:
    """Acquisitions (module docstring) of the recipes ``raw`` (N, 14), {name: (N,)}, larger = sooner.

    Args:
        model: the current surrogate (anything ``rollout`` accepts). x0: (2, D, H, W) initial state.
        steps: rollout length (``cfg.steps`` overrides it).
        train_unit: (M, 14) unit coordinates of the training recipes (for "distance").
        second: a second model (for "checkpoint").
    """
    import torch

    from nemsim.evaluation.truth import model_device

    names = check_acquisitions(names)
    raw = np.atleast_2d(np.asarray(raw, dtype=np.float64))
    out: dict[str, np.ndarray] = {}
    if "distance" in names:
        out["distance"] = nearest_distance(
            to_unit(raw), np.asarray(train_unit if train_unit is not None else np.zeros((0, N_CONTROLS)))
        )
    rolled = [n for n in names if n in MODEL_ACQUISITIONS]
    if not rolled:
        return out
    if "checkpoint" in rolled and second is None:
        raise ValueError("acquisition 'checkpoint' needs a second checkpoint")
    device = model_device(model)
    n = len(raw)
    steps = cfg.steps or steps
    u_all = torch.as_tensor(np.asarray(to_normalized(raw)), dtype=torch.float32)  # (N, 14)
    jitter = torch.as_tensor(
        np.random.default_rng(cfg.seed).standard_normal((cfg.members, n, N_CONTROLS)) * cfg.control_noise,
        dtype=torch.float32,
    )  # (M, N, 14)
    twins = perturbed_models(model, cfg.members, cfg.weight_noise, cfg.seed) if "ensemble" in rolled else []
    base_x = torch.as_tensor(np.asarray(x0), dtype=torch.float32, device=device)
    acc = {k: np.zeros(n) for k in rolled}
    bar = _bar(n, "acquisition", progress)
    for s in range(0, n, cfg.batch_size):
        u = u_all[s : s + cfg.batch_size].to(device)  # (B, 14)
        x = base_x[None].expand(len(u), *base_x.shape).contiguous()  # (B, 2, D, H, W)
        base = _signature(model, x, u, steps, cfg.every)  # (B, S, 2, D, H, W)
        if "change" in acc:
            acc["change"][s : s + len(u)] = _rms(base, x[:, None]).cpu().numpy()
        spreads: dict[str, list[Any]] = {"ensemble": [], "jitter": [], "checkpoint": []}
        for twin in twins:
            spreads["ensemble"].append(_rms(_signature(twin, x, u, steps, cfg.every), base) ** 2)
        if "jitter" in acc:
            for m in range(cfg.members):
                ju = u + jitter[m, s : s + len(u)].to(device)
                spreads["jitter"].append(_rms(_signature(model, x, ju, steps, cfg.every), base) ** 2)
        if "checkpoint" in acc:
            spreads["checkpoint"].append(_rms(_signature(second, x, u, steps, cfg.every), base) ** 2)
        for k, v in spreads.items():
            if v:
                acc[k][s : s + len(u)] = torch.stack(v).mean(dim=0).sqrt().cpu().numpy()
        if bar is not None:
            bar.update(len(u))
    if bar is not None:
        bar.close()
    out.update(acc)
    return {k: out[k] for k in names}


def _bar(total: int, desc: str, on: bool) -> Any:
    if not on:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="recipe", desc=desc, dynamic_ncols=True)


def select_batch(unit: np.ndarray, scores: np.ndarray, batch: int, pool_factor: int = 4) -> np.ndarray:
    """Indices of ``batch`` candidates: a score-weighted greedy k-center in unit space among the
    ``pool_factor`` x batch best by ``scores`` (module docstring); fewer if the pool holds fewer distinct
    points."""
    if batch < 1 or pool_factor < 1:
        raise ValueError(f"batch and pool_factor must be >= 1, got {batch}, {pool_factor}")
    scores = np.asarray(scores, dtype=np.float64)
    order = np.argsort(-scores, kind="stable")
    pool = order[: max(batch, pool_factor * batch)]
    pts = np.asarray(unit, dtype=np.float64)[pool]  # (P, 14)
    w = scores[pool] - scores[pool].min()  # (P,) weights in (0, 1]; equal scores: plain k-center
    w = (w / w.max() if w.max() > 0 else np.zeros_like(w)) + 1e-3
    chosen = [0]
    gap = np.linalg.norm(pts - pts[0], axis=1)  # (P,) distance to the nearest chosen point
    while len(chosen) < min(batch, len(pool)):
        k = int(np.argmax(w * gap))  # first of equals: the better-scored
        if gap[k] <= 0:
            break
        chosen.append(k)
        gap = np.minimum(gap, np.linalg.norm(pts - pts[k], axis=1))
    return pool[chosen]


# --- measuring the acquisitions --------------------------------------------------------------------


@dataclass(frozen=True)
class Probe:
    """Held-out simulated cases: raw controls (N, 14) and, per case, its simulated trajectories."""

    name: str
    raw: np.ndarray
    load: Callable[[int], list[np.ndarray]]  # case index -> [(T + 1, 2, D, H, W) float32, ...]


def file_probe(tf: Any, case_ids: Sequence[int], name: str) -> Probe:
    """The cases ``case_ids`` of an open trajectory file (one simulated run each)."""
    rows = [tf.row_of(int(c)) for c in case_ids]
    return Probe(
        name, np.asarray(tf.controls_raw)[rows], lambda i: [np.asarray(tf.states[rows[i]], dtype=np.float32)]
    )


def truth_probe(truth: Any, raw: np.ndarray, seeds: Sequence[int], name: str) -> tuple[Probe, int]:
    """(probe, skipped): the recipes of ``raw`` (N, 14) whose runs for every seed ``truth`` (a
    ``SimTruth``) holds already; the others are skipped, never simulated."""
    keep = [r for r in np.atleast_2d(raw) if all(truth.has(r, s) for s in seeds)]
    kept = np.array(keep).reshape(-1, N_CONTROLS)
    return (
        Probe(name, kept, lambda i: [truth.states(kept[i], s) for s in seeds]),
        len(np.atleast_2d(raw)) - len(kept),
    )


def report_recipes(report: dict[str, Any]) -> np.ndarray:
    """(N, 14) raw controls of a benchmark report's cases (`nemsim bench physics`, `nemsim bench
    extrapolation`): every entry of its ``heldout`` or ``cases`` list with 14 ``controls``."""
    rows = [c["controls"] for key in ("heldout", "cases") for c in report.get(key, [])
            if isinstance(c, dict) and len(c.get("controls") or []) == N_CONTROLS]  # fmt: skip
    if not rows:
        raise ValueError(f"no case with {N_CONTROLS} `controls` under `heldout` or `cases`")
    return np.asarray(rows, dtype=np.float64)


def rollout_errors(model: Any, probe: Probe, scene: Any, progress: bool = False) -> dict[str, np.ndarray]:
    """The model's actual errors on the probe's cases: {"avg_rmse": (N,) Avg RMSE over t = 1..T against
    each simulated run, averaged over runs; "depth_nm": (N,) |final etch depth error| in nm}."""
    from nemsim.evaluation.truth import avg_rmse, predict
    from nemsim.geometry.profile import profile_metrics_batch

    n = len(probe.raw)
    rmse, depth = np.empty(n), np.empty(n)
    bar = _bar(n, f"errors {probe.name}", progress)
    for i in range(n):
        sims = probe.load(i)
        _, pred = next(predict(model, sims[0][0], probe.raw[i : i + 1], len(sims[0]) - 1, batch_size=1))
        rmse[i] = np.mean([avg_rmse(pred, sim) for sim in sims])
        final = profile_metrics_batch(pred[-1:], scene)["etch_depth"][0]
        depth[i] = np.mean(
            [abs(final - profile_metrics_batch(sim[-1:], scene)["etch_depth"][0]) for sim in sims]
        )
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return {"avg_rmse": rmse, "depth_nm": depth}


def spearman(a: np.ndarray, b: np.ndarray) -> float | None:
    """Spearman rank correlation of two (N,) arrays over their finite pairs; None if undefined."""
    from scipy.stats import spearmanr

    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:
        return None
    return round(float(spearmanr(a[ok], b[ok]).statistic), 4)


def measure_acquisitions(
    model: Any,
    scene: Any,
    x0: np.ndarray,
    probes: Sequence[Probe],
    names: Sequence[str],
    cfg: ScoreConfig,
    *,
    train_unit: np.ndarray | None = None,
    second: Any = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Spearman correlation of each acquisition with the model's actual error on held-out cases, per probe
    set and over all of them ("all"): the report `nemsim learn measure` prints (``format_measurement``)."""
    names = check_acquisitions(names)
    cases: list[dict[str, Any]] = []
    for probe in probes:
        t0 = time.perf_counter()
        err = rollout_errors(model, probe, scene, progress)
        t1 = time.perf_counter()
        sc = score_candidates(
            model,
            x0,
            probe.raw,
            names,
            cfg,
            scene.n_transitions,
            train_unit=train_unit,
            second=second,
            progress=progress,
        )
        log.info(
            "%s: %d cases, errors %.1f s, acquisitions %.1f s",
            probe.name,
            len(probe.raw),
            t1 - t0,
            time.perf_counter() - t1,
        )
        for i in range(len(probe.raw)):
            cases.append(
                {
                    "set": probe.name,
                    "unit": [round(float(v), 4) for v in to_unit(probe.raw[i])],
                    **{k: float(v[i]) for k, v in err.items()},
                    "scores": {k: float(v[i]) for k, v in sc.items()},
                }
            )
    sets = [p.name for p in probes] + (["all"] if len(probes) > 1 else [])
    table: dict[str, Any] = {}
    for s in sets:
        rows = [c for c in cases if s == "all" or c["set"] == s]
        table[s] = {
            "n": len(rows),
            "spearman": {
                k: {
                    e: spearman(np.array([c["scores"][k] for c in rows]), np.array([c[e] for c in rows]))
                    for e in ("avg_rmse", "depth_nm")
                }
                for k in names
            },
        }
    return {
        "acquisitions": names,
        "config": asdict(cfg),
        "table": table,
        "cases": cases,
        "best": best_acquisition(table[sets[-1]]["spearman"]),
    }


def best_acquisition(spearman_of: dict[str, dict[str, float | None]]) -> str | None:
    """The acquisition with the highest Spearman correlation with the Avg RMSE (None if none is defined)."""
    rated = {k: v["avg_rmse"] for k, v in spearman_of.items() if v["avg_rmse"] is not None}
    return max(rated, key=lambda k: rated[k]) if rated else None


def format_measurement(report: dict[str, Any]) -> str:
    """A markdown table of ``measure_acquisitions``'s report: Spearman rho per acquisition and probe set."""
    sets = list(report["table"])
    head = " | ".join(f"{s} (n={report['table'][s]['n']}) Avg RMSE | depth" for s in sets)
    lines = [f"| acquisition | {head} |", "|---|" + "---:|---:|" * len(sets)]
    fmt = lambda v: "n/a" if v is None else f"{v:+.3f}"  # noqa: E731
    for k in report["acquisitions"]:
        cells = " | ".join(
            f"{fmt(report['table'][s]['spearman'][k]['avg_rmse'])} | "
            f"{fmt(report['table'][s]['spearman'][k]['depth_nm'])}"
            for s in sets
        )
        lines.append(f"| {k} | {cells} |")
    lines.append(f"\nbest over {sets[-1]} (Spearman with the Avg RMSE): {report['best']}")
    return "\n".join(lines)


# --- the loop ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LearnConfig:
    """What a learning run does each round (module docstring)."""

    rounds: int = 4
    batch: int = 16  # recipes simulated per round
    acquisition: Acquisition = DEFAULT_ACQUISITION
    pool_factor: int = 4  # the batch is chosen among the pool_factor x batch best candidates
    proposals: ProposalConfig = field(default_factory=ProposalConfig)
    scoring: ScoreConfig = field(default_factory=ScoreConfig)
    sim_seed: int = 100  # round r simulates with base seed sim_seed + r - 1 (`nemsim generate --seed`)
    sim_domain: Literal["auto", "full", "quarter"] = "auto"  # auto: quarter where the grid allows it
    state_dtype: str = "float16"

    def __post_init__(self) -> None:
        if self.rounds < 1 or self.batch < 1 or self.pool_factor < 1:
            raise ValueError(
                f"rounds, batch and pool_factor must be >= 1, got {self.rounds}, {self.batch}, "
                f"{self.pool_factor}"
            )
        if self.acquisition not in BASELINES:
            check_acquisitions([self.acquisition])
        if self.sim_domain not in ("auto", "full", "quarter"):
            raise ValueError(f"sim_domain {self.sim_domain!r}; expected one of ['auto', 'full', 'quarter']")


@dataclass(frozen=True)
class LearnJob:
    """A learning run: the starting checkpoint, its training data, the fine-tuning config and the output."""

    checkpoint: Path
    data: Path  # the trajectory file whose split trains and validates (e.g. data/small.h5)
    out: Path
    train: TrainConfig = field(default_factory=TrainConfig)  # each round's fine-tuning
    config: LearnConfig = field(default_factory=LearnConfig)
    setting: str = "control-id"
    splits: Path | None = None
    extra_data: tuple[Path, ...] = ()  # further files the checkpoint trained on (e.g. data/small-quarter.h5)
    second_checkpoint: Path | None = None  # the checkpoint's predecessor (acquisition "checkpoint", round 1)
    workers: int = 1  # simulations in parallel
    executor: Literal["process", "ray"] = "process"
    progress: bool = True

    def identity(self) -> dict[str, Any]:
        """What decides the results (the state file keeps it; workers and progress do not count)."""
        keep = ("checkpoint", "data", "setting", "splits", "extra_data", "second_checkpoint")
        train = {k: v for k, v in asdict(self.train).items() if k != "progress"}
        return json.loads(
            json.dumps(
                {"config": asdict(self.config), "train": train, **{k: getattr(self, k) for k in keep}},
                default=str,
            )
        )


def round_dir(out: Path, r: int) -> Path:
    return Path(out) / f"round-{r:02d}"


def _read_state(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {}


def _write_state(path: Path, state: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(state, indent=1, default=str) + "\n")
    tmp.replace(path)  # a stop mid-write never leaves half a state


def _reached(state: dict[str, Any], status: str) -> bool:
    return state.get("status") in STATUSES and STATUSES.index(state["status"]) >= STATUSES.index(status)


def training_recipes(data: Path, setting: str, splits: Path | None, extra: Sequence[Path]) -> np.ndarray:
    """(M, 14) raw controls a model trained on: the ``setting`` split's training cases of ``data`` and every
    complete case of the ``extra`` files."""
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest

    parts = []
    with open_trajectories(data) as tf:
        manifest, _ = resolve_manifest(
            setting, data, tf.case_ids, tf.controls_raw, tf.scene.n_transitions, splits
        )
        parts.append(np.asarray(tf.controls_raw)[[tf.row_of(int(c)) for c in manifest["train"]]])
    for path in extra:
        with open_trajectories(path) as tf:
            parts.append(np.asarray(tf.controls_raw)[np.asarray(tf.complete, dtype=bool)])
    return np.concatenate(parts)


def _write_candidates(
    path: Path, cands: Candidates, scores: dict[str, np.ndarray], chosen: np.ndarray
) -> None:
    picked = np.zeros(len(cands), dtype=bool)
    picked[chosen] = True
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([*CONTROL_NAMES, "kind", *scores, "chosen"])
        for i in range(len(cands)):
            w.writerow(
                [repr(float(v)) for v in cands.raw[i]]
                + [cands.kind[i]]
                + [f"{float(v[i]):.6g}" for v in scores.values()]
                + [int(picked[i])]
            )


def _choose(job: LearnJob, cands: Candidates, score: np.ndarray) -> np.ndarray:
    """Chosen candidate indices: ``select_batch`` over every candidate (recipes past the design box
    included: a trajectory file holds any admissible controls and warns about those beyond the box)."""
    cfg = job.config
    return select_batch(cands.unit, score, cfg.batch, cfg.pool_factor)


def _select(
    job: LearnJob, r: int, loaded: Any, x0: np.ndarray, rounds_data: list[Path], predecessor: Path | None
) -> dict[str, Any]:
    """Propose, score and choose round r's batch; writes candidates.csv and batch.csv; the state's part.
    ``predecessor``: the checkpoint the current one was trained from (acquisition "checkpoint")."""
    from nemsim.inference.checkpoint import load_checkpoint

    cfg = job.config
    rdir = round_dir(job.out, r)
    t0 = time.perf_counter()
    seed = _seed(cfg.proposals.seed, 100 + r)
    if cfg.acquisition == "lhs":  # the baseline: a fresh Latin hypercube, `nemsim design --n B --seed S`
        rdir.mkdir(parents=True, exist_ok=True)
        write_controls_csv(rdir / "batch.csv", lhs_design(cfg.batch, seed))
        return {"status": "selected", "chosen_kinds": {"interior": cfg.batch},
                "design_command": f"nemsim design --n {cfg.batch} --seed {seed}"}  # fmt: skip
    cands = propose(dataclasses.replace(cfg.proposals, seed=seed))
    use_second = cfg.acquisition == "checkpoint"
    if use_second and predecessor is None:
        raise ValueError("acquisition 'checkpoint' needs the checkpoint's predecessor (second_checkpoint)")
    second = load_checkpoint(predecessor).model if use_second and predecessor is not None else None
    need_train = cfg.acquisition == "distance"
    train_unit = (
        to_unit(training_recipes(job.data, job.setting, job.splits, [*job.extra_data, *rounds_data]))
        if need_train
        else None
    )
    scores = score_candidates(
        loaded.model,
        x0,
        cands.raw,
        [cfg.acquisition],
        cfg.scoring,
        loaded.scene.n_transitions,
        train_unit=train_unit,
        second=second,
        progress=job.progress,
    )
    chosen = _choose(job, cands, scores[cfg.acquisition])
    rdir.mkdir(parents=True, exist_ok=True)
    _write_candidates(rdir / "candidates.csv", cands, scores, chosen)
    write_controls_csv(rdir / "batch.csv", cands.raw[chosen])
    kinds = {k: int(np.count_nonzero(cands.kind[chosen] == k)) for k in KINDS}
    return {
        "status": "selected",
        "second_checkpoint": str(predecessor) if use_second else None,
        "candidates": cands.counts(),
        "chosen_kinds": kinds,
        "chosen_scores": [round(float(v), 6) for v in scores[cfg.acquisition][chosen]],
        "pool_best": round(float(scores[cfg.acquisition].max()), 6),
        "select_s": round(time.perf_counter() - t0, 1),
    }


def sim_config_for(loaded: Any, domain: str) -> Any:
    """The simulator configuration of the checkpoint's data (``sim_config``), on the requested domain
    ("auto": the quarter domain where the scene's grid allows it, else the full one)."""
    from nemsim.sim import SimConfig

    base = SimConfig.from_record(loaded.raw.get("sim_config")) or SimConfig()
    if domain == "auto":
        try:
            dataclasses.replace(base, domain="quarter").resolved(loaded.scene).check_scene(loaded.scene)
            domain = "quarter"
        except ValueError:
            domain = "full"
    return dataclasses.replace(base, domain=domain)


def _simulate(job: LearnJob, r: int, loaded: Any) -> dict[str, Any]:
    """Simulate round r's batch.csv into data.h5 (resumes a partial file); the state's part."""
    from nemsim.controls import read_controls_csv
    from nemsim.sim.generate import generate_dataset

    rdir = round_dir(job.out, r)
    raw = read_controls_csv(rdir / "batch.csv")
    config = sim_config_for(loaded, job.config.sim_domain)
    seed = job.config.sim_seed + r - 1
    rep = generate_dataset(
        rdir / "data.h5",
        loaded.scene,
        loaded.rules,
        raw,
        list(range(len(raw))),
        seed=seed,
        config=config,
        workers=job.workers,
        executor=job.executor,
        progress=job.progress,
        state_dtype=job.config.state_dtype,
    )
    command = (
        f"nemsim generate --scene {loaded.scene.name} --controls {rdir / 'batch.csv'} --seed {seed} "
        f"--sim-domain {config.domain} --state-dtype {job.config.state_dtype} --out {rdir / 'data.h5'}"
    )
    return {
        "status": "simulated",
        "sim_seed": seed,
        "sim_domain": config.domain,
        "simulated_now": rep["written"],
        "simulate_s": round(rep["wall_s"], 1),
        "command": command,
    }


def _train(job: LearnJob, r: int, loaded: Any, init: Path, rounds_data: list[Path]) -> dict[str, Any]:
    """Fine-tune from ``init`` on the checkpoint's data plus rounds 1..r (resumes train/last.pt)."""
    from nemsim.training.run import TrainJob, run_training

    out = round_dir(job.out, r) / "train"
    t0 = time.perf_counter()
    summary = run_training(
        TrainJob(
            model=loaded.name,
            data=job.data,
            setting=job.setting,
            out=out,
            config=job.train,
            model_overrides=dict(loaded.config),
            splits=job.splits,
            extra_data=(*job.extra_data, *rounds_data),
            resume=True,
            init_from=init,
            test=False,
        )
    )
    return {
        "status": "trained",
        "checkpoint": str(out / "best.pt"),
        "best_val": summary.get("best_val"),
        "select_metric": summary.get("select_metric"),
        "train_s": round(time.perf_counter() - t0, 1),
    }


def run_learning(job: LearnJob, echo: Callable[[str], None] = log.info) -> list[dict[str, Any]]:
    """Run (or resume) the job's rounds; each round's state (``round.json``), in order, with ``ran_now``:
    the phases this call ran (a finished round resumed: none).

    Raises ValueError when ``job.out`` holds a run with other options (``LearnJob.identity``).
    """
    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.sim.process import initial_state

    state_path = Path(job.out) / "learn.json"
    saved = _read_state(state_path)
    if saved and saved.get("identity") != job.identity():
        raise ValueError(
            f"{job.out} holds a learning run with other options ({state_path}); rerun with "
            "the same options to resume it, or choose another output directory"
        )
    _write_state(state_path, {"identity": job.identity(), "rounds": job.config.rounds})
    states: list[dict[str, Any]] = []
    rounds_data: list[Path] = []
    ckpt, predecessor = Path(job.checkpoint), job.second_checkpoint
    for r in range(1, job.config.rounds + 1):
        path = round_dir(job.out, r) / "round.json"
        state = {"round": r, "checkpoint_in": str(ckpt), **_read_state(path)}
        loaded = load_checkpoint(ckpt)
        if getattr(loaded.model.config, "domain", "full") == "section":
            raise ValueError(f"{ckpt} is a trench's cross-section model; active learning simulates the "
                             "checkpoint's own scene (a hole) and does not cover trenches")
        phases = [("selected", "choosing the batch"), ("simulated", "simulating"), ("trained", "fine-tuning")]
        ran: list[str] = []
        for status, doing in phases:
            if _reached(state, status):
                continue
            ran.append(status)
            echo(f"round {r}/{job.config.rounds}: {doing}")
            if status == "selected":
                x0 = initial_state(loaded.scene, sim_config_for(loaded, "full"))
                state.update(_select(job, r, loaded, x0, rounds_data, predecessor))
            elif status == "simulated":
                state.update(_simulate(job, r, loaded))
            else:
                state.update(_train(job, r, loaded, ckpt, [*rounds_data, round_dir(job.out, r) / "data.h5"]))
            _write_state(path, state)
        echo(
            f"round {r}/{job.config.rounds}: done, chose {state['chosen_kinds']}, validation "
            f"{state.get('select_metric')} {state.get('best_val')} -> {state['checkpoint']}"
        )
        rounds_data.append(round_dir(job.out, r) / "data.h5")
        ckpt, predecessor = Path(state["checkpoint"]), ckpt
        states.append({**state, "ran_now": ran})
    return states
