"""NEMSim: a neural surrogate for 3-D plasma-etch profile evolution.

Package map (paper part -> module):
  rules/       Event Rules Library compiler and kinetic laws   [supp_rule_schema, supp_kinetic_models]
  sim/         Monte Carlo feature-profile simulator           [supp_simulator]
  controls.py  the 14 process controls, transforms, LHS design [supp_data_generation, supp_representation]
  scenes.py    geometry/grid/horizon configs (paper, small, tiny)
  data/        HDF5 data contract, torch datasets, split manifests
  model/       encoder, EIC, MAC, MRC, decoder                  [Method, supp_eic, supp_mac, supp_mrc]
  baselines/   ConvLSTM, FNO, U-NO, CNO, DeepONet (+RuleFeat)  [supp_baselines, supp_rulefeat]
  registry.py  every model by name (NEMSim, ablations, baselines)
  inference/   the facade: weights-only checkpoint loader, runtimes, predictor
  training/    one-step training loop                          [supp_training]
  evaluation/  rollout protocol and metrics                    [supp_protocols]
  analysis/    counterfactual mechanism analysis, inverse design [supp_mechanism_alignment]
  geometry/    profile metrics and surface meshes
  cli/         the ``nemsim`` command, one module per command group

Imports point one way, between these packages and between files (tests/test_code_health.py, function-level
imports included); the library never imports ``service`` (the web API) or ``bench`` (the benchmark harness):
their commands join the CLI through the ``nemsim.cli`` entry points.
"""

__version__ = "0.1.0"
