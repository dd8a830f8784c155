"""A readable table of an inverse-design result (``nemsim inverse``'s output)."""

from __future__ import annotations

from typing import Any

from nemsim.analysis.inverse.verify import VERDICTS
from nemsim.controls import CONTROL_SPECS, control_index


def format_result(result: dict[str, Any]) -> str:
    """A readable table of a design result."""
    lines = [
        f"{result['status'].upper()}: {result['message']}",
        f"targets at step {result['step']} ({result['time_s']:g} s); model {result['model_id']}",
        "",
    ]
    names = list(result["recipes"][0]["targets"]) if result["recipes"] else []
    level = None
    if result["recipes"] and result["recipes"][0].get("intervals"):
        level = (
            "0.9"
            if "0.9" in result["recipes"][0]["intervals"]
            else next(iter(result["recipes"][0]["intervals"]))
        )
    head = ["rank"] + [f"{n} (target)" for n in names] + ["objective", "data", "verdict"]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---:|" * len(head))
    for r in result["recipes"]:
        cells = [str(r["rank"])]
        for n in names:
            t = r["targets"][n]
            iv = ""
            if level is not None:
                lo, hi = r["intervals"][level][n]
                iv = f" [{_f(lo)}, {_f(hi)}]"
            value, met = f"{t['value']:.1f}{iv}", t["met"]
            if "simulated_targets" in r:  # simulated: the simulator's value decides
                st = r["simulated_targets"][n]
                value, met = f"{value} / sim {st['value']:.1f}", st["met"]
            cells.append(f"{value} ({t['target']:g}±{t['tol']:g}){'' if met else ' MISS'}")
        cells += [f"{r['objective']:.3g}", r["training_data"]["flag"], _verdict(r, level)]
        lines.append("| " + " | ".join(cells) + " |")
    if level is not None:
        lines.append(f"(brackets: {100 * float(level):.0f} % conformal interval, nm)")
    if any("simulated_targets" in r for r in result["recipes"]):
        lines.append("(predicted / sim: the surrogate's prediction, the simulator's run of the recipe; nm)")
    lines.append("")
    for r in result["recipes"]:
        ctl = ", ".join(f"{k}={_ctl(k, v)}" for k, v in r["controls"].items())
        lines.append(f"recipe {r['rank']}: {ctl}")
    c = result["cost"]
    sims = ""
    if "simulator_runs" in c:
        sims = f", {c['simulator_runs']} simulator runs ({c['simulator_wall_s']:.1f} s)"
    lines.append(
        f"cost: {c['rollouts']} rollouts ({c['forward_rollouts']} forward, {c['gradient_rollouts']} "
        f"with gradients; {c['method']}){sims}, {c['wall_s']:.1f} s wall, {c['cpu_s']:.1f} s CPU"
    )
    ref = result.get("refinement")
    if ref:
        lines.append(
            f"simulator-corrected design: surrogate search {ref['surrogate_status']}; "
            f"stopped: {ref['stopped']}"
        )
        lines += [_round_line(rd) for rd in ref["rounds"]]
    ver = result.get("verification")
    if ver:
        for v in ver["recipes"]:
            parts = ", ".join(
                f"{k} {t['value']:.1f} ({'ok' if t['met'] else 'MISS'})" for k, t in v["targets"].items()
            )
            which = f"round {v['round']} recipe" if "round" in v else f"recipe {v['rank']}"
            lines.append(
                f"simulator (seed {ver['seed']}), {which}: {'MET' if v['met'] else 'NOT MET'}: {parts}"
            )
        for why in ver.get("skipped", []):
            lines.append(f"simulator skipped {why}")
    return "\n".join(lines)


def _round_line(rd: dict[str, Any]) -> str:
    """One simulator-corrected round: the offset it searched with, then predicted -> simulated metrics."""
    line = f"  round {rd['round']}: "
    if rd["round"] > 0:
        line += "offset " + ", ".join(f"{k} {v:+.1f}" for k, v in rd["offset"].items()) + "; "
    runs = []
    for s in rd["simulated"]:
        pairs = ", ".join(f"{k} {s['predicted'][k]:.1f} -> {s['simulated'][k]:.1f}" for k in s["predicted"])
        verdict = " MET" if s["met"] else f" (miss {', '.join(s['missed'])})"
        runs.append(f"predicted -> simulated {pairs}{verdict}")
    return line + ("; ".join(runs) or "nothing simulated")


def _verdict(r: dict[str, Any], level: str | None) -> str:
    """The recipe's verdict (``label_recipes``); a prediction whose interval is wider than a tolerance
    says so."""
    text = VERDICTS[r["verdict"]]
    if r["verdict"] == "predicted" and level is not None and not r["intervals_within_tolerance"][level]:
        text += f"; its {100 * float(level):.0f} % interval is wider than a tolerance"
    return text


def _f(v: float | None) -> str:
    return "-inf/inf" if v is None else f"{v:.1f}"


def _ctl(name: str, v: float) -> str:
    spec = CONTROL_SPECS[control_index(name)]
    return f"{int(v)}" if spec.kind == "int" else f"{v:.4g}"
