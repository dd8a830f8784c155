"""Stub surrogates with known behaviour for the simulator-judged benchmarks (invariants, physics,
extrapolation): a plausible one, and deliberately broken ones each check must flag."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from nemsim.controls import CONTROL_INDEX

ION = [CONTROL_INDEX[n] for n in ("flux_ar_plus", "flux_cl_plus", "flux_cl2_plus")]
ENERGY = [CONTROL_INDEX[n] for n in ("energy_mean_cl_plus", "energy_mean_cl2_plus", "energy_mean_ar_plus")]


class Plausible(torch.nn.Module):
    """Removes Si everywhere at a rate rising with every ion flux and ion energy, zero without ions."""

    def __init__(self, sign: float = 1.0) -> None:
        super().__init__()
        self.sign = sign  # -1: the rate falls with the Ar+ flux (a broken monotonicity)

    def rate(self, u: torch.Tensor) -> torch.Tensor:
        flux = torch.exp(u[:, ION])  # normalized log fluxes: 0 flux -> exp(-9) ~ 0
        flux[:, 0] = torch.exp(self.sign * u[:, ION[0]]) * (u[:, ION[0]] > -5)
        energy = 1.0 + 0.2 * u[:, ENERGY].mean(dim=1, keepdim=True)
        return 0.01 * (flux * energy).sum(dim=1)  # (B,) SDF units per step

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        y = x.clone()
        y[:, 1] = (y[:, 1] + self.rate(u)[:, None, None, None]).clamp(-1, 1)
        return y


class NoChange(torch.nn.Module):
    def forward(self, x, u):
        return x


class EtchesWithoutFlux(torch.nn.Module):
    """Etches Si and grows the mask whatever the controls (the issue's failure: change at zero flux)."""

    def forward(self, x, u):
        y = x.clone()
        y[:, 1] += 0.02
        y[:, 0] -= 0.01
        return y


class Unetches(torch.nn.Module):
    """Grows Si back every step: the depth decreases over time."""

    def forward(self, x, u):
        y = x.clone()
        y[:, 1] -= 0.02
        return y


@pytest.fixture(scope="session")
def stubs():
    return SimpleNamespace(Plausible=Plausible, NoChange=NoChange, EtchesWithoutFlux=EtchesWithoutFlux,
                           Unetches=Unetches, ION=ION, ENERGY=ENERGY)


@pytest.fixture(scope="module")
def truth(request, tiny_scene, tmp_path_factory):
    """A simulator on tiny with its own run cache; the test module's ``STEPS`` sets the transitions."""
    from nemsim.evaluation.truth import SimTruth
    from nemsim.rules import compile_rules, load_rules

    with SimTruth(tiny_scene, compile_rules(load_rules()), steps=request.module.STEPS,
                  cache_dir=tmp_path_factory.mktemp("sims")) as t:
        yield t


@pytest.fixture(scope="module")
def x0(tiny_scene):
    from nemsim.sim import initial_state

    return initial_state(tiny_scene)


@pytest.fixture(scope="session")
def two_seed_files():
    """two_seed_files(root, feature, cd, mask, *generate args) -> {"a": file, "b": file}: a 2-case design of
    ``feature`` on tiny simulated with seeds 1 and 2."""
    return _two_seed_files


def _two_seed_files(root, feature: str, cd_nm: str, mask_nm: str, *extra: str) -> dict:
    """A 2-case design of ``feature`` on tiny simulated with seeds 1 and 2 (``extra``: more generate
    arguments, e.g. the simulated domain): {"a": file, "b": file}."""
    from nemsim.cli import main

    design = root / "design.csv"
    assert main(["design", "--feature", feature, "--cd-nm", cd_nm, "--mask-nm", mask_nm, "--n", "2",
                 "--seed", "5", "--out", str(design)]) == 0
    files = {}
    for name, seed in (("a", "1"), ("b", "2")):
        files[name] = root / f"{feature}-{name}.h5"
        assert main(["generate", "--scene", "tiny", "--controls", str(design), "--seed", seed, *extra,
                     "--no-progress", "--out", str(files[name])]) == 0
    return files
