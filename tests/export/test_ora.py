"""OpenRaster export and import: the file layout the spec requires, the dodge pair for multipliers
above 1, what an independent W3C flattener makes of the layers, warnings, and the import round trip."""

from __future__ import annotations

import io
import warnings
import zipfile
from pathlib import Path
from xml.etree import ElementTree as ET

import numpy as np
import pytest
import torch

from lasagna.errors import ImageError
from lasagna.export.ora import encode_ora, export_ora
from lasagna.export.ora_import import import_ora, read_ora
from lasagna.export.rasters import dodge_codes
from lasagna.io.render import render_stack
from lasagna.io.stack import Stack, load_stack
from tests.export.oraflat import flatten, png_size, read_png_rgb
from tests.support.bounded import cpu_seconds, within
from tests.support.reference import composite_reference, to_uint8
from tests.support.stackcraft import random_stack

BASIC = Path(__file__).resolve().parents[2] / "examples" / "stacks" / "basic"


def _ora(tmp_path, stack, name="x.ora", **kw) -> Path:
    return export_ora(stack, tmp_path / name, **kw)


def test_layout_mimetype_first_and_stored(tmp_path):
    path = _ora(tmp_path, load_stack(BASIC))
    raw = path.read_bytes()
    assert raw[:4] == b"PK\x03\x04" and raw[30:38] == b"mimetype" and raw[38:54] == b"image/openraster"
    with zipfile.ZipFile(path) as zf:
        first = zf.infolist()[0]
        assert first.filename == "mimetype" and first.compress_type == zipfile.ZIP_STORED and first.extra == b""
        assert zf.read("mimetype") == b"image/openraster"
        names = set(zf.namelist())
        assert {"stack.xml", "mergedimage.png", "Thumbnails/thumbnail.png"} <= names
        root = ET.fromstring(zf.read("stack.xml"))
        for el in root.find("stack"):
            assert el.get("src") in names
            assert png_size(zf.read(el.get("src")))  # every layer is a readable PNG


def test_stack_xml_order_ops_and_attributes(tmp_path):
    stack = load_stack(BASIC)
    with zipfile.ZipFile(_ora(tmp_path, stack)) as zf:
        root = ET.fromstring(zf.read("stack.xml"))
    assert (root.tag, root.get("w"), root.get("h")) == ("image", "64", "48")
    layers = list(root.find("stack"))
    # Topmost first; the shading multiplier (values up to 1.6) is a multiply + colour-dodge pair.
    assert [layer.get("src") for layer in layers] == [
        "data/hidden.png",
        "data/glow.png",
        "data/sticker.png",
        "data/_dodge/shade.png",
        "data/shade.png",
        "data/base.png",
        "data/_background.png",
    ]
    assert [layer.get("composite-op") for layer in layers] == [
        "svg:src-over",
        "svg:plus",
        "svg:src-over",
        "svg:color-dodge",
        "svg:multiply",
        "svg:src-over",
        "svg:src-over",
    ]
    assert [layer.get("visibility") for layer in layers] == ["hidden"] + ["visible"] * 6
    assert layers[2].get("x") == "44" and layers[2].get("y") == "0"  # offset y = -6 is cropped to the canvas
    assert all(float(layer.get("opacity")) == 1.0 for layer in layers)


def test_merged_image_and_thumbnail(tmp_path):
    stack = Stack.from_image(torch.rand(3, 40, 300))
    ours = to_uint8(render_stack(stack, dtype=torch.float64).image.numpy())
    with zipfile.ZipFile(_ora(tmp_path, stack)) as zf:
        merged = read_png_rgb(zf.read("mergedimage.png"))
        thumb = zf.read("Thumbnails/thumbnail.png")
    np.testing.assert_array_equal(np.rint(merged * 255).astype(np.uint8), ours)
    w, h = png_size(thumb)
    assert max(w, h) == 256 and (w, h) == (256, 34)


