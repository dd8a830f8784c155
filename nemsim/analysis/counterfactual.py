"""Counterfactual control interventions and mechanism-response alignment ([supp_mechanism_alignment]).

For a frozen model, an initial state x_0 and a raw control vector u, the Cl+ flux (control
``flux_cl_plus``) and the neutral-Cl flux (``flux_cl``) are scaled by (s_+, s_n) in
I = {0.5, 1.0, 1.5}^2 \\ {(1, 1)} (eq. mechanism_interventions: eight interventions). The perturbed raw
controls go through the training transform and normalization (``nemsim.controls.to_normalized``,
no clipping). One one-step prediction per control vector -- base and all interventions in ONE batched
forward -- gives

    M_m = Σ_e T_{e,m}                                        (eq. mechanism_response_strength)
    ΔM_m(%) = 100 (M_m^cf - M_m^base) / M_m^base             (eq. mechanism_response_change)
    R = Σ_v max(φ̂^Si_1(v) - φ^Si_0(v), 0)                    (eq. material_removal_proxy)
    ΔR(%) = 100 (R^cf - R^base) / R^base                     (eq. material_removal_change)

The dataset analysis averages ΔM_m per intervention and family over the test trajectories and computes
Pearson correlations per intervention group: Cl+ increasing (s_+ = 1.5, any s_n; coupled response vs
ΔR), Cl+ decreasing (s_+ = 0.5; coupled), neutral-Cl-only increase (s_+ = 1, s_n = 1.5; chemical) and
decrease (s_+ = 1, s_n = 0.5; chemical).

Choices where the paper is silent:
  * R sums over all voxels of the (padded) Si channel, in normalized SDF units;
  * a relative change whose base value is 0 is reported as NaN (and dropped from means/correlations);
  * without an explicit x_0, ``mechanism_response`` starts from the scene's initial geometry
    (``nemsim.sim`` initial state), the same x_0 as every trajectory of the benchmark.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nemsim.evaluation.figure import pyplot, save_figure

log = logging.getLogger(__name__)

FACTORS: tuple[float, ...] = (0.5, 1.0, 1.5)
INTERVENTIONS: tuple[tuple[float, float], ...] = tuple(
    (sp, sn) for sp in FACTORS for sn in FACTORS if (sp, sn) != (1.0, 1.0)
)  # (s_+, s_n), eight pairs
CL_PLUS, CL_NEUTRAL = "flux_cl_plus", "flux_cl"


def intervention_controls(controls_raw: np.ndarray,
                          interventions: Sequence[tuple[float, float]]) -> np.ndarray:
    """Raw controls (14,) -> (1 + K, 14): the base vector first, then one row per (s_+, s_n)."""
    from nemsim.controls import CONTROL_NAMES

    raw = np.asarray(controls_raw, dtype=np.float64)
    if raw.shape != (len(CONTROL_NAMES),):
        raise ValueError(f"controls_raw must be ({len(CONTROL_NAMES)},) raw physical controls, "
                         f"got {raw.shape}")
    i_plus, i_neutral = CONTROL_NAMES.index(CL_PLUS), CONTROL_NAMES.index(CL_NEUTRAL)
    rows = [raw]
    for s_plus, s_neutral in interventions:
        r = raw.copy()
        r[i_plus] *= s_plus
        r[i_neutral] *= s_neutral
        rows.append(r)
    return np.stack(rows)  # (1 + K, 14)


def _relative_change(cf: np.ndarray, base: np.ndarray) -> np.ndarray:
    base = np.asarray(base, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 100.0 * (np.asarray(cf, dtype=np.float64) - base) / base
    return np.where(base != 0, out, np.nan)


@torch.no_grad()
def response_batch(
    model: torch.nn.Module, x0: torch.Tensor, controls_raw: np.ndarray,
    interventions: Sequence[tuple[float, float]] = INTERVENTIONS,
) -> dict[str, np.ndarray]:
    """Batched core for N cases: x0 (N, 2, D, H, W), controls_raw (N, 14).

    Returns arrays: M (N, 1+K, M_fam), R (N, 1+K), lambda (N, E), alpha (N, E, M_fam) of the base
    prediction, dM (N, K, M_fam) and dR (N, K) in percent. One forward of N·(1+K) samples.
    """
    from nemsim.controls import to_normalized

    N = x0.shape[0]
    K1 = 1 + len(interventions)
    raw = np.stack([intervention_controls(c, interventions) for c in np.asarray(controls_raw)])  # (N,1+K,14)
    p = next(model.parameters(), None)
    device = p.device if p is not None else torch.device("cpu")
    u = torch.as_tensor(to_normalized(raw), dtype=torch.float32, device=device).reshape(N * K1, -1)
    x = x0.to(device=device, dtype=torch.float32)
    xb = x[:, None].expand(N, K1, *x.shape[1:]).reshape(N * K1, *x.shape[1:])  # (N(1+K), 2, D, H, W)
    x1, aux = model(xb, u, return_aux=True)
    T = aux["T"].float().reshape(N, K1, *aux["T"].shape[1:])  # (N, 1+K, E, M)
    M = T.sum(dim=2)  # (N, 1+K, M)  eq. mechanism_response_strength
    # (N, 1+K)  eq. material_removal_proxy
    removal = (x1[:, 1] - xb[:, 1]).clamp_min(0).reshape(N, K1, -1).sum(-1)
    M_np, R_np = M.double().cpu().numpy(), removal.double().cpu().numpy()
    lam = aux["lambda"].float().reshape(N, K1, -1)[:, 0].cpu().numpy()
    alpha = aux["alpha"].float().reshape(N, K1, *aux["alpha"].shape[1:])[:, 0].cpu().numpy()
    return {
        "M": M_np, "R": R_np, "lambda": lam, "alpha": alpha,
        "dM": _relative_change(M_np[:, 1:], M_np[:, :1]),  # (N, K, M)
        "dR": _relative_change(R_np[:, 1:], R_np[:, :1]),  # (N, K)
    }


def mechanism_response(
    loaded: Any,
    controls_raw: Sequence[float] | np.ndarray,
    factors: Sequence[tuple[float, float]] = INTERVENTIONS,
    *,
    x0: np.ndarray | torch.Tensor | None = None,
) -> dict[str, Any]:
    """Counterfactual mechanism response for one control vector (the service calls this).

    Args:
        loaded: a ``LoadedModel`` (``nemsim.inference.checkpoint.load_checkpoint``) or anything with
            ``.model`` (NEMSim, supports return_aux) and ``.scene``.
        controls_raw: (14,) raw physical controls, CONTROL_NAMES order.
        factors: the (s_+, s_n) flux multipliers of Cl+ and neutral Cl; default the paper's eight.
        x0: (2, D, H, W) initial state; default the scene's initial geometry.

    Returns:
        {"families": [...], "base": {"M": {family: float}, "R": float, "lambda": [E], "alpha": [[M]*E],
         "event_names": [...]}, "interventions": [{"s_cl_plus", "s_cl", "M": {...}, "R",
         "delta_M_pct": {family: float}, "delta_R_pct": float}, ...]}
    """
    from nemsim.rules.vocab import FAMILIES

    model = loaded.model
    if x0 is None:
        from nemsim.sim import initial_state

        x0 = initial_state(loaded.scene)
    x = torch.as_tensor(np.asarray(x0), dtype=torch.float32)[None]  # (1, 2, D, H, W)
    out = response_batch(model, x, np.asarray(controls_raw, dtype=np.float64)[None], tuple(factors))
    fams = list(FAMILIES)[: out["M"].shape[-1]]

    def fam(v: np.ndarray) -> dict[str, float | None]:
        return {f: _num(v[k]) for k, f in enumerate(fams)}

    names = getattr(getattr(loaded, "rules", None), "names", None)
    return {
        "families": fams,
        "base": {
            "M": fam(out["M"][0, 0]),
            "R": _num(out["R"][0, 0]),
            "lambda": [float(v) for v in out["lambda"][0]],
            "alpha": out["alpha"][0].astype(float).tolist(),
            "event_names": [str(n) for n in names] if names is not None else None,
        },
        "interventions": [
            {
                "s_cl_plus": float(sp), "s_cl": float(sn),
                "M": fam(out["M"][0, k + 1]), "R": _num(out["R"][0, k + 1]),
                "delta_M_pct": fam(out["dM"][0, k]), "delta_R_pct": _num(out["dR"][0, k]),
            }
            for k, (sp, sn) in enumerate(factors)
        ],
    }


def _num(v: Any) -> float | None:
    v = float(v)
    return None if not np.isfinite(v) else v


def _pearson(a: np.ndarray, b: np.ndarray) -> tuple[float | None, int]:
    ok = np.isfinite(a) & np.isfinite(b)
    n = int(ok.sum())
    if n < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return None, n
    return float(np.corrcoef(a[ok], b[ok])[0, 1]), n


GROUPS: dict[str, tuple[str, Any]] = {
    # name: (family whose response is correlated with ΔR, selector over (s_+, s_n))
    "cl_plus_increase": ("coupled", lambda sp, sn: sp == 1.5),
    "cl_plus_decrease": ("coupled", lambda sp, sn: sp == 0.5),
    "cl_only_increase": ("chemical", lambda sp, sn: sp == 1.0 and sn == 1.5),
    "cl_only_decrease": ("chemical", lambda sp, sn: sp == 1.0 and sn == 0.5),
}


def analyze(
    model: torch.nn.Module,
    cases: Sequence[tuple[int, np.ndarray, np.ndarray]],
    *,
    interventions: Sequence[tuple[float, float]] = INTERVENTIONS,
    batch_size: int = 4,
) -> dict[str, Any]:
    """Dataset analysis. cases: (case_id, x0 (2, D, H, W), controls_raw (14,)).

    Returns {"table": [{s_cl_plus, s_cl, delta_M_pct: {family: mean}, delta_R_pct: mean}],
    "correlations": {group: {"family", "r", "n"}}, "pairs": per trajectory-intervention records}.
    """
    from nemsim.rules.vocab import FAMILIES

    interventions = tuple(interventions)
    dM_all, dR_all, ids = [], [], []  # type: ignore[var-annotated]
    for start in range(0, len(cases), batch_size):
        chunk = cases[start : start + batch_size]
        x0 = torch.stack([torch.as_tensor(np.asarray(c[1]), dtype=torch.float32) for c in chunk])
        raw = np.stack([np.asarray(c[2], dtype=np.float64) for c in chunk])
        out = response_batch(model, x0, raw, interventions)
        dM_all.append(out["dM"])
        dR_all.append(out["dR"])
        ids.extend(int(c[0]) for c in chunk)
    if not ids:
        raise ValueError("no cases to analyse")
    dM = np.concatenate(dM_all)  # (N, K, M)
    dR = np.concatenate(dR_all)  # (N, K)
    fams = list(FAMILIES)[: dM.shape[-1]]
    table = []
    for k, (sp, sn) in enumerate(interventions):
        table.append({
            "s_cl_plus": sp, "s_cl": sn,
            "delta_M_pct": {f: _num(np.nanmean(dM[:, k, j])) if np.isfinite(dM[:, k, j]).any() else None
                            for j, f in enumerate(fams)},
            "delta_R_pct": _num(np.nanmean(dR[:, k])) if np.isfinite(dR[:, k]).any() else None,
        })
    correlations = {}
    for name, (family, select) in GROUPS.items():
        ks = [k for k, (sp, sn) in enumerate(interventions) if select(sp, sn)]
        if not ks or family not in fams:
            continue
        j = fams.index(family)
        r, n = _pearson(dM[:, ks, j].ravel(), dR[:, ks].ravel())
        correlations[name] = {"family": family, "r": r, "n": n,
                              "interventions": [list(interventions[k]) for k in ks]}
    pairs = [
        {"case_id": cid, "s_cl_plus": sp, "s_cl": sn,
         "delta_M_pct": {f: _num(dM[i, k, j]) for j, f in enumerate(fams)}, "delta_R_pct": _num(dR[i, k])}
        for i, cid in enumerate(ids) for k, (sp, sn) in enumerate(interventions)
    ]
    return {"families": fams, "n_cases": len(ids), "table": table, "correlations": correlations,
            "pairs": pairs}


def format_table(result: dict[str, Any]) -> str:
    """Plain-text table: one row per intervention, ΔM_m (%) per family and ΔR (%)."""
    fams = result["families"]
    head = f"{'s_Cl+':>6} {'s_Cl':>6} " + " ".join(f"{'dM_' + f + ' %':>14}" for f in fams) + f" {'dR %':>10}"
    lines = [head]
    for row in result["table"]:
        cells = " ".join(f"{_fmt(row['delta_M_pct'][f]):>14}" for f in fams)
        lines.append(f"{row['s_cl_plus']:>6.1f} {row['s_cl']:>6.1f} {cells} {_fmt(row['delta_R_pct']):>10}")
    lines.append("Pearson r (response vs dR):")
    for name, c in result["correlations"].items():
        lines.append(f"  {name:<18} {c['family']:<9} r = {_fmt(c['r'], 3)}  (n = {c['n']})")
    return "\n".join(lines)


def _fmt(v: float | None, digits: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def write_outputs(result: dict[str, Any], out_dir: str | Path) -> dict[str, Path]:
    """counterfactual.json, counterfactual_table.csv, counterfactual.png (a: mean ΔM per family and
    intervention; b: per-pair response change vs ΔR for the four groups)."""
    import csv

    plt = pyplot()

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fams = result["families"]
    paths = {"json": out_dir / "counterfactual.json", "csv": out_dir / "counterfactual_table.csv",
             "png": out_dir / "counterfactual.png"}
    paths["json"].write_text(json.dumps(result, indent=2))
    with paths["csv"].open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["s_cl_plus", "s_cl", *[f"delta_M_{m}_pct" for m in fams], "delta_R_pct"])
        for row in result["table"]:
            deltas = [row["delta_M_pct"][m] for m in fams]
            w.writerow([row["s_cl_plus"], row["s_cl"], *deltas, row["delta_R_pct"]])

    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(13, 4.8))
    labels = [f"({r['s_cl_plus']:g}, {r['s_cl']:g})" for r in result["table"]]
    width = 0.8 / max(len(fams), 1)
    xs = np.arange(len(labels))
    for j, m in enumerate(fams):
        vals = [np.nan if r["delta_M_pct"][m] is None else r["delta_M_pct"][m] for r in result["table"]]
        ax_a.bar(xs + (j - (len(fams) - 1) / 2) * width, vals, width, label=m)
    ax_a.axhline(0, color="k", lw=0.6)
    ax_a.set_xticks(xs, labels, rotation=30)
    ax_a.set_xlabel("(s$_{Cl+}$, s$_{Cl}$)")
    ax_a.set_ylabel("mean ΔM$_m$ (%)")
    ax_a.set_title("(a) mechanism response change")
    ax_a.legend()
    for name, (family, select) in GROUPS.items():
        pts = [(p["delta_M_pct"][family], p["delta_R_pct"]) for p in result["pairs"]
               if select(p["s_cl_plus"], p["s_cl"]) and p["delta_M_pct"].get(family) is not None
               and p["delta_R_pct"] is not None]
        if pts:
            a = np.asarray(pts)
            r = result["correlations"].get(name, {}).get("r")
            ax_b.scatter(a[:, 0], a[:, 1], s=10, alpha=0.7, label=f"{name} ({family}) r={_fmt(r, 2)}")
    ax_b.axhline(0, color="k", lw=0.6)
    ax_b.axvline(0, color="k", lw=0.6)
    ax_b.set_xlabel("ΔM$_m$ (%)")
    ax_b.set_ylabel("ΔR (%)")
    ax_b.set_title("(b) response change vs material-removal change")
    ax_b.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, paths["png"], dpi=110)
    return paths
