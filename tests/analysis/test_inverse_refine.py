"""Simulator-corrected inverse design, tested deterministically: a toy surrogate on `tiny` whose etch depth
is linear in one control, and fake simulators (the surrogate plus a constant metric offset) injected in
place of the Monte Carlo simulator; then the in-process path on the tiny checkpoint with the real one."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from nemsim.analysis.intervals import Support
from nemsim.analysis.inverse import (
    InverseContext,
    RefineConfig,
    SimulationSkipped,
    refine_config_from_dict,
    refine_with_simulator,
    rollout_to,
    spec_from_dict,
)
from nemsim.controls import CONTROL_NAMES, control_index, from_normalized, to_normalized
from nemsim.geometry.profile import profile_metrics_batch

STEP = 6
FREE = "flux_cl"
SEARCH = {"screen": 8, "starts": 2, "iterations": 8, "batch": 8, "method": "adam"}
EXACT = RefineConfig(rounds=2, budget_s=1e9, radius=2.0, screen=4, starts=2, iterations=8)


class _Toy(torch.nn.Module):
    """Each step raises the Si SDF everywhere by 0.05 * (1.5 + u[flux_cl]): the hole floor sinks at a rate
    linear in the one free control, so the predicted etch depth at step 6 runs from 4.5 to 22.5 nm."""

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        rate = 0.05 * (1.5 + u[:, control_index(FREE)])  # (B,)
        d = torch.zeros_like(x)
        d[:, 1] = rate[:, None, None, None]
        return (x + d).clamp(-1.0, 1.0)


@pytest.fixture(scope="module")
def toy(tiny_scene):
    from nemsim.sim import initial_state

    x0 = torch.from_numpy(np.asarray(initial_state(tiny_scene), dtype=np.float32))
    return InverseContext(
        model=_Toy(),
        scene=tiny_scene,
        x0=x0,
        calibration=None,
        support=Support.from_record(None),
        model_id="toy",
    )


def _predict(ctx, raw: np.ndarray) -> dict[str, float]:
    u = torch.as_tensor(np.asarray(to_normalized(raw[None])), dtype=torch.float32)
    with torch.no_grad():
        x = rollout_to(ctx.model, ctx.x0, u, STEP)
    return {k: float(v[0]) for k, v in profile_metrics_batch(x.numpy(), ctx.scene).items()}


class FakeSimulator:
    """The surrogate's exact metrics plus a constant offset per metric; records every call."""

    def __init__(self, ctx, offset: dict[str, float], skip: bool = False) -> None:
        self.ctx, self.offset, self.skip = ctx, offset, skip
        self.calls: list[np.ndarray] = []

    def __call__(self, raw: np.ndarray, step: int) -> dict[str, float]:
        assert step == STEP
        if self.skip:
            raise SimulationSkipped("beyond the test's work limit")
        self.calls.append(np.array(raw))
        m = _predict(self.ctx, raw)
        return {k: v + self.offset.get(k, 0.0) for k, v in m.items()}


def _spec(depth: float, tol: float = 1.0, k: int = 3):
    centre = np.asarray(from_normalized(np.zeros(14)), dtype=np.float64)
    fixed = {n: float(v) for n, v in zip(CONTROL_NAMES, centre, strict=True) if n != FREE}
    return spec_from_dict(
        {
            "targets": {"etch_depth": {"value": depth, "tol": tol}},
            "step": STEP,
            "fixed": fixed,
            "k": k,
            "search": SEARCH,
        }
    )


