"""OpenRaster (.ora) import: the inverse of ``lasagna.export.ora``'s export, nested stacks included.

It refuses what it cannot read safely: entry names that are
absolute or contain ``..`` (zip-slip), archives whose declared or actual uncompressed size exceeds
a limit, PNGs over the pixel limit (checked from the header before decoding), DTDs/entities in
stack.xml, groups nested deeper than a stack may hold (``lasagna.limits.MAX_GROUP_DEPTH``; a crafted file
cannot exhaust the recursion of the reader, the compositor or the document's validation) and unknown
composite-ops. A name with characters a document name may not hold (controls: XML 1.0 carries tab, newline
and C1 controls) is imported with each replaced by U+FFFD, one warning line each.
"""

from __future__ import annotations

import math
import os
import re
import zipfile
import zlib
from collections.abc import Callable
from pathlib import PurePosixPath
from xml.etree import ElementTree as ET

import numpy as np

from lasagna.document.types import sanitise_name, unique_id
from lasagna.errors import ImageError
from lasagna.export.ora import DODGE_PREFIX, MIMETYPE, SVG_TO_BLEND
from lasagna.export.rasters import NORMALS_DIR
from lasagna.io.png import (
    DEFAULT_MAX_PIXELS,
    check_size,
    decode_png,
    parse_header,
    png_file_limit,
)
from lasagna.io.survey import load_bytes
from lasagna.limits import MAX_GROUP_DEPTH, check_memory

# An archive whose entries inflate to more than this is refused (zip bombs); 4 GiB holds 2^28
# RGBA pixels, the per-image limit, with room to spare.
DEFAULT_MAX_UNCOMPRESSED = 4 * 2**30


_SAFE_ENTRY = re.compile(r"^[^\\\x00-\x1f]+$")


def _check_entry_name(name: str, where: str) -> None:
    p = PurePosixPath(name)
    if not _SAFE_ENTRY.match(name) or name.startswith("/") or re.match(r"^[A-Za-z]:", name) or ".." in p.parts:
        raise ImageError(
            f"archive entry {name!r} is absolute or escapes the archive (zip-slip); expected relative names without "
            "'..'",
            where=where,
        )


def _float_attr(el, name: str, default: float, where: str) -> float:
    raw = el.get(name)
    if raw is None:
        return default
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ImageError(f"{name}={raw!r}; expected a finite number", where=where)
    return value


def _int_attr(el, name: str, where: str) -> int:
    raw = el.get(name, "0")
    try:
        return int(raw)
    except ValueError:
        try:
            f = float(raw)
        except ValueError:
            f = math.nan
        if not math.isfinite(f) or f != int(f):
            raise ImageError(f"{name}={raw!r}; expected an integer", where=where) from None
        return int(f)


def _utf8_xml(data: bytes, where: str) -> str:
    """stack.xml as text: UTF-8 only (any declared encoding must say so). Other encodings are refused, not
    decoded, so the DTD/entity check below sees the text the parser will see (UTF-16 hid it before)."""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ImageError(f"not UTF-8 (byte {exc.start}); expected OpenRaster XML in UTF-8", where=where) from None
    declared = re.match(r"""\s*<\?xml[^>]*encoding\s*=\s*["']([^"']+)["']""", text)
    if declared and declared.group(1).strip().lower().replace("_", "-") not in ("utf-8", "utf8"):
        raise ImageError(f"declares encoding {declared.group(1)!r}; expected OpenRaster XML in UTF-8", where=where)
    return text


