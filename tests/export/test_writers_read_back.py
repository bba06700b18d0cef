"""Every document a writer writes, we read back (#28): random documents — names of arbitrary Unicode (those the
name rule refuses are refused in one line, then imported as importers would), groups nested up to
``MAX_GROUP_DEPTH``, every blend mode — written as a stack folder, an OpenRaster file and a PSD, are read
back by ``load_stack`` / ``import_ora`` / ``read_psd`` to the same layer tree. Small canvases, bounded examples.

What the interchange files add is dropped before comparing: PSD's "(clamp to 1)" helper layers, its
"Background" layer and "Composite (exact)" layer (OpenRaster's import drops its own); groups' ids (the files
keep names, not ids; a PSD's layer ids come from names too); opacity is compared in 8-bit steps (PSD stores
round(255 · opacity)), and not for plus and dissolve layers (their fractional alpha × opacity, or dissolve's
pattern, is baked into the values, ``lasagna.export.rasters``); a PSD's plus reads back as linear-dodge.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lasagna.compose.layer import LayerTensors
from lasagna.document import Document
from lasagna.document.blend import BLEND_MODES
from lasagna.document.types import check_name, sanitise_name
from lasagna.errors import DocumentError
from lasagna.export.ora import encode_ora
from lasagna.export.ora_import import import_ora
from lasagna.export.rasters import COMPOSITE_NAME
from lasagna.io.stack import Stack, load_stack, save_stack
from lasagna.limits import MAX_GROUP_DEPTH

W, H = 3, 2
AWKWARD = [
    "a\x00b",
    "\t",
    "line\nbreak",
    "\x7f\x85",
    "&<>\"'",
    " ",
    "aux.png",
    "🎨 \u2028",
    "\ud800",
    "\ufffe",
    "é" * 40,
]
names = st.one_of(st.sampled_from(AWKWARD), st.text(min_size=1, max_size=10))


def _name(raw: str) -> str:
    """``raw`` if the name rule allows it; else the refusal is one line and the importers' stand-in is used."""
    try:
        return check_name(raw)
    except DocumentError as exc:
        assert "\n" not in str(exc)
    doc = {"format": "lasagna.stack", "version": 1, "canvas": {"width": 1, "height": 1}}
    with pytest.raises(DocumentError):
        Document.from_dict({**doc, "layers": [{"id": "a", "name": raw, "kind": "solid", "color": [0, 0, 0]}]})
    return sanitise_name(raw)


@st.composite
def documents(draw) -> Stack:
    """An opaque base, then a chain of ``depth`` nested groups (isolated with any blend, or pass-through), each
    level with up to one pixels layer of any blend beside the next group."""
    depth = draw(st.sampled_from([0, 1, 2, MAX_GROUP_DEPTH - 1, MAX_GROUP_DEPTH]) | st.integers(0, MAX_GROUP_DEPTH))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    tensors: dict[str, LayerTensors] = {}
    count = [0]

    def pixels(blend: str, base: bool = False) -> dict:
        lid = f"l{count[0]}"
        count[0] += 1
        h, w = (H, W) if base else (draw(st.integers(1, H)), draw(st.integers(1, W)))
        color = torch.from_numpy(rng.integers(0, 256, (3, h, w)).astype(np.float32) / 255)
        alpha = None if base else torch.from_numpy(rng.integers(1, 256, (1, h, w)).astype(np.float32) / 255)
        tensors[lid] = LayerTensors(color, alpha, None)
        return {
            "id": lid,
            "name": _name(draw(names)),
            "kind": "pixels",
            "source": f"layers/{lid}.png",
            "blend": blend,
            "opacity": 1.0 if base else draw(st.integers(0, 255)) / 255,
            "visible": base or draw(st.booleans()),
        }

    inner: list[dict] = []
    for level in reversed(range(depth + 1)):
        if draw(st.booleans()) or (level == depth and depth > 0):
            inner.insert(draw(st.integers(0, len(inner))), pixels(draw(st.sampled_from(BLEND_MODES))))
        if level == 0:
            break
        isolated = draw(st.booleans())
        group = {
            "id": f"g{level}",
            "name": _name(draw(names)),
            "kind": "group",
            "isolated": isolated,
            "blend": draw(st.sampled_from(BLEND_MODES)) if isolated else "normal",
            "opacity": draw(st.integers(0, 255)) / 255,
            "visible": draw(st.booleans()),
            "layers": inner,
        }
        inner = [group]
    doc = Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": W, "height": H, "background": [1.0, 1.0, 1.0]},
            "layers": [pixels("normal", base=True), *inner],
        }
    )
    return Stack(doc, None, tensors, {lid: 8 for lid in tensors})


