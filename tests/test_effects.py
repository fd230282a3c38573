"""The effect registry is the one vocabulary: plant tables, model components and the diagnosis agree."""

from __future__ import annotations

from hilbench import effects as E
from hilbench.diagnosis.evidence import EVIDENCE_CHECKS, SIGNATURES
from hilbench.diagnosis.refit import effect_specs
from hilbench.diagnosis.testability import REQUIREMENTS
from hilbench.models.bases import BASES
from hilbench.models.effect_components import EFFECTS as MODEL_EFFECTS
from hilbench.models.model import Model, split_spec
from hilbench.sim.schema import PLANT_SCHEMA


def test_every_effect_names_a_plant_table_a_component_and_a_signature():
    for effect in E.EFFECTS.values():
        assert effect.plant_table in PLANT_SCHEMA, effect.name
        assert effect.component in {**BASES, **MODEL_EFFECTS}, effect.name
        assert effect.signature in SIGNATURES, effect.name
        assert all(r in REQUIREMENTS for r in effect.requires), effect.name
        assert effect.evidence_check is None or effect.evidence_check in EVIDENCE_CHECKS
        assert effect.form_choice in ("train", "inner-split", "inner-split-both", "inner-range", "inner-blocks")
    assert E.AUX_CHANNEL.signature in SIGNATURES


def test_every_plant_table_is_an_effect_or_part_of_the_bench():
    for table in PLANT_SCHEMA:
        assert E.effect_of_plant_table(table)  # raises KeyError for a table nobody declared


def test_every_form_is_a_spec_the_model_library_builds():
    for effect in E.EFFECTS.values():
        base = "linear" if E.MEMORYLESS_BASE in effect.requires else "pi"
        for spec in effect_specs(base, effect.name):
            Model(spec)  # raises SpecError for an unknown component or option
            names = [name for name, _ in split_spec(spec)]
            if E.MEMORYLESS_BASE in effect.requires:  # its forms are bases that replace ``linear``
                assert names[0] in effect.spec_parts() and names[0] in BASES, (effect.name, spec)
            else:
                assert effect.component in names, (effect.name, spec)


def test_an_aux_channel_is_an_effect_by_its_name():
    assert E.effect("temperature") is E.AUX_CHANNEL
    assert E.effect_of_plant_table("temperature") == "temperature"
    assert E.effect_of_plant_table("rate_dependence") == "rate-dependence"
