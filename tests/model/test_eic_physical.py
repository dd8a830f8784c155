"""EIC and RuleFeat under ``kinetics="physical"``: the rule side responds to energy and angle; the option
changes no parameter, so state dicts load under either kinetics."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nemsim.baselines.rulefeat import RuleFeat
from nemsim.controls import CONTROL_INDEX, HIGH, IS_LOG, LOW, to_normalized
from nemsim.inference.checkpoint import load_checkpoint, save_checkpoint
from nemsim.model import NEMSim, NEMSimConfig
from nemsim.registry import build_model
from nemsim.rules import kinetics
from nemsim.scenes import TINY

ION_EVENTS = list(range(6, 22))


def recipes(name_group: tuple[str, ...], values) -> torch.Tensor:
    """(N, 14) float32 normalized: the box's median recipe with the group's controls at each value."""
    raw = np.tile(np.where(IS_LOG, np.sqrt(LOW * HIGH), 0.5 * (LOW + HIGH)), (len(values), 1))
    for name in name_group:
        raw[:, CONTROL_INDEX[name]] = values
    return torch.from_numpy(to_normalized(raw)).float()


@pytest.fixture(scope="module")
def models(rules):
    out = {}
    for kin in ("paper", "physical"):
        torch.manual_seed(0)
        out[kin] = NEMSim(rules, NEMSimConfig(kinetics=kin)).eval()
    return out


def intensities(model, u: torch.Tensor) -> torch.Tensor:
    x = torch.zeros(u.shape[0], *TINY.state_shape)
    with torch.no_grad():
        return model(x, u, return_aux=True)[1]["lambda"]  # (N, E)


def test_eic_at_init_is_the_physical_formula(models, rules):
    u = recipes(("energy_mean_ar_plus",), [160.0, 330.0, 500.0])
    lam = intensities(models["physical"], u)
    torch.testing.assert_close(lam, kinetics.formula_intensities(u, rules, "physical"))
    assert not torch.allclose(lam, intensities(models["paper"], u))


def test_eic_responds_to_energy_and_angle(models):
    ion_energies = ("energy_mean_cl_plus", "energy_mean_cl2_plus", "energy_mean_ar_plus")
    energy = recipes(ion_energies, [160.0, 330.0, 500.0])
    angle = recipes(("angle_cl_plus", "angle_cl2_plus", "angle_ar_plus"), [50.0, 3000.0])
    lam_e = intensities(models["physical"], energy)[:, ION_EVENTS]
    assert (lam_e.diff(dim=0) > 0).all() and (lam_e[-1] / lam_e[0] > 1.3).all()
    paper_e = intensities(models["paper"], energy)[:, ION_EVENTS]
    assert ((paper_e[-1] / paper_e[0] - 1).abs() < 0.03).all()  # saturated
    lam_a = intensities(models["physical"], angle)
    sputter = [e for e in ION_EVENTS if int(models["physical"].rules.angle_kind[e]) == 1]
    assert (lam_a[0, sputter] / lam_a[1, sputter] > 1.07).all()


def test_state_dicts_interchangeable(models, rules):
    """No parameter or buffer depends on the option: a paper checkpoint loads into a physical model."""
    sd = models["paper"].state_dict()
    assert sd.keys() == models["physical"].state_dict().keys()
    gated = NEMSim(rules, NEMSimConfig(kinetics="physical", flux_gate=True))
    gated.load_state_dict(sd, strict=True)
    assert NEMSimConfig.from_dict({}).kinetics == "paper" and NEMSimConfig.from_dict({}).flux_gate is False


def test_unknown_kinetics_names_the_choices(rules):
    with pytest.raises(ValueError, match="unknown kinetics 'phys'.*paper.*physical"):
        NEMSim(rules, NEMSimConfig.from_dict({"kinetics": "phys"}))


def test_rulefeat_physical(rules):
    u = recipes(("energy_mean_cl_plus",), [160.0, 500.0])
    feat = RuleFeat(rules, "physical")(u)  # (2, E (1 + M))
    E = rules.n_events
    torch.testing.assert_close(feat[:, :E], kinetics.formula_intensities(u, rules, "physical"))
    assert feat[1, 6] / feat[0, 6] > 1.3  # Cl+ on Si follows the energy
    torch.testing.assert_close(RuleFeat(rules)(u)[:, :E], kinetics.formula_intensities(u, rules, "paper"))


def test_config_keys_round_trip_through_a_checkpoint(rules, tmp_path):
    """The training recipe's ``model: {kinetics: physical, flux_gate: true}`` reaches the rebuilt model."""
    overrides = {"kinetics": "physical", "flux_gate": True}
    model = build_model("nemsim", TINY, rules, overrides)
    assert model.eic.kinetics == "physical" and model.config.flux_gate
    path = save_checkpoint(tmp_path / "m.pt", model, model_name="nemsim", model_config=model.config.to_dict(),
                           scene=TINY, rules=rules, summary={}, metrics={})  # fmt: skip
    loaded = load_checkpoint(path).model
    assert loaded.eic.kinetics == "physical" and loaded.config.flux_gate
    u = recipes(("energy_mean_ar_plus",), [200.0, 400.0])
    x = torch.zeros(2, *TINY.state_shape)
    with torch.no_grad():
        torch.testing.assert_close(loaded(x, u), model.eval()(x, u))
