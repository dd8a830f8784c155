"""`nemsim sensitivity`, `inverse` and `calibrate`: what the controls do, recipes for targets, intervals."""

from __future__ import annotations

import argparse

from nemsim.cli.common import (
    Subparsers,
    UserError,
    load_for_eval,
    output_path,
    read_text_arg,
    seed_arg,
    write_json,
)


def register(sub: Subparsers) -> None:
    _add_sensitivity(sub)
    _add_inverse(sub)


def _add_sensitivity(sub: Subparsers) -> None:
    p = sub.add_parser(
        "sensitivity",
        help="rank the 14 controls by their importance for the final etch profile",
        description=(
            "Importance score I = 0.7|beta| + 0.3|rho| ([supp_protocols], eq:supp_control_importance) of "
            "each control for etch depth, top-opening width, neck width, bottom width and bowing at the "
            "final state, averaged over the quantities; printed as a ranked table with percentages. "
            "It reads only the controls and the final states, so damage elsewhere in the file goes "
            "unnoticed here: `nemsim data check` reads every state. "
            "Writes nothing unless --json is given. Example: nemsim sensitivity data/small.h5"
        ),
    )
    p.add_argument("file", metavar="FILE", help="trajectory file (.h5) written by `nemsim generate`")
    p.add_argument("--json", metavar="OUT", default=None, help="also write the full result as JSON")
    p.set_defaults(handler=_cmd_sensitivity)


def _cmd_sensitivity(args: argparse.Namespace) -> int:
    import os

    from nemsim.analysis.sensitivity import sensitivity_from_file

    if not os.path.isfile(args.file):
        raise UserError(f"no such file: {args.file}")
    try:
        result = sensitivity_from_file(args.file)
    except (OSError, KeyError, ValueError) as exc:
        raise UserError(f"{args.file}: {exc}") from exc
    print(result.table())  # noqa: T201
    if args.json:
        write_json(args.json, result.to_dict())
    return 0


