"""NEMSim: a neural surrogate for 3-D plasma-etch profile evolution.

Package map (paper part -> module):
  rules/       Event Rules Library compiler and kinetic laws   [supp_rule_schema, supp_kinetic_models]
  sim/         Monte Carlo feature-profile simulator           [supp_simulator]
  controls.py  the 14 process controls, transforms, LHS design [supp_data_generation, supp_representation]
  scenes.py    geometry/grid/horizon configs (paper, small, tiny)
  data/        HDF5 data contract, torch datasets, split manifests
  model/       encoder, EIC, MAC, MRC, decoder                  [Method, supp_eic, supp_mac, supp_mrc]
  baselines/   ConvLSTM, FNO, U-NO, CNO, DeepONet (+RuleFeat)  [supp_baselines, supp_rulefeat]
  training/    one-step training loop                          [supp_training]
  evaluation/  rollout protocol and metrics                    [supp_protocols]
  analysis/    counterfactual mechanism analysis               [supp_mechanism_alignment]
  geometry/    profile metrics and surface meshes
"""

__version__ = "0.1.0"
