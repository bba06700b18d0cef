"""``import-psd``: PSDs built here with psd-tools (not written by Lasagna), flattened by psd-tools' own
``composite()`` laid over white, against ``read_psd`` + our composite.

Measured (8-bit codes, max |difference|): every mode (W3C's and Photoshop's), as a layer with partial alpha and
opacity, as an isolated group of that mode and inside a pass-through group with opacity: ≤ 1 (rounding).
Linear Dodge is read as ``linear-dodge`` (Photoshop's, clamped inside the blend), so partial alpha matches too.
Dissolve is read as dissolve (psd-tools draws it as normal: checked on its own). Clipping chains (a layer or a
group as base, clipped layers of other modes, base opacity and blend): ≤ 1, read as chains and written back with
the clipping flag.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

psd_tools = pytest.importorskip("psd_tools")
from psd_tools import PSDImage  # noqa: E402
from psd_tools.constants import BlendMode  # noqa: E402

from lasagna.cli import main  # noqa: E402
from lasagna.document.blend import BLEND_MODES  # noqa: E402
from lasagna.errors import ImageError  # noqa: E402
from lasagna.export.psd_import import read_psd  # noqa: E402
from lasagna.export.psd_tools_api import psd_blend_modes  # noqa: E402
from lasagna.io.render import render_stack  # noqa: E402
from lasagna.io.stack import load_stack  # noqa: E402
from tests.support.bounded import within  # noqa: E402

MODES = psd_blend_modes(BlendMode)
# Every mode psd-tools composites as Photoshop does (plus is written as LINEAR_DODGE, read back as linear-dodge;
# psd-tools draws dissolve as normal).
W3C = [m for m in BLEND_MODES if m not in ("plus", "dissolve")]
H, W = 16, 20


def rgba(rng, h, w, alpha="random"):
    a = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
    if alpha == "opaque":
        a[..., 3] = 255
    elif alpha == "binary":
        a[..., 3] = np.where(a[..., 3] > 127, 255, 0)
    return Image.fromarray(a)


def psd_tools_flat(path: Path) -> np.ndarray:
    """psd-tools' own composite of the file, laid over white (the page backdrop), as 8-bit codes."""
    c = np.asarray(PSDImage.open(path).composite(force=True).convert("RGBA"), dtype=np.float64) / 255.0
    return np.rint((c[..., :3] * c[..., 3:] + 1.0 - c[..., 3:]) * 255.0)


def ours(path: Path, warnings: list[str] | None = None) -> np.ndarray:
    """Our composite of the imported stack, a transparent document's laid over white as psd-tools' is."""
    stack = read_psd(path, warn=(warnings.append if warnings is not None else lambda m: None))
    result = render_stack(stack, dtype=torch.float64)
    image = np.clip(result.image.numpy().transpose(1, 2, 0), 0.0, 1.0)
    if result.alpha is not None:
        a = result.alpha.numpy().transpose(1, 2, 0)
        image = image * a + 1.0 - a
    return np.rint(image * 255.0)


def err(path: Path) -> float:
    return float(np.abs(psd_tools_flat(path) - ours(path)).max())


def new_psd():
    return PSDImage.new("RGBA", (W, H))


@pytest.mark.parametrize("mode", W3C)
def test_a_layer_of_every_mode_matches_psd_tools(tmp_path, mode):
    for seed in range(2):
        rng = np.random.default_rng(seed)
        psd = new_psd()
        psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
        top = psd.create_pixel_layer(rgba(rng, 10, 12), name="top", top=3, left=4, blend_mode=MODES[mode])
        top.opacity = int(rng.integers(80, 256))
        top.fill_opacity = int(rng.integers(80, 256))
        path = tmp_path / f"{seed}.psd"
        psd.save(path)
        assert err(path) <= 1, mode


@pytest.mark.parametrize("mode", W3C)
def test_isolated_and_pass_through_groups_of_every_mode_match_psd_tools(tmp_path, mode):
    rng = np.random.default_rng(9)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    group = psd.create_group(name="iso", blend_mode=MODES[mode], opacity=170)
    group.create_pixel_layer(rgba(rng, 8, 9), name="k1", top=1, left=2)
    group.create_pixel_layer(rgba(rng, 8, 9), name="k2", top=5, left=6, blend_mode=MODES[mode])
    passing = psd.create_group(name="pass", opacity=140)
    passing.create_pixel_layer(rgba(rng, 9, 9), name="k3", top=6, left=9, blend_mode=MODES[mode])
    inner = passing.create_group(name="inner", blend_mode=MODES[mode])
    inner.create_pixel_layer(rgba(rng, 6, 7), name="k4", top=2, left=11)
    path = tmp_path / "g.psd"
    psd.save(path)
    doc = read_psd(path).document
    assert doc.layer("iso").isolated and doc.layer("iso").blend == mode
    assert not doc.layer("pass").isolated and doc.layer("pass").opacity == pytest.approx(140 / 255)
    assert doc.layer("inner").isolated
    assert err(path) <= 1, mode


def test_masks_offsets_visibility_and_fill(tmp_path):
    rng = np.random.default_rng(3)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    a = psd.create_pixel_layer(rgba(rng, 10, 12), name="masked", top=-3, left=12, blend_mode=BlendMode.OVERLAY)
    a.create_mask(Image.fromarray(rng.integers(0, 256, (5, 6), dtype=np.uint8)), top=-1, left=14)
    a.fill_opacity = 100
    hidden = psd.create_pixel_layer(rgba(rng, 6, 6), name="hidden", top=1, left=1)
    hidden.visible = False
    group = psd.create_group(name="g", blend_mode=BlendMode.MULTIPLY)
    group.create_pixel_layer(rgba(rng, 12, 14), name="in", top=2, left=2)
    # (No group mask: psd-tools 1.26 writes a group's mask channel it cannot read back, "not a valid Compression".)
    path = tmp_path / "m.psd"
    psd.save(path)
    stack = read_psd(path)
    doc = stack.document
    assert doc.layer("masked").mask == "masks/masked.png" and doc.layer("masked").offset.x == 12
    assert doc.layer("masked").opacity == pytest.approx(100 / 255)
    assert not doc.layer("hidden").visible
    assert err(path) <= 1


