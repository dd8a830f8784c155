"""Analyses on trained models, built on ``nemsim.evaluation``'s rollouts and metrics (one way: evaluation
never imports analysis): counterfactual mechanism-response alignment ([supp_mechanism_alignment],
``counterfactual``), the sensitivity of the mechanism prior (``sensitivity``), inverse design (``inverse``)
and the conformal intervals of its profile metrics (``intervals``)."""
