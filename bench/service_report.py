"""The targets and the Markdown page of a `nemsim bench service --probes` report
(`bench.service_probes.run_probes`)."""

from __future__ import annotations

from typing import Any


def _f(v: Any, spec: str = ".1f") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool) or isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def _lat(d: dict[str, Any] | None) -> str:
    if not d or not d.get("n"):
        return "none answered"
    return f"p50 {d['p50_ms']:.0f} ms, p95 {d['p95_ms']:.0f} ms (n = {d['n']})"


def probes_markdown(report: dict[str, Any]) -> str:
    """The report as a page: the targets table, then each probe's figures."""
    p, cfg = report["probes"], report["config"]
    out = [
        "# Service probes",
        "",
        f"`nemsim bench service --probes` on `{report['checkpoint']}` (checkpoint id "
        f"`{report['checkpoint_id']}`), {report['server']}. CPU: {report['cpu']}."
        + (f" {report['note']}" if report.get("note") else ""),
        "",
        f"Rollouts of {cfg['steps']} steps; uncached ones with distinct controls drawn uniformly in the "
        f"design "
        f"box (seed {cfg['seed']}). The whole run took {report['wall_s'] / 60:.1f} min; the server was ready "
        f"{report['ready_s']:.0f} s after its start. The machine's 1-minute load average was "
        f"{report['load_average_1min']['start']:.1f} at the start and "
        f"{report['load_average_1min']['end']:.1f} at the end (this run's own processes included).",
        "",
        "| target | measured | wanted | met |",
        "|---|---:|---:|:---:|",
    ]
    for t in report["targets"]:
        met = {True: "yes", False: "**no**", None: "not measured"}[t["met"]]
        out.append(f"| {t['what']} | {_f(t['measured'], '.2f')} | {t['target']} | {met} |")
    out += ["", "## Figures", ""]
    errors = {k: v["error"] for k, v in p.items() if isinstance(v, dict) and "error" in v}
    for name, err in errors.items():
        out.append(f"- **{name} failed**: {err}")
    q = p.get("quiet", {})
    out.append(
        f"- **quiet** (one client, sequential): uncached {_lat(q.get('uncached'))}; cached "
        f"{_lat(q.get('cached'))}."
    )
    ld = p.get("load", {})
    if "routes" in ld:
        routes = "; ".join(f"{k} {_lat(v)}, status {v['status']}" for k, v in ld["routes"].items())
        out.append(
            f"- **load** ({ld['clients']} clients, each its own address, {ld['requests']} requests in "
            f"{ld['wall_s']:.1f} s): {routes}. 5xx {ld['server_errors_5xx']}, 429 {ld['rate_limited_429']}, "
            f"transport failures {ld['transport_failures']}, 404 on mesh links of the last 32 rollouts "
            f"{ld['mesh_404_last_32']}, repeats not served from the cache "
            f"{ld['repeats_not_served_from_cache']}."
        )
    b = p.get("burst", {})
    if "waves" in b:
        slowest = max(w["slowest_ms"] for w in b["waves"])
        out.append(
            f"- **burst** ({len(b['waves'])} waves of {b['clients']} clients released at once; uncached, "
            f"cached, mesh and /health in turn): status {b['status']}; 5xx {b['server_errors_5xx']} "
            f"(503 queue "
            f"full: {b['queue_full_503']}); slowest answer {slowest:.0f} ms."
        )
    s = p.get("slowloris", {})
    if "sockets" in s:
        cut = s["cut_s"] or {}
        out.append(
            f"- **slowloris** ({s['sockets']} sockets from one address, one header byte per "
            f"{s['byte_interval_s']:g} s): {s['dropped_at_once']} cut within 1 s, beyond the per-client "
            f"connection cap ({s['at_once']['answered_503']} answered 503 + Retry-After, "
            f"{s['at_once']['closed']} closed to make room for newer ones, {s['at_once']['reset']} reset); "
            f"{s['held_then_cut']} held then cut ({s['answered_408_then_closed']} with a 408) after "
            f"{_f(cut.get('min'))}-{_f(cut.get('max'))} s (median {_f(cut.get('p50'))} s); still open at the "
            f"{s['cap_s']:g} s cap: {s['still_open_at_cap']}; server alive: {s['server_alive']}; the other "
            f"client's /health: {_lat(s['other_client']['health'])}, failures "
            f"{s['other_client']['failures']}."
        )
    si = p.get("silent_sockets", {})
    if "sockets" in si:
        oc = si["other_client"]
        out.append(
            f"- **{si['sockets']} silent sockets** from 127.0.0.1 for {si['seconds']:g} s (each one closed "
            f"reopened every {si['reopen_s']:g} s: {si['reconnects']} reconnects; sockets held, median "
            f"{_f(si['sockets_still_open_per_second_p50'], '.0f')}), another client at "
            f"{si['other_client_source']} (a new connection per request): /health {_lat(oc['health'])}; "
            f"uncached rollouts {_lat(oc['rollout'])} (the same client just before: p50 "
            f"{_f(si['reference_rollout_p50_ms'], '.0f')} ms); failures {oc['failures']}."
        )
    fz = p.get("fuzz", {})
    if "calls" in fz:
        out.append(
            f"- **fuzz** ({fz['calls']} calls, seed {fz['seed']}, {fz['workers']} threads, "
            f"{fz['wall_s']:.0f} s; "
            f"{fz['guard_cases']} out-of-guard cases): status {fz['status']}; 5xx {fz['server_errors_5xx']}; "
            f"accepted out-of-guard {fz['out_of_guard_accepted']}, malformed {fz['malformed_accepted']}; "
            f"valid bodies refused {fz['valid_refused']}; error bodies not JSON "
            f"{fz['error_bodies_not_json']}, "
            f"showing a traceback or path {fz['error_bodies_leaking']}; 429 {fz['rate_limited_429']}; jobs "
            f"accepted and cancelled {fz['jobs_created_and_cancelled']}."
        )
    out += _job_lines(report)
    return "\n".join(out) + "\n"


