"""Monte Carlo feature-profile simulator: the reference that makes NEMSim's data ([supp_simulator]).

Pipeline (ViennaPS-like nouns, snake_case)::

    from nemsim.sim import SimConfig, simulate_trajectory
    states = simulate_trajectory(scene, rules, controls_raw, np.random.default_rng(0), SimConfig())

Modules: ``config`` (SimConfig, calibration), ``domain`` (voxel state, initial geometry), ``events``
(compiled rules -> kernel tables), ``kernels`` (numba particle transport and surface events), ``sdf``
(Psi: voxels -> signed distances), ``process`` (time stepping, one trajectory), ``generate`` (data sets:
case scheduling, resumable HDF5 writing, process pool or Ray), ``calibration`` (optional re-fits of the
rules' laws). Its benchmarks (speed, yields, bowing, noise floor) live in ``bench``; its calibration is the
``config`` module docstring.
"""

from .config import SimConfig
from .process import TrajectoryResult, initial_state, run_trajectory, simulate_trajectory

__all__ = ["SimConfig", "TrajectoryResult", "initial_state", "run_trajectory", "simulate_trajectory"]
