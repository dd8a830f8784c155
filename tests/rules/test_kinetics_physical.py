"""The "physical" kinetics ([supp_kinetic_models] on physical eV and incidence cosines): the simulator's own
laws, values by hand from rules/cl_si.yaml, responses across the design box, gradients; the torch-free
simulator path."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from nemsim.controls import CONTROL_INDEX, HIGH, IS_LOG, LOW, to_normalized
from nemsim.rules import kinetics as K
from nemsim.rules import laws
from nemsim.sim.kernels import unsaturated_factor

E7, E8, E9 = 6, 7, 8  # Cl+ on Si (P law, Yamamura), Cl+ on SiCl (P), Cl+ on SiCl (C law, const yield)
ION_EVENTS = range(6, 22)
ENERGY_MEANS = ("energy_mean_cl_plus", "energy_mean_cl2_plus", "energy_mean_ar_plus")
ION_ANGLES = ("angle_cl_plus", "angle_cl2_plus", "angle_ar_plus")


def median_raw() -> np.ndarray:
    """(14,) the design box's median recipe: geometric mean of the flux bounds, midpoint otherwise."""
    med = np.where(IS_LOG, np.sqrt(LOW * HIGH), 0.5 * (LOW + HIGH))
    med[4:8] = np.round(med[4:8])
    return med


def sweep(name_group: tuple[str, ...], values) -> torch.Tensor:
    """(N, 14) float64 normalized controls: the median recipe with every control of the group at v."""
    raw = np.tile(median_raw(), (len(values), 1))
    for name in name_group:
        raw[:, CONTROL_INDEX[name]] = values
    return torch.from_numpy(to_normalized(raw))


def event_laws(t, sel: slice) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(prob_model, prob_params, angle_kind) of the selected events as tensors."""
    pm, pp, ak = t.prob_model[sel], t.prob_params[sel], t.angle_kind[sel]
    return torch.from_numpy(pm), torch.from_numpy(pp), torch.from_numpy(ak)


def sim_prob(t, e: int, energy: float, cos: float) -> float:
    """The simulator's probability: ``laws.prob_physical`` times ``kernels.unsaturated_factor``."""
    p = laws.prob_physical(t.prob_model[e], t.prob_params[e], t.angle_kind[e], energy, cos)
    return p * unsaturated_factor(t.prob_model[e], t.prob_params[e], energy)


@pytest.mark.parametrize("e", list(ION_EVENTS))
def test_physical_laws_are_the_simulators(tensors, e):
    """Away from thresholds the smooth laws equal the simulator's hard ones at (mu, cos)."""
    energies = [60.0, 160.0, 330.0, 500.0, 1000.0]
    cosines = [1.0, 0.99, 0.9, 0.5]
    mu = torch.tensor([[en] for en in energies for _ in cosines], dtype=torch.float64)  # (B, 1)
    c = torch.tensor([[cc] for _ in energies for cc in cosines], dtype=torch.float64)
    sigma = torch.full_like(mu, 2.0)  # 60 eV is >= 12 sigma above every threshold of the library
    sel = slice(e, e + 1)
    p = K.probability_physical(mu, sigma, c, *event_laws(tensors, sel))
    yp = torch.from_numpy(tensors.yield_params[sel])
    y = K.yield_factor(mu, c, torch.from_numpy(tensors.yield_model[sel]), yp,
                       energy_gate=torch.special.ndtr((mu - yp[:, 0]) / sigma))  # fmt: skip
    # the C law's switch at 45 degrees is smoothed with width tau_C = 0.05 rad: < 0.3 % at 25.8 and 60 degrees
    rel = 3e-3 if tensors.angle_kind[e] == 2 else 1e-4
    for b in range(mu.shape[0]):
        en, cc = float(mu[b, 0]), float(c[b, 0])
        assert float(p[b, 0]) == pytest.approx(sim_prob(tensors, e, en, cc), rel=rel, abs=1e-12)
        y_sim = laws.yield_physical(tensors.yield_model[e], tensors.yield_params[e], en, cc)
        assert float(y[b, 0]) == pytest.approx(y_sim, rel=1e-4, abs=1e-12)


