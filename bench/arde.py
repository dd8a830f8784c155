"""The simulator's aspect-ratio-dependent etching (ARDE): hole (or trench) depth against the opening's CD.

Holes of CD 24, 32, 40, 48 and 64 nm under 80 nm of mask (``nemsim.geometry.feature``) on the scene's grid,
at three recipes (``recipes``): the centre of the control box, a high-ion-energy one (the three ion mean
energies at the top of their range) and a low-neutral-flux one (Gamma(Cl) at the bottom of its range), the
rest at the centre; two seeds each (recipe i, CD j, seed s: ``default_rng([s, i, j])``), on the quarter
domain (``SimConfig.domain``), the whole horizon. The etch depth (``nemsim.geometry.profile``) at 5 s and
10 s; the ARDE slope is the least-squares slope of depth against CD (nm of depth per nm of CD) for each seed,
reported as the mean of the two seeds' slopes with their spread (half the difference: one run's slope is
uncertain by about that). A hole that reached the bottom of the Si (depth >= the Si thickness less one
voxel) is flagged: its depth is cut off there.

``--feature trench``: trenches of the same widths instead, simulated on their cross-section (``--domain
section``, the default for trenches).

With ``--checkpoint CKPT`` the model's depths and slopes are added beside the simulator's (``model_arde``):
the same holes rolled out from each one's x_0 (``initial_state`` of the per-case scene) at the same
recipes, and each slope's ratio to the simulator's. The simulator's results are reused from ``--sim-from``
(with ``--checkpoint``, by default OUT.json when it exists) if they are for the same scene, domain, CDs,
mask and recipes.

Run: ``python -m bench.arde --scene small --out benchmarks/small/arde`` (writes arde.json and arde.md);
``python -m bench.arde --checkpoint CKPT --sim-from benchmarks/small/arde.json --out DIR/arde``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from nemsim.controls import ION_ENERGIES, from_unit, set_group
from nemsim.geometry.feature import Feature
from nemsim.geometry.profile import profile_metrics
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene
from nemsim.sim.config import SimConfig
from nemsim.sim.events import build_event_tables
from nemsim.sim.process import run_trajectory

CDS_NM = (24.0, 32.0, 40.0, 48.0, 64.0)
MASK_NM = 80.0
SEEDS = (1, 2)
TIMES_S = (5.0, 10.0)

LITERATURE = (
    "Literature. In Cl2 and Cl/Ar plasma etching of Si, narrower features etch more slowly at the same "
    "time: the etch rate falls as the aspect ratio grows (aspect-ratio-dependent etching, 'RIE lag'). "
    "Gottscho, Jurgensen and Vitkavage (J. Vac. Sci. Technol. B 10, 2133 (1992)) review the mechanisms: "
    "ion shadowing by the opening and by charging, neutral shadowing, and the Knudsen transport of neutrals "
    "down the feature (its conductance falls with the aspect ratio, so the neutral flux at the bottom of a "
    "narrow feature is smaller), plus product redeposition, and the lag is a function of the aspect ratio "
    "rather than of the size itself. Coburn and Winters (Appl. Phys. Lett. 55, 2730 "
    "(1989)) modelled the neutral-limited part by the conductance of the feature and a sticking "
    "coefficient: the neutral-limited part of the lag grows with the sticking probability. The expected "
    "sign is therefore a positive slope of depth against CD, with the neutral transport making it stronger "
    "where the neutral supply limits the etch."
)


def plural(kind: str) -> str:
    """'holes', 'trenches'."""
    return f"{kind}es" if kind.endswith("h") else f"{kind}s"


def verdict(rep: dict[str, Any]) -> str:
    """Whether the measured slopes follow the literature's sign, and where the relative lag is strongest."""
    t = str(rep["times_s"][-1])
    lo_cd, hi_cd = min(rep["cds_nm"]), max(rep["cds_nm"])
    parts, ratio = [], {}
    for row in rep["recipes"]:
        def depth(cd: float, row: dict[str, Any] = row) -> float:
            return float(np.mean([x["depth_nm"][t] for x in row["runs"] if x["cd_nm"] == cd]))
        ratio[row["recipe"]] = depth(lo_cd) / depth(hi_cd)
        sl = row["slope"][t]
        parts.append(f"{row['recipe']} {sl['mean']:+.3f} +- {sl['spread']:.3f} nm/nm "
                     f"(depth at {lo_cd:g} nm / at {hi_cd:g} nm: {ratio[row['recipe']]:.2f})")
    signs = all(row["slope"][t]["mean"] - 2 * row["slope"][t]["spread"] > 0 for row in rep["recipes"])
    strongest = min(ratio, key=lambda k: ratio[k])
    weakest = max(ratio, key=lambda k: ratio[k])
    follows = "follows" if signs else "does not clearly follow"
    return (f"Ours, at {float(t):g} s: {'; '.join(parts)}. Every slope is positive beyond twice its seed "
            f"spread: narrower {plural(rep.get('feature', 'hole'))} etch slower, so the simulator {follows} "
            "the reported ARDE sign. "
            if signs else f"Ours, at {float(t):g} s: {'; '.join(parts)}: not every slope is positive beyond "
            "twice its seed spread. ") + (
            f"The relative lag is strongest for {strongest} and weakest for {weakest}"
            + (", the neutral-limited recipe, the opposite of what neutral (Knudsen) transport alone would "
               "give; which events carry the lag is not measured here."
               if weakest == "low_neutral_flux" else "."))


