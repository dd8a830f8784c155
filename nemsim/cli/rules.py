"""`nemsim rules check|compile`: the Event Rules Library (rules/*.yaml) validated and compiled."""

from __future__ import annotations

import argparse

from nemsim.cli.common import Subparsers, output_path


def register(sub: Subparsers) -> None:
    p = sub.add_parser(
        "rules",
        help="validate and compile an Event Rules Library (rules/*.yaml)",
        description=(
            "Tools for the Event Rules Library, the YAML file of surface events (projectile, target, "
            "probability and yield models, products) that the simulator and the models read. "
            "`check` validates a file and prints its events; `compile` writes the fixed tensors. "
            "Example: nemsim rules check rules/cl_si.yaml"
        ),
    )
    rsub = p.add_subparsers(dest="rules_command", metavar="ACTION")
    rsub.required = True
    c = rsub.add_parser(
        "check",
        help="validate a rules file and print a summary table",
        description=(
            "Validate a rules YAML file against the schema and the species/controls vocabulary, then "
            "print one row per event (family, projectile, target, probability and yield model, products "
            "or deposition pool) and the library's sha256. The family is physical, chemical or coupled; "
            "the YAML spells the coupled family's group label `both`, as the paper's schema does "
            "([eq:supp_group_mapping]). Writes nothing. Exit code 0 if the file is valid, 2 (with the "
            "first error, and for a YAML syntax error its line, on stderr) if not. "
            "Example: nemsim rules check"
        ),
    )
    c.add_argument("path", nargs="?", default=None, help="rules YAML (default: the repo's rules/cl_si.yaml)")
    c.set_defaults(handler=_cmd_rules_check)
    k = rsub.add_parser(
        "compile",
        help="compile a rules file to fixed tensors (.npz)",
        description=(
            "Validate a rules YAML file and compile it to the fixed tensors the simulator and the models "
            "use; write them as one NumPy .npz file (arrays R, phi, psi, alpha0, r_mech, w_src, w_sink, "
            "s_dep, plus the event names and the library sha256) and print their shapes. "
            "Example: nemsim rules compile --out rules.npz"
        ),
    )
    k.add_argument("path", nargs="?", default=None, help="rules YAML (default: the repo's rules/cl_si.yaml)")
    k.add_argument("--out", required=True, metavar="FILE.npz", help="output .npz (arrays R, phi, psi, alpha0,"
                   " r_mech, w_src, w_sink, s_dep, plus names and sha256)")  # fmt: skip
    k.set_defaults(handler=_cmd_rules_compile)


def _load_compiled_rules(path: str | None):
    from nemsim.rules import compile_rules, load_rules

    spec = load_rules(path)  # RulesError (a ValueError) names the event and field; main() prints it
    return spec, compile_rules(spec)


def _cmd_rules_check(args: argparse.Namespace) -> int:
    from nemsim.rules.vocab import FAMILIES

    spec, rt = _load_compiled_rules(args.path)
    head = f"{'#':>3}  {'name':<28} {'family':<9} {'proj':<6} {'target':<7} {'prob':<9} {'yield':<9} relation"
    lines = [head, "-" * len(head)]
    for e, ev in enumerate(spec.events):
        if ev.is_primary:
            rel = ", ".join(f"+{p.species}({p.coeff})" for p in ev.products) or "-"
        else:
            rel = f"<-pool {ev.dep_params['species']} p_stick={ev.dep_params['p_stick']}"  # type: ignore[index]
        lines.append(
            f"{e + 1:>3}  {ev.name:<28} {FAMILIES[rt.group[e]]:<9} {ev.projectile:<6} {ev.target:<7} "
            f"{ev.prob_model or '-':<9} {ev.yield_model or '-':<9} {rel}"
        )
    n_primary = int(rt.is_primary.sum())
    lines.append(
        f"{rt.n_events} events ({n_primary} primary, {rt.n_events - n_primary} product-mediated); "
        f"sha256 {rt.sha256}"
    )
    print("\n".join(lines))  # noqa: T201
    return 0


def _cmd_rules_compile(args: argparse.Namespace) -> int:
    import numpy as np

    _, rt = _load_compiled_rules(args.path)
    arrays = rt.to_npz_dict()
    np.savez(output_path(args.out), **arrays, names=rt.names, sha256=np.array(rt.sha256))
    shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in arrays.items())
    print(f"wrote {args.out}: {shapes}; sha256 {rt.sha256}")  # noqa: T201
    return 0