def read_ora(
    path: str | os.PathLike,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    max_uncompressed: int = DEFAULT_MAX_UNCOMPRESSED,
    copies: int = 1,
) -> tuple[int, int, list[dict]]:
    """Read and check an OpenRaster file: canvas size and its layers bottom to top (decoded).

    Every layer's PNG header is read first; the decoded layers (plus ``copies`` more of them, what
    the caller makes of them: ``import_ora`` one) must fit the memory budget (``lasagna.limits``) before
    any is decoded, and each entry is read only up to what a PNG of its header can hold.

    Each layer is a dict with ``name``, ``src``, ``x``, ``y``, ``opacity``, ``visible``,
    ``blend`` (ours) and ``image`` (a decoded :class:`PngImage`); each nested ``<stack>`` a dict with
    ``kind="group"``, ``name``, ``opacity``, ``visible``, ``blend``, ``isolation`` ("isolate" | "auto") and its
    ``layers`` (bottom to top; their ``x``, ``y`` on the canvas, the stacks' offsets added).
    """
    where = str(path)
    try:
        zf = zipfile.ZipFile(path)
    except FileNotFoundError:
        raise ImageError("does not exist; expected an OpenRaster (.ora) file", where=where) from None
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ImageError(f"not a zip archive ({exc}); expected an OpenRaster (.ora) file", where=where) from None
    with zf:
        infos = zf.infolist()
        for info in infos:
            _check_entry_name(info.filename, where)
        declared = sum(i.file_size for i in infos)
        if declared > max_uncompressed:
            raise ImageError(
                f"entries inflate to {declared} bytes, over the limit of {max_uncompressed}; "
                "expected a smaller archive (zip-bomb guard)",
                where=where,
            )
        names = {i.filename: i for i in infos}
        budget = [max_uncompressed]

        def read(name: str, limit: int | None = None) -> bytes:
            info = names.get(name)
            if info is None:
                raise ImageError(f"archive has no entry {name!r}; expected it (named by stack.xml)", where=where)
            cap = min(budget[0], limit if limit is not None else budget[0])
            try:
                with zf.open(info) as fh:
                    data = fh.read(cap + 1)
            except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as exc:
                raise ImageError(
                    f"entry {name!r} is corrupt ({exc}); expected a valid zip entry", where=where
                ) from None
            if len(data) > cap:
                raise ImageError(
                    f"entry {name!r} inflates past {cap} bytes (zip-bomb guard); expected a smaller entry", where=where
                )
            budget[0] -= len(data)
            return data

        if "mimetype" not in names or read("mimetype", 64).strip() != MIMETYPE:
            raise ImageError("no 'mimetype' entry reading 'image/openraster'; expected an OpenRaster file", where=where)
        xml_bytes = read("stack.xml", 16 * 2**20)
        xml_text = _utf8_xml(xml_bytes, f"{where}: stack.xml")
        if "<!DOCTYPE" in xml_text or "<!ENTITY" in xml_text:
            raise ImageError(
                "stack.xml declares a DTD or entities; expected plain OpenRaster XML", where=f"{where}: stack.xml"
            )
        try:
            root = ET.fromstring(xml_text)
        except ET.ParseError as exc:
            raise ImageError(
                f"stack.xml is not well-formed XML ({exc}); expected OpenRaster XML", where=f"{where}: stack.xml"
            ) from None
        xwhere = f"{where}: stack.xml"
        if root.tag != "image":
            raise ImageError(f"root element is <{root.tag}>; expected <image>", where=xwhere)
        width, height = _int_attr(root, "w", xwhere), _int_attr(root, "h", xwhere)
        if not (1 <= width <= 32768 and 1 <= height <= 32768):
            raise ImageError(f"canvas is {width}x{height}; expected w and h in [1, 32768]", where=xwhere)
        stacks = [c for c in root if c.tag == "stack"]
        if len(stacks) != 1:
            raise ImageError(f"<image> holds {len(stacks)} <stack> elements; expected exactly one", where=xwhere)
        planned: list[dict] = []
        users: dict[str, int] = {}

        def items(stack_el, swhere: str, depth: int) -> list[dict]:
            """The layers and groups of a <stack>, bottom to top; every layer is appended to ``planned``."""
            if depth > MAX_GROUP_DEPTH:
                raise ImageError(
                    f"groups nest deeper than {MAX_GROUP_DEPTH}; expected at most {MAX_GROUP_DEPTH} nested <stack> "
                    "levels (a stack's limit)",
                    where=swhere,
                )
            out = []
            for n, el in enumerate(stack_el):
                lwhere = f"{swhere}[{n}]"
                if el.tag == "stack":
                    out.append(group(el, lwhere, depth + 1))
                    continue
                if el.tag != "layer":
                    raise ImageError(f"<{el.tag}> element is not supported; expected <layer> or <stack>", where=lwhere)
                out.append(leaf(el, lwhere, len(planned)))
            out.reverse()  # stack.xml is topmost first; documents are bottom first
            return out

        def common(el, lwhere: str) -> dict:
            op = el.get("composite-op", "svg:src-over")
            clip = op == "svg:src-atop"  # Krita's inherit alpha: read as a clipping mask (krita_clip_stacks)
            op = "svg:src-over" if clip else op
            if op not in SVG_TO_BLEND:
                raise ImageError(
                    f"composite-op {op!r} is not supported; expected one of {', '.join(SVG_TO_BLEND)}",
                    where=lwhere,
                )
            opacity = _float_attr(el, "opacity", 1.0, lwhere)
            if not 0.0 <= opacity <= 1.0:
                raise ImageError(f"opacity={opacity}; expected a number in [0, 1]", where=lwhere)
            visibility = el.get("visibility", "visible")
            if visibility not in ("visible", "hidden"):
                raise ImageError(f"visibility={visibility!r}; expected 'visible' or 'hidden'", where=lwhere)
            return dict(
                x=_int_attr(el, "x", lwhere),
                y=_int_attr(el, "y", lwhere),
                opacity=opacity,
                visible=visibility == "visible",
                blend=SVG_TO_BLEND[op],
                clip=clip,
                where=lwhere,
            )

        def group(el, lwhere: str, depth: int) -> dict:
            g = common(el, lwhere)
            isolation = el.get("isolation", "auto")
            if isolation not in ("isolate", "auto"):
                raise ImageError(f"isolation={isolation!r}; expected 'isolate' or 'auto'", where=lwhere)
            # Layers inside carry canvas offsets, as Krita writes them; a stack's own x, y move its layers.
            g.update(kind="group", name=el.get("name") or "", isolation=isolation)
            g["layers"] = items(el, f"{lwhere}: stack", depth)
            if g["x"] or g["y"]:
                for lay in _walk_leaves(g["layers"]):
                    lay["x"] += g["x"]
                    lay["y"] += g["y"]
            return g

        def leaf(el, lwhere: str, n: int) -> dict:
            src = el.get("src")
            if not src:
                raise ImageError("layer has no src; expected src naming a PNG in the archive", where=lwhere)
            _check_entry_name(src, lwhere)
            c = common(el, lwhere)
            # Check the PNG's header before inflating the rest of it.
            entry = names.get(src)
            if entry is None:
                raise ImageError(f"src {src!r} is not in the archive; expected a PNG entry", where=lwhere)
            if src in users:
                # Writers give every layer its own PNG; one entry named by many layers is a way to make a
                # tiny file decode to many full-size layers (counted, it would still cost their memory).
                raise ImageError(
                    f"src {src!r} is also the src of stack[{users[src]}]; expected each layer its own PNG entry",
                    where=lwhere,
                )
            users[src] = n
            pwhere = f"{where}: {src}"
            try:
                with zf.open(entry) as fh:
                    head = fh.read(33)
            except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as exc:
                raise ImageError(f"entry {src!r} is corrupt ({exc}); expected a valid zip entry", where=where) from None
            header = parse_header(head, pwhere)
            check_size(header, pwhere, max_pixels, 32768)
            layer = dict(name=el.get("name") or PurePosixPath(src).stem, src=src, header=header, **c)
            planned.append(layer)
            return layer

        tree = items(stacks[0], f"{xwhere}: stack", 0)
        # Every layer's header is known: refuse over the memory budget before decoding any of them.
        needed = load_bytes((layer["header"] for layer in planned), copies)
        check_memory(needed, f"decoding the {len(planned)} layers", where)
        for layer in planned:
            pwhere = f"{where}: {layer['src']}"
            data = read(layer["src"], png_file_limit(layer.pop("header")))
            layer["image"] = decode_png(data, pwhere, max_pixels=max_pixels, max_side=32768)
    return width, height, tree


