"""Evaluation: how a model is scored against the data or the simulator ([supp_protocols]).

``metrics`` (field and surface metrics), ``rollout`` (autoregressive rollouts), ``evaluate`` (a checkpoint
on a test split: ``nemsim evaluate``), ``truth`` (simulator runs that judge a model), ``figure`` (the
reports' PNG backend). The benchmark harness (``bench``) scores with exactly these functions. Kept
import-light: import the submodules you need; nothing heavy is imported here.
"""