def test_one_correction_round_removes_a_constant_offset(toy):
    sim = FakeSimulator(toy, {"etch_depth": 5.0})
    res = refine_with_simulator(toy, _spec(16.0), sim, refine=EXACT, sim_seed=3)
    ref = res["refinement"]
    r0, r1 = ref["rounds"][0], ref["rounds"][1]
    assert ref["surrogate_status"] == "met" and len(ref["rounds"]) == 2 and ref["stopped"] == "met"
    # round 0: the surrogate puts its recipes on target, the simulator is 5 nm deeper: both miss
    assert len(r0["simulated"]) == EXACT.verify_top
    for s in r0["simulated"]:
        assert abs(s["predicted"]["etch_depth"] - 16.0) <= 1.0 and not s["met"]
        assert s["offset"]["etch_depth"] == pytest.approx(5.0, abs=1e-3)
    # round 1 searches for a surrogate depth of 16 - 5 = 11 nm and its recipe meets the target
    assert r1["offset"]["etch_depth"] == pytest.approx(5.0, abs=1e-3)
    assert r1["shifted_targets"]["etch_depth"] == pytest.approx(11.0, abs=1e-3)
    (s1,) = r1["simulated"]
    assert abs(s1["predicted"]["etch_depth"] - 11.0) <= 1.0 and s1["met"]
    assert abs(s1["simulated"]["etch_depth"] - 16.0) <= 1.0
    assert res["status"] == "verified" and "simulator" in res["message"]
    top = res["recipes"][0]
    assert top["verified_by"] == "simulator" and top["round"] == 1 and top["simulator_met"] is True
    assert top["simulated"]["etch_depth"] == pytest.approx(s1["simulated"]["etch_depth"])
    assert top["targets"]["etch_depth"]["target"] == 16.0  # judged against the real target, not the shifted
    assert [r["rank"] for r in res["recipes"]] == [1, 2, 3]
    assert {r["verified_by"] for r in res["recipes"][1:]} <= {"simulator", "surrogate"}
    cost = res["cost"]
    assert cost["simulator_runs"] == len(sim.calls) == EXACT.verify_top + 1
    assert cost["rollouts"] == cost["forward_rollouts"] + cost["gradient_rollouts"] > 0
    assert cost["wall_s"] >= cost["search_wall_s"] > 0 and cost["cpu_s"] > 0
    assert [v["round"] for v in res["verification"]["recipes"]] == [0] * EXACT.verify_top + [1]
    assert {v["run"] for v in res["verification"]["recipes"]} == {"loop"}  # no confirmation simulator
    assert res["simulator_calls"] == cost["simulator_runs"] and cost["confirmation_runs"] == 0
    assert res["verification"]["seed"] == 3


def test_a_corrected_search_whose_best_was_run_tries_its_next_best(toy, monkeypatch):
    """A round whose corrected search ranks an already simulated recipe first simulates the best one not yet
    run, instead of stopping: here the real search's recipe, which meets the target."""
    from nemsim.analysis.inverse import refine as rf

    real = rf._corrected_search

    def best_already_run(ctx, spec, cfg, sims, rnd, **kwargs):
        res, record = real(ctx, spec, cfg, sims, rnd, **kwargs)
        ran = dict(res["recipes"][0], controls_normalized=[float(v) for v in sims[0].u])
        return {**res, "recipes": [ran, *res["recipes"]]}, record

    monkeypatch.setattr(rf, "_corrected_search", best_already_run)
    sim = FakeSimulator(toy, {"etch_depth": 5.0})
    res = refine_with_simulator(toy, _spec(16.0), sim, refine=EXACT, sim_seed=3)
    ref = res["refinement"]
    assert ref["stopped"] == "met" and len(ref["rounds"]) == 2 and res["status"] == "verified"
    assert len(sim.calls) == EXACT.verify_top + 1
    assert not np.allclose(sim.calls[-1], sim.calls[0])


def test_the_trust_region_bounds_each_round(toy):
    """A radius of 0.3 normalized units moves the depth by at most 0.3 * 9 nm per round: a 5 nm offset
    takes two rounds, and each round's recipe stays inside the region around its anchor."""
    sim = FakeSimulator(toy, {"etch_depth": 5.0})
    cfg = RefineConfig(verify_top=1, rounds=3, budget_s=1e9, radius=0.3, screen=4, starts=2, iterations=8)
    res = refine_with_simulator(toy, _spec(16.0), sim, refine=cfg)
    rounds = res["refinement"]["rounds"]
    j = control_index(FREE)
    u = [float(np.asarray(to_normalized(c[None]))[0, j]) for c in sim.calls]
    for a, b in zip(u, u[1:], strict=False):
        assert abs(b - a) <= 0.3 + 1e-6
    assert not rounds[1]["simulated"][0]["met"]  # one round cannot close 5 nm
    assert res["status"] == "verified" and len(rounds) == 3 and rounds[2]["simulated"][0]["met"]


def test_met_in_round_0_and_budget_stop(toy):
    sim = FakeSimulator(toy, {})
    res = refine_with_simulator(toy, _spec(16.0), sim, refine=EXACT)
    assert res["status"] == "verified" and res["refinement"]["stopped"] == "met"
    assert len(res["refinement"]["rounds"]) == 1 and len(sim.calls) == 1  # the first recipe met: no second
    sim = FakeSimulator(toy, {"etch_depth": 5.0})
    res = refine_with_simulator(toy, _spec(16.0), sim, refine=RefineConfig(verify_top=1, budget_s=0.0))
    assert res["refinement"]["stopped"] == "budget" and len(sim.calls) == 1
    assert res["status"] == "unverified" and "closest simulated" in res["message"]
    assert res["recipes"][0]["verified_by"] == "simulator" and not res["recipes"][0]["simulator_met"]