def _job_lines(report: dict[str, Any]) -> list[str]:
    """The figures of the job, memory, SIGTERM and kill -9 probes."""
    p, out = report["probes"], []
    d = p.get("design_job", {})
    if "status" in d:
        rss = d["server_rss_mib"]
        out.append(
            f"- **design job** (targets {d['targets']} at step {d['step']}, the default search): "
            f"{d['status']} after {d['wall_s']:.0f} s ({d['recipes']} recipes); job child processes "
            f"{d['job_children']}, nice {d['job_child_nice']}, peak RSS {d['job_child_peak_rss_mib']:.0f} "
            f"MiB; the server's RSS {rss['before']:.0f} MiB just before, at most "
            f"{rss['max_while_running']:.0f} MiB while it ran, {rss['after']:.0f} MiB after; its peak "
            f"{d['server_peak_rss_mib']['before']:.0f} MiB before, {d['server_peak_rss_mib']['after']:.0f} "
            "MiB after."
        )
    j = p.get("job_beside_rollouts", {})
    if "rollouts_during_job" in j:
        out.append(
            f"- **simulator job** ({j['job_flux_scale']:g}x the design-centre fluxes) beside sequential "
            f"uncached rollouts: just before {_lat(j['rollouts_before'])}; while the job's child ran "
            f"{_lat(j['rollouts_during_job'])} (ratio {_f(j['p50_ratio_to_just_before'], '.2f')}); failures "
            f"{j['rollout_failures']}; nice of the job's child {j['job_child_nice']}, of the server "
            f"{j['server_nice']}; scheduler autogroup of the child {j.get('job_child_autogroup')}, of the "
            f"server {j.get('server_autogroup')!r} (with autogroups on, a nice value counts only within its "
            "own session's group)."
        )
    m = p.get("memory", {})
    if m:
        out.append(
            f"- **memory** of the server after every probe above: RSS {m['rss_mib']:.0f} MiB, peak "
            f"(VmHWM) {m['peak_rss_mib']:.0f} MiB; budget {m['budget']}; "
            f"{report['rss_mib_when_ready']:.0f} MiB when ready; after each probe (RSS / peak, MiB): "
            + ", ".join(
                f"{k} {v['server_memory_mib_after']['rss']:.0f} / {v['server_memory_mib_after']['peak']:.0f}"
                for k, v in p.items()
                if isinstance(v, dict) and "server_memory_mib_after" in v
            )
            + "."
        )
    st = p.get("sigterm", {})
    if "exit_status" in st:
        out.append(
            f"- **SIGTERM** with {st['children_before']} job child running and "
            f"{st['job_folders_before']} job "
            f"folder: exit status {st['exit_status']} after {st['exit_s']:.1f} s (shutdown completed: "
            f"{st['graceful_shutdown']}; uvicorn re-raises the signal after it); children left "
            f"{st['children_left']}, job folders left {st['job_folders_left']}."
        )
    k9 = p.get("kill9_restart", {})
    if "exit_status" in k9:
        out.append(
            f"- **kill -9** with {k9['children_before_kill']} job child running: child gone "
            f"{_f(k9['child_gone_after_kill_s'])} s after the kill; job folders the dead server left: "
            f"{k9['job_folders_left_by_the_killed_server']}; after a restart on the same folder (ready in "
            f"{k9['restart_ready_s']:.0f} s): {k9['job_folders_after_restart']} folders, "
            f"{k9['children_after_restart']} children."
        )
    return out