# Leaves whose opacity the writers bake into their pixels (plus: its fractional α; dissolve: its pattern).
BAKED = ("plus", "dissolve")


def tree(layers, *, ids: str = "leaves", helpers: bool = False, psd: bool = False) -> list:
    """The layer tree as comparable tuples, with the ids of ``ids`` ("leaves" or "none"; group ids are made from
    names on import), the interchange files' helper layers dropped unless ``helpers``. ``psd``: plus is compared
    as linear-dodge (a PSD holds both as LINEAR_DODGE, read back as Photoshop's)."""
    out = []
    for layer in layers:
        if not helpers and (layer.name == COMPOSITE_NAME or layer.name.endswith(" (clamp to 1)")):
            continue
        blend = layer.blend.value if hasattr(layer.blend, "value") else str(layer.blend)
        baked = layer.kind == "pixels" and (blend in BAKED or (psd and blend == "linear-dodge"))
        row = (
            layer.id if ids == "leaves" and layer.kind != "group" else "",
            layer.kind,
            layer.name,
            "linear-dodge" if psd and blend == "plus" else blend,
            None if baked else round(layer.opacity * 255),
            layer.visible,
        )
        if layer.kind == "group":
            row += (layer.isolated, tuple(tree(layer.layers, ids=ids, helpers=helpers, psd=psd)))
        out.append(row)
    return out


SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(stack=documents())
def test_stack_folder_reads_back_the_same_tree(tmp_path_factory, stack):
    from lasagna.cli import main

    folder = tmp_path_factory.mktemp("s")
    save_stack(stack, folder)
    assert main(["validate", str(folder)]) == 0
    assert load_stack(folder).document == stack.document


@SETTINGS
@given(stack=documents())
def test_ora_reads_back_the_same_tree(tmp_path_factory, stack):
    path = tmp_path_factory.mktemp("o") / "x.ora"
    path.write_bytes(encode_ora(stack, warn=lambda m: None))
    back = import_ora(path, warn=lambda m: pytest.fail(m))
    assert tree(back.document.layers) == tree(stack.document.layers)


@SETTINGS
@given(stack=documents())
def test_psd_reads_back_the_same_tree(tmp_path_factory, stack):
    pytest.importorskip("psd_tools")
    from lasagna.export.psd import encode_psd
    from lasagna.export.psd_import import read_psd

    path = tmp_path_factory.mktemp("p") / "x.psd"
    path.write_bytes(encode_psd(stack, warn=lambda m: None))
    back = read_psd(path, warn=lambda m: None).document.layers
    # The PSD holds the canvas background as an opaque bottom layer, which import keeps as a layer.
    assert back[0].name == "Background" and back[0].kind == "pixels"
    assert tree(back[1:], ids="none", psd=True) == tree(stack.document.layers, ids="none", psd=True)


def test_an_ora_group_named_as_a_leaf_does_not_take_its_id(tmp_path):
    """A group's id is made from its name on import, a leaf's comes from its file (named by its id): a group named
    ``l1`` (or ``¬?l1``, which sanitises to it) above the leaf ``l1`` must not push the leaf to ``l1-2`` (found by the
    property test above)."""
    import torch

    doc = Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": 2, "height": 2},
            "layers": [
                {"id": "base", "kind": "pixels", "source": "layers/base.png"},
                {
                    "id": "g",
                    "kind": "group",
                    "name": "¬?l1",
                    "layers": [{"id": "l1", "kind": "pixels", "source": "layers/l1.png", "blend": "multiply"}],
                },
            ],
        }
    )
    tensors = {k: LayerTensors(torch.rand(3, 2, 2), None, None) for k in ("base", "l1")}
    stack = Stack(doc, None, tensors, {k: 8 for k in tensors})
    path = tmp_path / "x.ora"
    path.write_bytes(encode_ora(stack, warn=lambda m: None))
    back = import_ora(path, warn=lambda m: pytest.fail(m))
    assert [leaf.id for _, leaf in back.document.walk() if leaf.kind != "group"] == ["base", "l1"]
    assert tree(back.document.layers) == tree(stack.document.layers)
