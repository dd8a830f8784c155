"""Evaluation: field and surface metrics ([supp_protocols]) and autoregressive rollouts.

Kept import-light: import the submodules you need (``nemsim.evaluation.metrics``,
``nemsim.evaluation.rollout``); nothing heavy is imported here.
"""