def test_small_canvas_is_its_own_thumbnail_and_a_given_merged_png_is_kept(tmp_path):
    """A canvas within 256² is its own thumbnail (what Pillow's ``thumbnail`` would give: it never
    enlarges); ``merged_png`` (composite.png's bytes) is stored as mergedimage.png unchanged."""
    from lasagna.io.render import encode_composite

    stack = Stack.from_image(torch.rand(3, 50, 70))
    result = render_stack(stack)
    ours = to_uint8(render_stack(stack, dtype=torch.float64).image.numpy())
    given = encode_composite(result)
    marked = given + b"(kept as given)"  # a PNG reader stops at IEND: the marker shows the bytes were kept
    for merged_png in (None, marked):
        with zipfile.ZipFile(io.BytesIO(encode_ora(stack, composite=result.image, merged_png=merged_png))) as zf:
            merged, thumb = zf.read("mergedimage.png"), zf.read("Thumbnails/thumbnail.png")
        assert thumb == merged and png_size(thumb) == (70, 50)
        np.testing.assert_array_equal(np.rint(read_png_rgb(merged) * 255).astype(np.uint8), ours)
        assert merged == (marked if merged_png is not None else given)


@pytest.mark.parametrize("seed", range(6))
def test_flattened_layers_match_our_composite(tmp_path, seed):
    """Layers as an 8-bit W3C paint program flattens them ≈ our composite (sRGB, per-layer clamp)."""
    folder = random_stack(tmp_path / "s", 100 + seed, unit_only=seed % 2 == 0)
    stack = load_stack(folder)
    negative = [layer.id for layer in stack.document.layers if layer.range[0] < 0]
    seen: list[str] = []
    path = _ora(tmp_path, stack, warn=seen.append)
    with zipfile.ZipFile(path) as zf:
        top = list(ET.fromstring(zf.read("stack.xml")).find("stack"))[0].get("src")
    # Negative plus values cannot be expressed: said in one line, and the exact composite goes on top.
    assert len(seen) == (1 if negative else 0) and (top == "data/_composite.png") == bool(negative)
    ours = to_uint8(render_stack(stack, dtype=torch.float64).image.numpy()).astype(float)
    err = np.abs(flatten(path) * 255 - ours)
    assert err.max() <= 1.5 and err.mean() <= 0.5, (err.max(), err.mean())


def test_dodge_pair_reproduces_a_0_2_multiplier(tmp_path):
    base = torch.randint(0, 256, (3, 16, 32)) / 255.0  # 8-bit exact: isolates the pair's own error
    y = torch.linspace(0, 2, 32).expand(1, 16, 32).contiguous()
    stack = Stack.from_image(base)
    stack.add_layer("shade", y, blend="multiply", range=(0, 2))
    path = _ora(tmp_path, stack)
    exact = (base.double() * y.double()).clamp(0, 1).numpy().transpose(1, 2, 0)
    assert np.abs(flatten(path) - exact).max() <= 1.0 / 255  # exact pair, 8-bit layer values
    # Blending in 8 bits (as Krita does) the flattened codes are within one code of the exact ones.
    assert np.abs(np.rint(flatten(path, quantize=True) * 255) - np.rint(exact * 255)).max() <= 1


def test_dodge_codes_are_the_nearest_gain():
    y = np.linspace(1, 3, 2001)
    d = dodge_codes(y)
    gain = 1.0 / (1.0 - d)
    all_gains = 255.0 / (255.0 - np.arange(0, 255))
    best = np.abs(all_gains[None, :] - y[:, None]).min(axis=1)
    np.testing.assert_allclose(np.abs(gain - y), best, atol=1e-12)
    assert dodge_codes(np.array([1.0, 0.5]))[0] == 0.0 and dodge_codes(np.array([0.5]))[0] == 0.0