def _walk_leaves(items: list[dict]):
    for item in items:
        if item.get("kind") == "group":
            yield from _walk_leaves(item["layers"])
        else:
            yield item


def _same_geometry(a: dict, b: dict) -> bool:
    ia, ib = a["image"], b["image"]
    return (a["x"], a["y"], a["opacity"], a["visible"], ia.width, ia.height) == (
        b["x"],
        b["y"],
        b["opacity"],
        b["visible"],
        ib.width,
        ib.height,
    ) and (
        (ia.alpha is None and ib.alpha is None)
        or (ia.alpha is not None and ib.alpha is not None and np.array_equal(ia.alpha, ib.alpha))
    )


def import_ora(
    path: str | os.PathLike,
    out_folder: str | os.PathLike | None = None,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    max_uncompressed: int = DEFAULT_MAX_UNCOMPRESSED,
    warn: Callable[[str], None] | None = None,
    surfaces: bool = True,
):
    """Read an OpenRaster file as a :class:`~lasagna.io.stack.Stack` (saved to ``out_folder`` if given).

    Ids come from the layers' PNG names. Every ``svg:*`` composite-op of :data:`SVG_TO_BLEND` is
    read as that blend. The colour-dodge half of a multiplier above 1 (what :func:`export_ora`
    writes: src ``data/_dodge/…``, directly above an ``svg:multiply`` layer of the same geometry,
    opacity and alpha) is merged back into one multiply layer y = m/(1 − d) with range [0, ⌈max y⌉];
    any other ``svg:color-dodge`` layer is a colour-dodge layer. The background layer
    :func:`export_ora` adds becomes the canvas background, and its "Composite (exact)" top layer, if
    any, is dropped (the stack is re-composed from its layers). Without that background the document is
    transparent (``canvas.background`` null: the composite carries alpha, as the file's does) unless its bottom
    visible layer is an opaque, full-canvas ``svg:src-over`` one (nothing shows through it). ``warn`` receives one
    line per name changed to fit the document's name rule (default: ``warnings.warn``). A surface layer's rendered
    multiplier over its hidden normal map is made one surface layer again (``lasagna.export.surface_import``) unless
    ``surfaces`` is false.
    """
    import warnings

    warn = warn or (lambda message: warnings.warn(message, stacklevel=2))
    width, height, layers = read_ora(path, max_pixels=max_pixels, max_uncompressed=max_uncompressed)
    background: tuple[float, ...] | None = None
    if layers and layers[-1].get("src") == "data/_composite.png":
        layers = layers[:-1]  # the exact composite export_ora adds when layers cannot express the stack
    if layers and layers[0].get("src") == "data/_background.png":
        bg = layers[0]["image"]
        c = bg.color if bg.color.shape[0] == 3 else np.repeat(bg.color, 3, axis=0)
        opaque = bg.alpha is None or bool((bg.alpha == 1.0).all())
        if (
            opaque
            and (bg.width, bg.height) == (width, height)
            and layers[0]["x"] == layers[0]["y"] == 0
            and layers[0]["opacity"] == 1.0
            and layers[0]["visible"]
            and (c == c[:, :1, :1]).all()
        ):
            background = tuple(float(v) for v in c[:, 0, 0])
            layers = layers[1:]
    if background is None and _opaque_base(layers, width, height):
        background = (0.0, 0.0, 0.0)  # covered by its base: an opaque document, whatever the colour
    merged = _merge_dodges(layers)
    if not any(True for _ in _walk_leaves(merged)):
        raise ImageError("the file has no layers besides the background; expected at least one layer", where=str(path))
    import torch  # only now: a refused file never loads it

    from lasagna.io.stack import stack_from_tensors

    taken: set[str] = set()
    specs: list[dict] = []
    # Leaves first: their ids come from their files (our writer names each file by its layer's id), so a group
    # whose name happens to sanitise to a leaf's id must yield — a group's id is made up on import, a leaf's is kept.
    # A surface layer's hidden normal map (src data/_normals/<id>.png) is named last, so its layer keeps the id.
    leaves = sorted(_walk_leaves(merged), key=lambda leaf: leaf["src"].startswith(f"data/{NORMALS_DIR}/"))
    leaf_ids = {id(leaf): unique_id(PurePosixPath(leaf["src"]).stem or leaf["name"], taken) for leaf in leaves}

    def name_of(layer: dict) -> str:
        name = sanitise_name(layer["name"])
        if name != layer["name"]:
            warn(f"{layer['where']}: name {layer['name']!r} holds control characters; imported as {name!r}")
        return name

    clipped: set[str] = set()  # ids of the layers read with clip (Krita's svg:src-atop)

    def clip_of(layer: dict, n: int, items: list[dict]) -> bool:
        if not layer["clip"]:
            return False
        if n == 0:
            warn(
                f"{layer['where']}: svg:src-atop (inherit alpha) at the bottom of its stack clips to nothing; read "
                "as src-over"
            )
            return False
        if any(not below["clip"] for below in items[1:n]):
            warn(
                f"{layer['where']}: svg:src-atop inherits the alpha of several layers below; read as a clipping mask "
                "on the nearest one"
            )
        return True

    def tree(items: list[dict]) -> list:
        """The document's layer tree: a leaf's id (its fields come from ``stack_from_tensors``), or a group."""
        out: list = []
        for n, layer in enumerate(items):
            clip = clip_of(layer, n, items)
            if layer.get("kind") == "group":
                name = name_of(layer)
                gid = unique_id(name or "group", taken)
                # An "isolate" stack is an isolated group; an "auto" one passes through unless it has a blend of
                # its own (the OpenRaster spec then renders it isolated). Our pass-through opacity is Krita's.
                isolated = layer["isolation"] == "isolate" or layer["blend"] != "normal"
                out.append(
                    {
                        "id": gid,
                        "kind": "group",
                        "name": name or gid,
                        "isolated": isolated,
                        "blend": layer["blend"] if isolated else "normal",
                        "opacity": layer["opacity"],
                        "visible": layer["visible"],
                        "clip": clip,
                        "layers": tree(layer["layers"]),
                    }
                )
                continue
            img = layer["image"]
            values = layer.get("values", img.color)
            hi = max(1.0, float(np.ceil(values.max()))) if layer.get("dodged") else 1.0
            lid = leaf_ids[id(layer)]
            specs.append(
                dict(
                    id=lid,
                    image=torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32)),
                    alpha=torch.from_numpy(img.alpha) if img.alpha is not None else None,
                    name=name_of(layer) or lid,
                    blend=layer["blend"],
                    opacity=layer["opacity"],
                    visible=layer["visible"],
                    offset=(layer["x"], layer["y"]),
                    range=(0.0, hi),
                    bit_depth=16 if layer.get("dodged") or img.header.bit_depth == 16 else 8,
                )
            )
            out.append(lid)
            if clip:
                clipped.add(lid)
        return out

    shape = tree(merged)
    stack = stack_from_tensors(specs, width=width, height=height, background=background)
    if clipped or any(isinstance(item, dict) for item in shape):
        fields = {layer.id: layer.model_dump(mode="json", exclude_none=True) for layer in stack.document.layers}

        def nest(items: list) -> list:
            return [
                {**fields[item], "clip": item in clipped}
                if isinstance(item, str)
                else {**item, "layers": nest(item["layers"])}
                for item in items
            ]

        stack.document = stack.document.with_layers(nest(shape))
    from lasagna.export.surface_import import restore_surfaces

    if surfaces:
        restore_surfaces(stack, warn, str(path))
    if out_folder is not None:
        stack.save(out_folder)
    return stack


