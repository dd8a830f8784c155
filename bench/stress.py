"""Hard-case stability suite for a one-step surrogate.

Autoregressive rollouts (``nemsim.evaluation.rollout``) from the scene's initial state, past the trained
horizon (default 300 steps against the trained 100), on:

  * ``centre``: every control at the centre of its design range (normalized 0);
  * ``corner-<bits>``: corners of the flux and ion-energy-mean sub-box (bit 0 = design minimum, 1 =
    maximum, in ``CORNER_AXES`` order; the other controls at their centre): 2^7 = 128 corners, or
    ``max_corners`` of them evenly spaced, always with the all-min and all-max corners. The three energy
    spreads stay at their centre (2^10 corners would not run on a CPU; the spreads have the narrowest ranges);
  * ``angle-min`` / ``angle-max``: the four cosine-power exponents at their design minimum / maximum;
  * ``noise-<k>``: the centre controls plus Gaussian noise (``noise_control_std``, normalized units) and the
    initial state plus Gaussian noise (``noise_state_std``, normalized SDF units).

Per case, streamed per step (the trajectory is never held in memory): ``finite`` and
``first_nonfinite_step``; ``max_abs`` and ``bounded`` (finite, max_abs <= ``abs_bound``: the data are clipped
to [-1, 1], so beyond it is a blow-up); ``depth_decreases`` (steps where the etch depth falls by more than
``depth_tol_nm``), ``depth_max_drop_nm``, ``depth_final_nm``; ``norm_ratio`` = ‖x_T‖ / ‖x_0‖ and
``max_step_growth`` = max_t ‖x_{t+1}‖ / ‖x_t‖; ``max_step_change`` = max_t max |x_{t+1} - x_t|;
``mask_loss_min_nm`` (negative = the mask grew).

The physical invariants judged against the simulator are ``bench.invariants``; ``nemsim stress`` runs them
after these cases and judges these cases' depth drops and mask losses with the simulator's tolerances.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from nemsim.controls import CONTROL_INDEX, CONTROL_SPECS, N_CONTROLS
from nemsim.evaluation.rollout import rollout
from nemsim.evaluation.truth import model_device
from nemsim.geometry.profile import profile_metrics_batch

log = logging.getLogger(__name__)

CORNER_AXES: tuple[str, ...] = (
    "flux_ar_plus", "flux_cl_plus", "flux_cl2_plus", "flux_cl",
    "energy_mean_cl_plus", "energy_mean_cl2_plus", "energy_mean_ar_plus",
)
ANGLE_AXES: tuple[str, ...] = tuple(s.name for s in CONTROL_SPECS if s.name.startswith("angle_"))


@dataclass(frozen=True)
class StressConfig:
    steps: int = 300  # rollout length (the trained horizon is 100)
    max_corners: int | None = None  # None: all 2^7 corners; else an evenly spaced subset of this size
    angles: bool = True  # the angle-min / angle-max cases
    noise_cases: int = 4  # noisy-input cases
    noise_state_std: float = 0.02  # Gaussian noise on x_0 (normalized SDF units)
    noise_control_std: float = 0.1  # Gaussian noise on the normalized controls
    abs_bound: float = 1.5  # |value| above this is a blow-up
    depth_tol_nm: float = 0.05  # an etch-depth decrease larger than this counts as non-monotone
    batch_size: int = 16  # cases rolled out together
    seed: int = 0  # noise seed


@dataclass(frozen=True)
class StressCase:
    name: str
    u: np.ndarray  # (14,) normalized controls
    state_noise: float  # std of the Gaussian noise added to x_0 (0: none)


def initial_state(scene: Any) -> np.ndarray:
    """x_0 (2, D, H, W) float32 of ``scene``: the simulator's Ψ of the initial geometry."""
    from nemsim.sim import initial_state as build

    return np.asarray(build(scene), dtype=np.float32)


def corner_bits(max_corners: int | None) -> list[tuple[int, ...]]:
    """The 0/1 patterns over ``CORNER_AXES``: all 128, or ``max_corners`` evenly spaced in binary order
    (index 0 = all-min and 127 = all-max are always included)."""
    every = list(itertools.product((0, 1), repeat=len(CORNER_AXES)))
    if max_corners is None or max_corners >= len(every):
        return every
    if max_corners < 2:
        raise ValueError(f"max_corners must be >= 2 (all-min and all-max) or None, got {max_corners}")
    idx = np.unique(np.round(np.linspace(0, len(every) - 1, max_corners)).astype(int))
    return [every[i] for i in idx]


