"""The ``relight`` preset (issue #11): an already lit image relit by a 1-channel luminosity ratio in [0, 4].

Runs on the tiny random catalogue (tests/support/tinylayers.py): the machinery, the record and the maths of the layer
against the world's truth format, not the trained prior's quality (benchmarks/relight.py measures that).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.editing import edit
from lasagna.io.render import render_stack
from lasagna.world import generate
from lasagna.world.tasks import relight_sources, relighting


@pytest.fixture(autouse=True)
def _catalogue(tiny, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))


def lit_scene(size: int = 16):
    scene = generate("heldout", 1, seed=0, resolution=size, labels=["left"], dtype=torch.float64)
    return relighting(scene, relight_sources(scene.params))


def test_relight_layer_is_a_ratio_multiplied_onto_the_lit_image():
    rel = lit_scene()
    result = edit(rel.base[0].float(), "relight", "left")
    layer = result.stack.document.layer(result.layer_id)
    assert (layer.kind, layer.blend, tuple(layer.range), layer.preset) == ("learned", "multiply", (0.0, 4.0), "relight")
    y = result.layer
    assert y.shape == (1, 16, 16) and float(y.min()) >= 0.0 and float(y.max()) <= 4.0
    # the composite is the (stored) input times the ratio, clamped per layer: multiply's formula in float64
    base = result.stack.tensors["base"].color.double()
    want = (base * result.stack.tensors[result.layer_id].color.double()).clamp(0, 1)
    got = render_stack(result.stack, dtype=torch.float64).image
    assert torch.allclose(got, want, atol=1e-12)


def test_the_truth_ratio_in_the_layer_relights_the_scene_exactly():
    """The layer's range holds the world's ratio S_B / S_A ∈ [0.25, 4]: the true layer stored in a relight
    stack composites to the scene under B (up to 16-bit storage)."""
    from lasagna.io.stack import Stack

    rel = lit_scene()
    stack = Stack.from_image(rel.base[0])
    stack.add_layer("relit", rel.layer[0], blend="multiply", range=(0, 4), bit_depth=16)
    got = render_stack(stack, dtype=torch.float64).image
    assert float((got - rel.target[0].clamp(0, 1)).abs().max()) < 4 / 65535 + 1e-9


def test_relight_refuses_a_label_outside_its_vocabulary():
    from lasagna.errors import ConditionError

    with pytest.raises(ConditionError, match="top-left"):
        edit(lit_scene().base[0].float(), "relight", "sideways")


def test_relight_is_ready_in_the_catalogue_status(tiny):
    from lasagna import catalogue as cat

    status = cat.preset_status("relight", [tiny])
    assert status["usable"] and status["method"] == "per-image" and "relit-32" in status["why"]
    assert np.isclose(cat.load_preset("relight", catalogue_dirs=[tiny]).range[1], 4.0)


def test_any_direction_is_a_condition_recorded_as_given():
    rel = lit_scene()
    result = edit(rel.base[0].float(), "relight", "az=135,el=40")
    layer = result.stack.document.layer(result.layer_id)
    assert layer.condition.label == "az=135,el=40" and result.layer_id == "relight-az135-el40"
    named = edit(rel.base[0].float(), "relight", "az=135,el=60")  # top-left's direction, given as angles
    top_left = edit(rel.base[0].float(), "relight", "top-left")
    assert torch.equal(named.layer, top_left.layer)  # a named light is just its direction


def test_a_direction_needs_a_prior_trained_on_directions():
    from lasagna.errors import ConditionError

    with pytest.raises(ConditionError, match="--directions"):
        edit(torch.rand(3, 16, 16), "shading", "az=135,el=40", generator="free")
    with pytest.raises(ConditionError, match="unknown label 'az=135,el=40'"):  # the amortised generator: labels only
        edit(torch.rand(3, 16, 16), "shading", "az=135,el=40", generator="amortised")
    with pytest.raises(ConditionError, match="az=A,el=E"):
        edit(torch.rand(3, 16, 16), "relight", "az=135,el=95")