def test_primary_terms_by_hand(tensors):
    """E7 and E9 at the median recipe (Cl+ 330 eV, sigma 7.5 eV, m = 1525), from the YAML's numbers."""
    raw = median_raw()
    energy = (raw[CONTROL_INDEX["energy_mean_cl_plus"]], raw[CONTROL_INDEX["energy_std_cl_plus"]])
    assert energy == (330.0, 7.5)
    assert raw[CONTROL_INDEX["angle_cl_plus"]] == 1525.0
    u = torch.from_numpy(to_normalized(raw))[None]
    f, p, y = K.primary_terms(u, tensors, "physical")
    c = 1526.0 / 1527.0  # (m + 1)/(m + 2)
    # P law: q = -ln(R_P)/(ln c_P + 1 - c_P + eps), s = q c_P with c_P = cos 60, R_P = 5
    q = -math.log(5.0) / (math.log(0.5) + 0.5 + 1e-6)
    f_p = c**-q * math.exp(-q * 0.5 * (1 / c - 1))
    # E7: E_th 25, E_ref 100, p0 0.05, n 0.5; the simulator keeps x^n above E_ref
    assert float(p[0, E7]) == pytest.approx(0.05 * f_p * math.sqrt((330 - 25) / (100 - 25)), rel=1e-6)
    # E7 yield: Yamamura (E_th 25, theta_max 60, Y_max 2.2, Y0 1.2)
    qy = -math.log(2.2 / 1.2) / (math.log(0.5) + 0.5 + 1e-6)
    assert float(y[0, E7]) == pytest.approx(c**-qy * math.exp(-qy * 0.5 * (1 / c - 1)), rel=1e-6)
    # E9: C law, incidence far below 45 degrees -> F^C = 1; E_th 10, p0 0.2; constant unit yield
    assert float(p[0, E9]) == pytest.approx(0.2 * math.sqrt((330 - 10) / (100 - 10)), rel=1e-6)
    assert float(y[0, E9]) == 1.0
    # supply: softplus of the normalized log flux, as in the paper's kinetics
    u_flux = float(u[0, CONTROL_INDEX["flux_cl_plus"]])
    assert float(f[0, E7]) == pytest.approx(math.log1p(math.exp(u_flux)), rel=1e-9)
    # neutral E1 (constant 0.55, unit yield) is the same under both kinetics
    f0, p0, y0 = K.primary_terms(u, tensors, "paper")
    assert float(p[0, 0] * y[0, 0]) == float(p0[0, 0] * y0[0, 0]) == pytest.approx(0.55)


def test_below_threshold_is_smooth_and_vanishes(tensors):
    """Energies below E_th: the gate is the probability that E' ~ N(mu, sigma^2) exceeds it."""
    mu = torch.tensor([[0.0], [15.0], [25.0], [35.0], [60.0]], dtype=torch.float64)
    sigma = torch.full_like(mu, 5.0)
    sel = slice(E7, E7 + 1)
    p = K.probability_physical(mu, sigma, torch.ones_like(mu), *event_laws(tensors, sel))
    p = p[:, 0].tolist()
    assert p[0] < 1e-5 and all(a < b for a, b in zip(p, p[1:], strict=False))  # 5 sigma below E_th
    # at the threshold: expected excess = sigma phi(0) = 5/sqrt(2 pi)
    assert p[2] == pytest.approx(0.05 * math.sqrt(5.0 / math.sqrt(2 * math.pi) / 75.0), rel=1e-7)
    excess = K.expected_excess(torch.tensor([40.0]), torch.tensor(25.0), torch.tensor(1e-3))
    assert float(excess) == pytest.approx(15.0)