def _add_inverse(sub: Subparsers) -> None:
    p = sub.add_parser(
        "inverse",
        help="recipes (controls) whose predicted profile meets target metrics, with intervals",
        description=(
            "Search the control box for recipes whose predicted profile metrics (etch depth, top width, "
            "bottom width, mask loss, bowing; any subset, each with a tolerance, in nm) meet the targets "
            "at a time step: screening of quasi-random recipes, then multi-start Adam on normalized "
            "controls through the differentiable rollout; integer controls are rounded at the end and "
            "re-evaluated. Prints K ranked recipes with predicted metrics, conformal intervals (from "
            "<checkpoint stem>.calibration.json, see `nemsim calibrate`), a distance-to-training-data "
            "flag and the search's cost; a target no recipe meets is reported as unreachable with the "
            "closest recipe and its miss. Spec (JSON): {\"targets\": {\"etch_depth\": {\"value\": 100, "
            "\"tol\": 5}, \"bottom_width\": {\"value\": 30, \"tol\": 3}}, \"step\": 100, \"fixed\": "
            "{\"angle_cl\": 5}, \"bounds\": {\"flux_cl\": [0.002, 0.01]}, \"secondary\": {\"metric\": "
            "\"mask_loss\", \"goal\": \"min\"}, \"k\": 3}. Targets lie in the scene's physical ranges (depth "
            "0 to the Si thickness, widths and bowing 0 to the domain width, mask loss 0 to the mask "
            "thickness), tolerances are at least 0.1 nm, held and bounded controls physically possible and "
            "within the scale guard (e.g. a flux at most 10^3 x its design maximum), as for a rollout; "
            "anything else exits 2 naming the key. With --refine the simulator works inside the "
            "design loop: it runs the top --verify-top recipes; if none meets every tolerance, the "
            "simulator-minus-surrogate offset at the best one shifts the targets and a local search "
            "around it (a trust region) proposes a new recipe for the simulator, for up to --rounds rounds "
            "or until --budget seconds; the top recipe is then the best simulated one (labelled as such). "
            "--verify does this by default (--no-refine: only simulate the top recipes). Example: nemsim "
            "inverse --checkpoint checkpoints/nemsim-small.pt --spec target.json --verify"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="NEMSim checkpoint .pt")
    p.add_argument("--spec", required=True, metavar="FILE.json",
                   help="the design spec (JSON file, or - for stdin); see the description")
    p.add_argument("--verify", action="store_true",
                   help="also run the simulator on the top recipes (about 2.5 s each on small) and report "
                   "achieved against target; by default inside the design loop (--refine), so the top "
                   "recipe is the best simulated one")
    p.add_argument("--refine", action=argparse.BooleanOptionalAction, default=None,
                   help="simulator-corrected design (implies --verify; see the description); default: on "
                   "with --verify (--no-refine: only simulate the top recipes)")
    p.add_argument("--verify-top", type=int, default=None, metavar="R",
                   help="recipes simulated (default 1; with --refine 2, the round-0 recipes)")
    p.add_argument("--rounds", type=int, default=None, metavar="N",
                   help="simulator-corrected rounds at most (default 2)")
    p.add_argument("--budget", type=float, default=None, metavar="S",
                   help="wall seconds of the whole design: a corrected round starts only if its estimated "
                   "cost fits (default 60)")
    p.add_argument("--sim-seed", type=seed_arg, default=1,
                   help="simulator seed of the verification runs (default 1)")
    p.add_argument("--seed", type=seed_arg, default=0, help="search seed (default 0)")
    p.add_argument("--json", dest="json_out", default=None, metavar="FILE",
                   help="write the full result as JSON to FILE (- for stdout, then no table)")
    p.set_defaults(handler=_cmd_inverse)

    p = sub.add_parser(
        "calibrate",
        help="conformal intervals of profile metrics for a checkpoint (writes <stem>.calibration.json)",
        description=(
            "Split-conformal calibration of a checkpoint's per-step profile-metric errors: roll the model "
            "out on the validation cases of a setting, take the residuals predicted - simulated per metric "
            "and step, and store the interval offsets for the nominal levels next to the checkpoint "
            "(<stem>.calibration.json; the service and `nemsim inverse` read it), with the coverage "
            "measured on the test cases and the training cases' controls (distance flag). Example: "
            "nemsim calibrate --checkpoint checkpoints/nemsim-small.pt --data data/small.h5 --splits "
            "data/splits"
        ),
    )
    p.add_argument("--checkpoint", required=True, help="checkpoint .pt")
    p.add_argument("--data", required=True, metavar="FILE.h5", help="trajectory file the checkpoint was "
                   "trained on")
    p.add_argument("--splits", default=None, metavar="DIR", help="split manifests directory (default: "
                   "<data dir>/splits, else computed)")
    p.add_argument("--setting", default="control-id", help="split setting (default control-id)")
    p.add_argument("--levels", default="0.8,0.9", help="nominal coverages, comma-separated (default 0.8,0.9)")
    p.add_argument("--max-cases", type=int, default=None, help="first N cases of each split (quick runs)")
    p.add_argument("--out", default=None, metavar="FILE.json",
                   help="output file (default: <checkpoint dir>/<stem>.calibration.json)")
    p.set_defaults(handler=_cmd_calibrate)


def _cmd_inverse(args: argparse.Namespace) -> int:
    import json

    from nemsim.analysis.inverse import (
        REFINE_WITH_VERIFY,
        check_targets,
        format_result,
        load_inverse_context,
        refine_config_from_dict,
        run_inverse,
        spec_from_dict,
    )

    _check_inverse_options(args)
    text = read_text_arg(args.spec, "--spec")
    try:
        data = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise UserError(f"--spec {args.spec}: not JSON: {exc}") from None
    try:
        spec = spec_from_dict(data)
    except ValueError as exc:
        raise UserError(f"--spec {args.spec}: {exc}") from None
    refine = None
    if args.refine or (args.refine is None and args.verify and REFINE_WITH_VERIFY):
        given = {"rounds": args.rounds, "budget_s": args.budget, "verify_top": args.verify_top}
        refine = refine_config_from_dict({k: v for k, v in given.items() if v is not None})
    top = 1 if args.verify_top is None else args.verify_top
    ctx = load_inverse_context(args.checkpoint)
    try:
        check_targets(spec.targets, ctx.scene)
    except ValueError as exc:
        raise UserError(f"--spec {args.spec}: {exc}") from None
    result = run_inverse(ctx, spec, seed=args.seed, verify=args.verify, verify_top=top,
                         sim_seed=args.sim_seed, progress=args.json_out != "-", refine=refine)
    if args.json_out == "-":
        print(json.dumps(result, indent=2))  # noqa: T201
        return 0
    print(format_result(result))  # noqa: T201
    if args.json_out:
        write_json(args.json_out, result)
        print(f"wrote {args.json_out}")  # noqa: T201
    return 0


def _check_inverse_options(args: argparse.Namespace) -> None:
    """UserError naming the first out-of-range option of `nemsim inverse` (whether or not it is used)."""
    if args.budget is not None and not args.budget >= 0:  # NaN too
        raise UserError(f"--budget must be a number of seconds >= 0, got {args.budget:g}")
    if args.rounds is not None and not 0 <= args.rounds <= 10:
        raise UserError(f"--rounds must be in 0..10, got {args.rounds}")
    if args.verify_top is not None and not 1 <= args.verify_top <= 10:
        raise UserError(f"--verify-top must be in 1..10, got {args.verify_top}")


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from nemsim.analysis.intervals import calibrate, calibration_path, format_coverage

    try:
        levels = tuple(float(v) for v in args.levels.split(","))
    except ValueError:
        raise UserError(f"--levels must be numbers in (0, 1) separated by commas, got {args.levels!r}"
                        ) from None
    if args.max_cases is not None and args.max_cases < 2:
        raise UserError(f"--max-cases must be >= 2, got {args.max_cases}")
    args.device = "cpu"
    loaded, tf, manifest = load_for_eval(args)
    cal = calibrate(loaded, tf, manifest, args.checkpoint, levels=levels, max_cases=args.max_cases,
                    progress=True)
    out = cal.write(output_path(args.out) if args.out else calibration_path(args.checkpoint))
    print(format_coverage(cal))  # noqa: T201
    print(f"wrote {out}")  # noqa: T201
    return 0