def test_linear_dodge_is_photoshops_under_partial_alpha(tmp_path):
    rng = np.random.default_rng(4)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    psd.create_pixel_layer(rgba(rng, 10, 12, "binary"), name="add", top=3, left=4, blend_mode=BlendMode.LINEAR_DODGE)
    psd.create_pixel_layer(rgba(rng, 10, 12), name="soft", top=5, left=6, blend_mode=BlendMode.LINEAR_DODGE)
    path = tmp_path / "partial.psd"
    psd.save(path)
    warnings: list[str] = []
    assert float(np.abs(psd_tools_flat(path) - ours(path, warnings)).max()) <= 1
    assert warnings == []
    assert read_psd(path).document.layer("soft").blend == "linear-dodge"


def test_dissolve_is_read_as_dissolve_and_shows_a_fraction_alpha(tmp_path):
    psd = new_psd()
    psd.create_pixel_layer(Image.new("RGBA", (W, H), (0, 0, 0, 255)), name="base")
    top = psd.create_pixel_layer(
        Image.new("RGBA", (W, H), (255, 255, 255, 255)), name="d", blend_mode=BlendMode.DISSOLVE
    )
    top.opacity = 128
    path = tmp_path / "d.psd"
    psd.save(path)
    flat = ours(path)
    assert read_psd(path).document.layer("d").blend == "dissolve"
    assert set(np.unique(flat).tolist()) <= {0.0, 255.0}
    assert float((flat == 255).mean()) == pytest.approx(128 / 255, abs=0.1)


def test_fill_inside_the_special_modes_is_reported(tmp_path):
    rng = np.random.default_rng(7)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    burn = psd.create_pixel_layer(rgba(rng, 8, 8), name="burn", blend_mode=BlendMode.LINEAR_BURN)
    burn.fill_opacity = 128
    mult = psd.create_pixel_layer(rgba(rng, 8, 8), name="mult", blend_mode=BlendMode.MULTIPLY)
    mult.fill_opacity = 128
    path = tmp_path / "fill.psd"
    psd.save(path)
    warnings: list[str] = []
    read_psd(path, warn=warnings.append)
    assert len(warnings) == 1 and "layer 'burn': fill opacity 128/255 of a linear-burn layer" in warnings[0]


def test_what_cannot_be_represented_is_reported_one_line_each(tmp_path):
    rng = np.random.default_rng(5)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    psd.create_pixel_layer(rgba(rng, 8, 8), name="burn", blend_mode=BlendMode.LINEAR_BURN)  # a mode of its own now
    clipped_base = psd.create_pixel_layer(rgba(rng, 10, 10), name="clipbase", top=4, left=6)
    clip = psd.create_pixel_layer(rgba(rng, 12, 12, "opaque"), name="clip", top=2, left=5)
    clip.clipping = True
    path = tmp_path / "r.psd"
    psd.save(path)
    warnings: list[str] = []
    stack = read_psd(path, warn=warnings.append)
    assert warnings == []  # a clipping mask of pixel layers is a clipping chain now, not a rasterised layer
    assert stack.document.layer("burn").blend == "linear-burn"
    assert stack.document.layer("clip").clip and not stack.document.layer("clipbase").clip
    assert clipped_base.clipping is False
    assert err(path) <= 1
    PSDImage.open(path)  # still a valid file
    psd2 = new_psd()
    psd2.create_pixel_layer(rgba(np.random.default_rng(5), H, W, "opaque"), name="base")
    b2 = psd2.create_pixel_layer(rgba(rng, 10, 10), name="clipbase", top=4, left=6)
    c2 = psd2.create_pixel_layer(rgba(rng, 12, 12, "opaque"), name="clip", top=2, left=5)
    c2.clipping = True
    assert b2.has_clip_layers()
    path2 = tmp_path / "clip.psd"
    psd2.save(path2)
    assert err(path2) <= 1


def test_a_psd_not_covering_its_canvas_imports_as_a_transparent_document(tmp_path):
    """Layers that do not cover the canvas: ``background`` null, and the composite's colour and alpha are
    psd-tools' own (not laid over anything) within 1/255; an opaque full-canvas base keeps the document opaque."""
    rng = np.random.default_rng(6)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, 10, 12), name="a", top=2, left=3)
    psd.create_pixel_layer(rgba(rng, 10, 12), name="b", top=4, left=5, blend_mode=BlendMode.SCREEN)
    path = tmp_path / "open.psd"
    psd.save(path)
    stack = read_psd(path)
    assert stack.document.canvas.background is None and stack.document.ids == ("a", "b")
    assert err(path) <= 1
    theirs = np.asarray(PSDImage.open(path).composite(force=True).convert("RGBA"), dtype=np.float64)
    result = render_stack(stack, dtype=torch.float64)
    alpha = np.rint(result.alpha.numpy()[0] * 255.0)
    assert np.abs(alpha - theirs[..., 3]).max() <= 1
    assert alpha.min() == 0 and (alpha == 0).sum() > 0  # the corners stay transparent
    seen = theirs[..., 3] >= 32  # colour is defined where there is alpha (8-bit premultiplied rounding below)
    color = np.rint(np.clip(result.image.numpy().transpose(1, 2, 0), 0, 1) * 255.0)
    assert np.abs(color[seen] - theirs[..., :3][seen]).max() <= 2
    out = tmp_path / "stack"
    assert main(["import-psd", str(path), "-o", str(out)]) == 0
    assert main(["composite", str(out)]) == 0
    with Image.open(out / "composite.png") as im:
        assert im.mode == "RGBA" and np.abs(np.asarray(im)[..., 3] - alpha).max() == 0
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="bg")
    path = tmp_path / "closed.psd"
    psd.save(path)
    closed = read_psd(path).document
    assert closed.ids == ("bg",) and closed.canvas.background is not None


