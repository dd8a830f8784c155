"""Training: TrainConfig ([supp_training]), the one-step training loop, checkpoints with provenance.

Import the submodules (``config``, ``loop``, ``checkpoint``); nothing heavy happens here.
"""