def stress_cases(cfg: StressConfig, rng: np.random.Generator) -> list[StressCase]:
    """The case list of the module docstring, normalized controls."""
    centre = np.zeros(N_CONTROLS)
    cases = [StressCase("centre", centre, 0.0)]
    for bits in corner_bits(cfg.max_corners):
        u = centre.copy()
        for name, bit in zip(CORNER_AXES, bits, strict=True):
            u[CONTROL_INDEX[name]] = 1.0 if bit else -1.0
        cases.append(StressCase("corner-" + "".join(map(str, bits)), u, 0.0))
    if cfg.angles:
        for tag, value in (("min", -1.0), ("max", 1.0)):
            u = centre.copy()
            u[[CONTROL_INDEX[n] for n in ANGLE_AXES]] = value
            cases.append(StressCase(f"angle-{tag}", u, 0.0))
    for k in range(cfg.noise_cases):
        u = centre + cfg.noise_control_std * rng.standard_normal(N_CONTROLS)
        cases.append(StressCase(f"noise-{k}", u, cfg.noise_state_std))
    return cases


def _norms(x: torch.Tensor) -> torch.Tensor:
    """Frobenius norm per sample, (B,), in float64; NaN/Inf propagate."""
    return x.double().flatten(1).norm(dim=1)


def _max_abs_finite(x: torch.Tensor) -> torch.Tensor:
    """max |value| over the finite entries per sample, (B,)."""
    a = x.float().abs().flatten(1)
    return torch.where(torch.isfinite(a), a, torch.zeros_like(a)).amax(dim=1)


def _depth_mask(x: torch.Tensor, scene: Any) -> tuple[np.ndarray, np.ndarray]:
    """Etch depth and mask loss (B,), (B,) in nm of states (B, 2, D, H, W); NaN where not finite."""
    arr = x.detach().float().cpu().numpy()
    ok = np.isfinite(arr).reshape(arr.shape[0], -1).all(axis=1)
    m = profile_metrics_batch(np.nan_to_num(arr, nan=0.0, posinf=1.0, neginf=-1.0), scene)
    return np.where(ok, m["etch_depth"], np.nan), np.where(ok, m["mask_loss"], np.nan)


@torch.no_grad()
def run_stress(
    model: Any, scene: Any, x0: np.ndarray | torch.Tensor, cfg: StressConfig | None = None, *,
    progress: bool = False,
) -> dict[str, Any]:
    """Run the suite; returns {"config", "scene", "cases": [per-case dict], "summary"} (JSON-ready).

    Args:
        model: anything ``rollout`` accepts (NEMSim uses its cached-control fast path).
        scene: the scene of ``x0`` (etch depth is measured with it).
        x0: (2, D, H, W) initial state (normalized SDF), e.g. ``nemsim.sim.initial_state(scene)``.
        cfg: ``StressConfig``. progress: a tqdm bar (stderr) over the cases.
    """
    cfg = cfg or StressConfig()
    if cfg.steps < 1 or cfg.batch_size < 1:
        raise ValueError(f"steps and batch_size must be >= 1, got {cfg.steps} and {cfg.batch_size}")
    rng = np.random.default_rng(cfg.seed)
    cases = stress_cases(cfg, rng)
    device = model_device(model)
    base = torch.as_tensor(np.asarray(x0), dtype=torch.float32, device=device)  # (2, D, H, W)
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
    results: list[dict[str, Any]] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(cases), unit="case", desc=f"stress rollouts ({scene.name})", dynamic_ncols=True)
    with torch.inference_mode():
        for start in range(0, len(cases), cfg.batch_size):
            chunk = cases[start : start + cfg.batch_size]
            results.extend(_run_chunk(model, scene, base, chunk, cfg, gen))
            if bar is not None:
                bar.update(len(chunk))
            else:
                log.info("stress: %d/%d cases done", len(results), len(cases))
    if bar is not None:
        bar.close()
    return {
        "config": asdict(cfg),
        "scene": scene.name,
        "corner_axes": list(CORNER_AXES),
        "cases": results,
        "summary": summarize(results),
    }