def test_cli_import_then_composite(tmp_path, capsys):
    rng = np.random.default_rng(7)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    g = psd.create_group(name="g", blend_mode=BlendMode.HUE, opacity=200)
    g.create_pixel_layer(rgba(rng, 9, 9), name="x", top=2, left=2, blend_mode=BlendMode.SOFT_LIGHT)
    path = tmp_path / "in.psd"
    psd.save(path)
    out = tmp_path / "stack"
    assert main(["import-psd", str(path), "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    assert main(["composite", str(out), "-o", str(tmp_path / "c.png")]) == 0
    with Image.open(tmp_path / "c.png") as im:
        got = np.asarray(im).astype(float)
    assert np.abs(got - psd_tools_flat(path)).max() <= 1
    assert load_stack(out).document == read_psd(path).document


def test_a_psd_of_every_mode_composites_as_the_float64_reference(tmp_path):
    # One psd-tools-written PSD holding a layer of every blend mode (partial alpha, opacity), imported with
    # ``lasagna import-psd`` and composited with ``lasagna composite``: within 3/255 of tests/support/reference.py's
    # float64 composite of the imported stack folder (independent of the compositor), and of psd-tools' own
    # flattening except dissolve (psd-tools draws it as normal).
    from tests.support.reference import composite_reference, to_uint8

    rng = np.random.default_rng(11)
    T = 8
    modes = [m for m in BLEND_MODES if m != "plus"]  # plus is LINEAR_DODGE, i.e. linear-dodge, in a PSD
    psd = PSDImage.new("RGBA", (T * len(modes), T))
    psd.create_pixel_layer(rgba(rng, T, T * len(modes), "opaque"), name="base")
    for i, mode in enumerate(modes):
        layer = psd.create_pixel_layer(rgba(rng, T, T), name=mode, left=T * i, blend_mode=MODES[mode])
        layer.opacity = int(rng.integers(120, 256))
    path = tmp_path / "modes.psd"
    psd.save(path)
    out = tmp_path / "stack"
    assert main(["import-psd", str(path), "-o", str(out)]) == 0
    assert [layer.blend for layer in load_stack(out).document.layers] == ["normal", *modes]
    assert main(["composite", str(out), "-o", str(tmp_path / "c.png")]) == 0
    with Image.open(tmp_path / "c.png") as im:
        got = np.asarray(im.convert("RGB")).astype(int)
    assert np.abs(got - to_uint8(composite_reference(out)).astype(int)).max() <= 3
    flat = psd_tools_flat(path)
    drawn = np.ones(got.shape[1], dtype=bool)
    drawn[T * modes.index("dissolve") : T * (modes.index("dissolve") + 1)] = False
    assert np.abs(got - flat)[:, drawn].max() <= 1


def test_cli_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.psd"
    bad.write_bytes(b"8BPS" + b"\x00" * 40)
    code = main(["import-psd", str(bad), "-o", str(tmp_path / "o")])
    err_text = capsys.readouterr().err
    assert code == 2 and err_text.count("\n") == 1 and "psd-tools cannot read it" in err_text
    assert not (tmp_path / "o").exists()
    code = main(["import-psd", str(tmp_path / "missing.psd"), "-o", str(tmp_path / "o")])
    err_text = capsys.readouterr().err
    assert code == 2 and err_text.count("\n") == 1 and "expected a PSD file" in err_text
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    psd = new_psd()
    psd.create_pixel_layer(rgba(np.random.default_rng(0), H, W, "opaque"), name="base")
    psd.save(tmp_path / "ok.psd")
    code = main(["import-psd", str(tmp_path / "ok.psd"), "-o", str(tmp_path / "full")])
    assert code == 2 and capsys.readouterr().err.count("\n") == 1


def test_huge_canvas_is_refused_before_decoding(tmp_path):
    psd = PSDImage.new("RGBA", (64, 64))
    psd.create_pixel_layer(Image.new("RGBA", (64, 64)), name="a")
    psd.save(tmp_path / "big.psd")
    with pytest.raises(ImageError, match="canvas is 64x64; expected .* at most 1000 pixels"):
        read_psd(tmp_path / "big.psd", max_pixels=1000)


# ---- #28 -------------------------------------------------------------------------------------------------


def test_layers_named_like_windows_devices_import(tmp_path):
    rng = np.random.default_rng(3)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    for name in ("aux.png", "con.x", "nul.a", "COM1.txt", "lpt9", "aux.png"):
        psd.create_pixel_layer(rgba(rng, 4, 4), name=name)
    path = tmp_path / "dev.psd"
    psd.save(path)
    doc = within(20, lambda: read_psd(path)).document
    assert doc.ids == ("base", "aux_.png", "con_.x", "nul_.a", "COM1_.txt", "lpt9_", "aux_-2.png")
    assert [layer.name for layer in doc.layers][1:] == ["aux.png", "con.x", "nul.a", "COM1.txt", "lpt9", "aux.png"]


def _big_mask_psd(path: Path, side: int) -> Path:
    """An 8×8 canvas and layer whose user mask's stored rectangle is ``side``² (zeros, ZIP-compressed row by
    row, so neither this process nor the file holds the raw mask: 16384² is ~1 MB on disk, 256 MB decoded)."""
    import zlib

    from psd_tools.constants import ChannelID, Compression

    psd = PSDImage.new("RGBA", (8, 8))
    layer = psd.create_pixel_layer(Image.new("RGBA", (8, 8), (9, 9, 9, 255)), name="small")
    layer.create_mask(Image.new("L", (8, 8), 255), top=0, left=0)
    record = layer._record.mask_data
    record.top, record.left, record.bottom, record.right = 0, 0, side, side
    channel = layer._channels[[c.id for c in layer._record.channel_info].index(ChannelID.USER_LAYER_MASK)]
    deflate, row = zlib.compressobj(1), bytes(side)
    channel.compression = Compression.ZIP
    channel.data = b"".join([deflate.compress(row) for _ in range(side)] + [deflate.flush()])
    psd.save(path)
    return path


def test_a_masks_stored_rectangle_counts_in_the_memory_estimate(tmp_path):
    from lasagna.limits import memory_budget_scope

    small = _big_mask_psd(tmp_path / "small.psd", 64)
    assert read_psd(small).document.layer("small").mask == "masks/small.png"  # cut to the layer: 8×8
    path = _big_mask_psd(tmp_path / "big.psd", 16384)
    with memory_budget_scope("512M"), pytest.raises(Exception) as info:
        read_psd(path)
    assert "over the memory budget" in str(info.value) and str(path) in str(info.value)


def test_a_huge_mask_is_refused_in_bounded_memory(tmp_path):
    from tests.support.peak import run_cli

    path = _big_mask_psd(tmp_path / "big.psd", 16384)
    code, out, err, peak = run_cli("import-psd", path, "-o", tmp_path / "out", "--memory-budget", "512M")
    assert code == 2 and err.count("\n") == 1 and "over the memory budget" in err, err
    assert peak < 500, f"refusing a 16384² mask peaked at {peak:.0f} MB"
    assert not (tmp_path / "out").exists()


def _nested_psd(path: Path, depth: int, opaque_base: bool) -> Path:
    rng = np.random.default_rng(5)
    psd = new_psd()
    if opaque_base:
        psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    parent = psd
    for i in range(depth):
        parent = parent.create_group(name=f"g{i}", blend_mode=BlendMode.MULTIPLY if i % 2 else BlendMode.PASS_THROUGH)
    parent.create_pixel_layer(rgba(rng, 4, 4), name="leaf")
    psd.save(path)
    return path


def test_groups_nested_as_deep_as_a_stack_allows_import_and_validate(tmp_path, capsys):
    from lasagna.limits import MAX_GROUP_DEPTH

    path = _nested_psd(tmp_path / "ok.psd", MAX_GROUP_DEPTH, opaque_base=True)
    assert main(["import-psd", str(path), "-o", str(tmp_path / "out")]) == 0
    assert main(["validate", str(tmp_path / "out")]) == 0, capsys.readouterr().err


@pytest.mark.parametrize("depth, opaque_base", [(31, True), (40, True), (31, False)])
def test_groups_nested_deeper_than_a_stack_allows_are_one_line(tmp_path, capsys, depth, opaque_base):
    path = _nested_psd(tmp_path / "deep.psd", depth, opaque_base)
    code = main(["import-psd", str(path), "-o", str(tmp_path / "out")])
    err_text = capsys.readouterr().err
    assert code == 2 and err_text.count("\n") == 1 and "expected at most" in err_text, err_text
    assert "Traceback" not in err_text and not (tmp_path / "out").exists()


def test_names_with_control_characters_import_replaced_with_a_warning(tmp_path, capsys):
    rng = np.random.default_rng(6)
    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    psd.create_pixel_layer(rgba(rng, 4, 4), name="bad\x01name\n")
    psd.create_group(name="\x07").create_pixel_layer(rgba(rng, 4, 4), name="in")
    path = tmp_path / "names.psd"
    psd.save(path)
    assert main(["import-psd", str(path), "-o", str(tmp_path / "out")]) == 0
    err_text = capsys.readouterr().err
    assert err_text.count("holds control characters") == 2 and err_text.count("\n") == 2, err_text
    names = [layer.name for _, layer in load_stack(tmp_path / "out").document.walk()]
    assert names == ["base", "bad\ufffdname\ufffd", "\ufffd", "in"]
    assert main(["validate", str(tmp_path / "out")]) == 0


def _chain_psd(path: Path, rng, *, group_base: bool = False, blend=BlendMode.NORMAL) -> None:
    """A PSD with a clipping chain over an opaque base: a partly transparent base (or a group of two as base)
    with its opacity and blend, two clipped layers (the upper with a mode and partial opacity), a layer above."""
    from psd_tools.api.layers import Group

    psd = new_psd()
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="ground")
    if group_base:
        group = Group.new(psd, name="base")
        for n in range(2):
            group.append(psd.create_pixel_layer(rgba(rng, 8, 9), name=f"g{n}", top=2 + 3 * n, left=3 + 4 * n))
        base = group
    else:
        base = psd.create_pixel_layer(rgba(rng, 10, 12), name="base", top=3, left=4, blend_mode=blend)
    base.opacity = int(rng.integers(120, 256))
    a = psd.create_pixel_layer(rgba(rng, 12, 14), name="a", top=1, left=2)
    b = psd.create_pixel_layer(rgba(rng, H, W), name="b", blend_mode=BlendMode.MULTIPLY)
    b.opacity = int(rng.integers(80, 256))
    a.clipping = b.clipping = True
    psd.create_pixel_layer(rgba(rng, 5, 5), name="top", top=9, left=12)
    psd.save(path)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("group_base", [False, True])
def test_a_clipping_chain_is_imported_as_one_and_matches_psd_tools(tmp_path, seed, group_base):
    rng = np.random.default_rng(seed)
    path = tmp_path / "clip.psd"
    _chain_psd(path, rng, group_base=group_base, blend=BlendMode.SCREEN)
    said: list[str] = []
    stack = read_psd(path, warn=said.append)
    layers = stack.document.layers
    assert [(layer.id, layer.clip) for layer in layers] == [
        ("ground", False),
        ("base", False),
        ("a", True),
        ("b", True),
        ("top", False),
    ]
    assert not any("rasterised" in s for s in said), said
    assert err(path) <= 1


def test_a_clipping_layer_at_the_bottom_is_left_out_with_a_warning(tmp_path):
    rng = np.random.default_rng(0)
    psd = new_psd()
    alone = psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="alone")
    alone.clipping = True
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="over")
    path = tmp_path / "orphan.psd"
    psd.save(path)
    said: list[str] = []
    assert [layer.id for layer in read_psd(path, warn=said.append).document.layers] == ["over"]
    assert any("clipped to no layer" in s for s in said)


