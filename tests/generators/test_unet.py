"""LayerGenerator and FreeLayer: identity start for every preset, shapes at any size, ranges, the
gradient path through the composite, condition handling, and save/load."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lasagna.document.preset import load_preset
from lasagna.errors import ConditionError, LasagnaError
from lasagna.generators import FreeLayer, FreeLayerConfig, LayerGenerator, LayerGeneratorConfig, LayerSpec, composite

LAYERS = Path(__file__).resolve().parents[2] / "layers"
PRESETS = ("shading", "color", "light")


def toy(preset: str = "shading", **kw) -> LayerGenerator:
    torch.manual_seed(0)
    return LayerGenerator(LayerGeneratorConfig.for_preset(load_preset(LAYERS / preset), channels=(8, 16, 16), **kw))


def perturb(model: torch.nn.Module, seed: int = 1, scale: float = 0.05) -> None:
    """Random head weights, so outputs leave the identity (the trained case)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn(p.shape, generator=g) * scale)


class TestLayerGenerator:
    @pytest.mark.parametrize("preset", PRESETS)
    @pytest.mark.parametrize("condition", ["frequency", "embedding"])
    def test_first_composite_equals_input(self, preset, condition):
        gen = toy(preset, condition=condition)
        p = load_preset(LAYERS / preset)
        base = torch.rand(3, 3, 16, 16, generator=torch.Generator().manual_seed(2))
        layer = gen(base, list(p.vocabulary[:1]) * 3)
        assert (composite(base, layer, gen.spec) - base).abs().max() <= 1e-5

    def test_default_widths_and_size(self):
        cfg = LayerGeneratorConfig.for_preset(load_preset(LAYERS / "shading"))
        assert cfg.channels == (16, 32, 64, 128) and cfg.blocks == 2 and cfg.condition == "frequency"
        n = sum(p.numel() for p in LayerGenerator(cfg).parameters())
        assert 300_000 < n < 700_000

    @pytest.mark.parametrize("hw", [(16, 16), (8, 24), (13, 7), (1, 1), (33, 20)])
    def test_shapes_at_any_size(self, hw):
        gen = toy("color")
        base = torch.rand(2, 3, *hw)
        assert gen(base, "natural").shape == (2, 4, *hw)

    @pytest.mark.parametrize("preset", PRESETS)
    def test_output_in_range_after_training_like_weights(self, preset):
        gen = toy(preset)
        perturb(gen)
        spec = gen.spec
        y = gen(torch.rand(4, 3, 16, 16), load_preset(LAYERS / preset).vocabulary[0])
        lo, hi = spec.range
        colour = y[:, : spec.colour_channels]
        assert colour.min() >= lo and colour.max() <= hi
        if spec.has_alpha:
            assert y[:, 3:].min() >= 0 and y[:, 3:].max() <= 1

    def test_labels_change_the_output(self):
        gen = toy("shading")
        perturb(gen)
        base = torch.rand(1, 3, 8, 8)
        assert not torch.allclose(gen(base, "left"), gen(base, "right"))
        idx = torch.tensor([0, 1])
        assert torch.equal(gen(base.repeat(2, 1, 1, 1), idx), gen(base.repeat(2, 1, 1, 1), ["left", "right"]))

    def test_condition_errors(self):
        gen = toy("shading")
        with pytest.raises(ConditionError, match="unknown label 'sideways'"):
            gen(torch.rand(1, 3, 8, 8), "sideways")
        with pytest.raises(ConditionError, match="3 labels for a batch of 2"):
            gen(torch.rand(2, 3, 8, 8), ["left", "right", "top"])
        with pytest.raises(ConditionError, match="indices"):
            gen(torch.rand(1, 3, 8, 8), torch.tensor([99]))
        with pytest.raises(LasagnaError, match=r"expected \(B, 3, H, W\)"):
            gen(torch.rand(1, 1, 8, 8), "left")

    @pytest.mark.parametrize("preset", PRESETS)
    def test_gradient_reaches_every_parameter_through_the_composite(self, preset):
        gen = toy(preset)
        perturb(gen)
        base = torch.rand(2, 3, 8, 8)
        target = torch.rand(2, 3, 8, 8)
        out = composite(base, gen(base, load_preset(LAYERS / preset).vocabulary[0]), gen.spec)
        (out - target).pow(2).mean().backward()
        grads = {n: p.grad for n, p in gen.named_parameters()}
        assert all(g is not None and torch.isfinite(g).all() for g in grads.values())
        assert grads["head.weight"].abs().sum() > 0 and grads["enc.0.0.weight"].abs().sum() > 0

    def test_at_identity_only_the_head_moves_first(self):
        """Zero head weights: the first gradient reaches the head (not the trunk): the start is stable."""
        gen = toy("shading")
        base = torch.rand(2, 3, 8, 8)
        composite(base, gen(base, "left"), gen.spec).sum().backward()
        assert gen.head.weight.grad.abs().sum() > 0 and gen.head.bias.grad.abs().sum() > 0
        assert gen.enc[0][0].weight.grad.abs().sum() == 0

    def test_save_load_roundtrip(self, tmp_path):
        gen = toy("color", condition="embedding")
        perturb(gen)
        gen.save_pretrained(tmp_path / "g")
        back = LayerGenerator.from_pretrained(tmp_path / "g")
        base = torch.rand(1, 3, 8, 8)
        assert back.config == gen.config and torch.equal(back(base, "natural"), gen(base, "natural"))

    def test_load_refuses_other_format(self, tmp_path):
        fl = FreeLayer(FreeLayerConfig(layer=LayerSpec(blend="plus", channels=3), height=2, width=2))
        fl.save_pretrained(tmp_path / "f")
        with pytest.raises(LasagnaError, match="lasagna.layer_generator"):
            LayerGenerator.from_pretrained(tmp_path / "f")


class TestFreeLayer:
    @pytest.mark.parametrize("preset", PRESETS)
    def test_identity_and_shape(self, preset):
        spec = LayerSpec.from_preset(load_preset(LAYERS / preset))
        fl = FreeLayer(FreeLayerConfig(layer=spec, batch=2, height=5, width=6))
        base = torch.rand(2, 3, 5, 6)
        y = fl(base)
        assert y.shape == (2, spec.channels, 5, 6)
        assert torch.equal(composite(base, y, spec), base)

    def test_shape_mismatch(self):
        fl = FreeLayer(FreeLayerConfig(layer=LayerSpec(blend="plus", channels=3), batch=1, height=4, width=4))
        with pytest.raises(LasagnaError, match=r"expected \(1, C, 4, 4\)"):
            fl(torch.rand(1, 3, 4, 5))

    def test_from_layer_starts_there(self):
        spec = LayerSpec(blend="multiply", channels=1, range=(0.0, 2.0))
        y = torch.rand(2, 1, 3, 3) * 1.8 + 0.1
        assert torch.allclose(FreeLayer.from_layer(spec, y)(), y, atol=1e-5)

    def test_save_load(self, tmp_path):
        fl = FreeLayer(FreeLayerConfig(layer=LayerSpec(blend="normal", channels=4), batch=1, height=3, width=3))
        with torch.no_grad():
            fl.u.normal_()
        fl.save_pretrained(tmp_path / "f")
        assert torch.equal(FreeLayer.from_pretrained(tmp_path / "f")(), fl())
