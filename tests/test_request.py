"""``lasagna.request``: what a request may ask of a preset, checked once and without torch.

References: the shipped presets' own fields (vocabulary, ``surface``, ``layer_kind``), and the same requests made
by ``lasagna.edit`` (through ``Recipe.for_edit``), which must refuse exactly what ``check_request`` refuses."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lasagna.catalogue import load_preset
from lasagna.errors import ConditionError, LasagnaError
from lasagna.request import PROMPT_LABEL, EditRequest, check_request, layer_kind

ROOT = Path(__file__).resolve().parents[1]
CATALOGUE = [ROOT / "layers"]


def preset(name: str):
    return load_preset(name, catalogue_dirs=CATALOGUE)


def test_importing_it_imports_no_torch():
    code = "import sys, lasagna.request, lasagna.catalogue; print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert done.stdout.split() == ["False"]


@pytest.mark.parametrize("name", ["shading", "relight", "color", "light"])
def test_the_default_label_is_the_vocabularys_first(name):
    p = preset(name)
    assert check_request(EditRequest(preset=name), p) == p.vocabulary[0]
    for label in p.vocabulary:
        assert check_request(EditRequest(preset=name, condition=label), p) == label


def test_a_label_outside_the_vocabulary_is_refused_with_the_vocabulary():
    p = preset("color")
    with pytest.raises(ConditionError, match="not in preset 'color'") as e:
        check_request(EditRequest(preset="color", condition="sideways"), p)
    assert all(label in e.value.message for label in p.vocabulary)


def test_a_prompt_needs_no_label():
    p = preset("shading")
    assert check_request(EditRequest(preset="shading", prompt="soft light", layer_kind="free"), p) == PROMPT_LABEL


def test_the_kind_and_its_light():
    relight = preset("relight")
    assert layer_kind(EditRequest(preset="relight"), relight) == relight.layer_kind
    assert layer_kind(EditRequest(preset="relight", prompt="x"), relight) == "free"  # only a free layer reads text
    # a source light is only a surface relight's (rule FK): --from alone makes one; a free layer's method does not
    assert layer_kind(EditRequest(preset="relight", source_light="top"), relight) == "surface"
    assert layer_kind(EditRequest(preset="relight", source_light="top", generator="free"), relight) == "free"
    assert layer_kind(EditRequest(preset="color", source_light="top"), preset("color")) == preset("color").layer_kind
    surface = EditRequest(preset="relight", layer_kind="surface", condition="az=30,el=40")
    assert check_request(surface, relight) == "az=30,el=40"  # any light, not only the vocabulary's
    with pytest.raises(ConditionError, match="az=A,el=E"):
        check_request(EditRequest(preset="relight", layer_kind="surface", condition="sideways"), relight)
    with pytest.raises(LasagnaError, match="names no surface estimator"):
        check_request(EditRequest(preset="color", layer_kind="surface"), preset("color"))
    with pytest.raises(LasagnaError, match="expected --layer-kind surface"):
        check_request(EditRequest(preset="relight", layer_kind="free", source_light="left"), relight)


def test_a_bad_source_light_is_reported_at_from():
    with pytest.raises(ConditionError) as e:
        EditRequest(preset="relight", layer_kind="surface", source_light="az=999")
    assert e.value.where == "from" and "az=999" in e.value.message


@pytest.mark.parametrize(
    "request_",
    [
        EditRequest(preset="color", condition="sideways"),
        EditRequest(preset="relight", layer_kind="surface", condition="sideways"),
        EditRequest(preset="color", layer_kind="surface"),
        EditRequest(preset="relight", layer_kind="free", source_light="left"),
        EditRequest(preset="shading", generator="amortised", prompt="x"),
    ],
)
def test_the_edit_refuses_what_the_check_refuses(request_, tmp_path):
    """``Recipe.for_edit`` calls ``check_request``: the library's refusal is the check's, message for message."""
    import lasagna

    with pytest.raises(LasagnaError) as checked:
        check_request(request_, preset(request_.preset))
    with pytest.raises(LasagnaError) as edited:
        lasagna.edit(ROOT / "examples" / "photos" / "chelsea.png", request=request_)
    assert (edited.value.message, edited.value.where) == (checked.value.message, checked.value.where)