def test_plus_above_one_is_split_exactly(tmp_path):
    stack = Stack.from_image(torch.full((3, 4, 4), 0.1))
    stack.add_layer("light", torch.full((3, 4, 4), 1.6), blend="plus", range=(0, 2))
    path = _ora(tmp_path, stack)
    with zipfile.ZipFile(path) as zf:
        ops = [layer.get("composite-op") for layer in ET.fromstring(zf.read("stack.xml")).find("stack")]
    assert ops == ["svg:plus", "svg:plus", "svg:src-over", "svg:src-over"]
    assert np.abs(flatten(path) - 1.0).max() == 0  # 0.1 + 1.6, clamped
    stack.document = stack.document.replace_layer("light", opacity=0.5)  # α baked in: 0.8, one layer
    path = _ora(tmp_path, stack)
    assert np.abs(flatten(path) - (0.1 + 0.5 * 1.6)).max() <= 1 / 255


def test_inexpressible_features_warn_and_add_the_exact_composite(tmp_path):
    stack = Stack.from_image(torch.full((3, 4, 4), 0.5), blend_space="linear", clamp="output")
    stack.add_layer("big", torch.full((3, 4, 4), 0.9), blend="plus")  # above 1 in between ...
    stack.add_layer("neg", torch.full((3, 4, 4), -0.5), blend="plus", range=(-0.5, 0.5))  # ... and back
    seen = []
    path = export_ora(stack, tmp_path / "x.ora", warn=seen.append)
    assert len(seen) == 1 and "\n" not in seen[0]
    for fragment in ("blend_space='linear'", "negative values of layer 'neg'", "clamp='output'", "Composite (exact)"):
        assert fragment in seen[0]
    ours = to_uint8(render_stack(stack).image.double().numpy())  # the float32 render the export made
    np.testing.assert_array_equal(np.rint(flatten(path) * 255), ours)  # flattens to the exact composite
    assert import_ora(path).ids == ("base", "big", "neg")  # the composite layer is not imported
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        encode_ora(stack)  # without warn=, it is a Python warning
    assert len(record) == 1 and issubclass(record[0].category, UserWarning)


def test_clamp_output_that_does_not_matter_adds_nothing(tmp_path):
    stack = Stack.from_image(torch.rand(3, 4, 4), clamp="output")
    stack.add_layer("m", torch.rand(1, 4, 4), blend="multiply")
    seen = []
    encode_ora(stack, warn=seen.append)
    assert seen == []


def test_export_is_atomic_on_error(tmp_path):
    target = tmp_path / "keep.ora"
    target.write_bytes(b"old")
    stack = Stack.from_image(torch.rand(3, 4, 4))
    stack.tensors["base"].color.fill_(float("nan"))
    with pytest.raises(Exception):
        export_ora(stack, target)
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["keep.ora"]


# ---- import ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_import_round_trip_unit_stacks(tmp_path, seed):
    folder = random_stack(tmp_path / "s", 200 + seed, unit_only=True)
    stack = load_stack(folder)
    path = _ora(tmp_path, stack)
    back = import_ora(path, tmp_path / "back")
    ours = to_uint8(composite_reference(folder)).astype(int)
    again = to_uint8(composite_reference(tmp_path / "back")).astype(int)
    assert np.abs(ours - again).max() <= 1
    canvas, back_canvas = stack.document.canvas, back.document.canvas
    assert (back_canvas.width, back_canvas.height) == (canvas.width, canvas.height)
    assert np.abs(np.subtract(back_canvas.background, canvas.background)).max() <= 0.5 / 255  # 8-bit layer
    assert set(back.ids) <= set(stack.ids)  # layers wholly outside the canvas are dropped, nothing added
    for layer in back.document.layers:
        original = stack.layer(layer.id)
        assert (layer.blend, layer.visible) == (original.blend, original.visible)
        if layer.blend != "plus":  # (a plus layer's fractional alpha and opacity are baked into its values)
            assert layer.opacity == pytest.approx(original.opacity, abs=1e-6)


