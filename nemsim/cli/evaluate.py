"""`nemsim evaluate`, `models` and `counterfactual`: a checkpoint rolled out, scored and probed."""

from __future__ import annotations

import argparse
from pathlib import Path

from nemsim.cli.common import (
    Subparsers,
    UserError,
    add_monotone_option,
    apply_monotone,
    load_for_eval,
    run_output,
)
from nemsim.data.splits import SETTINGS

# the runtimes of nemsim.inference.runtime, "<backend>-<precision>" (BACKENDS x PRECISIONS), spelled out here
# so that building the parser does not import torch
RUNTIMES = ("torch-f32", "torch-bf16", "openvino-f32", "openvino-bf16", "cuda-f32", "cuda-bf16")


def register(sub: Subparsers) -> None:
    p = sub.add_parser(
        "evaluate",
        help="100-step autoregressive evaluation of a checkpoint ([supp_protocols])",
        description=(
            "Roll a checkpoint out autoregressively from x_0 over the full horizon on one split of a "
            "setting and print Avg RMSE, Final RMSE (normalized SDF units), the final-step Chamfer "
            "distance (voxels), the parameter count and the rollout time per trajectory. Writes a PNG "
            "figure (see --plot) and optionally the metrics as JSON and the predictions as HDF5. "
            "Example: nemsim evaluate --checkpoint runs/nemsim/best.pt --data data/small.h5 "
            "--setting control-id --json runs/nemsim/eval.json"
        ),
    )
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="checkpoint .pt (e.g. OUT/best.pt of `nemsim train`); its scene must match --data")
    p.add_argument("--data", required=True, type=Path, help="HDF5 dataset file")
    p.add_argument("--setting", default="control-id", choices=SETTINGS,
                   help="split setting whose cases are scored (default control-id)")
    p.add_argument("--split", default="test", choices=("train", "val", "test"),
                   help="which part of the setting (default test)")
    p.add_argument("--splits", type=Path,
                   help="directory of split manifests <setting>.json (default: <data dir>/splits if present, "
                   "else computed from the data file)")
    p.add_argument("--json", type=Path, help="write the metrics as JSON here")
    p.add_argument("--save-rollouts", type=Path, help="write predictions (N, T+1, 2, D, H, W) to this HDF5")
    p.add_argument("--plot", type=Path,
                   help="PNG path (default: --json with .png, else "
                   "runs/evaluate/<checkpoint dir>-<checkpoint name>_<setting>.png)")
    p.add_argument("--steps", type=int, help="rollout length in transitions (default: full horizon, 100)")
    p.add_argument("--batch-size", type=int, default=1,
                   help="trajectories rolled out together (default 1, the paper's per-trajectory timing)")
    p.add_argument("--no-cd", action="store_true", help="skip the Chamfer distance (the slowest metric)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:N")
    p.add_argument("--runtime", default="torch-f32", choices=RUNTIMES,
                   help="what runs the rollouts: torch-f32 (PyTorch, the reference; default), torch-bf16 "
                   "(CPU autocast), openvino-f32 or openvino-bf16 (the exported step graph the service runs; "
                   "falls back to torch, named in the output, when OpenVINO is missing; CPU), cuda-f32 or "
                   "cuda-bf16 (CUDA graphs, no launch overhead; with --device cuda)")
    p.add_argument("--threads", type=int, default=1,
                   help="torch and OpenVINO threads (default 1, as the benchmarks and the service)")
    add_monotone_option(p)
    p.set_defaults(handler=_cmd_evaluate)

    p = sub.add_parser(
        "models",
        help="list registered models with their trainable-parameter counts",
        description=(
            "Build every registered model (NEMSim and the baselines) for a scene with the default rules "
            "library and print its name and trainable-parameter count; the names are what "
            "`nemsim train --model` accepts. Writes nothing unless --json is given. "
            "Example: nemsim models --scene small"
        ),
    )
    p.add_argument("--scene", default="small", help="scene name: paper, small or tiny (default small)")
    p.add_argument("--json", type=Path, help='write {name: {"params": int}} here')
    p.set_defaults(handler=_cmd_models)

    p = sub.add_parser(
        "counterfactual",
        help="Cl+/Cl flux interventions vs mechanism response ([supp_mechanism_alignment])",
        description=(
            "For each case of the split, scale the Cl+ and neutral-Cl fluxes by {0.5, 1, 1.5} (eight "
            "interventions), predict one step from the case's initial state, and relate the change of "
            "each mechanism family's response (ΔM, %) to the change of Si removal (ΔR, %) with "
            "per-group Pearson correlations. Prints the table and writes counterfactual.json, "
            "counterfactual_table.csv and counterfactual.png to --out (default under runs/). "
            "Runs on the CPU. "
            "Example: nemsim counterfactual --checkpoint runs/nemsim/best.pt --data data/small.h5"
        ),
    )
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="checkpoint .pt of a NEMSim model (needs its mechanism outputs); scene must match "
                   "--data")
    p.add_argument("--data", required=True, type=Path, help="HDF5 dataset file")
    p.add_argument("--setting", default="control-id", choices=SETTINGS,
                   help="split setting whose cases are used (default control-id)")
    p.add_argument("--split", default="test", choices=("train", "val", "test"),
                   help="which part of the setting (default test)")
    p.add_argument("--splits", type=Path,
                   help="directory of split manifests <setting>.json (default: <data dir>/splits if present, "
                   "else computed from the data file)")
    p.add_argument("--out", type=Path,
                   help="output directory (default: runs/counterfactual/<checkpoint dir>-<checkpoint name>)")
    p.add_argument("--max-cases", type=int, help="analyse only the first N cases of the split (default: all)")
    p.set_defaults(handler=_cmd_counterfactual)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import torch

    from nemsim.data.dataset import TrajectoryDataset
    from nemsim.evaluation.evaluate import evaluate, plot_evaluation, write_json
    from nemsim.inference.runtime import compile_model

    if args.batch_size < 1:
        raise UserError(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    on_gpu = args.runtime.startswith("cuda-")
    if args.runtime != "torch-f32" and not on_gpu and args.device != "cpu":
        raise UserError(f"--runtime {args.runtime} runs on the CPU only; drop --device {args.device}")
    if on_gpu and not args.device.startswith("cuda"):
        raise UserError(f"--runtime {args.runtime} runs on a CUDA device; give --device cuda")
    loaded, tf, manifest = load_for_eval(args)
    apply_monotone(args, loaded.model)
    horizon = loaded.scene.n_transitions
    if args.steps is not None and not 1 <= args.steps <= horizon:
        raise UserError(f"--steps must be in [1, {horizon}] (the scene's horizon), got {args.steps}")
    cases = TrajectoryDataset(args.data, manifest, args.split)
    if len(cases) == 0:
        raise UserError(f"split {args.split!r} of setting {args.setting!r} is empty")
    torch.set_num_threads(args.threads)
    predictor = None
    if args.runtime != "torch-f32":
        backend, precision = args.runtime.split("-")
        predictor = compile_model(loaded.model, backend, precision, threads=args.threads)  # type: ignore[arg-type]
    result = evaluate(loaded.model, cases, loaded.scene, steps=args.steps, batch_size=args.batch_size,  # type: ignore[arg-type]
                      device=args.device, chamfer=not args.no_cd, rollout_path=args.save_rollouts,
                      rollout_attrs={"checkpoint": str(args.checkpoint), "setting": args.setting,
                                     "model": loaded.name, "runtime": args.runtime},
                      predictor=predictor)
    cd = "n/a" if result.cd is None else f"{result.cd:.4f}"
    print(f"{loaded.name} on {args.setting}/{args.split} ({result.n_cases} cases, {result.steps} steps, "  # noqa: T201
          f"{result.runtime})")
    if predictor is not None and predictor.fallback_reason:
        print(f"  note: {args.runtime} was asked for; {predictor.fallback_reason}")  # noqa: T201
    print(f"  Avg RMSE   {result.avg_rmse:.5f}")  # noqa: T201
    print(f"  Final RMSE {result.final_rmse:.5f}")  # noqa: T201
    print(f"  CD         {cd} voxels")  # noqa: T201
    print(f"  Params     {result.params} ({result.params / 1e6:.3f} M)")  # noqa: T201
    print(f"  Rollout    {result.rollout_seconds:.2f} s total, "  # noqa: T201
          f"{result.rollout_seconds_per_case:.3f} s per trajectory")
    extra = {"setting": args.setting, "split": args.split, "model": loaded.name,
             "checkpoint": str(args.checkpoint)}
    if args.json:
        write_json(result, args.json, extra)
    plot = args.plot or (args.json.with_suffix(".png") if args.json
                         else run_output("evaluate", args.checkpoint, f"_{args.setting}.png"))
    plot_evaluation(result, loaded.scene, plot, title=f"{loaded.name} {args.setting}")
    print(f"  figure     {plot}")  # noqa: T201
    return 0


def _cmd_models(args: argparse.Namespace) -> int:
    import json

    from nemsim.evaluation.metrics import count_params
    from nemsim.registry import available_models, build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.scenes import get_scene

    try:
        scene = get_scene(args.scene)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    rules = compile_rules(load_rules())
    table = {}
    for name in available_models():
        table[name] = {"params": int(count_params(build_model(name, scene, rules)))}
        print(f"{name:<18} {table[name]['params']:>10,d}")  # noqa: T201
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(table, indent=2))
    return 0


def _cmd_counterfactual(args: argparse.Namespace) -> int:
    import numpy as np

    from nemsim.analysis.counterfactual import analyze, format_table, write_outputs

    if args.max_cases is not None and args.max_cases < 1:
        raise UserError(f"--max-cases must be >= 1, got {args.max_cases}")
    args.device = "cpu"
    loaded, tf, manifest = load_for_eval(args)
    ids = list(manifest[args.split])[: args.max_cases]
    if not ids:
        raise UserError(f"split {args.split!r} of setting {args.setting!r} is empty")
    row_of = {int(c): r for r, c in enumerate(np.asarray(tf.case_ids))}
    raw = np.asarray(tf.controls_raw)
    cases = [(int(c), np.asarray(tf.states[row_of[int(c)], 0]), raw[row_of[int(c)]]) for c in ids]
    result = analyze(loaded.model, cases)
    out = args.out or run_output("counterfactual", args.checkpoint)
    paths = write_outputs(result, out)
    print(format_table(result))  # noqa: T201
    print(f"wrote {paths['json']}, {paths['csv']}, {paths['png']}")  # noqa: T201
    return 0


# ==== section: metrics, sensitivity ============================================
