"""The small Python API (``lasagna.api``) and the runnable tour in examples/api_tour.py."""

from __future__ import annotations

import runpy
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import lasagna.api as api
from tests.support.reference import composite_reference, to_uint8

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


def test_to_pil_and_to_numpy_equal_the_composite_png(tmp_path):
    stack = api.load(BASIC)
    api.save(stack, tmp_path / "copy", composite=True)
    png = np.asarray(Image.open(tmp_path / "copy/composite.png").convert("RGB"))
    for source in (stack, BASIC, api.render(stack), api.render(stack).image):
        codes = api.to_numpy(source)
        assert codes.shape == (48, 64, 3) and codes.dtype == np.uint8
        assert np.array_equal(codes, png)
    pil = api.to_pil(stack)
    assert pil.mode == "RGB" and pil.size == (64, 48) and np.array_equal(np.asarray(pil), png)
    gray = api.to_numpy(torch.full((1, 2, 3), 0.5))
    assert gray.shape == (2, 3, 3) and (gray == 128).all()  # round half to even of 127.5
    with pytest.raises(api.ImageError, match="expected a RenderResult"):
        api.to_pil(torch.zeros(2, 3, 4, 4))
    with pytest.raises(api.ImageError, match="NaN"):
        api.to_pil(torch.full((3, 2, 2), float("nan")))


def test_numpy_arrays_may_be_channels_last():
    g = np.random.default_rng(0)
    hwc = g.integers(0, 256, (6, 9, 3), dtype=np.uint8)
    a = api.from_image(hwc)
    b = api.from_image(hwc.transpose(2, 0, 1))  # channels first, as before
    assert (a.width, a.height) == (9, 6)
    assert torch.equal(a.tensors["base"].color, b.tensors["base"].color)
    rgba = g.random((7, 5, 4)).astype(np.float32)
    c = api.from_image(rgba)
    assert c.tensors["base"].color.shape == (3, 7, 5) and c.tensors["base"].alpha.shape == (1, 7, 5)
    assert torch.equal(c.tensors["base"].alpha[0], torch.from_numpy(rgba[..., 3]))
    # tensors stay channels first: a (6, 9, 3) tensor is refused with the rule
    with pytest.raises(api.ImageError, match="numpy array may be"):
        api.from_image(torch.from_numpy(hwc).float())


def test_top_level_names_are_the_api_functions():
    import lasagna
    import lasagna.editing

    assert lasagna.edit is api.edit is lasagna.editing.edit
    assert lasagna.edit_many is api.edit_many and lasagna.render_learned is api.render_learned
    assert lasagna.to_pil is api.to_pil


def test_the_api_names_are_declared_once_and_listed_lazily():
    import subprocess
    import sys

    import lasagna

    assert lasagna.__all__ == ["__version__", *api.__all__]
    assert set(api.__all__) <= set(dir(lasagna)) and all(getattr(lasagna, n) is getattr(api, n) for n in api.__all__)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        lasagna.nope  # noqa: B018
    code = (
        "import sys, lasagna, lasagna.document\nfrom lasagna import catalogue, errors\n"
        "assert 'torch' not in sys.modules and 'lasagna.api' not in sys.modules\n"
        "print(len(dir(lasagna)), 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[1] == "True"  # dir() loads the API


def test_edit_refuses_a_preset_object_in_one_line():
    from lasagna.catalogue import resolve
    from lasagna.errors import LasagnaError

    preset = resolve("shading", need_prior=False).preset
    with pytest.raises(LasagnaError, match="got a Preset; expected a catalogue name") as err:
        api.edit(torch.rand(3, 8, 8), preset=preset)
    assert "\n" not in str(err.value)