def test_import_restores_ids_blends_and_the_multiplier(tmp_path):
    stack = load_stack(BASIC)
    back = import_ora(_ora(tmp_path, stack))
    assert back.ids == stack.ids
    assert [layer.blend for layer in back.document.layers] == [layer.blend for layer in stack.document.layers]
    assert back.layer("shade").range == (0.0, 2.0)
    assert back.layer("hidden").visible is False and back.layer("sticker").offset.x == 44
    err = (back.tensors["shade"].color - stack.tensors["shade"].color.expand(3, -1, -1)).abs().max().item()
    assert err <= 2 * 2 / 255  # 8-bit multiply and dodge codes


def test_read_ora_limits(tmp_path):
    path = _ora(tmp_path, load_stack(BASIC))
    with pytest.raises(ImageError, match="zip-bomb"):
        read_ora(path, max_uncompressed=1000)
    with pytest.raises(ImageError, match="over the limit of 100"):
        read_ora(path, max_pixels=100)


# ---- hostile archives (#16) ---------------------------------------------------------------------------


def _write_ora(path: Path, entries: dict[str, bytes]) -> Path:
    """An .ora from ``entries`` (mimetype first, stored; the rest deflated), as an attacker would zip it."""
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("mimetype", b"image/openraster", compress_type=zipfile.ZIP_STORED)
        for name, data in entries.items():
            zf.writestr(name, data, compress_type=zipfile.ZIP_DEFLATED)
    return path


def _xml(layers: str, w: int = 8, h: int = 8, head: str = "<?xml version='1.0' encoding='UTF-8'?>\n") -> str:
    return f'{head}<image version="0.0.5" w="{w}" h="{h}"><stack>{layers}</stack></image>'


def _layer(src: str, name: str = "a") -> str:
    return f'<layer name="{name}" src="{src}" x="0" y="0" opacity="1" visibility="visible" />'


def _png8(w: int = 8, h: int = 8) -> bytes:
    from tests.support import pngcraft

    return pngcraft.gray8(w, h, 90)


def _refused_ora(path: Path, **kw) -> str:
    with pytest.raises(ImageError) as info:
        read_ora(path, **kw)
    message = str(info.value)
    assert "\n" not in message and str(path) in message
    return message


def test_one_entry_named_by_many_layers_is_refused(tmp_path, monkeypatch):
    import lasagna.export.ora_import as ora_module

    xml = _xml("".join(_layer("data/a.png", f"l{i}") for i in range(40)), 4096, 4096)
    path = _write_ora(tmp_path / "x.ora", {"stack.xml": xml.encode(), "data/a.png": _png8(4096, 4096)})
    monkeypatch.setattr(ora_module, "decode_png", lambda *a, **k: pytest.fail("decoded"))
    start = cpu_seconds()
    assert "src 'data/a.png' is also the src of stack[0]" in _refused_ora(path)
    assert cpu_seconds() - start < 2  # CPU seconds: refused from the XML, not after inflating 40 × 4096²