def test_a_clipping_chain_is_written_back_with_the_clipping_flag(tmp_path):
    from lasagna.export.psd import export_psd

    path = tmp_path / "clip.psd"
    _chain_psd(path, np.random.default_rng(4), blend=BlendMode.MULTIPLY)
    stack = read_psd(path)
    said: list[str] = []
    export_psd(stack, tmp_path / "back.psd", warn=said.append)
    assert said == []
    back = PSDImage.open(tmp_path / "back.psd")
    assert [(layer.name, layer.clipping) for layer in back] == [
        ("Background", False),
        ("ground", False),
        ("base", False),
        ("a", True),
        ("b", True),
        ("top", False),
    ]
    assert np.abs(psd_tools_flat(tmp_path / "back.psd") - ours(path)).max() <= 1
    again = read_psd(tmp_path / "back.psd").document.layers
    assert [layer.clip for layer in again] == [False, False, False, True, True, False]


def test_adjustment_layers_written_by_psd_tools_import_with_their_parameters(tmp_path):
    # psd-tools writes adjustment records as tagged blocks (it has no constructor for adjustment layers): levels,
    # legacy brightness/contrast, invert, posterize and threshold over a base, one of them clipped, one masked, one
    # inside a group. Imported with ``lasagna import-psd`` and composited: within 3/255 of tests/support/reference.py's
    # float64 composite of the stack folder, each adjustment read with its parameters.
    from psd_tools.constants import Tag
    from psd_tools.psd.adjustments import LevelRecord

    from tests.support.reference import composite_reference, to_uint8

    rng = np.random.default_rng(5)
    psd = PSDImage.new("RGBA", (W, H))
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    empty = Image.fromarray(np.zeros((H, W, 4), dtype=np.uint8))

    def adjustment(name, tag, *data, **fields):
        layer = psd.create_pixel_layer(empty, name=name)
        layer.tagged_blocks.set_data(tag, *data, **fields)
        return layer

    records = [LevelRecord(20, 230, 10, 250, 130), LevelRecord(0, 200, 0, 255, 80)]
    records += [LevelRecord(0, 255, 0, 255, 100)] * 27
    adjustment("levels", Tag.LEVELS, items=records, version=2)
    adjustment("legacy", Tag.BRIGHTNESS_AND_CONTRAST, 30, 65536 - 40, 127, 0)
    group = psd.create_group(name="group")
    group.append(psd.create_pixel_layer(rgba(rng, H, W), name="inner"))
    inv = adjustment("invert", Tag.INVERT)
    inv.opacity = 150
    adjustment("posterize", Tag.POSTERIZE, 4)
    adjustment("threshold", Tag.THRESHOLD, 140).clipping = True
    path = tmp_path / "adjust.psd"
    psd.save(path)
    out = tmp_path / "stack"
    assert main(["import-psd", str(path), "-o", str(out)]) == 0
    doc = load_stack(out).document
    kinds = {layer.id: layer.adjustment for _, layer in doc.walk() if layer.kind == "adjustment"}
    assert [a.type for a in kinds.values()] == ["levels", "brightness-contrast", "invert", "posterize", "threshold"]
    assert kinds["levels"].rgb.in_black == 20 / 255 and kinds["levels"].red.gamma == 0.8
    assert (kinds["legacy"].brightness, kinds["legacy"].contrast, kinds["legacy"].legacy) == (30.0, -40.0, True)
    assert kinds["posterize"].levels == 4 and kinds["threshold"].level == pytest.approx(139.5 / 255)
    assert main(["composite", str(out), "-o", str(tmp_path / "c.png")]) == 0
    with Image.open(tmp_path / "c.png") as im:
        got = np.asarray(im.convert("RGB")).astype(int)
    assert np.abs(got - to_uint8(composite_reference(out)).astype(int)).max() <= 3


