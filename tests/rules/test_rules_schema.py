"""Validation of rules YAML: every error names the event and the field."""

from __future__ import annotations

import pytest
import yaml

from nemsim.rules import RulesError, parse_rules


def _edit(text: str, index: int, **changes) -> str:
    data = yaml.safe_load(text)
    ev = data["events"][index]
    for key, value in changes.items():
        if value is _DELETE:
            del ev[key]
        else:
            ev[key] = value
    return yaml.safe_dump(data, sort_keys=False)


_DELETE = object()


def _expect(text: str, event: str, field: str) -> str:
    with pytest.raises(RulesError) as info:
        parse_rules(text)
    msg = str(info.value)
    assert f"event '{event}'" in msg and f"field '{field}'" in msg, msg
    assert "\n" not in msg
    return msg


def test_library_loads(spec):
    assert len(spec.events) == 37
    assert sum(ev.is_primary for ev in spec.events) == 22
    assert spec.events[0].name == "Cl_on_Si_to_SiCl"
    assert spec.events[4].name == "Cl_on_SiCl3_etch"


def test_unknown_species(rules_text):
    msg = _expect(_edit(rules_text, 6, projectile="Cl3+"), "Clp_on_Si_phys", "projectile")
    assert "unknown species" in msg and "'Cl3+'" in msg
    _expect(_edit(rules_text, 0, target="Ge"), "Cl_on_Si_to_SiCl", "target")


def test_unknown_control_key(rules_text):
    msg = _expect(_edit(rules_text, 7, flux_key="flux_xe_plus"), "Clp_on_SiCl_phys", "flux_key")
    assert "unknown control key" in msg


def test_missing_field(rules_text):
    msg = _expect(_edit(rules_text, 1, flux_key=_DELETE), "Cl_on_SiCl_to_SiCl2", "flux_key")
    assert "missing field" in msg
    # a required parameter of the model
    data = yaml.safe_load(rules_text)
    del data["events"][8]["prob_params"]["p0"]
    _expect(yaml.safe_dump(data), "Clp_on_SiCl_chem", "prob_params.p0")
    # a required identity field: the event is named by its index
    data = yaml.safe_load(rules_text)
    del data["events"][3]["group"]
    _expect(yaml.safe_dump(data), "Cl_on_SiCl2_to_SiCl_back", "group")


def test_unsupported_model(rules_text):
    msg = _expect(_edit(rules_text, 6, prob_model="arrhenius"), "Clp_on_Si_phys", "prob_model")
    assert "unsupported model" in msg
    _expect(_edit(rules_text, 6, yield_model="sigmund"), "Clp_on_Si_phys", "yield_model")
    _expect(_edit(rules_text, 30, dep_model="from_gas"), "SiCl2_dep_on_SiCl3", "dep_model")


def test_unsupported_angular_law(rules_text):
    data = yaml.safe_load(rules_text)
    data["events"][8]["prob_params"]["angle"] = "Q"
    msg = _expect(yaml.safe_dump(data), "Clp_on_SiCl_chem", "prob_params.angle")
    assert "unsupported angular law" in msg


def test_bad_product_relation(rules_text):
    bad = [{"species": "SiCl2", "coeff": -1.0}]
    msg = _expect(_edit(rules_text, 1, products=bad), "Cl_on_SiCl_to_SiCl2", "products[0].coeff")
    assert "bad product relation" in msg
    twice = [{"species": "SiCl", "coeff": 1.0}, {"species": "SiCl", "coeff": "yield"}]
    _expect(_edit(rules_text, 0, products=twice), "Cl_on_Si_to_SiCl", "products[1].species")
    _expect(_edit(rules_text, 0, products=[{"species": "SiCl", "coeff": "twice"}]), "Cl_on_Si_to_SiCl",
            "products.0.coeff")  # fmt: skip
    # a deposition species nobody generates
    data = yaml.safe_load(rules_text)
    for ev in data["events"][:22]:
        ev["products"] = [p for p in ev.get("products", []) if p["species"] != "SiCl3"]
    _expect(yaml.safe_dump(data), "SiCl3_dep_on_Si", "dep_params.species")


def test_duplicate_name(rules_text):
    msg = _expect(_edit(rules_text, 5, name="Cl_on_Si_to_SiCl"), "Cl_on_Si_to_SiCl", "name")
    assert "duplicate" in msg and "#6" in msg


def test_unknown_field_and_ranges(rules_text):
    _expect(_edit(rules_text, 0, colour="blue"), "Cl_on_Si_to_SiCl", "colour")
    _expect(_edit(rules_text, 0, prob_params={"p_const": 1.5}), "Cl_on_Si_to_SiCl", "prob_params.p_const")
    _expect(_edit(rules_text, 22, flux_key="flux_cl"), "SiCl_dep_on_Si", "flux_key")


def test_not_yaml():
    with pytest.raises(RulesError):
        parse_rules("events: [")
    with pytest.raises(RulesError):
        parse_rules("just text")
