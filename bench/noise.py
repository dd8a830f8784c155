"""Monte Carlo noise floor of the simulator (``nemsim bench noise``).

The Avg RMSE [eq:supp_avg_rmse] between two runs of the same controls
with different seeds, over t = 1..100, computed with ``nemsim.evaluation.metrics`` exactly as for model
predictions; a surrogate cannot be expected to beat it. On a scene with the square's symmetry it also
reports the floor of symmetrized states (each averaged over the 8 symmetries: the quieter targets of
``symmetrize_targets``) and what a predictor of the mean evolution scores against raw trajectories.

``bench_pair_noise`` (``nemsim bench pair-noise``): the noise of a sweep pair's simulated difference (two
recipes that differ in one control group) when both members share their random numbers, against two
independently seeded runs: what the pair loss of ``TrainConfig.pair_loss_weight`` is trained on.
"""

from __future__ import annotations

import numpy as np

from nemsim.evaluation.metrics import rmse_per_step
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene
from nemsim.sim.config import SimConfig
from nemsim.sim.events import build_event_tables
from nemsim.sim.process import run_trajectory


def bench_noise(
    scene: Scene,
    rules: RuleTensors,
    design: np.ndarray,
    config: SimConfig | None = None,
    seeds: tuple[int, int] = (1, 2),
) -> dict:
    """Avg and final RMSE between two seeds of the same controls, per case and over the cases.

    Args: design (n, 14) raw controls; seeds: the two base seeds (case i uses default_rng([seed, i])).
    """
    config = (config or SimConfig()).resolved(scene)
    tables = build_event_tables(rules, config)
    runs = []
    for s in seeds:
        states = [
            run_trajectory(scene, rules, u, np.random.default_rng([s, i]), config, tables=tables).states
            for i, u in enumerate(design)
        ]
        runs.append(np.stack(states))  # (n, T+1, 2, D, H, W)
    a, b = runs[0][:, 1:], runs[1][:, 1:]  # t = 1..100
    per_case = [rmse_per_step(a[i : i + 1], b[i : i + 1]) for i in range(len(design))]
    r_t = rmse_per_step(a, b)
    out = {
        "scene": scene.name,
        "n_cases": len(design),
        "seeds": list(seeds),
        "avg_rmse": float(r_t.mean()),
        "final_rmse": float(r_t[-1]),
        "per_case_avg_rmse": [float(r.mean()) for r in per_case],
        "per_channel_avg_rmse": [float(rmse_per_step(a[:, :, c], b[:, :, c]).mean()) for c in range(2)],
    }
    if scene.symmetry != "none":
        out["symmetrized"] = _symmetrized_floor(a, b)
    return out


def _symmetrized_floor(a: np.ndarray, b: np.ndarray) -> dict:
    """The floors of symmetrized targets (``nemsim.symmetry``) from two seeds' states a, b (n, T, 2, D, H, W):
    ``avg_rmse`` between the two symmetrized runs (the seed-to-seed noise of the targets a model trained on
    them sees), ``vs_raw_avg_rmse`` of one symmetrized run against the other raw run (about what a predictor
    of the mean evolution scores against raw simulator trajectories, the metric of the control-id test),
    and their per-case values."""
    import torch

    from nemsim.symmetry import symmetrize

    sa, sb = (symmetrize(torch.from_numpy(np.ascontiguousarray(x))).numpy() for x in (a, b))
    cases = range(len(a))
    return {
        "avg_rmse": float(rmse_per_step(sa, sb).mean()),
        "vs_raw_avg_rmse": float(rmse_per_step(sa, b).mean()),
        "per_case_avg_rmse": [float(rmse_per_step(sa[i : i + 1], sb[i : i + 1]).mean()) for i in cases],
        "per_case_vs_raw_avg_rmse": [float(rmse_per_step(sa[i : i + 1], b[i : i + 1]).mean()) for i in cases],
    }


def pair_group(raw_a: np.ndarray, raw_b: np.ndarray) -> str:
    """The ``CONTROL_GROUPS`` name of the controls in which two recipes (14,) differ ("none" if equal,
    "mixed" if they differ outside one group)."""
    from nemsim.controls import CONTROL_GROUPS, CONTROL_NAMES

    moved = {CONTROL_NAMES[j] for j in np.flatnonzero(np.asarray(raw_a) != np.asarray(raw_b))}
    if not moved:
        return "none"
    for name, members in CONTROL_GROUPS.items():
        if moved <= set(members):
            return name
    return "mixed"