def test_a_surrogate_unreachable_target_the_simulator_meets_is_verified(toy):
    """The surrogate cannot etch 30 nm in 6 steps (at most 22.5); the simulator etches 12 nm more, so the
    corrected search asks for 18 nm and the simulator meets 30 nm: not unreachable."""
    sim = FakeSimulator(toy, {"etch_depth": 12.0})
    res = refine_with_simulator(toy, _spec(30.0), sim, refine=EXACT)
    assert res["refinement"]["surrogate_status"] == "unreachable"
    assert res["status"] == "verified"
    assert abs(res["recipes"][0]["simulated"]["etch_depth"] - 30.0) <= 1.0


def test_an_unreachable_target_stays_unreachable_with_the_closest_simulated_miss(toy):
    sim = FakeSimulator(toy, {"etch_depth": 2.0})
    res = refine_with_simulator(toy, _spec(200.0), sim, refine=EXACT)
    assert res["status"] == "unreachable" and "closest simulated" in res["message"]
    ref = res["refinement"]
    assert ref["surrogate_status"] == "unreachable" and ref["stopped"] in ("rounds", "converged")
    assert all(r["search"]["status"] == "unreachable" for r in ref["rounds"])
    top = res["recipes"][0]
    assert top["verified_by"] == "simulator" and not top["simulator_met"]
    best = max(v["achieved"]["etch_depth"] for v in res["verification"]["recipes"])
    assert top["simulated"]["etch_depth"] == pytest.approx(best)  # the closest miss is the deepest run
    assert best == pytest.approx(22.5 + 2.0, abs=0.5)


def test_declined_simulations_leave_the_surrogate_result(toy):
    sim = FakeSimulator(toy, {"etch_depth": 5.0}, skip=True)
    res = refine_with_simulator(toy, _spec(16.0), sim, refine=EXACT)
    assert res["status"] == "met"  # the surrogate's word, since nothing was simulated
    assert res["refinement"]["stopped"] == "no simulated recipe"
    assert len(res["verification"]["skipped"]) == EXACT.verify_top and res["verification"]["recipes"] == []
    assert all(r["verified_by"] == "surrogate" for r in res["recipes"])


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"rounds": -1}, "rounds"),
        ({"radius": 0}, "radius"),
        ({"shrink": 0}, "shrink"),
        ({"shrink": 1.5}, "shrink"),
        ({"colour": 1}, "unknown keys"),
        ({"verify_top": 1.5}, "integers"),
        ({"budget_s": "x"}, "number"),
    ],
)
def test_refine_config_errors_name_the_field(bad, match):
    with pytest.raises(ValueError, match=match):
        refine_config_from_dict(bad)


def test_refine_config_from_dict_reads_a_subset():
    cfg = refine_config_from_dict({"rounds": 1, "radius": 0.5})
    assert cfg.rounds == 1 and cfg.radius == 0.5 and cfg.verify_top == RefineConfig().verify_top


def test_run_inverse_refines_with_the_real_simulator(tiny_checkpoint):
    """The in-process path: the checkpoint's simulator, one round-0 run and at most one corrected run."""
    from nemsim.analysis.inverse import format_result, load_inverse_context, run_inverse

    ctx = load_inverse_context(tiny_checkpoint)
    spec = spec_from_dict(
        {
            "targets": {"etch_depth": {"value": 8.0, "tol": 2.0}},
            "step": 2,
            "k": 2,
            "search": {"screen": 4, "starts": 1, "iterations": 1, "batch": 4, "method": "adam"},
        }
    )
    cfg = RefineConfig(verify_top=1, rounds=1, budget_s=1e9, screen=2, starts=1, iterations=1)
    res = run_inverse(ctx, spec, refine=cfg, sim_seed=5)
    runs = res["verification"]["recipes"]
    assert 1 <= len(runs) <= 2 and res["cost"]["simulator_runs"] == len(runs)
    assert res["status"] in ("verified", "unverified", "unreachable")
    assert (res["status"] == "verified") == any(v["met"] for v in runs)
    assert res["recipes"][0]["verified_by"] == "simulator"
    achieved = runs[0]["achieved"]["etch_depth"]
    assert np.isfinite(achieved) and achieved >= 0
    text = format_result(res)
    assert "simulator-corrected design" in text and "round 0:" in text and "simulator runs" in text


