"""Training: TrainConfig ([supp_training]) and the training loop. Checkpoint I/O is ``nemsim.inference.checkpoint``
(a level below, so evaluation reads checkpoints without depending on training).

Import the submodules (``config``, ``loop``); nothing heavy happens here.
"""