def _opaque_base(layers: list[dict], width: int, height: int) -> bool:
    """Whether the bottom visible layer covers the canvas opaquely with blend normal (no group, no clip)."""
    for layer in layers:
        if not layer["visible"]:
            continue
        img = layer.get("image")
        return (
            layer.get("kind") != "group"
            and img is not None
            and layer["blend"] == "normal"
            and not layer["clip"]
            and layer["opacity"] == 1.0
            and layer["x"] == layer["y"] == 0
            and (img.width, img.height) == (width, height)
            and (img.alpha is None or bool((img.alpha == 1.0).all()))
        )
    return False


def _merge_dodges(layers: list[dict]) -> list[dict]:
    """``layers`` (and every group's, recursively) with the multiply + colour-dodge pairs ``export_ora`` writes
    for multipliers above 1 merged back into the multiply layer (``values`` y = m/(1 − d), ``dodged``)."""
    merged: list[dict] = []
    for layer in layers:
        if layer.get("kind") == "group":
            merged.append({**layer, "layers": _merge_dodges(layer["layers"])})
            continue
        if layer["blend"] == "color-dodge" and layer["src"].startswith(DODGE_PREFIX):
            below = merged[-1] if merged else None
            if (
                below is None
                or below.get("kind") == "group"
                or below["blend"] != "multiply"
                or below.get("dodged")
                or not _same_geometry(below, layer)
            ):
                raise ImageError(
                    f"colour-dodge helper {layer['src']!r} is not directly above an svg:multiply layer of the "
                    "same position, size, opacity and alpha; expected the pair export_ora writes for a "
                    "multiplier above 1 (rename the PNG to import it as a colour-dodge layer)",
                    where=layer["where"],
                )
            m, d = below["image"].color, layer["image"].color
            below["values"] = m / np.maximum(1.0 - d, 1.0 / 255.0)
            below["dodged"] = True
            continue
        merged.append(dict(layer))
    return merged