def test_colour_adjustments_written_by_psd_tools_import_with_their_parameters(tmp_path):
    # Channel mixer, color balance, vibrance, black & white (tinted), gradient map, photo filter and hue/saturation's
    # colour ranges, as psd-tools writes their records (psd-tools composites none of them): each read with its
    # parameters, and the imported stack within 3/255 of tests/support/reference.py's float64 composite of it.
    import struct

    from psd_tools.constants import Tag
    from psd_tools.psd.adjustments import ColorStop, TransparencyStop
    from psd_tools.psd.descriptor import Bool, Descriptor, Double, Integer
    from psd_tools.psd.tagged_blocks import DescriptorBlock, TaggedBlock

    from tests.support.reference import composite_reference, to_uint8

    rng = np.random.default_rng(7)
    psd = PSDImage.new("RGBA", (W, H))
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    empty = Image.fromarray(np.zeros((H, W, 4), dtype=np.uint8))

    def adjustment(layer_name, tag, *data, **fields):
        layer = psd.create_pixel_layer(empty, name=layer_name)
        layer.tagged_blocks.set_data(tag, *data, **fields)
        layer.opacity = 200
        return layer

    def descriptor(name, tag, values):
        layer = psd.create_pixel_layer(empty, name=name)
        block = DescriptorBlock()
        for key, value in values.items():
            block[key] = value
        layer.tagged_blocks[tag] = TaggedBlock(key=tag, data=block)
        return layer

    rest = struct.pack(">10h", -10, 120, 0, 0, -8, 25, 25, 60, 0, 0) + bytes(12)
    adjustment("mixer", Tag.CHANNEL_MIXER, version=1, monochrome=0, data=[80, 30, -20, 0, 5], unknown=rest)
    adjustment("balance", Tag.COLOR_BALANCE, (30, -20, 10), (-40, 15, 55), (10, 35, -25), 1)
    descriptor("vibrance", Tag.VIBRANCE, {b"vibrance": Integer(60), b"Strt": Integer(-15)})
    tint = Descriptor(classID=b"RGBC")
    tint[b"Rd  "], tint[b"Grn "], tint[b"Bl  "] = Double(204.0), Double(153.0), Double(76.5)
    bw = {b"Rd  ": Integer(120), b"Yllw": Integer(-30), b"Grn ": Integer(40), b"Cyn ": Integer(60)}
    bw |= {b"Bl  ": Integer(200), b"Mgnt": Integer(80), b"useTint": Bool(True), b"tintColor": tint}
    descriptor("bw", Tag.BLACK_AND_WHITE, bw).opacity = 90
    stops = [ColorStop(200, 50, 0, (6553, 0, 19660, 0)), ColorStop(2048, 30, 0, (58981, 13107, 6553, 0))]
    stops.append(ColorStop(3700, 70, 0, (65535, 62258, 39321, 0)))
    opaque = [TransparencyStop(0, 50, 100), TransparencyStop(4096, 50, 100)]
    adjustment(
        "gmap", Tag.GRADIENT_MAP, version=1, is_reversed=0, is_dithered=0, name="g", color_stops=stops,
        transparency_stops=opaque, minimum_color=[0] * 4, maximum_color=[0] * 4,
    )  # fmt: skip
    adjustment("filter", Tag.PHOTO_FILTER, version=2, xyz=None, color_space=0, color_components=(0, 28180, 65535, 0),
               density=60, luminosity=1)  # fmt: skip
    items = [[(315, 345, 15, 45), (25, 40, -30)], [(75, 105, 135, 165), (-40, -60, 20)]] + [
        [(0, 0, 0, 0), (0, 0, 0)]
    ] * 4
    adjustment(
        "hues", Tag.HUE_SATURATION, version=2, enable=0, colorization=(0, 25, 0), master=(10, 15, 0), items=items
    )
    path = tmp_path / "colour.psd"
    psd.save(path)
    out = tmp_path / "stack"
    assert main(["import-psd", str(path), "-o", str(out)]) == 0
    doc = load_stack(out).document
    got = {layer.id: layer.adjustment for _, layer in doc.walk() if layer.kind == "adjustment"}
    assert [a.type for a in got.values()] == [
        "channel-mixer", "color-balance", "vibrance", "black-and-white", "gradient-map", "photo-filter",
        "hue-saturation",
    ]  # fmt: skip
    assert got["mixer"].green == (-10.0, 120.0, 0.0, -8.0) and got["mixer"].gray is None
    assert got["balance"].highlights == (10.0, 35.0, -25.0) and got["balance"].preserve_luminosity
    assert (got["vibrance"].vibrance, got["vibrance"].saturation) == (60.0, -15.0)
    assert got["bw"].reds == 120.0 and got["bw"].tint == pytest.approx((0.8, 0.6, 0.3))
    gmap = got["gmap"].stops
    assert [s.location for s in gmap] == pytest.approx([200 / 4096, 0.5, 3700 / 4096])
    assert [s.midpoint for s in gmap[:2]] == [0.3, 0.7]  # a PSD stop's midpoint is of the segment ending at it
    assert got["filter"].color == pytest.approx((0.0, 28180 / 65535, 1.0)) and got["filter"].density == 60.0
    assert [r.hue for r in got["hues"].ranges] == [25.0, -40.0] and got["hues"].hue == 10.0
    assert main(["composite", str(out), "-o", str(tmp_path / "c.png")]) == 0
    with Image.open(tmp_path / "c.png") as im:
        flat = np.asarray(im.convert("RGB")).astype(int)
    assert np.abs(flat - to_uint8(composite_reference(out)).astype(int)).max() <= 3


