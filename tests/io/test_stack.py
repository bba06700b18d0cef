"""Stack folders: loading (range mapping, channel rules, masks, safe paths, limits), saving (16-bit
ranged layers, range errors, atomicity), building stacks from tensors and PIL images, rendering."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from PIL import Image

from lasagna.errors import DocumentError, ImageError, PathError
from lasagna.io.png import read_png
from lasagna.io.render import render_stack, write_composite
from lasagna.io.stack import NOT_RENDERED, Stack, load_stack, save_stack, stack_from_tensors
from tests.support.bounded import cpu_seconds
from tests.support.reference import composite_reference, read_png64, to_uint8
from tests.support.stackcraft import random_stack, write_png8, write_png16, write_stack

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "stacks"


def _doc(layers, w=6, h=4, **extra):
    return {"format": "lasagna.stack", "version": 1, "canvas": {"width": w, "height": h}, "layers": layers, **extra}


# ---- loading ----------------------------------------------------------------------------------------


def test_load_examples_and_range_mapping():
    stack = load_stack(EXAMPLES / "basic")
    assert stack.ids == ("base", "shade", "sticker", "glow", "hidden")
    shade = stack.tensors["shade"]
    assert shade.color.shape == (1, 48, 64) and shade.color.dtype == torch.float32
    stored, _ = read_png64(EXAMPLES / "basic/layers/shade.png")  # independent read: v
    np.testing.assert_allclose(shade.color.double().numpy(), 2.0 * stored, atol=1e-6)  # y = 0 + 2v
    assert "hidden" not in stack.tensors  # a solid layer: drawn from the document
    assert stack.bit_depths["shade"] == 16


def test_gray_alpha_multiply_is_one_channel_with_alpha(tmp_path):
    codes = np.stack([np.full((4, 6), 30000), np.full((4, 6), 65535)], axis=-1)
    codes[0, 0, 1] = 0
    write_png16(tmp_path / "layers/m.png", codes)
    write_png8(tmp_path / "layers/base.png", np.full((4, 6, 3), 200))
    write_stack(
        tmp_path,
        _doc(
            [
                {"id": "base", "kind": "pixels", "source": "layers/base.png"},
                {"id": "m", "kind": "pixels", "source": "layers/m.png", "blend": "multiply", "range": [0, 2]},
            ]
        ),
    )
    t = load_stack(tmp_path).tensors["m"]
    assert t.color.shape == (1, 4, 6) and t.alpha.shape == (1, 4, 6)
    assert t.color[0, 1, 1].item() == pytest.approx(2 * 30000 / 65535, abs=1e-6)
    assert t.alpha[0, 0, 0].item() == 0.0 and t.alpha[0, 1, 1].item() == 1.0  # alpha never range-mapped


def test_learned_layer_without_source_is_skipped_with_reason(tmp_path):
    write_png8(tmp_path / "layers/base.png", np.full((4, 6, 3), 100))
    write_stack(
        tmp_path,
        _doc(
            [
                {"id": "base", "kind": "pixels", "source": "layers/base.png"},
                {
                    "id": "relit",
                    "kind": "learned",
                    "preset": "shading",
                    "condition": {"label": "left"},
                    "conditioned_on": "base",
                    "blend": "multiply",
                },
            ]
        ),
    )
    stack = load_stack(tmp_path)
    assert stack.not_rendered == {"relit": NOT_RENDERED}
    result = render_stack(stack)
    assert result.skipped == {"relit": NOT_RENDERED} and result.evaluated == ["base"]


def test_symlink_inside_the_folder_is_fine(tmp_path):
    write_png8(tmp_path / "layers/real.png", np.full((4, 6, 3), 10))
    os.symlink(tmp_path / "layers/real.png", tmp_path / "layers/alias.png")
    write_stack(tmp_path, _doc([{"id": "base", "kind": "pixels", "source": "layers/alias.png"}]))
    assert load_stack(tmp_path / "stack.json").tensors["base"].color.shape == (3, 4, 6)


def test_escapes_and_limits(tmp_path):
    (tmp_path / "out").mkdir()
    write_png8(tmp_path / "out/x.png", np.zeros((4, 6, 3)))
    s = tmp_path / "s"
    (s / "layers").mkdir(parents=True)
    os.symlink(tmp_path / "out/x.png", s / "layers/x.png")
    write_stack(s, _doc([{"id": "base", "kind": "pixels", "source": "layers/x.png"}]))
    with pytest.raises(PathError, match="outside the stack folder"):
        load_stack(s)
    (s / "layers/x.png").unlink()
    write_png8(s / "layers/x.png", np.zeros((4, 6, 3)))
    with pytest.raises(ImageError, match="over the limit of 10"):
        load_stack(s, max_pixels=10)
    with pytest.raises(ImageError, match="in total"):
        load_stack(s, max_total_pixels=10)
    write_stack(s, _doc([{"id": "base", "kind": "pixels", "source": "layers/x.png"}]) | {"blend_space": "sRGB"})
    with pytest.raises(DocumentError, match="blend_space"):
        load_stack(s)


# ---- saving -----------------------------------------------------------------------------------------


@settings(max_examples=20, deadline=None)
@given(lo=st.floats(-2, 0), width=st.floats(0.5, 4), seed=st.integers(0, 2**16), channels=st.sampled_from([1, 3]))
def test_16bit_multiplier_round_trip_within_half_a_step(tmp_path_factory, lo, width, seed, channels):
    """A ranged layer saved as 16-bit comes back within (hi − lo)/65535/2 (plus float32 rounding)."""
    hi = lo + width
    assume((lo, hi) != (0.0, 1.0))  # [0, 1] layers are stored 8-bit (their own rule)
    rng = np.random.default_rng(seed)
    y = torch.from_numpy(lo + width * rng.random((channels, 5, 7)))
    stack = Stack.from_image(torch.rand(3, 5, 7))
    stack.add_layer("m", y, blend="plus" if lo < 0 else "multiply", range=(lo, hi))
    folder = tmp_path_factory.mktemp("rt")
    stack.save(folder)
    assert read_png(folder / "layers/m.png").header.bit_depth == 16
    back = load_stack(folder).tensors["m"].color.double()
    assert (back - y).abs().max().item() <= width / 65535 / 2 + 4e-7 * max(abs(lo), abs(hi))


def test_save_refuses_out_of_range_and_leaves_folder(tmp_path):
    stack = Stack.from_image(torch.rand(3, 4, 6))
    stack.add_layer("m", torch.full((1, 4, 6), 1.5), blend="multiply")  # range [0, 1]
    with pytest.raises(ImageError, match=r"outside the layer's range \[0, 1\].*clip=True"):
        stack.save(tmp_path / "s")
    assert not (tmp_path / "s").exists()
    stack.save(tmp_path / "s", clip=True)
    assert load_stack(tmp_path / "s").tensors["m"].color.max().item() == 1.0


def test_save_load_round_trip_examples(tmp_path):
    for name in ("basic", "masked", "linear", "learned"):
        stack = load_stack(EXAMPLES / name)
        save_stack(stack, tmp_path / name)
        again = load_stack(tmp_path / name)
        assert again.document == stack.document
        for id, t in stack.tensors.items():
            u = again.tensors[id]
            assert torch.equal(t.color, u.color)
            assert (t.alpha is None) == (u.alpha is None) and (t.alpha is None or torch.equal(t.alpha, u.alpha))
            assert (t.mask is None) == (u.mask is None) and (t.mask is None or torch.equal(t.mask, u.mask))


def test_save_requires_a_folder_and_pixels():
    stack = Stack.from_image(torch.rand(3, 2, 2))
    with pytest.raises(PathError, match="save\\(folder\\)"):
        stack.save()


# ---- building from tensors and PIL images ----------------------------------------------------------------


def test_build_from_pil_numpy_and_tensors(tmp_path):
    base = Image.fromarray(np.full((4, 6, 3), 51, dtype=np.uint8))
    stack = Stack.from_image(base, id="base", background=(0.1, 0.2, 0.3))
    assert stack.tensors["base"].color.max().item() == pytest.approx(0.2)
    # uint8 codes are mapped by the range like a PNG; float values are taken as they are.
    stack.add_layer("m8", np.full((1, 4, 6), 255, dtype=np.uint8), blend="multiply", range=(0, 2))
    assert stack.tensors["m8"].color.max().item() == pytest.approx(2.0)
    stack.add_layer("mf", torch.full((4, 6), 1.25), blend="multiply", range=(0, 2))
    assert stack.tensors["mf"].color.shape == (1, 4, 6) and stack.tensors["mf"].color.max().item() == 1.25
    rgba = torch.rand(4, 3, 3)
    stack.add_layer("paint", rgba, offset=(4, -1), opacity=0.5)
    assert torch.equal(stack.tensors["paint"].alpha, rgba[3:])
    la = Image.fromarray(np.stack([np.full((4, 6), 255), np.full((4, 6), 128)], -1).astype(np.uint8))
    stack.add_layer("gray", la, blend="multiply", range=(0, 2))
    assert stack.tensors["gray"].alpha.max().item() == pytest.approx(128 / 255)  # alpha not mapped
    stack.add_solid("tint", (1.0, 0.0, 0.0, 0.25), size=(2, 2), offset={"x": 1, "y": 1})
    stack.add_layer("masked", torch.rand(3, 4, 6), mask=torch.rand(1, 4, 6))
    assert stack.ids == ("base", "m8", "mf", "paint", "gray", "tint", "masked")
    stack.save(tmp_path / "s")
    doc = json.loads((tmp_path / "s/stack.json").read_text())
    assert doc["layers"][-1]["mask"] == "masks/masked.png" and doc["canvas"]["background"] == [0.1, 0.2, 0.3]
    # What we save, a reference compositor reads back to the same composite.
    write_composite(render_stack(stack), tmp_path / "c.png")
    ours = np.asarray(Image.open(tmp_path / "c.png")).astype(int)
    assert np.abs(ours - to_uint8(composite_reference(tmp_path / "s"))).max() <= 1


@pytest.mark.parametrize(
    "bad,pattern",
    [
        (torch.full((3, 2, 2), float("nan")), "NaN"),
        (torch.rand(5, 2, 2), "expected \\(C, h, w\\)"),
        (torch.rand(2, 3, 2, 2), "expected \\(C, h, w\\)"),
        (torch.zeros(3, 2, 2, dtype=torch.bool), "dtype"),
        ("not an image", "expected a torch tensor"),
    ],
)
def test_bad_images_are_refused(bad, pattern):
    stack = Stack.from_image(torch.rand(3, 2, 2))
    with pytest.raises(ImageError, match=pattern):
        stack.add_layer("x", bad)
    assert stack.ids == ("base",)


def test_bad_layer_fields_are_refused():
    stack = Stack.from_image(torch.rand(3, 2, 2))
    with pytest.raises(DocumentError, match="unknown layer field"):
        stack.add_layer("x", torch.rand(3, 2, 2), colour="red")
    with pytest.raises(DocumentError, match="blend"):
        stack.add_layer("x", torch.rand(3, 2, 2), blend="grain-merge")
    with pytest.raises(ImageError, match="mask is 3x2"):
        stack.add_layer("x", torch.rand(3, 2, 2), mask=torch.rand(1, 2, 3))
    assert stack.ids == ("base",) and set(stack.tensors) == {"base"}  # nothing half-added
    stack.document = stack.document.with_layer(
        {
            "id": "relit",
            "kind": "learned",
            "preset": "shading",
            "condition": {"label": "left"},
            "conditioned_on": "base",
        }
    )
    with pytest.raises(DocumentError, match="set_pixels"):
        stack.add_layer("relit", torch.rand(3, 2, 2))


def test_stack_from_tensors_and_set_pixels(tmp_path):
    stack = stack_from_tensors(
        [
            ("base", torch.rand(3, 4, 5)),
            {"id": "shade", "image": torch.rand(1, 4, 5) * 2, "blend": "multiply", "range": (0, 2)},
            {"id": "sun", "color": (1.0, 0.9, 0.5, 0.5), "blend": "plus"},
        ],
        width=6,
        height=5,
        blend_space="linear",
    )
    assert (stack.width, stack.height) == (6, 5) and stack.document.blend_space == "linear"
    grad = torch.rand(1, 4, 5, requires_grad=True)
    stack.set_pixels("shade", grad * 2)
    render_stack(stack).image.sum().backward()
    assert grad.grad is not None and grad.grad.abs().sum() > 0
    with pytest.raises(DocumentError, match="solid"):
        stack.set_pixels("sun", torch.rand(3, 2, 2))


def test_render_stack_dtype_and_solid_range(tmp_path):
    folder = random_stack(tmp_path / "r", 5)
    stack = load_stack(folder)
    r64 = render_stack(stack, dtype=torch.float64)
    r32 = render_stack(stack)
    assert r64.image.dtype == torch.float64 and (r64.image - r32.image).abs().max() < 1e-5
    np.testing.assert_allclose(r64.image.numpy(), composite_reference(folder), atol=1e-6)
    # A solid multiply colour is mapped by its range, like a PNG's values.
    write_stack(
        tmp_path / "solid",
        _doc([{"id": "s", "kind": "solid", "color": [0.75, 0.75, 0.75], "blend": "multiply", "range": [0, 2]}])
        | {"canvas": {"width": 2, "height": 2, "background": [0.4, 0.4, 0.4]}},
    )
    image = render_stack(load_stack(tmp_path / "solid"), dtype=torch.float64).image
    assert image.max().item() == pytest.approx(0.6)


def test_remove_layer_drops_the_layer_its_tensors_and_bit_depth():
    stack = Stack.from_image(torch.rand(3, 4, 6))
    stack.add_layer("shade", torch.rand(1, 4, 6) * 2, blend="multiply", range=(0, 2))
    stack.add_solid("tint", (1.0, 0.5, 0.0, 0.25))
    assert stack.remove_layer("shade") is stack
    assert stack.ids == ("base", "tint") and "shade" not in stack.tensors and "shade" not in stack.bit_depths
    torch.testing.assert_close(
        stack.render().image,
        stack_from_tensors([("base", stack.tensors["base"].color)]).render().image * 0.75
        + torch.tensor([1.0, 0.5, 0.0]).view(3, 1, 1) * 0.25,
    )
    with pytest.raises(DocumentError, match="nope"):
        stack.remove_layer("nope")


# ---- hostile input (#16): huge layers and canvases are checked or refused before decoding -------------


def _big_layer_stack(folder: Path, side: int) -> Path:
    from tests.support.peak import zero_rgb_png

    zero_rgb_png(folder / "layers" / "big.png", side)
    return write_stack(folder, _doc([{"id": "big", "kind": "pixels", "source": "layers/big.png"}], w=8, h=8))


@pytest.fixture(scope="module")
def big8k(tmp_path_factory) -> Path:
    """An 8×8 canvas whose one layer is an 8192² RGB PNG of zeros (196 KB; 1 GiB as float32 RGBA)."""
    return _big_layer_stack(tmp_path_factory.mktemp("big8k"), 8192)


@pytest.fixture(scope="module")
def big16k(tmp_path_factory) -> Path:
    """The same with a 16384² layer (~780 KB; 4 GiB as float32 RGBA)."""
    return _big_layer_stack(tmp_path_factory.mktemp("big16k"), 16384)


def _validate_without_decoding(folder: Path, side: int) -> None:
    from tests.support.peak import run_cli

    code, out, err, peak = run_cli("validate", folder)
    assert code == 0 and err == "", err
    assert out == "ok: 1 layers (8x8, blend_space=srgb)"
    assert peak < 600, f"validate of a {side}² layer peaked at {peak:.0f} MB"  # decoding would be ≥ 1 GiB


def test_validate_checks_an_8192_layer_without_decoding(big8k):
    _validate_without_decoding(big8k, 8192)


@pytest.mark.slow
def test_validate_checks_a_16384_layer_without_decoding(big16k):
    _validate_without_decoding(big16k, 16384)


@pytest.mark.parametrize("size", ["big8k", pytest.param("big16k", marks=pytest.mark.slow)])
def test_composite_of_a_big_layer_is_refused_under_the_budget(request, capsys, monkeypatch, size):
    import lasagna.io.stack as stack_module
    from lasagna.cli import main

    folder = request.getfixturevalue(size)
    monkeypatch.setattr(stack_module, "read_png", lambda *a, **k: pytest.fail("decoded"))
    code = main(["composite", str(folder), "-o", str(folder.parent / "out.png"), "--memory-budget", "1G"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "over the memory budget of 1.0 GB" in err and "decoding the stack's 1 PNGs" in err
    assert not (folder.parent / "out.png").exists()


def test_load_stack_under_a_scope_refuses_before_decoding(big8k, monkeypatch):
    import lasagna.io.stack as stack_module
    from lasagna.limits import BudgetError, memory_budget_scope

    monkeypatch.setattr(stack_module, "read_png", lambda *a, **k: pytest.fail("decoded"))
    with memory_budget_scope("512M"), pytest.raises(BudgetError, match="over the memory budget of 512.0 MB"):
        load_stack(big8k)


def test_load_stack_budget_counts_every_layer(tmp_path):
    from lasagna.limits import BudgetError, memory_budget_scope

    write_png8(tmp_path / "a.png", np.zeros((64, 64, 3)))
    folder = write_stack(tmp_path, _doc([{"id": f"l{i}", "kind": "pixels", "source": "a.png"} for i in range(4)]))
    with memory_budget_scope(4 * 64 * 64 * 16):  # each layer fits; four of them plus decoding do not
        with pytest.raises(BudgetError, match="decoding the stack's 4 PNGs"):
            load_stack(folder)
    with memory_budget_scope("64M"):
        assert len(load_stack(folder).ids) == 4


def _solid_stack(folder: Path, side: int, color=(0.2, 0.4, 0.6)) -> Path:
    layer = {"id": "fill", "kind": "solid", "color": list(color)}
    return write_stack(folder, _doc([layer], w=side, h=side))


def test_composite_of_a_32768_solid_canvas_is_refused_in_bounded_memory(tmp_path):
    from tests.support.peak import run_cli

    folder = _solid_stack(tmp_path / "s", 32768)
    code, out, err, peak = run_cli("composite", folder, "-o", tmp_path / "out.png")
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "rendering its 32768x32768 canvas" in err and "over the memory budget of 8.0 GB" in err
    assert peak < 500 and not (tmp_path / "out.png").exists()


def test_a_2048_solid_canvas_renders_in_bounded_memory(tmp_path):
    from tests.support.peak import baseline_mb, run_cli

    folder = _solid_stack(tmp_path / "s", 2048)
    code, out, err, peak = run_cli("composite", folder, "-o", tmp_path / "out.png")
    assert code == 0, err
    with Image.open(tmp_path / "out.png") as im:
        codes = np.asarray(im)
    assert codes.shape == (2048, 2048, 3) and np.all(codes == np.array([51, 102, 153], np.uint8))
    # The canvas is 48 MB of float32 RGB and ~12 MB of codes and deflate; materialising the solid layer
    # (RGBA, float32) and the old whole-image float64 encode would add ~64 + 100 MB each. 400 MB is far
    # below the several copies of a canvas the old path made, and well above this one's ~60 MB.
    assert peak - baseline_mb() < 400, f"peak {peak:.0f} MB over a baseline of {baseline_mb():.0f} MB"


def test_ranges_of_expanded_solid_views_match_a_materialised_copy():
    from lasagna.compose.layer import LayerTensors

    color = torch.tensor([0.25, -0.5, 1.5]).reshape(3, 1, 1).expand(3, 5, 7)
    alpha = torch.full((1, 1, 1), 0.75).expand(1, 5, 7)
    mask = torch.rand(1, 5, 7, generator=torch.Generator().manual_seed(0))
    lt = LayerTensors(color, alpha, mask)
    ref = LayerTensors(color.contiguous(), alpha.contiguous(), mask)
    assert lt.color_range() == ref.color_range() == (-0.5, 1.5)
    assert lt.alpha_range() == ref.alpha_range()
    assert lt.alpha_range() == pytest.approx((0.75 * float(mask.min()), 0.75 * float(mask.max())))
    # expanded along one axis only: rows differ, columns are repeated
    rows = torch.linspace(0, 1, 5).reshape(1, 5, 1).expand(3, 5, 7)
    assert LayerTensors(rows).color_range() == LayerTensors(rows.contiguous()).color_range() == (0.0, 1.0)
    nan = torch.tensor([0.0, float("nan"), 1.0]).reshape(3, 1, 1).expand(3, 4, 4)
    lo, hi = LayerTensors(nan).color_range()
    assert np.isnan(lo) and np.isnan(hi)


def test_ranges_of_a_32768_expanded_view_do_not_materialise_it():
    from lasagna.compose.layer import LayerTensors

    side = 2**15
    color = torch.tensor([0.1, 0.2, 0.3]).reshape(3, 1, 1).expand(3, side, side)  # 12 GiB if materialised
    alpha = torch.full((1, 1, 1), 0.5).expand(1, side, side)
    start = cpu_seconds()
    lt = LayerTensors(color, alpha)
    assert lt.color_range() == pytest.approx((0.1, 0.3))
    assert lt.alpha_range() == (0.5, 0.5)
    assert cpu_seconds() - start < 2  # CPU seconds (not wall: a loaded machine stretches that); 12 GiB takes far more


# ---- stored values without encoding ---------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(
    lo=st.sampled_from([0.0, 0.25]),
    width=st.sampled_from([1.0, 2.0, 3.75]),
    channels=st.sampled_from([1, 3]),
    alpha=st.booleans(),
    mask=st.booleans(),
    depth=st.sampled_from([8, 16]),
    seed=st.integers(0, 2**16),
)
def test_stored_tensors_equal_an_encode_decode_round_trip(lo, width, channels, alpha, mask, depth, seed):
    """``stored_tensors`` is bit-identical to encoding the layer's PNGs and loading them back."""
    from lasagna.io.png import decode_png
    from lasagna.io.stack import encode_layer, layer_tensors, stored_tensors

    g = torch.Generator().manual_seed(seed)
    hi = lo + width
    values = lo + width * torch.rand((channels, 5, 7), generator=g)
    stack = Stack.from_image(torch.rand((3, 5, 7), generator=g))
    stack.add_layer(
        "x",
        values,
        range=(lo, hi),
        blend="multiply",
        alpha=torch.rand((1, 5, 7), generator=g) if alpha else None,
        mask=torch.rand((1, 5, 7), generator=g) if mask else None,
    )
    stack.bit_depths["x"] = depth
    data, mask_data = encode_layer(stack, "x")
    img = decode_png(data, "x")
    ref = layer_tensors(img, (lo, hi), decode_png(mask_data, "m") if mask_data else None)
    got, got_depth = stored_tensors(stack, "x")
    assert got_depth == img.header.bit_depth
    for a, b in zip(got.tensors(), ref.tensors()):
        assert (a is None) == (b is None)
        if a is not None:
            assert a.dtype == b.dtype and torch.equal(a, b)


def test_as_stored_keeps_loaded_tensors_until_they_or_the_range_change(tmp_path):
    from lasagna.learned import as_stored

    stack = load_stack(EXAMPLES / "basic")
    before = dict(stack.tensors)
    as_stored(stack)
    assert all(stack.tensors[i] is before[i] for i in before)  # loaded values are stored values: kept
    shade = stack.tensors["shade"]
    shade.color.add_(1e-3)  # modified in place: no longer on the 16-bit grid
    as_stored(stack, ["shade"])
    assert stack.tensors["shade"] is not shade
    step = 2.0 / 65535
    k = stack.tensors["shade"].color.double() / step
    assert torch.allclose(k, k.round(), atol=1e-2)  # back on the grid of the range's codes
    kept = stack.tensors["shade"]
    as_stored(stack, ["shade"])
    assert stack.tensors["shade"] is kept  # made here: noted as stored
    stack.document = stack.document.with_layer({**stack.document.layer("shade").model_dump(), "range": [0.0, 4.0]})
    as_stored(stack, ["shade"])
    assert stack.tensors["shade"] is not kept  # another range: other codes