class _FakeTruth:
    """`SimTruth.metrics` over the fake simulator ({name: (STEP + 1,)}, the value at STEP); records seeds."""

    def __init__(self, sim: FakeSimulator) -> None:
        self.sim, self.seeds = sim, []

    def metrics(self, raw: np.ndarray, seed: int) -> dict[str, np.ndarray]:
        self.seeds.append(seed)
        return {k: np.full(STEP + 1, v) for k, v in self.sim(raw, STEP).items()}


def test_bench_run_judges_the_refined_design_with_an_independent_seed(toy):
    from bench.inverse import LOOP_SEED, VERIFY_SEED, _inverse_run, _summary

    truth = _FakeTruth(FakeSimulator(toy, {"etch_depth": 5.0}))
    plain = _inverse_run(toy, _spec(16.0), "adam", True, truth, STEP)
    assert truth.seeds == [VERIFY_SEED] and not plain["success"] and plain["status"] == "met"
    truth.seeds.clear()
    refined = _inverse_run(toy, _spec(16.0), "adam", True, truth, STEP, EXACT)
    assert truth.seeds[-1] == VERIFY_SEED and set(truth.seeds[:-1]) == {LOOP_SEED}
    assert refined["success"] and refined["status"] == "verified"
    assert refined["cost"]["simulator_runs"] == len(truth.seeds) - 1 == EXACT.verify_top + 1
    assert abs(refined["achieved"]["etch_depth"] - 16.0) <= 1.0
    cases = [{"reachable": True, "runs": {"adam": plain, "adam+refine": refined}}]
    s = _summary(cases, "adam")
    assert s["reachable_success"] == 0 and s["simulator_runs_mean"] == 0
    s = _summary(cases, "adam+refine")
    assert (
        s["reachable_success"] == s["loop_verified"] == 1 and s["simulator_runs_mean"] == EXACT.verify_top + 1
    )


def _narrow_calibration(half_width: float):
    """Intervals of +-``half_width`` nm around every prediction, at every step and both levels."""
    from nemsim.analysis.intervals import Calibration

    metrics = ("etch_depth", "top_width", "neck_width", "bottom_width", "bowing", "mask_loss")
    band = {"lower": [-half_width] * (STEP + 1), "upper": [half_width] * (STEP + 1)}
    return Calibration(
        checkpoint_sha256="toy",
        scene="tiny",
        levels=(0.8, 0.9),
        metrics=metrics,
        offsets={lv: {m: dict(band) for m in metrics} for lv in ("0.8", "0.9")},
        calibration={"setting": "toy", "split": "val", "cases": 0, "method": "fixed"},
    )


def test_a_loop_run_that_met_must_be_confirmed_and_the_mean_anchors_the_next_round(toy):
    """Loop simulator: the surrogate exactly; confirmation simulator: 3 nm deeper; no claim. Round 0's recipe
    meets 16 +- 2 in its loop run and misses in its confirmation, so it is not the answer; the next round's
    offset is the mean of the two runs (+1.5 nm) and its recipe meets the target in both runs."""
    loop, again = FakeSimulator(toy, {}), FakeSimulator(toy, {"etch_depth": 3.0})
    no_claim = replace(EXACT, claim_level=1.0)
    res = refine_with_simulator(toy, _spec(16.0, tol=2.0), loop, refine=no_claim, confirm=again)
    ref = res["refinement"]
    r0 = ref["rounds"][0]["simulated"][0]
    assert r0["met"] and r0["confirmed"] is False and not r0["claimed"]
    assert r0["confirmation"]["etch_depth"] == pytest.approx(r0["simulated"]["etch_depth"] + 3.0, abs=1e-3)
    r1 = ref["rounds"][1]
    assert r1["offset"]["etch_depth"] == pytest.approx(1.5, abs=1e-3) and r1["anchor"]["runs"] == 2
    assert r1["shifted_targets"]["etch_depth"] == pytest.approx(14.5, abs=1e-3)
    assert res["status"] == "verified" and ref["stopped"] == "met" and ref["confirmation"] is True
    top = res["recipes"][0]
    assert top["round"] == 1 and top["confirmed"] is True and top["simulator_met"] is True
    entries = res["verification"]["recipes"]
    assert [e["run"] for e in entries] == ["loop", "confirmation", "loop", "confirmation"]
    assert len(loop.calls) == len(again.calls) == 2
    assert (
        res["simulator_calls"] == res["cost"]["simulator_runs"] == 4 and res["cost"]["confirmation_runs"] == 2
    )
    assert all(abs(e["achieved"]["etch_depth"] - 16.0) <= 2.0 for e in entries[2:])  # both runs of the answer