def _run_chunk(
    model: Any, scene: Any, base: torch.Tensor, chunk: list[StressCase], cfg: StressConfig,
    gen: torch.Generator,
) -> list[dict[str, Any]]:
    B = len(chunk)
    x0 = base[None].repeat(B, 1, 1, 1, 1)  # (B, 2, D, H, W)
    for i, case in enumerate(chunk):
        if case.state_noise > 0:
            noise = torch.randn(base.shape, generator=gen) * case.state_noise
            x0[i] += noise.to(x0.device)
    u = torch.as_tensor(np.stack([c.u for c in chunk]), dtype=torch.float32, device=x0.device)  # (B, 14)
    T = cfg.steps
    norms = np.empty((T + 1, B))
    depth = np.empty((T + 1, B))
    mask_loss = np.empty((T + 1, B))
    max_abs = _max_abs_finite(x0).cpu().numpy()
    max_change = np.zeros(B)
    prev = [x0]
    first_bad = np.full(B, -1)
    norms[0] = _norms(x0).cpu().numpy()
    depth[0], mask_loss[0] = _depth_mask(x0, scene)

    def on_step(t: int, x: torch.Tensor) -> None:
        nonlocal max_abs, max_change
        max_change = np.maximum(max_change, _max_abs_finite(x - prev[0]).cpu().numpy())
        prev[0] = x
        finite = torch.isfinite(x).flatten(1).all(dim=1).cpu().numpy()  # (B,)
        first_bad[(~finite) & (first_bad < 0)] = t
        max_abs = np.maximum(max_abs, _max_abs_finite(x).cpu().numpy())
        norms[t] = _norms(x).cpu().numpy()
        depth[t], mask_loss[t] = _depth_mask(x, scene)

    rollout(model, x0, u, T, keep=False, on_step=on_step)
    out = []
    with np.errstate(divide="ignore", invalid="ignore"):
        growth = norms[1:] / norms[:-1]  # (T, B)
        drops = depth[:-1] - depth[1:]  # (T, B) positive = depth decreased
    for i, case in enumerate(chunk):
        finite = bool(first_bad[i] < 0)
        g = growth[:, i]
        d = drops[:, i]
        out.append({
            "name": case.name,
            "u": [float(v) for v in case.u],
            "state_noise": case.state_noise,
            "finite": finite,
            "first_nonfinite_step": None if finite else int(first_bad[i]),
            "max_abs": float(max_abs[i]),
            "bounded": finite and bool(max_abs[i] <= cfg.abs_bound),
            "depth_initial_nm": _num(depth[0, i]),
            "depth_final_nm": _num(depth[-1, i]),
            "depth_decreases": int(np.sum(d[np.isfinite(d)] > cfg.depth_tol_nm)),
            "depth_max_drop_nm": _num(np.nanmax(d)) if np.isfinite(d).any() else None,
            "mask_loss_min_nm": _num(np.nanmin(ml)) if np.isfinite(ml := mask_loss[:, i]).any() else None,
            "norm_ratio": _num(norms[-1, i] / norms[0, i]),
            "max_step_growth": _num(np.nanmax(g)) if np.isfinite(g).any() else None,
            "max_step_change": float(max_change[i]),
        })
    return out


def _num(v: Any) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def summarize(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals over cases: counts of non-finite / unbounded / non-monotone cases and the worst figures."""

    def worst(key: str) -> float | None:
        vals = [r[key] for r in results if r[key] is not None]
        return max(vals) if vals else None

    return {
        "n_cases": len(results),
        "n_nonfinite": sum(not r["finite"] for r in results),
        "n_unbounded": sum(not r["bounded"] for r in results),
        "n_nonmonotone_depth": sum(r["depth_decreases"] > 0 for r in results),
        "max_abs": worst("max_abs"),
        "max_depth_drop_nm": worst("depth_max_drop_nm"),
        "max_norm_ratio": worst("norm_ratio"),
        "max_step_growth": worst("max_step_growth"),
        "max_step_change": worst("max_step_change"),
        "passed": all(r["bounded"] for r in results),
    }


def format_table(report: dict[str, Any], max_rows: int | None = None) -> str:
    """A plain-text table of the per-case figures plus the summary line."""
    head = (f"{'case':16s} {'finite':>6s} {'max|x|':>7s} {'depth0':>7s} {'depthT':>7s} {'#dec':>5s} "
            f"{'maxdrop':>8s} {'|xT|/|x0|':>9s} {'maxgrow':>8s} {'max|dx|':>8s}")
    lines = [head, "-" * len(head)]

    def f(v: float | None, spec: str) -> str:
        return format(v, spec) if v is not None else "nan"

    rows = report["cases"] if max_rows is None else report["cases"][:max_rows]
    for r in rows:
        lines.append(
            f"{r['name']:16s} {('yes' if r['finite'] else 'NO'):>6s} {r['max_abs']:7.3f} "
            f"{f(r['depth_initial_nm'], '7.2f')} {f(r['depth_final_nm'], '7.2f')} {r['depth_decreases']:5d} "
            f"{f(r['depth_max_drop_nm'], '8.3f')} {f(r['norm_ratio'], '9.4f')} "
            f"{f(r['max_step_growth'], '8.4f')} {r['max_step_change']:8.4f}"
        )
    if max_rows is not None and len(report["cases"]) > max_rows:
        lines.append(f"... {len(report['cases']) - max_rows} more cases (see the JSON)")
    s = report["summary"]
    lines.append(
        f"{s['n_cases']} cases, {report['config']['steps']} steps: non-finite {s['n_nonfinite']}, "
        f"unbounded (|x| > {report['config']['abs_bound']:g}) {s['n_unbounded']}, non-monotone depth "
        f"{s['n_nonmonotone_depth']}; worst max|x| {f(s['max_abs'], '.3f')}, depth drop "
        f"{f(s['max_depth_drop_nm'], '.3f')} nm, norm ratio {f(s['max_norm_ratio'], '.4f')}, step growth "
        f"{f(s['max_step_growth'], '.4f')}, step change {f(s['max_step_change'], '.4f')} -> "
        f"{'PASS' if s['passed'] else 'FAIL'}"
    )
    return "\n".join(lines)