def recipes() -> dict[str, np.ndarray]:
    """The named recipes, raw controls (14,) each: centre, high_ion_energy, low_neutral_flux (docstring)."""
    centre = from_unit(np.full(14, 0.5))
    return {
        "centre": centre,
        "high_ion_energy": set_group(centre, ION_ENERGIES, 1.0),
        "low_neutral_flux": set_group(centre, ("flux_cl",), -1.0),
    }


def _slope(cds: np.ndarray, depths: np.ndarray) -> float:
    """Least-squares slope of depths (n,) against cds (n,), nm / nm."""
    return float(np.polyfit(cds, depths, 1)[0])


def bench_arde(base: Scene, rules: RuleTensors, chosen: dict[str, np.ndarray],
               cds: tuple[float, ...] = CDS_NM, mask_nm: float = MASK_NM,
               config: SimConfig | None = None, kind: str = "hole") -> dict[str, Any]:
    """Simulate every (recipe, CD, seed) (module docstring); returns the JSON report."""
    cfg = config or SimConfig(domain="quarter")
    tables = build_event_tables(rules, cfg.resolved(base))
    idx = {t: int(round(t / base.snapshot_dt_s)) for t in TIMES_S}
    out = []
    for i, (name, u) in enumerate(chosen.items()):
        runs: list[dict[str, Any]] = []
        for j, cd in enumerate(cds):
            scene = Feature(kind, cd, mask_nm).apply(base)  # type: ignore[arg-type]
            si_nm = scene.si_top * scene.voxel_nm
            for s in SEEDS:
                c0 = time.process_time()
                r = run_trajectory(scene, rules, u, np.random.default_rng([s, i, j]), cfg, tables=tables)
                depth = {str(t): profile_metrics(r.states[k], scene)["etch_depth"] for t, k in idx.items()}
                runs.append({"cd_nm": cd, "seed": s, "depth_nm": depth, "cpu_s": time.process_time() - c0,
                             "through": depth[str(TIMES_S[-1])] >= si_nm - scene.voxel_nm})
        slopes = {}
        for t in TIMES_S:
            per_seed = []
            for s in SEEDS:
                rs = [x for x in runs if x["seed"] == s]
                per_seed.append(_slope(np.array([x["cd_nm"] for x in rs]),
                                       np.array([x["depth_nm"][str(t)] for x in rs])))
            slopes[str(t)] = {"per_seed": per_seed, "mean": float(np.mean(per_seed)),
                              "spread": float(abs(per_seed[0] - per_seed[1]) / 2.0)}
        out.append({"recipe": name, "controls": [float(v) for v in u], "runs": runs, "slope": slopes})
    return {"scene": base.name, "feature": kind, "mask_nm": mask_nm, "cds_nm": list(cds),
            "seeds": list(SEEDS), "domain": cfg.domain, "times_s": list(TIMES_S), "recipes": out}


