"""Analyses on trained models: counterfactual mechanism-response alignment ([supp_mechanism_alignment])."""