def test_narrow_intervals_claim_the_round_0_recipe_with_one_call(toy):
    """Claims at level 0.8: the top recipe's 80 % interval (+-0.2 nm) lies inside 16 +- 2: its first run is
    the confirmation, which meets the target, so the design spends one simulator call and never runs the
    loop simulator."""
    from dataclasses import replace as dc_replace

    at_80 = replace(EXACT, claim_level=0.8)
    ctx = dc_replace(toy, calibration=_narrow_calibration(0.2))
    loop, again = FakeSimulator(ctx, {}), FakeSimulator(ctx, {"etch_depth": 0.5})
    res = refine_with_simulator(ctx, _spec(16.0, tol=2.0), loop, refine=at_80, confirm=again)
    assert res["status"] == "verified" and res["simulator_calls"] == 1
    assert loop.calls == [] and len(again.calls) == 1
    (entry,) = res["verification"]["recipes"]
    assert entry["run"] == "claim" and entry["met"]
    assert res["refinement"]["rounds"][0]["simulated"][0]["claimed"] is True
    # wide intervals (+-3 nm, beyond the tolerance): no claim, the loop run comes first
    ctx = dc_replace(toy, calibration=_narrow_calibration(3.0))
    loop, again = FakeSimulator(ctx, {}), FakeSimulator(ctx, {"etch_depth": 0.5})
    res = refine_with_simulator(ctx, _spec(16.0, tol=2.0), loop, refine=at_80, confirm=again)
    assert [e["run"] for e in res["verification"]["recipes"]] == ["loop", "confirmation"]
    assert res["status"] == "verified" and res["simulator_calls"] == 2
    # level 0: the interval is the prediction itself, inside 16 +- 2 whatever the calibration: a claim
    loop, again = FakeSimulator(ctx, {}), FakeSimulator(ctx, {"etch_depth": 0.5})
    at_0 = replace(EXACT, claim_level=0.0)
    res = refine_with_simulator(ctx, _spec(16.0, tol=2.0), loop, refine=at_0, confirm=again)
    assert [e["run"] for e in res["verification"]["recipes"]] == ["claim"] and res["simulator_calls"] == 1
    # level 1: the interval is unbounded, never inside, even with the narrow calibration
    ctx = dc_replace(toy, calibration=_narrow_calibration(0.2))
    loop, again = FakeSimulator(ctx, {}), FakeSimulator(ctx, {"etch_depth": 0.5})
    res = refine_with_simulator(ctx, _spec(16.0, tol=2.0), loop, refine=replace(EXACT, claim_level=1.0),
                                confirm=again)
    assert [e["run"] for e in res["verification"]["recipes"]] == ["loop", "confirmation"]


def test_a_claim_that_misses_is_the_next_round_s_anchor(toy):
    """The default claim (level 0: the prediction meets the target). A claim whose run misses costs no
    extra call: that run anchors round 1 as a loop run would (offset +3 nm), and round 1's recipe is
    verified by a loop run and its confirmation: three calls in all."""
    loop, again = FakeSimulator(toy, {"etch_depth": 3.0}), FakeSimulator(toy, {"etch_depth": 3.0})
    res = refine_with_simulator(toy, _spec(16.0, tol=1.0), loop, refine=EXACT, confirm=again)
    assert [e["run"] for e in res["verification"]["recipes"]] == ["claim", "loop", "confirmation"]
    r1 = res["refinement"]["rounds"][1]
    assert r1["offset"]["etch_depth"] == pytest.approx(3.0, abs=1e-3) and r1["anchor"]["round"] == 0
    assert res["status"] == "verified" and res["simulator_calls"] == 3 and res["recipes"][0]["round"] == 1