def test_a_solid_colour_fill_is_imported_as_a_solid_layer(tmp_path):
    # A solid colour fill (no mask) over a base, of multiply at opacity 200: a solid layer of its colour, and the
    # stack flattens as psd-tools' own composite of the file over white (which draws the fill from its setting).
    from psd_tools.constants import Tag
    from psd_tools.psd.descriptor import Descriptor, Double
    from psd_tools.psd.tagged_blocks import DescriptorBlock, TaggedBlock

    rng = np.random.default_rng(11)
    psd = PSDImage.new("RGBA", (W, H))
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    fill = psd.create_pixel_layer(Image.fromarray(np.zeros((H, W, 4), dtype=np.uint8)), name="fill")
    color = Descriptor(classID=b"RGBC")
    color[b"Rd  "], color[b"Grn "], color[b"Bl  "] = Double(51.0), Double(153.0), Double(204.0)
    block = DescriptorBlock()
    block[b"Clr "] = color
    fill.tagged_blocks[Tag.SOLID_COLOR_SHEET_SETTING] = TaggedBlock(key=Tag.SOLID_COLOR_SHEET_SETTING, data=block)
    fill.blend_mode, fill.opacity = BlendMode.MULTIPLY, 200
    path = tmp_path / "fill.psd"
    psd.save(path)
    stack = read_psd(path)
    (layer,) = [lay for lay in stack.document.layers if lay.id == "fill"]
    assert layer.kind == "solid" and layer.color == pytest.approx((0.2, 0.6, 0.8)) and layer.blend == "multiply"
    got = np.rint(render_stack(stack, dtype=torch.float64).image.numpy().transpose(1, 2, 0) * 255.0)
    assert np.abs(got - psd_tools_flat(path)).max() <= 1