def model_arde(loaded: Any, base: Scene, rep: dict[str, Any],
               config: SimConfig | None = None) -> dict[str, Any]:
    """The model's depths and ARDE slopes at the report's recipes, CDs and mask (module docstring).

    Args:
        loaded: a ``LoadedModel`` (``nemsim.inference.checkpoint.load_checkpoint``) of ``base``'s grid.
        base: the scene whose feature is replaced by each hole.
        rep: ``bench_arde``'s report (recipes with raw controls, ``cds_nm``, ``mask_nm``, ``times_s``).
        config: the simulator configuration x_0 is built with (default: the report's domain).
    Returns:
        {"recipes": [{"recipe", "depth_nm": {cd: {t: nm}}, "slope": {t: nm/nm},
        "ratio": {t: model slope / simulator slope}}], "rollout_s"}.
    """
    import torch

    from nemsim.controls import to_normalized
    from nemsim.evaluation.rollout import rollout
    from nemsim.sim.process import initial_state

    cfg = config or SimConfig(domain=rep["domain"])
    cds = [float(c) for c in rep["cds_nm"]]
    kind = rep.get("feature", "hole")
    scenes = [Feature(kind, cd, float(rep["mask_nm"])).apply(base) for cd in cds]
    x0 = torch.from_numpy(np.stack([initial_state(sc, cfg) for sc in scenes]))  # (B, 2, D, H, W)
    idx = {str(t): int(round(float(t) / base.snapshot_dt_s)) for t in rep["times_s"]}
    steps = max(idx.values())
    rows, seconds = [], 0.0
    for row in rep["recipes"]:
        u = torch.from_numpy(to_normalized(np.asarray(row["controls"], dtype=np.float64))).float()
        t0 = time.perf_counter()
        with torch.no_grad():
            u_b = u[None].expand(len(cds), -1).contiguous()  # (B, 14)
            pred = rollout(loaded.model, x0, u_b, steps)  # (B, T+1, 2, D, H, W)
        seconds += time.perf_counter() - t0
        depth = {str(cd): {t: profile_metrics(pred[b, k], sc)["etch_depth"] for t, k in idx.items()}
                 for b, (cd, sc) in enumerate(zip(cds, scenes, strict=True))}
        slope = {t: _slope(np.array(cds), np.array([depth[str(cd)][t] for cd in cds])) for t in idx}
        ratio = {t: slope[t] / row["slope"][t]["mean"] for t in idx}
        rows.append({"recipe": row["recipe"], "depth_nm": depth, "slope": slope, "ratio": ratio})
    return {"recipes": rows, "rollout_s": seconds}


def same_holes(rep: dict[str, Any], scene: str, domain: str, chosen: dict[str, np.ndarray],
               kind: str = "hole") -> bool:
    """Whether a cached report simulated this scene, feature kind, domain, CDs, mask and recipes (names and
    controls)."""
    try:
        return (rep["scene"] == scene and rep.get("feature", "hole") == kind and rep["domain"] == domain
                and list(rep["cds_nm"]) == list(CDS_NM)
                and float(rep["mask_nm"]) == MASK_NM
                and [r["recipe"] for r in rep["recipes"]] == list(chosen)
                and all(np.allclose(r["controls"], chosen[r["recipe"]]) for r in rep["recipes"]))
    except (KeyError, TypeError):
        return False


def model_markdown(rep: dict[str, Any], model: dict[str, Any], tolerance: float = 0.25) -> list[str]:
    """The model's depths and slopes beside the simulator's (Markdown lines)."""
    cds = [str(float(c)) for c in rep["cds_nm"]]
    name, cid = model.get("checkpoint", "?"), model.get("checkpoint_id", "?")
    kind = plural(rep.get("feature", "hole"))
    lines = [f"Model `{name}` (id `{cid}`): the same {kind} rolled out from x_0; "
             f"ratio = model slope / simulator slope (within +-{100 * tolerance:g} %: ok).", "",
             "| recipe | t (s) | " + " | ".join(f"CD {float(c):g}" for c in cds)
             + " | model slope | simulator slope | ratio |", "|---|---:|" + "---:|" * (len(cds) + 3)]
    sim = {r["recipe"]: r for r in rep["recipes"]}
    for row in model["recipes"]:
        for t in row["slope"]:
            ratio = row["ratio"][t]
            verdict = "ok" if abs(ratio - 1.0) <= tolerance else "off"
            lines.append(f"| {row['recipe']} | {float(t):g} | "
                         + " | ".join(f"{row['depth_nm'][c][t]:.1f}" for c in cds)
                         + f" | {row['slope'][t]:+.3f} | {sim[row['recipe']]['slope'][t]['mean']:+.3f} | "
                         f"{ratio:.2f} ({verdict}) |")
    return lines