def test_energy_response_across_the_box(tensors):
    """Physical: every ion event's rate grows with its energy across 160-500 eV (as sqrt of the excess);
    paper: saturated (< 3 % change)."""
    u = sweep(ENERGY_MEANS, np.linspace(160.0, 500.0, 8))
    lam_phys = K.base_intensity(u, tensors, "physical")[:, list(ION_EVENTS)]  # (8, 16)
    lam_paper = K.base_intensity(u, tensors, "paper")[:, list(ION_EVENTS)]
    assert (lam_phys.diff(dim=0) > 0).all()
    ratio = lam_phys[-1] / lam_phys[0]
    e_th = torch.from_numpy(tensors.prob_params[list(ION_EVENTS), 0])
    n = torch.from_numpy(tensors.prob_params[list(ION_EVENTS), 3])
    torch.testing.assert_close(ratio, ((500 - e_th) / (160 - e_th)) ** n, rtol=1e-9, atol=0)
    assert (ratio > 1.3).all()
    assert ((lam_paper[-1] / lam_paper[0] - 1).abs() < 0.03).all()


def test_angle_response_across_the_box(tensors):
    """Physical: every ion event's rate is the simulator's p Y at the mean cosine (m+1)/(m+2); the P-law
    (sputter) events fall as m grows from 50 to 3000, the C-law events are flat (every mean incidence is
    far below 45 degrees). Paper: the effective cosine ignores m's physical scale."""
    m = np.array([50.0, 100.0, 300.0, 1000.0, 3000.0])
    u = sweep(ION_ANGLES, m)
    lam = K.base_intensity(u, tensors, "physical")  # (5, E)
    c = (m + 1) / (m + 2)
    for e in ION_EVENTS:
        py = np.array([sim_prob(tensors, e, 330.0, cc) * laws.yield_physical(
            tensors.yield_model[e], tensors.yield_params[e], 330.0, cc) for cc in c])  # fmt: skip
        np.testing.assert_allclose(lam[:, e].numpy() / lam[-1, e].item(), py / py[-1], rtol=1e-5)  # C switch
        if tensors.angle_kind[e] == 1:
            assert py[0] / py[-1] > 1.07 and np.all(np.diff(py) < 0)
        else:
            assert np.ptp(py) == 0.0


def test_gradients_finite_everywhere(tensors):
    """Inside, outside and far outside the box (zero flux, zero energy, zero exponent)."""
    gen = torch.Generator().manual_seed(0)
    u = torch.rand(16, 14, generator=gen, dtype=torch.float64) * 8 - 4
    u[0] = torch.from_numpy(to_normalized(np.zeros(14)))
    u.requires_grad_(True)
    lam = K.formula_intensities(u, tensors.torch_buffers(torch.float64), "physical")
    assert torch.isfinite(lam).all() and (lam >= 0).all()
    lam.sum().backward()
    assert torch.isfinite(u.grad).all()
    assert u.grad[:, CONTROL_INDEX["energy_mean_cl_plus"]].abs().sum() > 0


def test_unknown_kinetics(tensors):
    with pytest.raises(ValueError, match="unknown kinetics 'phys'.*'paper', 'physical'"):
        K.primary_terms(torch.zeros(1, 14), tensors, "phys")  # type: ignore[arg-type]


def test_simulator_path_does_not_import_torch():
    code = (
        "import sys\n"
        "import nemsim.sim, nemsim.sim.generate, nemsim.sim.process, nemsim.sim.kernels, nemsim.rules.laws\n"
        "import numpy as np\n"
        "assert nemsim.rules.laws.prob_physical(0, np.array([0.5, 0, 0, 0, 0.0]), 0, 1.0, 1.0) == 0.5\n"
        "assert 'torch' not in sys.modules, sorted(m for m in sys.modules if m.startswith('torch'))[:5]\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
