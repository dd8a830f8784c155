"""Evaluation: everything that scores or times a model against the data or the simulator ([supp_protocols]).

One package, three groups of modules (each a small module named after what it measures):

  protocol   ``metrics`` (field and surface metrics), ``rollout`` (autoregressive rollouts), ``evaluate``
             (a checkpoint on a test split: ``nemsim evaluate``), ``runtime`` (the inference backends)
  stress     ``stress``, ``invariants`` (physical invariants, ``nemsim stress``), ``truth`` (simulator runs
             that judge a model), ``physics``, ``extrapolation`` (``nemsim bench physics|extrapolation``)
  speed      ``speed_error`` (``nemsim bench speed-error``), ``rollout_speed`` (``nemsim bench rollout``),
             ``noise`` (the Monte Carlo noise floor, ``nemsim bench noise``), ``results`` (``bench collect``)

They share the metrics and rollouts, which is why they stay one package rather than three (every benchmark
scores with exactly the functions ``nemsim evaluate`` uses). Kept import-light: import the submodules you
need; nothing heavy is imported here.
"""
