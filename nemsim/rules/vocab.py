"""Vocabularies of the Event Rules Library ([supp_rule_schema], [eq:supp_projectile_vocab],
[eq:supp_target_vocab], [eq:supp_group_mapping]).

Every categorical field of ``rules/*.yaml`` is resolved against one of these tuples; the position in the
tuple is the integer identifier used by the compiled tensors (``R``, ``phi``, ``psi``, ``W_src``/``W_sink``
columns). Nothing else in NEMSim spells these lists out.
"""

from __future__ import annotations

# Projectile / product-species vocabulary, N_s = 8; index = column of W_src and W_sink.
PROJECTILES: tuple[str, ...] = ("Cl", "Cl2", "Cl+", "Cl2+", "Ar+", "SiCl", "SiCl2", "SiCl3")
# Target surface species.
TARGETS: tuple[str, ...] = ("Si", "SiCl", "SiCl2", "SiCl3", "Resist")
# Mechanism families, M = 3, in the paper's order (physical, chemical, coupled).
FAMILIES: tuple[str, ...] = ("physical", "chemical", "coupled")
# YAML `group` labels; `both` maps to the coupled family ([eq:supp_group_mapping]).
GROUPS: tuple[str, ...] = ("physical", "chemical", "both")
GROUP_TO_FAMILY: dict[str, int] = {"physical": 0, "chemical": 1, "both": 2}

# Optional `effect` field ([supp_rule_schema]: reaction, etching, sputtering or deposition).
EFFECTS: tuple[str, ...] = ("react", "etch", "sputter", "deposit")
# Kinetic model identifiers (index = compiled id).
PROB_MODELS: tuple[str, ...] = ("const", "probModel")
YIELD_MODELS: tuple[str, ...] = ("const", "yamamura")
ANGLE_KINDS: tuple[str, ...] = ("None", "P", "C")  # 0 none, 1 physical, 2 chemical angular law
DEP_MODELS: tuple[str, ...] = ("from_products_pool",)

# Species classes used by the meta flags.
ION_PROJECTILES: frozenset[str] = frozenset({"Cl+", "Cl2+", "Ar+"})
NEUTRAL_PROJECTILES: frozenset[str] = frozenset({"Cl", "Cl2"})
CHLORINATED_TARGETS: frozenset[str] = frozenset({"SiCl", "SiCl2", "SiCl3"})

N_SPECIES = len(PROJECTILES)
N_FAMILIES = len(FAMILIES)

__all__ = [
    "ANGLE_KINDS",
    "CHLORINATED_TARGETS",
    "DEP_MODELS",
    "EFFECTS",
    "FAMILIES",
    "GROUPS",
    "GROUP_TO_FAMILY",
    "ION_PROJECTILES",
    "NEUTRAL_PROJECTILES",
    "N_FAMILIES",
    "N_SPECIES",
    "PROB_MODELS",
    "PROJECTILES",
    "TARGETS",
    "YIELD_MODELS",
]