def _gradient_fill_block(style: bytes, angle: float, scale: float, reverse: bool, stops, opacities):
    """A 'GdFl' descriptor as Photoshop writes one (psd-tools has no constructor for fill layers): Type, Angl, Scl,
    Rvrs, Dthr, Algn, and Grad (custom stops: Clrs of colour, Lctn 0…4096 and Mdpn percent; Trns of Opct)."""
    from psd_tools.psd.descriptor import Bool, Descriptor, Double, Enumerated, Integer, List, String, UnitFloat
    from psd_tools.psd.tagged_blocks import DescriptorBlock
    from psd_tools.terminology import Unit

    def stop(kind: bytes, location: int, **values):
        d = Descriptor(classID=kind)
        for key, value in values.items():
            d[key.encode().ljust(4)] = value
        d[b"Lctn"], d[b"Mdpn"] = Integer(location), Integer(50)
        return d

    colors = []
    for location, (r, g, b) in stops:
        c = Descriptor(classID=b"RGBC")
        c[b"Rd  "], c[b"Grn "], c[b"Bl  "] = Double(r), Double(g), Double(b)
        colors.append(stop(b"Clrt", location, Clr=c, Type=Enumerated(b"Clry", b"UsrS")))
    grad = Descriptor(classID=b"Grdn")
    grad[b"Nm  "], grad[b"GrdF"] = String("Custom"), Enumerated(b"GrdF", b"CstS")
    grad[b"Intr"], grad[b"Clrs"] = Double(0.0), List(colors)
    grad[b"Trns"] = List([stop(b"TrnS", loc, Opct=UnitFloat(unit=Unit.Percent, value=o)) for loc, o in opacities])
    block = DescriptorBlock()
    block[b"Type"] = Enumerated(b"GrdT", style)
    block[b"Angl"] = UnitFloat(unit=Unit.Angle, value=angle)
    block[b"Scl "] = UnitFloat(unit=Unit.Percent, value=scale)
    block[b"Rvrs"], block[b"Dthr"], block[b"Algn"] = Bool(reverse), Bool(False), Bool(True)
    block[b"Grad"] = grad
    return block


@pytest.mark.parametrize(
    "style,angle,scale,reverse",
    [(b"Lnr ", 30.0, 100.0, False), (b"Rdl ", 90.0, 80.0, True), (b"Angl", -45.0, 100.0, False),
     (b"Rflc", 120.0, 150.0, False), (b"Dmnd", 10.0, 60.0, True)],
)  # fmt: skip
def test_a_gradient_fill_is_imported_as_a_gradient_layer(tmp_path, style, angle, scale, reverse):
    # A gradient fill of each style (three colour stops, two opacity stops) over a base, one at full canvas and one
    # masked on a smaller rectangle, written by psd-tools' low-level API: imported as gradient layers, and the stack
    # composites within 3/255 of psd-tools' own composite of the file (which draws the fills from their settings).
    from psd_tools.constants import Tag
    from psd_tools.psd.tagged_blocks import TaggedBlock

    rng = np.random.default_rng(13)
    psd = PSDImage.new("RGBA", (W, H))
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    stops = [(0, (230.0, 20.0, 40.0)), (1500, (20.0, 200.0, 60.0)), (4096, (30.0, 60.0, 240.0))]
    for name, box, mode in (("fill", (0, 0, W, H), BlendMode.NORMAL), ("small", (3, 2, 15, 12), BlendMode.MULTIPLY)):
        pixels = Image.fromarray(np.zeros((box[3] - box[1], box[2] - box[0], 4), dtype=np.uint8))
        layer = psd.create_pixel_layer(pixels, name=name, left=box[0], top=box[1])
        block = _gradient_fill_block(style, angle, scale, reverse, stops, [(0, 100.0), (4096, 35.0)])
        layer.tagged_blocks[Tag.GRADIENT_FILL_SETTING] = TaggedBlock(key=Tag.GRADIENT_FILL_SETTING, data=block)
        layer.blend_mode, layer.opacity = mode, 220
    path = tmp_path / "gradient.psd"
    psd.save(path)
    warnings: list[str] = []
    stack = read_psd(path, warn=warnings.append)
    fills = [lay for lay in stack.document.layers if lay.kind == "gradient"]
    assert [f.id for f in fills] == ["fill", "small"] and not warnings
    g = fills[0].gradient
    assert (g.angle, g.scale, g.reverse, len(g.stops)) == (angle, scale, reverse, 3)
    assert g.stops[1].location == pytest.approx(1500 / 4096) and g.opacity_stops[1].opacity == pytest.approx(0.35)
    assert fills[1].size.width == 12 and (fills[1].offset.x, fills[1].offset.y) == (3, 2)
    got = ours(path)
    assert np.abs(got - psd_tools_flat(path)).max() <= 3


