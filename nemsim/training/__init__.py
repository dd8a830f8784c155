"""Training: TrainConfig ([supp_training]) and the training loop; checkpoints are written and read by
``nemsim.inference.checkpoint``.

Import the submodules (``config``, ``loop``); nothing heavy happens here.
"""