PAIR_METRICS = ("etch_depth", "top_width", "bottom_width", "mask_loss")
_PAIR_KEYS = ("response", "crn_noise", "independent_noise")


def _pair_noise(xa1: np.ndarray, xb1: np.ndarray, xa2: np.ndarray, xb2: np.ndarray, scene: Scene) -> dict:
    """One pair under two base seeds, states (T, 2, D, H, W) for t = 1..T: {"field": {key: RMS SDF},
    metric: {key: nm at the final state}} with key in ``_PAIR_KEYS`` (``bench_pair_noise``)."""
    from nemsim.geometry.profile import profile_metrics_batch

    d1, d2 = xb1 - xa1, xb2 - xa2  # the pair's difference under each seed
    cross = (xb2 - xa1) - (xb1 - xa2)  # two independent-seed differences, subtracted
    out = {"field": {"response": float(np.sqrt(np.mean((0.5 * (d1 + d2)) ** 2))),
                     "crn_noise": float(np.sqrt(np.mean((d1 - d2) ** 2 / 2))),
                     "independent_noise": float(np.sqrt(np.mean(cross**2 / 2)))}}
    final = profile_metrics_batch(np.stack([x[-1] for x in (xa1, xb1, xa2, xb2)]), scene)
    for k in PAIR_METRICS:
        a1, b1, a2, b2 = final[k]
        out[k] = {"response": float(0.5 * ((b1 - a1) + (b2 - a2))),
                  "crn_noise": float(abs((b1 - a1) - (b2 - a2)) / np.sqrt(2)),
                  "independent_noise": float(abs((b2 - a1) - (b1 - a2)) / np.sqrt(2))}
    return out


def bench_pair_noise(path: str, other: str) -> dict:
    """How much of the Monte Carlo noise common random numbers take out of a sweep pair's difference.

    ``path`` and ``other`` hold the same pair design (``nemsim design --kind pairs``) simulated with two
    base seeds (``other`` may hold only its first cases). For each pair (a, b) complete in both, with
    D_s = x_b,s - x_a,s the simulated difference under base seed s (both members one seed):
      * common random numbers: the noise of D is (D_1 - D_2) / sqrt(2);
      * independent seeds: x_b,2 - x_a,1 and x_b,1 - x_a,2 are two differences of independently seeded
        runs, and their noise is their difference over sqrt(2);
      * the response is the mean of D_1 and D_2.
    Fields: RMS over t = 1..T and every voxel (normalized SDF); profile metrics (nm) at the final state.
    Reported per pair, as RMS over the pairs of each control group (``pair_group``) and over all pairs.
    """
    from nemsim.data.hdf5 import open_trajectories

    rows: list[dict] = []
    with open_trajectories(path) as f1, open_trajectories(other) as f2:
        if f1.scene != f2.scene:
            raise ValueError(f"{path} and {other} are of different scenes")
        row2 = {int(c): r for r, c in enumerate(f2.case_ids) if f2.complete[r]}
        for a, b in f1.seed_pairs():
            ca, cb = int(f1.case_ids[a]), int(f1.case_ids[b])
            if ca not in row2 or cb not in row2:
                continue
            a2, b2 = row2[ca], row2[cb]
            same = (np.array_equal(f1.controls_raw[a], f2.controls_raw[a2])
                    and np.array_equal(f1.controls_raw[b], f2.controls_raw[b2]))
            if not same:
                raise ValueError(f"case {ca} or {cb} has other controls in {other} than in {path}")
            if f2.seeds[a2] != f2.seeds[b2]:
                raise ValueError(f"cases {ca} and {cb} do not share a seed in {other}")
            noise = _pair_noise(f1.states[a][1:], f1.states[b][1:], f2.states[a2][1:], f2.states[b2][1:],
                                f1.scene)
            rows.append({"cases": [ca, cb], "group": pair_group(f1.controls_raw[a], f1.controls_raw[b]),
                         **noise})
        scene = f1.scene.name
    if not rows:
        raise ValueError(f"no sweep pair of {path} is complete in {other}")

    def summary(sel: list[dict]) -> dict:
        out: dict = {"n_pairs": len(sel)}
        for part in ("field", *PAIR_METRICS):
            out[part] = {key: float(np.sqrt(np.mean([r[part][key] ** 2 for r in sel]))) for key in _PAIR_KEYS}
        return out

    groups = sorted({r["group"] for r in rows})
    return {"scene": scene, "files": [str(path), str(other)], "pairs": rows,
            "by_group": {g: summary([r for r in rows if r["group"] == g]) for g in groups},
            "all": summary(rows)}