def _pattern(ident: str, tile: np.ndarray, alpha: bool = True):
    """A 'Patt' pattern record as Photoshop writes one (psd-tools' low-level classes): RGB channel slots, an unused
    slot, then the transparency slot; 8-bit raw planes."""
    from psd_tools.constants import ColorMode
    from psd_tools.psd.patterns import Pattern, VirtualMemoryArray, VirtualMemoryArrayList

    th, tw = tile.shape[:2]

    def plane(values):
        v = VirtualMemoryArray()
        v.set_data((tw, th), np.ascontiguousarray(values).tobytes(), 8)
        return v

    slots = [plane(tile[..., c]) for c in range(3)] + [VirtualMemoryArray()]
    slots.append(plane(tile[..., 3]) if alpha else VirtualMemoryArray())
    data = VirtualMemoryArrayList(rectangle=(0, 0, th, tw), channels=slots)
    return Pattern(image_mode=ColorMode.RGB, point=(th, tw), name="tile", pattern_id=ident, data=data)


def _pattern_fill_block(ident: str, scale: float, phase=(0.0, 0.0), angle: float | None = None):
    """A 'PtFl' descriptor as Photoshop writes one: Ptrn {Nm, Idnt}, Scl, Algn, phase {Hrzn, Vrtc} (and Angl)."""
    from psd_tools.psd.descriptor import Bool, Descriptor, Double, String, UnitFloat
    from psd_tools.psd.tagged_blocks import DescriptorBlock
    from psd_tools.terminology import Unit

    ref = Descriptor(classID=b"Ptrn")
    ref[b"Nm  "], ref[b"Idnt"] = String("tile\x00"), String(ident + "\x00")
    point = Descriptor(classID=b"Pnt ")
    point[b"Hrzn"], point[b"Vrtc"] = Double(phase[0]), Double(phase[1])
    block = DescriptorBlock()
    block[b"Ptrn"], block[b"Scl "], block[b"Algn"], block[b"phase"] = (
        ref, UnitFloat(unit=Unit.Percent, value=scale), Bool(True), point)  # fmt: skip
    if angle is not None:
        block[b"Angl"] = UnitFloat(unit=Unit.Angle, value=angle)
    return block


@pytest.mark.parametrize("scale,alpha", [(100.0, True), (170.0, True), (63.0, False)])
def test_a_pattern_fill_is_imported_as_a_pattern_layer(tmp_path, scale, alpha):
    # A pattern fill over a base, one at full canvas and one masked (multiply) on a smaller rectangle, its pattern in
    # the file's 'Patt' block, written by psd-tools' low-level API: imported as pattern layers with their tile, and
    # the stack composites within 3/255 of psd-tools' own composite of the file (which tiles the pattern itself).
    from psd_tools.constants import Tag
    from psd_tools.psd.patterns import Patterns
    from psd_tools.psd.tagged_blocks import TaggedBlock

    rng = np.random.default_rng(17)
    psd = PSDImage.new("RGBA", (W, H))
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    tile = rng.integers(0, 256, (5, 7, 4), dtype=np.uint8)
    for name, box, mode in (("fill", (0, 0, W, H), BlendMode.NORMAL), ("small", (3, 2, 15, 12), BlendMode.MULTIPLY)):
        pixels = Image.fromarray(np.zeros((box[3] - box[1], box[2] - box[0], 4), dtype=np.uint8))
        layer = psd.create_pixel_layer(pixels, name=name, left=box[0], top=box[1])
        block = _pattern_fill_block("5e1713ab-e968", scale)
        layer.tagged_blocks[Tag.PATTERN_FILL_SETTING] = TaggedBlock(key=Tag.PATTERN_FILL_SETTING, data=block)
        layer.blend_mode, layer.opacity = mode, 220
    psd.tagged_blocks.set_data(Tag.PATTERNS1, Patterns([_pattern("5e1713ab-e968", tile, alpha)]))
    path = tmp_path / "pattern.psd"
    psd.save(path)
    warnings: list[str] = []
    stack = read_psd(path, warn=warnings.append)
    fills = [lay for lay in stack.document.layers if lay.kind == "pattern"]
    assert [f.id for f in fills] == ["fill", "small"] and not warnings
    assert (
        fills[0].pattern.scale == scale
        and fills[1].size.width == 12
        and (fills[1].offset.x, fills[1].offset.y) == (3, 2)
    )
    t = stack.tensors["fill"]
    assert t.color.shape == (3, 5, 7) and (t.alpha is not None) == alpha
    assert np.array_equal(np.rint(t.color.numpy() * 255).astype(np.uint8), tile[..., :3].transpose(2, 0, 1))
    assert np.abs(ours(path) - psd_tools_flat(path)).max() <= 3
    stack.save(tmp_path / "s")  # the tile is the stack's own file, and renders the same from it
    assert (tmp_path / "s" / "layers" / "fill.png").is_file()
    loaded = render_stack(load_stack(tmp_path / "s"), dtype=torch.float64).image
    assert torch.equal(loaded, render_stack(stack, dtype=torch.float64).image)


def test_a_pattern_fill_without_its_pattern_keeps_its_pixels_with_one_warning(tmp_path):
    from psd_tools.constants import Tag
    from psd_tools.psd.tagged_blocks import TaggedBlock

    rng = np.random.default_rng(19)
    psd = PSDImage.new("RGBA", (W, H))
    psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="base")
    layer = psd.create_pixel_layer(rgba(rng, H, W, "opaque"), name="fill")
    block = _pattern_fill_block("missing", 100.0, phase=(2.5, 0.0), angle=30.0)
    layer.tagged_blocks[Tag.PATTERN_FILL_SETTING] = TaggedBlock(key=Tag.PATTERN_FILL_SETTING, data=block)
    path = tmp_path / "pattern.psd"
    psd.save(path)
    warnings: list[str] = []
    stack = read_psd(path, warn=warnings.append)
    assert stack.document.layer("fill").kind == "pixels"
    fill = [w for w in warnings if "fill" in w]
    assert len(fill) == 1 and "pattern 'missing' is not in the file" in fill[0] and "\n" not in fill[0]
