"""The optional subject.yaml: known facts, their validation, and what the fit records."""

import pytest
import yaml

from torchfit.config import Config
from torchfit.errors import DataError
from torchfit.io.dataset import load_subject, validate_facts
from torchfit.pipeline.prepare import prepare_subject


def test_valid_facts_are_read(tmp_path):
    (tmp_path / "subject.yaml").write_text("height_m: 1.74\nweight_kg: 70.5\nsex: female\n")
    subject = load_subject(tmp_path)
    assert subject.facts == {"height_m": 1.74, "weight_kg": 70.5, "sex": "female"}
    assert not any("subject.yaml" in p for p in subject.problems)


@pytest.mark.parametrize(
    "facts, message",
    [
        ({"height_m": 0.9}, "height_m must be a number from 1 to 2.5 m, got 0.9"),
        ({"height_m": 2.6}, "height_m must be a number from 1 to 2.5 m, got 2.6"),
        ({"height_m": "tall"}, "height_m must be a number from 1 to 2.5 m"),
        ({"sex": "other"}, "sex must be 'female' or 'male', got 'other'"),
        ({"weight_kg": -3}, "weight_kg must be a number from 20 to 300 kg"),
        ({"age": 30}, "unknown key 'age' (valid keys: height_m, weight_kg, sex)"),
    ],
)
def test_bad_facts_fail_the_subject_with_a_clear_message(tmp_path, facts, message):
    (tmp_path / "subject.yaml").write_text(yaml.safe_dump(facts))
    subject = load_subject(tmp_path)
    found = [p for p in subject.problems if "subject.yaml" in p]
    assert len(found) == 1 and message in found[0], found
    assert subject.facts == {}
    with pytest.raises(DataError, match="subject.yaml"):
        prepare_subject(subject, Config())


def test_not_a_mapping_and_bad_yaml(tmp_path):
    assert validate_facts([1, 2]) == ["subject.yaml: expected a mapping of facts, got list"]
    (tmp_path / "subject.yaml").write_text("height_m: [1.7\n")
    problems = load_subject(tmp_path).problems
    assert any("subject.yaml: invalid YAML" in p for p in problems)


def test_subject_yaml_counts_in_the_fingerprint(tmp_path, model):
    from template_subjects import make_template_subject

    from torchfit.pipeline.fingerprint import inputs_digest

    make_template_subject(tmp_path / "s", model, seed=2)
    before = inputs_digest(load_subject(tmp_path / "s"))
    (tmp_path / "s" / "subject.yaml").write_text("height_m: 1.7\n")
    with_height = inputs_digest(load_subject(tmp_path / "s"))
    (tmp_path / "s" / "subject.yaml").write_text("height_m: 1.71\n")
    changed = inputs_digest(load_subject(tmp_path / "s"))
    assert len({before, with_height, changed}) == 3
