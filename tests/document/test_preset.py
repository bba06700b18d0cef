"""Learned-layer presets: the catalogue's files, the rules, prompts and how references resolve."""

from __future__ import annotations

import json

import pytest

from lasagna.document import Preset, load_preset
from lasagna.errors import ConditionError, DocumentError
from tests.document.cases import DELETE, ROOT, load_json, patched

CATALOGUE = ROOT / "layers"


def shading() -> dict:
    return load_json(CATALOGUE / "shading" / "preset.json")


def test_catalogue_presets_load():
    presets = {name: load_preset(CATALOGUE / name) for name in ("shading", "color", "light")}
    assert (presets["shading"].blend, presets["shading"].channels, presets["shading"].range) == (
        "multiply",
        1,
        (0.0, 2.0),
    )
    assert presets["shading"].vocabulary == (
        "left",
        "right",
        "top",
        "bottom",
        "top-left",
        "top-right",
        "bottom-left",
        "bottom-right",
    )
    assert (presets["color"].blend, presets["color"].channels) == ("normal", 4)
    assert (presets["light"].blend, presets["light"].channels, presets["light"].range) == ("plus", 3, (0.0, 1.0))
    for name, preset in presets.items():
        assert preset.name == name
        assert (CATALOGUE / name / "preset.json").read_text(encoding="utf-8") == preset.to_json()  # canonical


def test_prompt_for_a_label():
    preset = Preset.from_dict(shading())
    assert preset.prompt_for("top-left") == "A photo of an object with top-left lighting"
    with pytest.raises(ConditionError, match="^condition.label: label 'up' is not in preset 'shading'"):
        preset.prompt_for("up")


INVALID = [
    ("unknown loss", "distill.loss", "vsd", "distill.loss", "expected 'sds', 'lmc-sds'"),
    ("t_min above t_max", "distill.t_min", 0.99, "distill.t_min", "t_min < t_max"),
    ("negative guidance", "distill.guidance", -1.0, "distill.guidance", "greater than 0"),
    ("zero steps", "distill.steps", 0, "distill.steps", "greater than or equal to 1"),
    ("lmc-sds without corrective", "corrective", None, "corrective", "needs a corrective"),
    ("two channels", "channels", 2, "channels", "expected 1, 3 or 4"),
    ("range for normal", "blend", "normal", "range", "allowed only for multiply and plus"),
    ("prompt without placeholder", "prompt", "A photo", "prompt", "exactly one '{label}'"),
    ("prompt with another placeholder", "prompt", "{label} {colour}", "prompt", "exactly one '{label}'"),
    ("prompt with a stray brace", "prompt", "{label", "prompt", "not a valid template"),
    ("repeated label", "vocabulary", ["left", "left"], "vocabulary[1]", "labels are unique"),
    ("padded label", "vocabulary", [" left"], "vocabulary[0]", "outer spaces"),
    ("empty vocabulary", "vocabulary", [], "vocabulary", "expected at least 1"),
    ("prior escaping", "prior", "../weights", "prior", "escapes the stack folder"),
    ("unknown field", "weights", "x", "weights", "unknown field"),
    ("missing format", "format", DELETE, "format", "required field is missing"),
]


@pytest.mark.parametrize(("what", "path", "value", "json_path", "rule"), INVALID, ids=[c[0] for c in INVALID])
def test_invalid_presets(what, path, value, json_path, rule):
    data = shading()
    if what == "lmc-sds without corrective":
        data["distill"]["loss"] = "lmc-sds"
    with pytest.raises(DocumentError) as info:
        Preset.from_dict(patched(data, path, value), "preset.json")
    assert str(info.value).startswith(f"preset.json: {json_path}: "), str(info.value)
    assert rule in str(info.value), str(info.value)


def test_name_must_match_folder(tmp_path):
    (tmp_path / "relight").mkdir()
    (tmp_path / "relight" / "preset.json").write_text(json.dumps(shading()), encoding="utf-8")
    with pytest.raises(DocumentError, match=r"name: name 'shading' differs from its folder 'relight'"):
        load_preset(tmp_path / "relight")
