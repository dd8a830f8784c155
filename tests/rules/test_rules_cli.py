"""`nemsim rules check` and `nemsim rules compile`."""

from __future__ import annotations

import numpy as np

from nemsim.cli import main


def test_check_default(capsys):
    assert main(["rules", "check"]) == 0
    out = capsys.readouterr().out
    assert "37 events (22 primary, 15 product-mediated)" in out
    assert "Cl_on_Si_to_SiCl" in out and "SiCl3_dep_on_Resist" in out


def test_check_bad_input(tmp_path, rules_text, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(rules_text.replace("flux_key: flux_ar_plus", "flux_key: flux_xe_plus", 1))
    assert main(["rules", "check", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "event 'Arp_on_Si_phys'" in err and "field 'flux_key'" in err
    assert main(["rules", "check", str(tmp_path / "missing.yaml")]) == 2


def test_compile(tmp_path, tensors, capsys):
    out = tmp_path / "rules.npz"
    assert main(["rules", "compile", "--out", str(out)]) == 0
    with np.load(out) as data:
        for key in ("R", "phi", "psi", "alpha0", "r_mech", "w_src", "w_sink", "s_dep"):
            np.testing.assert_array_equal(data[key], getattr(tensors, key))
        assert str(data["sha256"]) == tensors.sha256
