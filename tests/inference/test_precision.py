"""``nemsim.inference.precision``: the default precision follows what the CPU computes in, read from
/proc/cpuinfo (``cpu_info``, replaced here by fakes of three kinds of CPU)."""

from __future__ import annotations

import pytest

from nemsim.inference import precision

ZEN3 = {"model name": "AMD EPYC 7B13", "flags": "fpu sse2 avx avx2 fma"}  # AVX2 only
SKYLAKE = {"model name": "Intel(R) Xeon(R) Gold 6148", "flags": "avx2 avx512f avx512bw avx512vl"}  # no BF16
SAPPHIRE = {"model name": "Intel(R) Xeon(R) Platinum 8480+", "flags": "avx2 avx512f avx512_bf16 amx_bf16"}


@pytest.mark.parametrize(("info", "expected", "flags"),
                         [(ZEN3, "f32", []), (SKYLAKE, "f32", []),
                          (SAPPHIRE, "bf16", ["avx512_bf16", "amx_bf16"])])  # fmt: skip
def test_auto_is_bf16_only_where_the_cpu_computes_in_it(monkeypatch, info, expected, flags):
    monkeypatch.setattr(precision, "cpu_info", lambda: info)
    assert precision.resolve_precision("auto") == expected
    expected_machine = {"cpu": info["model name"], "bf16_flags": flags, "default_precision": expected}
    assert precision.machine() == expected_machine
    # an explicit precision is kept whatever the CPU; a GPU computes in bf16
    assert [precision.resolve_precision(p) for p in ("f32", "bf16")] == ["f32", "bf16"]
    assert precision.resolve_precision("auto", "cuda") == "bf16"


def test_without_cpuinfo_the_cpu_is_named_by_its_architecture(monkeypatch):
    monkeypatch.setattr(precision, "cpu_info", lambda: {})
    assert precision.resolve_precision("auto") == "f32" and precision.cpu_name()


def test_an_unknown_precision_names_the_choices():
    with pytest.raises(ValueError, match=r"'fp16'; expected one of \['auto', 'f32', 'bf16'\]"):
        precision.resolve_precision("fp16")


def test_the_predictor_resolves_auto_and_reports_the_choice(monkeypatch, tiny_checkpoint):
    from nemsim.inference import Predictor

    monkeypatch.setattr(precision, "cpu_info", lambda: ZEN3)
    pred = Predictor.from_checkpoint(tiny_checkpoint, backend="torch", precision="auto")
    info = pred.runtime_info()
    assert pred.runtime.precision == "f32"
    assert info["precision"] == "f32" and info["precision_requested"] == "auto"
    assert info["backend"] == "torch" and info["cpu"] == "AMD EPYC 7B13" and info["bf16_flags"] == []
    monkeypatch.setattr(precision, "cpu_info", lambda: SAPPHIRE)
    pred = Predictor.from_checkpoint(tiny_checkpoint, backend="torch", precision="auto")
    assert pred.runtime.precision == "bf16"