def test_a_target_beyond_the_intervals_is_unreachable_without_a_simulator_run(toy):
    """The toy etches at most 22.5 nm in 6 steps; 40 +- 1 nm lies beyond every recipe's 90 % interval
    (+-0.5 nm), so the design answers unreachable with no run. With wide intervals it simulates."""
    from dataclasses import replace as dc_replace

    ctx = dc_replace(toy, calibration=_narrow_calibration(0.5))
    sim = FakeSimulator(ctx, {})
    res = refine_with_simulator(ctx, _spec(40.0), sim, refine=EXACT)
    assert res["status"] == "unreachable" and res["refinement"]["stopped"] == "intervals"
    assert sim.calls == [] and res["simulator_calls"] == 0 and "no simulator run" in res["message"]
    assert all(v == ["etch_depth"] for v in res["refinement"]["rounds"][0]["beyond_intervals"].values())
    ctx = dc_replace(toy, calibration=_narrow_calibration(30.0))
    sim = FakeSimulator(ctx, {})
    res = refine_with_simulator(ctx, _spec(40.0), sim, refine=EXACT)
    assert res["status"] == "unreachable" and len(sim.calls) >= 1


def test_max_runs_caps_the_simulator_calls(toy):
    """A 5 nm offset and a 0.3 trust radius take three corrected rounds; two calls stop the loop first."""
    sim = FakeSimulator(toy, {"etch_depth": 5.0})
    cfg = RefineConfig(rounds=5, budget_s=1e9, radius=0.3, screen=4, starts=2, iterations=8, max_runs=2)
    res = refine_with_simulator(toy, _spec(16.0), sim, refine=cfg)
    assert len(sim.calls) == res["simulator_calls"] == 2
    assert res["refinement"]["stopped"] == "max runs" and res["status"] == "unverified"
    # with a confirmation simulator a loop run starts only when its confirmation fits too
    sim, again = FakeSimulator(toy, {"etch_depth": 5.0}), FakeSimulator(toy, {"etch_depth": 5.0})
    no_claim = replace_cfg(cfg, max_runs=3, claim_level=1.0)
    res = refine_with_simulator(toy, _spec(16.0), sim, refine=no_claim, confirm=again)
    assert res["simulator_calls"] <= 3 and len(sim.calls) == 2 and again.calls == []


def test_the_trust_region_shrinks_while_the_anchor_stays(toy):
    """Every run after the first lands farther off (offset 5, 15, 25 nm): the first stays the anchor, and
    each corrected round searches a region ``shrink`` times the last one's."""
    sim = FakeSimulator(toy, {"etch_depth": 5.0})
    real = sim.__call__

    class Growing:
        calls = sim.calls

        def __call__(self, raw, step):
            out = real(raw, step)
            return {**out, "etch_depth": out["etch_depth"] + 10.0 * (len(sim.calls) - 1)}

    cfg = RefineConfig(rounds=3, budget_s=1e9, radius=0.8, shrink=0.5, screen=4, starts=2, iterations=8)
    res = refine_with_simulator(toy, _spec(16.0), Growing(), refine=cfg)
    rounds = res["refinement"]["rounds"][1:]
    assert [r["anchor"]["round"] for r in rounds] == [0] * len(rounds) and len(rounds) >= 2
    assert [r["radius"] for r in rounds] == [0.8 * 0.5**i for i in range(len(rounds))]


def replace_cfg(cfg: RefineConfig, **kw) -> RefineConfig:
    from dataclasses import replace

    return replace(cfg, **kw)


def test_the_carried_offset_weighs_runs_by_their_distance_from_the_anchor():
    """Anchor: one run, offset +2 nm; a recipe one radius away: two runs, offsets +4 and +6 (weight
    exp(-1/2) each); one ten radii away: offset +100 (weight exp(-50), nothing)."""
    from nemsim.analysis.inverse.refine import _carried_offset, _Simulated

    def sim(u0: float, offsets: list[float]) -> _Simulated:
        u = [u0] + [0.0] * 13
        rec = {"controls_normalized": u, "predicted": {"etch_depth": 10.0}}
        runs = [{"etch_depth": 10.0 + d} for d in offsets]
        return _Simulated(0, rec, {"achieved": runs[0]}, runs)

    anchor = sim(0.0, [2.0])
    others = [sim(0.3, [4.0, 6.0]), sim(3.0, [100.0])]
    w = np.exp(-0.5)
    got = _carried_offset(anchor, [anchor, *others], ["etch_depth"], 0.3)["etch_depth"]
    assert got == pytest.approx((2.0 + w * (4.0 + 6.0)) / (1.0 + 2 * w), abs=1e-6)
    assert _carried_offset(anchor, [anchor], ["etch_depth"], 0.3)["etch_depth"] == pytest.approx(2.0)