def to_markdown(rep: dict[str, Any], command: str, cpu: str) -> str:
    t_last = str(rep["times_s"][-1])
    kind = rep.get("feature", "hole")
    lines = [f"# ARDE: {kind} depth against CD on `{rep['scene']}`", "", f"Command: `{command}`  ",
             f"CPU: {cpu}, one core", "",
             f"{plural(kind).capitalize()} of CD {', '.join(f'{c:g}' for c in rep['cds_nm'])} nm under "
             f"{rep['mask_nm']:g} nm of mask, {rep['domain']} domain, seeds {rep['seeds']} (bench/arde.py). "
             "Slope: least squares of depth on CD per seed; mean of the seeds +- half their difference.", "",
             "| recipe | t (s) | " + " | ".join(f"CD {c:g}" for c in rep["cds_nm"]) + " | slope (nm/nm) |",
             "|---|---:|" + "---:|" * (len(rep["cds_nm"]) + 1)]
    for row in rep["recipes"]:
        for t in rep["times_s"]:
            cells = []
            for cd in rep["cds_nm"]:
                ds = [x["depth_nm"][str(t)] for x in row["runs"] if x["cd_nm"] == cd]
                through = any(x["through"] for x in row["runs"] if x["cd_nm"] == cd) and str(t) == t_last
                cells.append(f"{np.mean(ds):.1f} ({ds[0]:.1f}, {ds[1]:.1f}){' *' if through else ''}")
            sl = row["slope"][str(t)]
            lines.append(f"| {row['recipe']} | {t:g} | " + " | ".join(cells)
                         + f" | {sl['mean']:+.3f} +- {sl['spread']:.3f} |")
    lines += ["", "Depths in nm: mean (seed 1, seed 2); * = reached the bottom of the Si (cut off).", "",
              LITERATURE, "", verdict(rep), ""]
    if "model" in rep:
        lines += model_markdown(rep, rep["model"]) + [""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from bench.machine import cpu_name
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.scenes import get_scene

    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(prog="python -m bench.arde", description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="small")
    ap.add_argument("--feature", default="hole", choices=("hole", "trench"),
                    help="holes (default) or trenches of the same widths")
    ap.add_argument("--domain", default=None, choices=("full", "quarter", "section"),
                    help="simulated domain (default: quarter for holes, section for trenches)")
    ap.add_argument("--recipes", default=",".join(recipes()), help="comma-separated names from recipes()")
    ap.add_argument("--out", type=Path, default=None, help="writes OUT.json and OUT.md")
    ap.add_argument("--checkpoint", type=Path, default=None,
                    help="also roll out this model at the same holes and recipes (its slopes beside the "
                         "simulator's)")
    ap.add_argument("--sim-from", type=Path, default=None,
                    help="reuse the simulator's results of this arde.json when they are for the same holes "
                         "(with --checkpoint, by default OUT.json if it exists)")
    args = ap.parse_args(argv)
    all_recipes = recipes()
    unknown = sorted(set(args.recipes.split(",")) - set(all_recipes))
    if unknown:
        ap.error(f"unknown recipes {unknown}; expected some of {sorted(all_recipes)}")
    chosen = {n: all_recipes[n] for n in args.recipes.split(",")}
    args.domain = args.domain or ("section" if args.feature == "trench" else "quarter")
    if (args.domain == "section") != (args.feature == "trench") and args.domain != "full":
        ap.error(f"--domain {args.domain} does not simulate a {args.feature}")
    base = get_scene(args.scene)
    cache = args.sim_from or (args.out.with_suffix(".json")
                              if args.out is not None and args.checkpoint is not None else None)
    cached = json.loads(cache.read_text()) if cache is not None and cache.is_file() else None
    if cached is not None and same_holes(cached, base.name, args.domain, chosen, args.feature):
        rep = {k: cached.get(k, "hole") for k in ("scene", "feature", "mask_nm", "cds_nm", "seeds", "domain",
                                                   "times_s", "recipes")}
        sys.stderr.write(f"simulator results reused from {cache}\n")
    else:
        rep = bench_arde(base, compile_rules(load_rules()), chosen, config=SimConfig(domain=args.domain),
                         kind=args.feature)
    if args.checkpoint is not None:
        from nemsim.inference.checkpoint import checkpoint_id, load_checkpoint

        loaded = load_checkpoint(args.checkpoint, scene=base.name)
        rep["model"] = {"checkpoint": str(args.checkpoint), "checkpoint_id": checkpoint_id(args.checkpoint),
                        **model_arde(loaded, base, rep, SimConfig(domain=args.domain))}
    command, cpu = " ".join(["python -m bench.arde", *argv]), cpu_name()
    write_report(args.out, to_markdown(rep, command, cpu), {"command": command, "cpu": cpu, **rep})


def write_report(out: Path | None, text: str, record: dict[str, Any],
                 stamp: tuple[str, str] | None = None) -> None:
    """Print a report's Markdown; with ``out`` also write it as OUT.md and its record as OUT.json, both
    stamped with ``stamp`` = (checkpoint path, checkpoint id) when given (``bench.stamp``)."""
    if out is not None:
        from bench.stamp import stamp_json, stamp_markdown

        out.parent.mkdir(parents=True, exist_ok=True)
        js, md = out.with_suffix(".json"), out.with_suffix(".md")
        js.write_text(json.dumps(record, indent=1))
        md.write_text(text)
        if stamp is not None:
            stamp_json(js, *stamp)
            stamp_markdown(md, *stamp)
    sys.stdout.write(text)


if __name__ == "__main__":
    main()
