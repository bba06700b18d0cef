"""A stack folder surveyed without decoding a pixel and without torch: the document read and validated,
every path it names resolved inside the folder, every PNG header read, the size limits and the memory
budget (``lasagna.limits``) checked. ``load_stack`` decodes only what a survey passed, and the CLI runs
a survey before it imports the tiers that need torch, so a hostile stack is refused in a fraction of a
second. ``verify_stack`` adds a full structural check of every PNG (``lasagna validate``).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lasagna.document import (
    AdjustmentLayer,
    Document,
    GradientLayer,
    GroupLayer,
    LearnedLayer,
    PatternLayer,
    PixelsLayer,
    SurfaceLayer,
    load_document,
    stack_file,
)
from lasagna.document.pattern import tile_problem
from lasagna.errors import ImageError, PathError
from lasagna.io.png import DEFAULT_MAX_PIXELS, check_size, decode_bytes, read_png_header, verify_png
from lasagna.limits import check_memory

# The document's largest canvas side; a layer PNG may not be larger either.
MAX_SIDE = 32768

# Decoded pixels summed over all layers and masks of one stack, checked from the PNG headers
# before any is decoded: 4 layers at the per-image limit (16 GiB of float32 RGBA) is the ceiling.
DEFAULT_MAX_TOTAL_PIXELS = 4 * DEFAULT_MAX_PIXELS

# ---- safe paths -------------------------------------------------------------------------------------


def resolve_inside(folder: Path, relative: str, where: str) -> Path:
    """``folder/relative`` resolved (symlinks followed); ``PathError`` if it leaves ``folder``."""
    root = folder.resolve()
    target = (folder / relative).resolve()
    if target != root and root not in target.parents:
        raise PathError(
            f"{relative!r} resolves to {target}, outside the stack folder {root}; "
            "expected a path inside the stack folder (symlinks included)",
            where=where,
        )
    return target


def entry_inside(folder: Path, relative: str, where: str) -> Path:
    """The directory entry ``folder/relative`` itself, its last component *not* followed: the file a stack
    owns and may replace or remove. A symlink there is the stack's entry (replacing or unlinking it leaves
    its target alone); the folders above it are resolved and must lie inside ``folder`` (``resolve_inside``)."""
    rel = Path(relative)
    if rel.name in ("", ".", ".."):
        raise PathError(f"{relative!r} names no file; expected a file path inside the stack folder", where=where)
    return resolve_inside(folder, rel.parent.as_posix(), where) / rel.name


def _rasters(doc: Document) -> Iterable[tuple[str, Any, str, str]]:
    """(JSON path, layer, field, relative path) for every PNG the document names, groups' layers and masks
    included (``layers[2].layers[0]``, depth first)."""
    for loc, layer in doc.walk():
        if isinstance(layer, (PixelsLayer, LearnedLayer, SurfaceLayer, PatternLayer)) and layer.source is not None:
            yield loc, layer, "source", layer.source
            if layer.mask is not None:
                yield loc, layer, "mask", layer.mask
        elif isinstance(layer, (GroupLayer, AdjustmentLayer, GradientLayer)) and layer.mask is not None:
            yield loc, layer, "mask", layer.mask


@dataclass(frozen=True)
class _Raster:
    """One PNG a document names, resolved and with its header read (nothing decoded yet)."""

    loc: str  # the layer's JSON path, e.g. layers[2].layers[0]
    layer: Any
    field: str  # "source" or "mask"
    rel: str
    target: Path
    header: Any  # lasagna.io.png.PngHeader

    @property
    def where(self) -> str:
        return f"{self.loc}.{self.field} ({self.rel})"


def _plan_rasters(
    file: Path, doc: Document, max_pixels: int, max_total_pixels: int, unrendered: bool = False
) -> list[_Raster]:
    """Resolve every path a document names and read every PNG header (cheap) before decoding anything:
    sizes per image and in total, masks the size of their source (a group's mask may have any size).
    ``unrendered``: a learned layer's missing source is skipped (``survey_stack``)."""
    folder = file.parent
    planned: list[_Raster] = []
    sources: dict[str, Any] = {}
    total = 0
    for loc, layer, fieldname, rel in _rasters(doc):
        where = f"{file}: {loc}.{fieldname}"
        target = resolve_inside(folder, rel, where)
        if unrendered and isinstance(layer, LearnedLayer) and fieldname == "source" and not target.exists():
            continue
        if not target.is_file():
            what = "is not a file" if target.exists() else "does not exist"
            raise ImageError(f"{rel!r} {what} (looked for {target}); expected a PNG file", where=where)
        try:
            header = read_png_header(target)
            check_size(header, str(target), max_pixels, MAX_SIDE)
        except ImageError as err:
            raise err.at(f"{where} ({rel})") from None
        total += header.pixels
        if total > max_total_pixels:
            raise ImageError(
                f"the stack's PNGs hold more than {max_total_pixels} pixels in total; expected at most that many",
                where=where,
            )
        if isinstance(layer, GradientLayer):  # no source: its mask is the size of its rectangle
            size = layer.size or doc.canvas
            if (header.width, header.height) != (size.width, size.height):
                raise ImageError(
                    f"mask is {header.width}x{header.height}; expected the gradient layer's size "
                    f"{size.width}x{size.height}",
                    where=f"{where} ({rel})",
                )
        if isinstance(layer, PatternLayer):  # a tile (RGB or RGBA, bounded as resampled) and its rectangle's mask
            _check_pattern(layer, doc, fieldname, header, f"{where} ({rel})")
            planned.append(_Raster(loc, layer, fieldname, rel, target, header))
            continue
        if fieldname == "source":
            sources[loc] = header
        elif loc in sources:
            src = sources[loc]
            if (header.width, header.height) != (src.width, src.height):
                raise ImageError(
                    f"mask is {header.width}x{header.height}; expected the size of its layer's source, "
                    f"{src.width}x{src.height}",
                    where=f"{where} ({rel})",
                )
        planned.append(_Raster(loc, layer, fieldname, rel, target, header))
    return planned


def _check_pattern(layer: PatternLayer, doc: Document, fieldname: str, header: Any, where: str) -> None:
    """A pattern layer's PNGs, from their headers: the tile RGB or RGBA and within ``tile_problem``'s bound at the
    layer's scale; the mask the size of the layer's rectangle."""
    if fieldname == "source":
        if header.kind not in ("rgb", "rgba"):
            raise ImageError(f"tile is a {header.kind} PNG; expected an RGB or RGBA PNG", where=where)
        problem = tile_problem(header.height, header.width, layer.pattern.scale)
        if problem is not None:
            raise ImageError(problem, where=where)
        return
    size = layer.size or doc.canvas
    if (header.width, header.height) != (size.width, size.height):
        raise ImageError(
            f"mask is {header.width}x{header.height}; expected the pattern layer's size {size.width}x{size.height}",
            where=where,
        )


def load_bytes(rasters: Iterable[Any], copies: int = 0) -> int:
    """Peak bytes of decoding PNGs with these headers and keeping them all (float32 tensors): what they
    keep (and ``copies`` more of it, what the caller makes of them, e.g. an exporter's), plus the largest
    one's transient buffers and range mapping (``lasagna.io.png.decode_bytes``)."""
    kept, transient = 0, 0
    for header in rasters:
        k, t = decode_bytes(header)
        kept += k
        transient = max(transient, t + k)  # + k: range mapping makes one new colour tensor
    return kept * (1 + copies) + transient


def verify_stack(
    path: str | os.PathLike, *, max_pixels: int = DEFAULT_MAX_PIXELS, max_total_pixels: int = DEFAULT_MAX_TOTAL_PIXELS
) -> Document:
    """Check a stack folder completely without decoding a pixel: the document, every path, and every PNG
    (``lasagna.io.png.verify_png``: structure, CRCs, the image data's size and filters). Memory: one file at
    a time; time: inflating each PNG once. What ``lasagna validate`` runs."""
    file = stack_file(path)
    doc = load_document(path)
    for r in _plan_rasters(file, doc, max_pixels, max_total_pixels):
        try:
            verify_png(r.target, max_pixels=max_pixels, max_side=MAX_SIDE)
        except ImageError as err:
            raise err.at(f"{file}: {r.where}") from None
    return doc


# Bytes a canvas pixel costs a render: the RGB output in float32; the no-grad engine works in bands and solid
# layers are zero-stride views, so nothing else of canvas size is allocated (``lasagna.io.render``).
RENDER_CHANNELS = 3
# ... and writing it as composite.png: one band of codes and the compressed bytes (at most ~3 a pixel).
ENCODE_BYTES_PER_PIXEL = 3


def composite_bytes(width: int, height: int) -> int:
    """Bytes of rendering a canvas in float32 and writing it as composite.png (``write_composite``)."""
    return width * height * (RENDER_CHANNELS * 4 + ENCODE_BYTES_PER_PIXEL)


@dataclass(frozen=True)
class Survey:
    """What ``survey_stack`` found: the stack file, its validated document and its rasters (headers read)."""

    file: Path
    document: Document
    rasters: list[_Raster]
    max_pixels: int  # the per-image limit the headers were checked against; decoding keeps it


def survey_stack(
    path: str | os.PathLike,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    max_total_pixels: int = DEFAULT_MAX_TOTAL_PIXELS,
    composite: bool = False,
    copies: int = 0,
    unrendered: bool = False,
) -> Survey:
    """Survey a stack folder (or its stack.json) and check that decoding it fits the memory budget, with
    room for rendering and writing its canvas (``composite``, ``composite_bytes``) and for ``copies`` more
    of the decoded layers (what an exporter makes of them). ``lasagna.io.stack.load_surveyed`` decodes it.
    ``unrendered``: a learned layer whose PNG is missing is not rendered yet (left without pixels, for
    ``lasagna render`` to make) rather than refused."""
    file = stack_file(path)
    doc = load_document(path)
    planned = _plan_rasters(file, doc, max_pixels, max_total_pixels, unrendered)
    parts = [f"decoding the stack's {len(planned)} PNGs"] if planned else []
    parts += [f"rendering its {doc.canvas.width}x{doc.canvas.height} canvas"] if composite else []
    what = " and ".join(parts) or "loading the stack"
    extra = composite_bytes(doc.canvas.width, doc.canvas.height) if composite else 0
    check_memory(load_bytes((r.header for r in planned), copies) + extra, what, str(file))
    return Survey(file, doc, planned, max_pixels)