def _get(d: dict[str, Any], *path: str) -> Any:
    for k in path:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _ratio(a: Any, b: Any) -> float | None:
    return a / b if isinstance(a, int | float) and isinstance(b, int | float) and b > 0 else None


def targets(report: dict[str, Any], rss_budget_bytes: int) -> list[dict[str, Any]]:
    """(what, measured, target, met) of each target of a `run_probes` report."""
    p, silent = report["probes"], f"{report['config']['silent_sockets']} silent sockets"
    quiet_p50 = _get(p, "quiet", "uncached", "p50_ms")
    rows: list[tuple[str, Any, str, Any]] = [
        ("fuzz calls", _get(p, "fuzz", "calls"), ">= 10000", lambda v: v >= 10_000),
        ("fuzz: answers >= 500", _get(p, "fuzz", "server_errors_5xx"), "0", lambda v: v == 0),
        (
            "fuzz: out-of-guard requests accepted",
            _get(p, "fuzz", "out_of_guard_accepted"),
            "0",
            lambda v: v == 0,
        ),
        ("fuzz: malformed requests accepted", _get(p, "fuzz", "malformed_accepted"), "0", lambda v: v == 0),
        ("load: answers >= 500", _get(p, "load", "server_errors_5xx"), "0", lambda v: v == 0),
        (
            "load: 404 on mesh links of the last 32 rollouts",
            _get(p, "load", "mesh_404_last_32"),
            "0",
            lambda v: v == 0,
        ),
        (
            "burst: answers >= 500 (503 = queue full)",
            _get(p, "burst", "server_errors_5xx"),
            "0",
            lambda v: v == 0,
        ),
        (
            "slowloris: other client's /health failures",
            _get(p, "slowloris", "other_client", "failures"),
            "0",
            lambda v: v == 0,
        ),
        (
            f"{silent}: other client's failures",
            _get(p, "silent_sockets", "other_client", "failures"),
            "0",
            lambda v: v == 0,
        ),
        (
            f"{silent}: other client's rollout p50 / quiet p50",
            _ratio(_get(p, "silent_sockets", "other_client", "rollout", "p50_ms"), quiet_p50),
            "<= 2",
            lambda v: v <= 2,
        ),
        (
            "simulator job running: rollout p50 / quiet p50",
            _ratio(_get(p, "job_beside_rollouts", "rollouts_during_job", "p50_ms"), quiet_p50),
            "<= 1.5",
            lambda v: v <= 1.5,
        ),
        (
            "simulator job running: rollout p50 / p50 just before the job",
            _get(p, "job_beside_rollouts", "p50_ratio_to_just_before"),
            "<= 1.5",
            lambda v: v <= 1.5,
        ),
        ("SIGTERM: children left", _get(p, "sigterm", "children_left"), "0", lambda v: v == 0),
        ("SIGTERM: job folders left", _get(p, "sigterm", "job_folders_left"), "0", lambda v: v == 0),
        (
            "kill -9: children left",
            _get(p, "kill9_restart", "children_left_after_kill"),
            "0",
            lambda v: v == 0,
        ),
        (
            "kill -9 + restart: job folders left",
            _get(p, "kill9_restart", "job_folders_after_restart"),
            "0",
            lambda v: v == 0,
        ),
        (
            "peak RSS, MiB",
            _get(p, "memory", "peak_rss_mib"),
            f"<= {rss_budget_bytes / 2**20:.0f}",
            lambda v: v * 2**20 <= rss_budget_bytes,
        ),
    ]
    return [
        {"what": w, "measured": v, "target": t, "met": None if v is None else bool(ok(v))}
        for w, v, t, ok in rows
    ]
