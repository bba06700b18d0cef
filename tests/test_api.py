"""The small Python API (``lasagna.api``) and the runnable tour in examples/api_tour.py."""

from __future__ import annotations

import runpy
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import lasagna.api as api
from tests.reference import composite_reference, to_uint8

ROOT = Path(__file__).resolve().parents[1]
BASIC = ROOT / "examples" / "stacks" / "basic"


def test_load_render_save(tmp_path):
    stack = api.load(BASIC)
    result = api.render(stack)
    assert result.image.shape == (3, 48, 64) and result.skipped == {"hidden": "hidden"}
    same = api.render(BASIC)  # a path works too
    assert torch.equal(same.image, result.image)
    written = api.save(stack, tmp_path / "copy", composite=True)
    assert written == tmp_path / "copy" / "stack.json"
    ours = np.asarray(Image.open(tmp_path / "copy/composite.png")).astype(int)
    assert np.abs(ours - to_uint8(composite_reference(BASIC))).max() <= 1


def test_build_from_tensors_and_pil(tmp_path):
    albedo = Image.fromarray((np.random.default_rng(0).random((8, 10, 3)) * 255).astype(np.uint8))
    stack = api.from_tensors(
        [
            ("albedo", albedo),
            {"id": "shade", "image": torch.full((1, 8, 10), 1.5), "blend": "multiply", "range": (0, 2)},
        ]
    )
    api.save(stack, tmp_path / "s")
    ref = composite_reference(tmp_path / "s")
    # In memory the multiplier is exactly 1.5; saved it is the nearest 16-bit step of [0, 2] (±1.5e-5).
    assert np.abs(api.render(stack, dtype=torch.float64).image.numpy() - ref).max() < 2e-5
    assert api.from_image(albedo).ids == ("base",)
    api.export_psd(stack, tmp_path / "s.psd")
    api.export_ora(stack, tmp_path / "s.ora")
    back = api.import_ora(tmp_path / "s.ora")
    assert back.ids == ("albedo", "shade") and back.layer("shade").range == (0.0, 2.0)


def test_gradients_reach_layer_tensors_and_opacity():
    base = torch.rand(3, 6, 6)
    shade = torch.rand(1, 6, 6, requires_grad=True)
    stack = api.from_image(base)
    stack.add_layer("shade", shade, blend="multiply")
    api.render(stack).image.sum().backward()
    np.testing.assert_allclose(shade.grad.numpy()[0], base.sum(0).numpy(), rtol=1e-5)  # d(Σ base·y)/dy


def test_api_tour_example_runs(tmp_path, capsys):
    module = runpy.run_path(str(ROOT / "examples" / "api_tour.py"))
    module["main"](tmp_path)
    out = capsys.readouterr().out
    assert (
        "gradients flow" in out and (tmp_path / "tour.ora").is_file() and (tmp_path / "stack/composite.png").is_file()
    )


def test_render_refuses_batches_for_png(tmp_path):
    from lasagna.errors import ImageError

    with pytest.raises(ImageError, match="expected \\(3, H, W\\)"):
        api.write_composite(torch.rand(2, 3, 4, 4), tmp_path / "x.png")
