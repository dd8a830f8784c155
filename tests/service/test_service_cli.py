"""`nemsim serve` and `nemsim bench service` command-line handling."""

from __future__ import annotations

import json

import pytest

from nemsim.cli import build_parser, main


def test_serve_flags_parse():
    args = build_parser().parse_args(
        ["serve", "--checkpoint", "x.pt", "--host", "0.0.0.0", "--port", "9000", "--workers", "2"]
    )
    assert (args.checkpoint, args.host, args.port, args.workers) == ("x.pt", "0.0.0.0", 9000, 2)


def test_serve_missing_checkpoint_exit_2(tmp_path, capsys):
    assert main(["serve", "--checkpoint", str(tmp_path / "nope.pt")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_bench_service(tiny_checkpoint, tmp_path, capsys):
    out = tmp_path / "bench.json"
    code = main(
        [
            "bench",
            "service",
            "--checkpoint",
            str(tiny_checkpoint),
            "--steps",
            "2",
            "-n",
            "2",
            "--cached-requests",
            "120",  # more than the default rate-limit burst: the benchmark runs without the limit
            "--sim-cases",
            "1",
            "--json",
            str(out),
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "uncached: p50" in text and "cached:" in text
    report = json.loads(out.read_text())
    assert report["uncached"]["n"] == 2 and report["cached"]["n"] == 120
    u = report["uncached"]
    assert 0 < u["outside_rollout_p50_ms"] <= u["p50_ms"]  # per request 0 < wall - rollout <= wall
    assert report["cached"]["p50_ms"] < report["uncached"]["p50_ms"] * 10
    sim = report["simulator"]  # the full-domain simulator on the first uncached recipe, in the same run
    assert sim["n_cases"] == 1 and sim["median"]["wall_s"] > 0
    assert report["simulator_speedup"] == pytest.approx(sim["median"]["wall_s"] / (u["p50_ms"] / 1e3))
    assert "full-domain simulator (n=1)" in text
    too_many = ["bench", "service", "--checkpoint", str(tiny_checkpoint), "-n", "2", "--sim-cases", "3"]
    assert main(too_many) == 2


def test_bench_service_load(tiny_checkpoint, tmp_path, capsys):
    """Load mode: a real server, a few clients for a moment; every route answered, no errors."""
    out = tmp_path / "load.json"
    code = main(
        ["bench", "service", "--checkpoint", str(tiny_checkpoint), "--steps", "2", "--clients", "2",
         "--seconds", "2", "--json", str(out)]
    )
    assert code == 0
    report = json.loads(out.read_text())
    assert report["errors"] == 0 and report["server"]["rss_mb"] > 0
    assert report["routes"]["GET /health"]["n"] > 0 and report["routes"]["POST /rollout cached"]["n"] > 0
    assert "p99 ms" in capsys.readouterr().out


def test_serve_port_from_env(monkeypatch, capsys):
    monkeypatch.setenv("NEMSIM_PORT", "not-a-port")
    assert main(["serve"]) == 2
    assert "NEMSIM_PORT" in capsys.readouterr().err


def test_bad_setting_exit_2(monkeypatch, tiny_checkpoint, capsys):
    # `serve` writes these two into the environment; monkeypatch restores them afterwards
    monkeypatch.setenv("NEMSIM_CHECKPOINT", str(tiny_checkpoint))
    monkeypatch.setenv("NEMSIM_EXIT_ON_LOAD_FAILURE", "0")
    monkeypatch.setenv("NEMSIM_API_KEYS", "short")
    assert main(["serve", "--checkpoint", str(tiny_checkpoint)]) == 2
    assert "at least 16" in capsys.readouterr().err