def _padded_entry_ora(path: Path, tail: int) -> Path:
    """An .ora whose layer entry is an 8×8 PNG followed by ``tail`` zero bytes (deflated to ~tail/1000)."""
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("mimetype", b"image/openraster", compress_type=zipfile.ZIP_STORED)
        zf.writestr("stack.xml", _xml(_layer("data/a.png")).encode(), compress_type=zipfile.ZIP_DEFLATED)
        info = zipfile.ZipInfo("data/a.png")
        info.compress_type = zipfile.ZIP_DEFLATED
        with zf.open(info, "w", force_zip64=True) as fh:
            fh.write(_png8())
            zero = bytes(2**20)
            for _ in range(tail // len(zero)):
                fh.write(zero)
    return path


def test_an_entry_padded_past_its_png_is_refused_unread(tmp_path):
    from lasagna.io.png import PngHeader, png_file_limit

    cap = png_file_limit(PngHeader(8, 8, 8, 0, False))  # 64 MiB of slack for ancillary chunks
    path = _padded_entry_ora(tmp_path / "x.ora", cap + 2**20)
    assert path.stat().st_size < 2**20
    assert f"entry 'data/a.png' inflates past {cap} bytes" in _refused_ora(path)


@pytest.mark.slow
def test_an_entry_padded_with_1gib_is_refused_in_bounded_memory(tmp_path):
    from tests.support.peak import run_cli

    path = _padded_entry_ora(tmp_path / "x.ora", 2**30)
    assert path.stat().st_size < 4 * 2**20
    code, out, err, peak = run_cli("import-ora", path, "-o", tmp_path / "out")
    assert code == 2 and "inflates past" in err and len(err.splitlines()) == 1, err
    assert peak < 500 and not (tmp_path / "out").exists()


def test_utf16_stack_xml_with_an_entity_is_refused(tmp_path):
    xml = _xml(
        _layer("data/a.png", "&boom;"),
        head='<?xml version="1.0" encoding="UTF-16"?>\n<!DOCTYPE image [<!ENTITY boom "x">]>\n',
    )
    path = _write_ora(tmp_path / "x.ora", {"stack.xml": xml.encode("utf-16"), "data/a.png": _png8()})
    assert "stack.xml: not UTF-8" in _refused_ora(path)


def test_a_declared_non_utf8_encoding_is_refused(tmp_path):
    xml = _xml(_layer("data/a.png"), head="<?xml version='1.0' encoding='ISO-8859-1'?>\n")
    path = _write_ora(tmp_path / "x.ora", {"stack.xml": xml.encode("latin-1"), "data/a.png": _png8()})
    assert "declares encoding 'ISO-8859-1'; expected OpenRaster XML in UTF-8" in _refused_ora(path)


def test_a_utf8_dtd_is_refused(tmp_path):
    xml = _xml(_layer("data/a.png"), head='<?xml version="1.0"?>\n<!DOCTYPE image [<!ENTITY e "x">]>\n')
    path = _write_ora(tmp_path / "x.ora", {"stack.xml": xml.encode(), "data/a.png": _png8()})
    assert "declares a DTD or entities" in _refused_ora(path)


def test_a_plain_utf8_archive_is_read(tmp_path):
    for head in ("", "<?xml version='1.0' encoding='utf8'?>\n", "\ufeff<?xml version='1.0' encoding='UTF-8'?>\n"):
        path = _write_ora(tmp_path / "x.ora", {"stack.xml": _xml(_layer("data/a.png", "é"), head=head).encode()})
        with zipfile.ZipFile(path, "a") as zf:
            zf.writestr("data/a.png", _png8())
        width, height, layers = read_ora(path)
        assert (width, height, layers[0]["name"]) == (8, 8, "é")


def test_import_is_refused_over_the_budget_before_decoding(tmp_path, monkeypatch):
    import lasagna.export.ora_import as ora_module
    from lasagna.limits import BudgetError, memory_budget_scope

    path = _ora(tmp_path, load_stack(BASIC))
    monkeypatch.setattr(ora_module, "decode_png", lambda *a, **k: pytest.fail("decoded"))
    with memory_budget_scope(100_000), pytest.raises(BudgetError) as info:
        import_ora(path)
    assert "decoding the 7 layers needs" in str(info.value) and "over the memory budget of 97.7 KB" in str(info.value)


def _every_mode_stack(folder: Path) -> Stack:
    from lasagna.document.blend import BLEND_MODES

    g = torch.Generator().manual_seed(3)
    stack = Stack.from_image(torch.rand(3, 8, 8 * len(BLEND_MODES), generator=g), id="base")
    for i, mode in enumerate(BLEND_MODES):
        stack.add_layer(f"m-{mode}", torch.rand(4, 8, 8, generator=g), blend=mode, offset=(8 * i, 0))
    stack.save(folder)
    return load_stack(folder)


def test_every_mode_is_a_composite_op_krita_reads_and_imports_back(tmp_path):
    from lasagna.document.blend import BLEND_MODES
    from lasagna.export.ora import KRITA_OPS

    stack = _every_mode_stack(tmp_path / "s")
    path = _ora(tmp_path, stack)
    with zipfile.ZipFile(path) as zf:
        ops = {el.get("name"): el.get("composite-op") for el in ET.fromstring(zf.read("stack.xml")).find("stack")}
    for mode in BLEND_MODES:
        # The OpenRaster spec's svg: names where it has one (Krita reads those), Krita's own for exclusion (which it
        # reads as normal under svg:) and Photoshop's modes.
        expect = "svg:src-over" if mode == "normal" else f"svg:{mode}"
        assert ops[f"m-{mode}"] == (f"krita:{KRITA_OPS[mode]}" if mode in KRITA_OPS else expect)
    assert ops["m-exclusion"] == "krita:exclusion" and ops["m-linear-light"] == "krita:linear light"
    back = import_ora(path, tmp_path / "back")
    assert [layer.blend for layer in back.document.layers] == ["normal", *BLEND_MODES]  # a lone dodge included
    ours = to_uint8(composite_reference(tmp_path / "s")).astype(int)
    again = to_uint8(composite_reference(tmp_path / "back")).astype(int)
    assert np.abs(ours - again).max() <= 1  # dissolve's pattern is baked into its alpha, so it reads back exactly


def test_svg_exclusion_of_earlier_files_still_reads_as_exclusion(tmp_path):
    stack = _every_mode_stack(tmp_path / "s")
    path = _ora(tmp_path, stack)
    with zipfile.ZipFile(path) as zf:
        entries = {i.filename: zf.read(i) for i in zf.infolist()}
    entries["stack.xml"] = entries["stack.xml"].replace(b'"krita:exclusion"', b'"svg:exclusion"')
    old = tmp_path / "old.ora"
    with zipfile.ZipFile(old, "w") as zf:
        zf.writestr("mimetype", entries.pop("mimetype"), compress_type=zipfile.ZIP_STORED)
        for name, data in entries.items():
            zf.writestr(name, data)
    back = import_ora(old)
    assert {layer.id: layer.blend for layer in back.document.layers}["m-exclusion"] == "exclusion"


def test_an_unknown_composite_op_lists_the_supported_ones(tmp_path):
    stack = _every_mode_stack(tmp_path / "s")
    path = _ora(tmp_path, stack)
    with zipfile.ZipFile(path) as zf:
        entries = {n: zf.read(n) for n in zf.namelist()}
    entries["stack.xml"] = entries["stack.xml"].replace(b"svg:hue", b"svg:vivid-light")
    bad = tmp_path / "bad.ora"
    with zipfile.ZipFile(bad, "w") as zf:
        zf.writestr(zipfile.ZipInfo("mimetype"), entries.pop("mimetype"))
        for n, data in entries.items():
            zf.writestr(n, data)
    with pytest.raises(
        ImageError, match="composite-op 'svg:vivid-light' is not supported; expected one of svg:src-over"
    ):
        import_ora(bad)


# ---- #28 -------------------------------------------------------------------------------------------------


def test_srcs_named_like_windows_devices_import(tmp_path):
    srcs = ["data/aux.png", "data/con.x.png", "data/nul.a.png", "data/COM3.png", "x/aux.png"]
    xml = _xml("".join(_layer(s, f"n{i}") for i, s in enumerate(srcs)))
    path = _write_ora(tmp_path / "dev.ora", {"stack.xml": xml.encode(), **{s: _png8() for s in srcs}})
    stack = within(20, lambda: import_ora(path))
    assert stack.document.ids == ("aux_", "COM3_", "nul_.a", "con_.x", "aux_-2")  # bottom first


def _nested_ora(path: Path, depth: int) -> Path:
    xml = _xml("".join("<stack>" for _ in range(depth)) + _layer("data/a.png") + "</stack>" * depth)
    return _write_ora(path, {"stack.xml": xml.encode(), "data/a.png": _png8()})


def test_stacks_nested_as_deep_as_a_stack_allows_import_and_validate(tmp_path, capsys):
    from lasagna.cli import main
    from lasagna.limits import MAX_GROUP_DEPTH

    path = _nested_ora(tmp_path / "ok.ora", MAX_GROUP_DEPTH)
    assert main(["import-ora", str(path), "-o", str(tmp_path / "out")]) == 0
    assert main(["validate", str(tmp_path / "out")]) == 0, capsys.readouterr().err


@pytest.mark.parametrize("depth", [31, 32, 40])
def test_stacks_nested_deeper_than_a_stack_allows_are_one_line(tmp_path, capsys, depth):
    from lasagna.cli import main

    code = main(["import-ora", str(_nested_ora(tmp_path / "deep.ora", depth)), "-o", str(tmp_path / "out")])
    err_text = capsys.readouterr().err
    assert code == 2 and err_text.count("\n") == 1 and "groups nest deeper than" in err_text, err_text
    assert not (tmp_path / "out").exists()


def test_names_with_control_characters_import_replaced_with_a_warning(tmp_path, capsys):
    from lasagna.cli import main

    xml = _xml(f'<stack name="g&#9;">{_layer("data/a.png", "a&#10;b&#x85;")}</stack>')
    path = _write_ora(tmp_path / "n.ora", {"stack.xml": xml.encode(), "data/a.png": _png8()})
    assert main(["import-ora", str(path), "-o", str(tmp_path / "out")]) == 0
    err_text = capsys.readouterr().err
    assert err_text.count("holds control characters") == 2 and err_text.count("\n") == 2, err_text
    names = [layer.name for _, layer in load_stack(tmp_path / "out").document.walk()]
    assert names == ["g\ufffd", "a\ufffdb\ufffd"]


def _chain_stack(group_base: bool = False) -> Stack:
    """An opaque ground, a clipping chain (a half-transparent base of opacity .8, or a group as base; a normal
    and a multiply clipped layer), a layer above."""
    from lasagna.io.stack import stack_from_tensors

    g = torch.Generator().manual_seed(5)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    stack = stack_from_tensors(
        [
            dict(id="ground", image=r(3, 12, 16)),
            dict(id="base", image=r(3, 6, 8), alpha=r(1, 6, 8), offset=(3, 2), opacity=0.8, blend="screen"),
            dict(id="a", image=r(3, 12, 16), alpha=r(1, 12, 16)),
            dict(id="top", image=r(3, 4, 4), offset=(10, 7)),
        ]
    )
    layers = [layer.model_dump() for layer in stack.document.layers]
    layers[2]["clip"] = True
    if group_base:
        layers[1] = {
            "id": "g",
            "kind": "group",
            "isolated": True,
            "opacity": 0.8,
            "layers": [layers[1] | {"opacity": 1.0}],
        }
    stack.document = stack.document.with_layers(layers)
    return stack


@pytest.mark.parametrize("group_base", [False, True])
def test_a_clipping_chain_is_written_as_krita_writes_inherit_alpha_and_read_back(tmp_path, group_base):
    stack = _chain_stack(group_base)
    said: list[str] = []
    path = _ora(tmp_path, stack, warn=said.append)
    assert said == []
    root = ET.fromstring(zipfile.ZipFile(path).read("stack.xml"))
    chain = [el for el in root.iter("stack") if el.get("isolation") == "isolate" and len(el) == 2][-1]
    assert [el.get("composite-op") for el in chain] == ["svg:src-atop", "svg:src-over"]  # topmost first
    assert chain.get("composite-op") == ("svg:src-over" if group_base else "svg:screen")
    back = import_ora(path)
    assert any(layer.clip for _, layer in back.document.walk())
    ours = to_uint8(render_stack(stack, dtype=torch.float64).image.numpy()).astype(int)
    again = to_uint8(render_stack(back, dtype=torch.float64).image.numpy()).astype(int)
    assert np.abs(ours - again).max() <= 1  # the layers' 8-bit codes
