"""JSON Schemas: committed files match the models, and examples, presets and the invalid table are
judged the same way by jsonschema (Draft 2020-12) as by the pydantic models, where JSON Schema can
express the rule."""

from __future__ import annotations

import json

import pytest
from jsonschema import Draft202012Validator

from lasagna.document import SCHEMA_BASE, Document, Preset, schemas, write_schemas
from lasagna.document.schema import schema_text
from tests.document.cases import ROOT, load_json, patched, valid_stack
from tests.document.test_models import INVALID, VALID

SCHEMA_DIR = ROOT / "schemas"
STACKS = sorted(ROOT.glob("examples/**/stack.json"))
PRESETS = sorted(ROOT.glob("layers/*/preset.json"))


@pytest.fixture(scope="module")
def stack_validator() -> Draft202012Validator:
    return Draft202012Validator(load_json(SCHEMA_DIR / "stack.schema.json"))


@pytest.fixture(scope="module")
def preset_validator() -> Draft202012Validator:
    return Draft202012Validator(load_json(SCHEMA_DIR / "preset.schema.json"))


@pytest.mark.parametrize("name", ["stack.schema.json", "preset.schema.json"])
def test_committed_schemas_match_the_models(name):
    generated = schemas()[name]
    assert (SCHEMA_DIR / name).read_text(encoding="utf-8") == schema_text(generated), (
        f"schemas/{name} is stale; regenerate with lasagna.document.write_schemas('schemas')"
    )
    Draft202012Validator.check_schema(generated)
    assert generated["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert generated["$id"] == SCHEMA_BASE + name


def test_write_schemas(tmp_path):
    written = write_schemas(tmp_path)
    assert sorted(p.name for p in written) == ["preset.schema.json", "stack.schema.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preset.schema.json", "stack.schema.json"]
    assert json.loads(written[0].read_text(encoding="utf-8")) == schemas()[written[0].name]


def test_there_are_examples_to_check():
    assert {p.parent.name for p in STACKS} >= {"basic", "linear", "masked", "learned"}
    assert {p.parent.name for p in PRESETS} >= {"shading", "color", "light"}


@pytest.mark.parametrize("path", STACKS, ids=[p.parent.name for p in STACKS])
def test_example_stacks_validate_both_ways(path, stack_validator):
    data = load_json(path)
    assert list(stack_validator.iter_errors(data)) == []
    doc = Document.from_dict(data, str(path))
    assert doc.to_json() == path.read_text(encoding="utf-8")  # examples are written canonical


@pytest.mark.parametrize("path", PRESETS, ids=[p.parent.name for p in PRESETS])
def test_catalogue_presets_validate_both_ways(path, preset_validator):
    data = load_json(path)
    assert list(preset_validator.iter_errors(data)) == []
    assert Preset.from_dict(data, str(path)).name == path.parent.name


@pytest.mark.parametrize(("what", "path", "value"), VALID, ids=[v[0] for v in VALID])
def test_schema_accepts_every_valid_document(what, path, value, stack_validator):
    assert list(stack_validator.iter_errors(patched(valid_stack(), path, value))) == []


@pytest.mark.parametrize(
    ("what", "path", "value", "json_path", "rule", "in_schema"), INVALID, ids=[c[0] for c in INVALID]
)
def test_schema_rejects_invalid_documents_where_it_can(what, path, value, json_path, rule, in_schema, stack_validator):
    errors = list(stack_validator.iter_errors(patched(valid_stack(), path, value)))
    # The flag is honest both ways: rules JSON Schema cannot state (lo < hi, unique ids, references,
    # escapes below the first segment, NaN) are left to the models.
    assert bool(errors) == in_schema, [e.message for e in errors]


@pytest.mark.parametrize(
    ("path", "value"),
    [
        ("distill.loss", "vsd"),
        ("distill.guidance", 0),
        ("distill.steps", 0),
        ("channels", 2),
        ("blend", "screen"),
        ("vocabulary", ["left", "left"]),
        ("prior", "/abs"),
        ("version", 2),
    ],
)
def test_preset_schema_rejects(path, value, preset_validator):
    data = load_json(ROOT / "layers" / "shading" / "preset.json")
    assert list(preset_validator.iter_errors(data)) == []
    assert list(preset_validator.iter_errors(patched(data, path, value))) != []
