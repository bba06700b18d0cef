"""Stack folders: a validated document, the folder it lives in, and its layers' tensors.

``load_stack`` reads ``stack.json`` (through the document tier), resolves every ``source`` and
``mask`` inside the stack folder (symlinks included), refuses oversized PNGs from their headers
before decoding any, and maps stored values to each layer's range, y = lo + (hi − lo)·v (alpha and
masks are never mapped). ``save_stack`` is the inverse: v = (y − lo)/(hi − lo), 16-bit for ranged
and learned layers; a value outside the range is an error unless the caller asks to clip.

Layer images given to the API (``Stack.add_layer``) follow one rule: *tensors and float arrays
are values y* (a shading tensor in [0, 2] is given as is), channels first (C, h, w) or (h, w);
*PIL images and integer arrays are stored codes v*, exactly as a PNG in the folder would be.
C = 1 gray, 2 gray+alpha, 3 RGB, 4 RGBA.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from lasagna.atomic import atomic_write_all
from lasagna.compose.layer import LayerTensors
from lasagna.compose.pattern import TileTensors
from lasagna.compose.surface import encode_normal_map
from lasagna.document import (
    AdjustmentLayer,
    Document,
    GradientLayer,
    GroupLayer,
    LearnedLayer,
    PatternLayer,
    PixelsLayer,
    SolidLayer,
    SurfaceLayer,
    stack_file,
)
from lasagna.document.condition import AMBIENT
from lasagna.document.pattern import tile_problem
from lasagna.errors import DocumentError, ImageError, PathError
from lasagna.io.png import (
    DEFAULT_MAX_PIXELS,
    PngImage,
    encode_bands,
    quantize_band,
    read_png,
)
from lasagna.io.render import render_stack
from lasagna.io.survey import (  # noqa: F401  (MAX_SIDE, DEFAULT_MAX_TOTAL_PIXELS, resolve_inside: their old home)
    DEFAULT_MAX_TOTAL_PIXELS,
    MAX_SIDE,
    Survey,
    entry_inside,
    resolve_inside,
    survey_stack,
    verify_stack,
)
from lasagna.numerics import RANGE_SAVE_TOLERANCE

NOT_RENDERED = "not rendered (run `lasagna render`)"


# ---- the stack ------------------------------------------------------------------------------------


@dataclass
class Stack:
    """A document, the folder it was loaded from (or None), and the tensors of its raster layers.

    ``tensors[id]`` is a ``LayerTensors(color, alpha, mask)`` of values y (range-mapped) for every
    pixels layer and every learned layer that has a ``source``; solid and gradient layers need none (the
    compositor draws them from the document); a group, adjustment or gradient with a mask has ``LayerTensors``
    whose ``mask`` is it (``group_mask_tensors``); a pattern layer has ``TileTensors``: its tile's colour and alpha,
    and the mask of its rectangle. ``bit_depths[id]`` is the depth a layer was read at,
    so saving never loses precision it had.
    """

    document: Document
    folder: Path | None = None
    tensors: dict[str, Any] = field(default_factory=dict)
    bit_depths: dict[str, int] = field(default_factory=dict)

    # ---- reading ----------------------------------------------------------------------------------

    @property
    def ids(self) -> tuple[str, ...]:
        return self.document.ids

    @property
    def width(self) -> int:
        return self.document.canvas.width

    @property
    def height(self) -> int:
        return self.document.canvas.height

    @property
    def not_rendered(self) -> dict[str, str]:
        """Learned layers without pixels yet: id → reason (composite skips them)."""
        return {
            layer.id: NOT_RENDERED
            for layer in self.document.layers
            if layer.id not in self.tensors and isinstance(layer, LearnedLayer)
        }

    def layer(self, id: str):
        return self.document.layer(id)

    def __repr__(self) -> str:
        layers = ", ".join(f"{layer.id}:{layer.kind}/{layer.blend}" for layer in self.document.layers)
        return f"Stack({self.width}x{self.height}, {self.document.blend_space}, [{layers}], folder={self.folder})"

    # ---- building ---------------------------------------------------------------------------------

    @classmethod
    def from_image(
        cls,
        image,
        *,
        id: str = "base",
        alpha=None,
        mask=None,
        bit_depth: int | None = None,
        background: Sequence[float] | None | Literal["auto"] = "auto",
        blend_space: str = "srgb",
        clamp: str = "layer",
        metadata: Mapping[str, Any] | None = None,
        **fields: Any,
    ) -> Stack:
        """A stack whose canvas is ``image``'s size, with ``image`` as its bottom pixels layer ``id``.

        ``fields`` are the layer's document fields, as for :meth:`add_layer`. ``background``: RGB, None (a
        transparent document) or ``"auto"``: transparent when the image has alpha (an RGBA or gray + alpha image,
        or ``alpha`` given), so its composite keeps that alpha; else black.
        """
        range_ = tuple(fields.get("range", (0.0, 1.0)))
        color, a = image_to_tensors(image, range_, where=f"layer {id!r}", alpha=alpha)
        h, w = color.shape[-2:]
        if isinstance(background, str):
            if background != "auto":
                raise DocumentError(f"background is {background!r}; expected RGB, None or 'auto'", "Stack.from_image")
            background = None if a is not None else (0.0, 0.0, 0.0)
        doc = Document.from_dict(
            {
                "format": "lasagna.stack",
                "version": 1,
                "canvas": {
                    "width": int(w),
                    "height": int(h),
                    "background": None if background is None else [float(c) for c in background],
                },
                "blend_space": blend_space,
                "clamp": clamp,
                "layers": [_layer_dict(id, "pixels", fields, has_mask=mask is not None)],
                "metadata": dict(metadata or {}),
            },
            where="Stack.from_image",
        )
        tensors = _make_tensors(id, color, a, mask, bit_depth)
        stack = cls(doc)
        stack._store(id, tensors, bit_depth)
        return stack

    def add_layer(
        self,
        id: str,
        image,
        *,
        alpha=None,
        mask=None,
        index: int | None = None,
        bit_depth: int | None = None,
        **fields: Any,
    ) -> Stack:
        """Add (on top, or at ``index``) or replace the pixels layer ``id``; returns ``self``.

        ``fields`` are document fields: ``blend``, ``opacity``, ``visible``, ``offset`` ({x, y} or
        (x, y)), ``range``, ``name``. ``image``: see the module docstring. ``bit_depth`` forces 8 or
        16 on save (default: 16 for a range other than [0, 1], else the depth it was read at, else 8).
        """
        fields = dict(fields)
        range_ = tuple(fields.get("range", (0.0, 1.0)))
        color, a = image_to_tensors(image, range_, where=f"layer {id!r}", alpha=alpha)
        tensors = _make_tensors(id, color, a, mask, bit_depth)
        existing = self.document.layer(id) if id in self.ids else None
        if existing is not None and not isinstance(existing, PixelsLayer):
            raise DocumentError(
                f"layer {id!r} is a {existing.kind} layer; expected set_pixels for it, or a new id", where="add_layer"
            )
        source = existing.source if existing is not None else None
        layer = _layer_dict(id, "pixels", fields, has_mask=mask is not None, source=source)
        self.document = (
            self.document.with_layer(layer) if existing is not None else self.document.with_layer(layer, index)
        )
        self._store(id, tensors, bit_depth)
        return self

    def add_solid(self, id: str, color: Sequence[float], *, index: int | None = None, **fields: Any) -> Stack:
        """Add a solid layer (RGB or RGBA ``color`` in [0, 1]; optional ``size`` {width, height})."""
        layer = _layer_dict(id, "solid", fields, has_mask=False)
        layer["color"] = [float(c) for c in color]
        if "size" in fields and fields["size"] is not None:
            size = fields["size"]
            layer["size"] = size if isinstance(size, Mapping) else {"width": int(size[0]), "height": int(size[1])}
        self.document = self.document.with_layer(layer, index if id not in self.ids else None)
        self.tensors.pop(id, None)
        return self

    def add_gradient(
        self, id: str, gradient: Mapping[str, Any], *, index: int | None = None, mask=None, **fields: Any
    ) -> Stack:
        """Add (on top, or at ``index``) or replace the gradient fill layer ``id``: ``gradient`` is the document's
        ``gradient`` record (style, angle, scale, reverse, align, shift, stops, opacity_stops); optional ``size``
        {width, height} and a ``mask`` of that size (default the canvas)."""
        layer = _layer_dict(id, "gradient", fields, has_mask=mask is not None)
        layer["gradient"] = dict(gradient)
        if fields.get("size") is not None:
            size = fields["size"]
            layer["size"] = size if isinstance(size, Mapping) else {"width": int(size[0]), "height": int(size[1])}
        m = None
        if mask is not None:
            m = mask_to_tensor(mask, where=f"layer {id!r} mask")
            w, h = (layer["size"]["width"], layer["size"]["height"]) if "size" in layer else (self.width, self.height)
            if tuple(m.shape[-2:]) != (h, w):
                got = f"{m.shape[-1]}x{m.shape[-2]}"
                raise ImageError(f"mask is {got}; expected the layer's size {w}x{h}", f"layer {id!r}")
        self.document = self.document.with_layer(layer, index if id not in self.ids else None)
        self.tensors.pop(id, None)
        if m is not None:
            self.tensors[id] = group_mask_tensors(m)
        return self

    def add_pattern(
        self,
        id: str,
        tile,
        pattern: Mapping[str, Any] | None = None,
        *,
        index: int | None = None,
        mask=None,
        bit_depth: int = 8,
        **fields: Any,
    ) -> Stack:
        """Add (on top, or at ``index``) or replace the pattern fill layer ``id``: ``tile`` an RGB or RGBA image (see
        the module docstring), kept as its PNG of ``bit_depth`` bits gives it back (so the stack renders the same
        bits before saving and after loading); ``pattern`` the document's ``pattern`` record (scale, phase, align);
        optional ``size`` {width, height} and a ``mask`` of that size (default the canvas)."""
        where = f"layer {id!r}"
        color, a = image_to_tensors(tile, (0.0, 1.0), where=where)
        if color.shape[0] != 3:
            raise ImageError(f"tile has {color.shape[0]} colour channel(s); expected an RGB or RGBA tile", where)
        if bit_depth not in (8, 16):
            raise ImageError(f"bit_depth {bit_depth!r}; expected 8 or 16", where=where)
        existing = self.document.layer(id) if id in self.document.all_ids else None
        if existing is not None and not isinstance(existing, PatternLayer):
            raise DocumentError(f"layer {id!r} is a {existing.kind} layer; expected a new id", where="add_pattern")
        layer = _layer_dict(id, "pattern", fields, has_mask=mask is not None)
        layer["pattern"] = dict(pattern or {})
        if fields.get("size") is not None:
            size = fields["size"]
            layer["size"] = size if isinstance(size, Mapping) else {"width": int(size[0]), "height": int(size[1])}
        problem = tile_problem(color.shape[-2], color.shape[-1], float(layer["pattern"].get("scale", 100.0)))
        if problem is not None:
            raise ImageError(problem, where)
        planes: list[Plane] = [(color, 0.0, 1.0)] + ([] if a is None else [(a, 0.0, 1.0)])
        for t, _, _ in planes:
            _check_stored(t, 0.0, 1.0, where, clip=False)
        values = torch.from_numpy(_decoded(planes, bit_depth))
        m = None
        if mask is not None:
            m = mask_to_tensor(mask, where=f"{where} mask")
            w, h = (layer["size"]["width"], layer["size"]["height"]) if "size" in layer else (self.width, self.height)
            if tuple(m.shape[-2:]) != (h, w):
                raise ImageError(f"mask is {m.shape[-1]}x{m.shape[-2]}; expected the layer's size {w}x{h}", where)
        tensors = TileTensors(values[:3], values[3:] if a is not None else None, m)
        self.document = self.document.with_layer(layer, index if existing is None else None)
        self._store(id, tensors, bit_depth)
        return self

    def set_pixels(self, id: str, image, *, alpha=None, mask=None, bit_depth: int | None = None) -> Stack:
        """Give the existing pixels or learned layer ``id`` new pixels (a learned layer gets a ``source``)."""
        layer = self.document.layer(id)
        if isinstance(layer, SolidLayer):
            raise DocumentError(f"layer {id!r} is a solid layer; expected a pixels or learned layer", "set_pixels")
        color, a = image_to_tensors(image, tuple(layer.range), where=f"layer {id!r}", alpha=alpha)
        old_mask = self.tensors[id].mask if id in self.tensors and mask is None else mask
        tensors = _make_tensors(id, color, a, old_mask, bit_depth)
        changes: dict[str, Any] = {}
        if layer.source is None:
            changes["source"] = f"layers/{id}.png"
        if mask is not None and layer.mask is None:
            changes["mask"] = f"masks/{id}.png"
        if changes:
            self.document = self.document.replace_layer(id, **changes)
        self._store(id, tensors, bit_depth)
        return self

    def add_surface(
        self,
        id: str,
        normals: torch.Tensor,
        light: str,
        *,
        source_light: str | None = None,
        ambient: float = AMBIENT,
        index: int | None = None,
        mask=None,
        **fields: Any,
    ) -> Stack:
        """Add (on top, or at ``index``) or replace the surface layer ``id`` of unit ``normals`` (3, h, w) (camera
        frame, +Y up), rendered under ``light`` (a named light or ``az=…,el=…``; with ``source_light``, the relight
        ratio). The normals are kept as a 16-bit normal map's values, exactly as the saved PNG gives them back,
        so the stack renders the same bits before saving and after loading. ``fields``: name, opacity, visible,
        offset."""
        if not isinstance(normals, torch.Tensor) or normals.ndim != 3 or normals.shape[0] != 3:
            got = tuple(normals.shape) if isinstance(normals, torch.Tensor) else type(normals).__name__
            raise ImageError(f"normals have shape {got}; expected (3, h, w) unit vectors", where=f"layer {id!r}")
        if not bool(torch.isfinite(normals).all()):
            raise ImageError("normals hold NaN or infinite values; expected unit vectors", where=f"layer {id!r}")
        color = stored_normals(normals)
        tensors = _make_tensors(id, color, None, mask, 16)
        existing = self.document.layer(id) if id in self.document.all_ids else None
        if existing is not None and not isinstance(existing, SurfaceLayer):
            raise DocumentError(f"layer {id!r} is a {existing.kind} layer; expected a new id", where="add_surface")
        layer = _layer_dict(id, "surface", {**fields, "blend": "multiply"}, has_mask=mask is not None)
        layer.update(light=light, source_light=source_light, ambient=float(ambient))
        if existing is not None:
            self.document = self.document.with_layer(layer)
        else:
            self.document = self.document.with_layer(layer, index)
        self._store(id, tensors, 16)
        return self

    def set_light(
        self,
        id: str,
        light: str,
        *,
        source_light: str | None = ...,
        ambient: float | None = None,
        relief: float | None = None,
        light_color: tuple[float, float, float] | None = None,
        light_intensity: float | None = None,
        extra_lights: Sequence[Any] | None = None,
        gloss: float | None = None,
        shininess: float | None = None,
        shadows: float | None = None,
        occlusion: float | None = None,
        shadow_depth: float | None = None,
    ) -> Stack:
        """Re-light the surface layer ``id``: a new ``light`` (and ``source_light`` / ``ambient`` / ``relief`` /
        ``light_color`` / ``light_intensity`` / ``extra_lights`` / ``gloss`` / ``shininess`` / ``shadows`` /
        ``occlusion`` / ``shadow_depth`` when given). No pixels change; the next render draws the stored surface under
        the new light."""
        self.document = self.document.relit(
            id,
            light,
            source_light=source_light,
            ambient=ambient,
            relief=relief,
            light_color=light_color,
            light_intensity=light_intensity,
            extra_lights=extra_lights,
            gloss=gloss,
            shininess=shininess,
            shadows=shadows,
            occlusion=occlusion,
            shadow_depth=shadow_depth,
        )
        return self

    def remove_layer(self, id: str) -> Stack:
        """Remove layer ``id`` (at any depth; a group with its layers) with its tensors; a ``DocumentError`` if a
        learned layer is conditioned on it."""
        before = set(self.document.all_ids)
        self.document = self.document.without_layer(id)
        for gone in before - set(self.document.all_ids):
            self.tensors.pop(gone, None)
            self.bit_depths.pop(gone, None)
        return self

    def _store(self, id: str, tensors, bit_depth: int | None) -> None:
        self.tensors[id] = tensors
        if bit_depth is not None:
            self.bit_depths[id] = bit_depth

    # ---- verbs ------------------------------------------------------------------------------------

    def render(self, dtype: torch.dtype = torch.float32, **kwargs: Any):
        """Composite the stack; see :func:`lasagna.io.render.render_stack`."""
        return render_stack(self, dtype=dtype, **kwargs)

    def save(self, folder: str | os.PathLike | None = None, *, clip: bool = False) -> Path:
        """Write stack.json and every layer PNG into ``folder`` (default: where it was loaded from)."""
        return save_stack(self, folder, clip=clip)


def _make_tensors(id: str, color: torch.Tensor, alpha, mask, bit_depth: int | None):
    """Checked ``LayerTensors`` (mask the layer's size, bit depth 8/16) before the document changes."""
    m = None
    if mask is not None:
        m = mask_to_tensor(mask, where=f"layer {id!r} mask")
        if m.shape[-2:] != color.shape[-2:]:
            raise ImageError(
                f"mask is {m.shape[-1]}x{m.shape[-2]}; expected the layer's size {color.shape[-1]}x{color.shape[-2]}",
                where=f"layer {id!r}",
            )
    if bit_depth not in (None, 8, 16):
        raise ImageError(f"bit_depth {bit_depth!r}; expected 8 or 16", where=f"layer {id!r}")
    # A gray (1-channel) colour stays one channel: the compositor broadcasts it over RGB.
    return LayerTensors(color, alpha, m)


def _layer_dict(
    id: str, kind: str, fields: Mapping[str, Any], *, has_mask: bool, source: str | None = None
) -> dict[str, Any]:
    allowed = {"name", "blend", "opacity", "visible", "offset"}
    allowed |= {"size"} if kind in ("solid", "gradient", "pattern") else set()
    allowed |= {"range"} if kind not in ("gradient", "pattern") else set()
    unknown = set(fields) - allowed
    if unknown:
        raise DocumentError(
            f"unknown layer field(s) {', '.join(sorted(unknown))}; expected some of {', '.join(sorted(allowed))}",
            where=f"layer {id!r}",
        )
    out: dict[str, Any] = {"id": id, "kind": kind}
    for key in ("name", "blend", "opacity", "visible"):
        if key in fields and fields[key] is not None:
            out[key] = fields[key]
    if fields.get("offset") is not None:
        off = fields["offset"]
        out["offset"] = dict(off) if isinstance(off, Mapping) else {"x": int(off[0]), "y": int(off[1])}
    if fields.get("range") is not None:
        out["range"] = [float(v) for v in fields["range"]]
    if kind not in ("solid", "gradient"):
        out["source"] = source or f"layers/{id}.png"
    if has_mask:
        out["mask"] = f"masks/{id}.png"
    return out


# ---- images given by the caller -----------------------------------------------------------------


def _pil_to_codes(image) -> np.ndarray:
    """A PIL image as (C, h, w) float64 stored codes v in [0, 1], as a viewer shows it (EXIF orientation applied,
    an ICC-tagged image converted to sRGB: ``lasagna.io.image.as_seen``, as for an image file)."""
    from lasagna.io.image import as_seen

    image = as_seen(image, "image")
    mode = image.mode
    if mode in ("I;16", "I;16B", "I;16L"):
        arr = np.asarray(image, dtype=np.float64)[None] / 65535.0
        return arr
    if mode == "P":
        image = image.convert("RGBA" if "transparency" in image.info else "RGB")
    elif mode == "1":
        image = image.convert("L")
    elif mode not in ("L", "LA", "RGB", "RGBA"):
        raise ImageError(f"PIL mode {mode!r}; expected L, LA, RGB, RGBA, P, 1 or I;16", where="image")
    arr = np.asarray(image, dtype=np.float64) / 255.0
    return arr[None] if arr.ndim == 2 else arr.transpose(2, 0, 1)


def _channels_first(image, where: str) -> tuple[torch.Tensor, bool]:
    """(C, h, w) tensor of a caller's image, and whether it holds stored codes v (not values y)."""
    if hasattr(image, "mode") and hasattr(image, "getbands"):  # a PIL image: stored codes
        return torch.from_numpy(_pil_to_codes(image)), True
    if not isinstance(image, (torch.Tensor, np.ndarray)):
        raise ImageError(f"got {type(image).__name__}; expected a torch tensor, numpy array or PIL image", where=where)
    if isinstance(image, np.ndarray) and image.ndim == 3 and image.shape[-1] <= 4 < image.shape[0]:
        image = image.transpose(2, 0, 1)  # (h, w, C) as PIL and imageio give arrays
    t = image if isinstance(image, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(image))
    codes = not t.is_floating_point()
    if codes:
        if t.dtype not in (torch.uint8, torch.uint16):
            raise ImageError(f"dtype {t.dtype}; expected float values, or uint8/uint16 codes", where=where)
        t = t.double() / (255.0 if t.dtype == torch.uint8 else 65535.0)
    if t.ndim == 4 and t.shape[0] == 1:
        t = t[0]
    if t.ndim == 2:
        t = t[None]
    if t.ndim != 3 or t.shape[0] not in (1, 2, 3, 4) or t.shape[1] < 1 or t.shape[2] < 1:
        raise ImageError(
            f"shape {tuple(t.shape)}; expected (C, h, w) or (h, w) with C in 1..4 (a numpy array may be (h, w, C))",
            where=where,
        )
    return t, codes


def image_to_tensors(
    image, range_: tuple[float, float], *, where: str, alpha=None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Colour (C, h, w), C ∈ {1, 3}, of values y and alpha (1, h, w) or None, from a caller's image.

    C = 2 or 4 means gray+alpha or RGBA; alpha is never range-mapped. Codes (PIL images, integer
    arrays) are mapped y = lo + (hi − lo)·v and returned as float32; float tensors are kept as
    given (dtype, device and autograd graph included), so gradients reach whatever produced them.
    """
    t, codes = _channels_first(image, where)
    _check_finite(t, where)
    color, a = (t[:-1], t[-1:]) if t.shape[0] in (2, 4) else (t, None)
    if codes:
        lo, hi = float(range_[0]), float(range_[1])
        color = (lo + (hi - lo) * color).float()
        a = a.float() if a is not None else None
    if alpha is not None:
        if a is not None:
            raise ImageError(
                "image already has an alpha channel and alpha= was given; expected one of them", where=where
            )
        a = mask_to_tensor(alpha, where=f"{where} alpha")
        if a.shape[-2:] != color.shape[-2:]:
            raise ImageError(
                f"alpha is {a.shape[-1]}x{a.shape[-2]}; expected {color.shape[-1]}x{color.shape[-2]}", where=where
            )
    return color, a


def mask_to_tensor(mask, *, where: str) -> torch.Tensor:
    """A mask or alpha given by the caller as (1, h, w) values in [0, 1] (PIL images, integer arrays: codes)."""
    t, codes = _channels_first(mask, where)
    if t.shape[0] != 1:
        raise ImageError(f"has {t.shape[0]} channels; expected one (a gray image, (1, h, w) or (h, w))", where=where)
    _check_finite(t, where)
    return t.float() if codes else t  # float tensors are kept as given (they may carry gradients)


def _check_finite(t: torch.Tensor, where: str) -> None:
    bad = ~torch.isfinite(t.detach())
    if bool(bad.any()):
        raise ImageError(f"{int(bad.sum())} values are NaN or infinite; expected finite values", where=where)


def stack_from_tensors(
    layers: Sequence[Mapping[str, Any] | tuple[str, Any]],
    *,
    width: int | None = None,
    height: int | None = None,
    background: Sequence[float] | None = (0.0, 0.0, 0.0),
    blend_space: str = "srgb",
    clamp: str = "layer",
    metadata: Mapping[str, Any] | None = None,
) -> Stack:
    """Build a stack from images, bottom first: ``(id, image)`` pairs or dicts with ``id``, ``image``
    (or ``color`` for a solid layer) and layer fields. The canvas defaults to the first image's size;
    ``background=None`` makes a transparent document.
    """
    if not layers:
        raise DocumentError("no layers given; expected at least one", where="stack_from_tensors")
    specs = [dict(id=layer[0], image=layer[1]) if isinstance(layer, tuple) else dict(layer) for layer in layers]
    first = specs[0]
    if "image" not in first:
        raise DocumentError("the bottom layer needs an image (it sets the canvas)", where="stack_from_tensors")
    fid, fimage = first.pop("id"), first.pop("image")
    stack = Stack.from_image(
        fimage, id=fid, background=background, blend_space=blend_space, clamp=clamp, metadata=metadata, **first
    )
    if width is not None or height is not None:
        bg = None if background is None else list(background)
        canvas = {"width": width or stack.width, "height": height or stack.height, "background": bg}
        stack.document = stack.document.replace(canvas=canvas)
    for spec in specs[1:]:
        lid = spec.pop("id")
        if "color" in spec:
            stack.add_solid(lid, spec.pop("color"), **spec)
        else:
            stack.add_layer(lid, spec.pop("image"), **spec)
    return stack


# ---- loading -------------------------------------------------------------------------------------


def load_stack(
    path: str | os.PathLike,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    max_total_pixels: int = DEFAULT_MAX_TOTAL_PIXELS,
    composite: bool = False,
    copies: int = 0,
) -> Stack:
    """Load a stack folder (or its stack.json): the validated document and every layer's tensors.

    All paths are resolved and all PNG headers checked (size limits, per image and in total, and the
    memory budget of ``lasagna.limits`` for decoding them all, with room for the canvas when ``composite``
    and ``copies`` more of the layers: ``lasagna.io.survey.survey_stack``) before any pixel is decoded.
    Errors are one-line ``LasagnaError``s naming the file and the layer.
    """
    survey = survey_stack(
        path, max_pixels=max_pixels, max_total_pixels=max_total_pixels, composite=composite, copies=copies
    )
    return load_surveyed(survey)


def load_surveyed(survey: Survey) -> Stack:
    """Decode the stack a ``survey_stack`` passed (the CLI surveys before it imports torch, then decodes
    what it surveyed: the document is read and the headers are checked once)."""
    file, doc, planned = survey.file, survey.document, survey.rasters
    images: dict[tuple[str, str], PngImage] = {}
    for r in planned:
        try:
            images[(r.loc, r.field)] = read_png(r.target, max_pixels=survey.max_pixels, max_side=MAX_SIDE)
        except ImageError as err:
            raise err.at(f"{file}: {r.where}") from None

    stack = Stack(doc, file.parent)
    for r in planned:
        layer = r.layer
        if isinstance(layer, (GroupLayer, AdjustmentLayer, GradientLayer)):  # a mask with no source beside it
            stack.tensors[layer.id] = group_mask_tensors(images.pop((r.loc, "mask")), f"{file}: {r.where}")
            continue
        if r.field != "source":
            continue
        if isinstance(layer, PatternLayer):  # the tile, and the mask of the layer's rectangle (its own size)
            img = images.pop((r.loc, "source"))
            mask = images.pop((r.loc, "mask")) if layer.mask is not None else None
            mask_t = None if mask is None else _mask_array(mask, f"{file}: {r.loc}.mask ({layer.mask})")
            alpha = None if img.alpha is None else torch.from_numpy(img.alpha)
            stack.tensors[layer.id] = TileTensors(torch.from_numpy(img.color), alpha, mask_t)
            stack.bit_depths[layer.id] = img.header.bit_depth if img.header.bit_depth == 16 else 8
            continue
        img = images.pop((r.loc, "source"))
        mask_img = images.pop((r.loc, "mask")) if layer.mask is not None else None
        stack.tensors[layer.id] = layer_tensors(img, layer.range, mask_img, f"{file}: {r.loc}.mask ({layer.mask})")
        stack.tensors[layer.id].note("stored", tuple(layer.range))  # what the folder holds (learned.as_stored)
        stack.bit_depths[layer.id] = img.header.bit_depth if img.header.bit_depth == 16 else 8
    return stack


def group_mask_tensors(mask, where: str = "mask") -> LayerTensors:
    """A group's mask (a decoded PNG: one channel times its own alpha; or a (1, h, w) tensor) as
    ``LayerTensors``: ``mask`` is the mask, and ``color`` a zero-stride view of ones of its size (a group
    has no pixels; ``tensors[id].mask`` is then every kind's mask, and saving writes it back)."""
    mask = mask if isinstance(mask, torch.Tensor) else _mask_array(mask, where)
    return LayerTensors(mask.new_ones(()).expand(mask.shape), mask=mask)


def _mask_array(m, where: str) -> torch.Tensor:
    c = m.color
    if c.shape[0] == 3 and not (np.array_equal(c[0], c[1]) and np.array_equal(c[0], c[2])):
        raise ImageError("mask is a colour image; expected a gray PNG (or RGB with equal channels)", where=where)
    mask_np = m.color[:1]
    if m.alpha is not None:
        mask_np = mask_np * m.alpha  # a transparent mask pixel hides the layer
    return torch.from_numpy(np.ascontiguousarray(mask_np))


def layer_tensors(img, value_range, mask_img=None, mask_where: str = "mask"):
    """A decoded PNG (and mask PNG) as a layer's tensors: colour mapped to ``value_range``
    (y = lo + (hi − lo)·v; alpha never mapped), the mask as one channel times its own alpha."""
    lo, hi = value_range
    color = torch.from_numpy(img.color)
    if (lo, hi) != (0.0, 1.0):
        color = lo + (hi - lo) * color
    alpha = torch.from_numpy(img.alpha) if img.alpha is not None else None
    mask = _mask_array(mask_img, mask_where) if mask_img is not None else None
    return LayerTensors(color, alpha, mask)


# ---- saving --------------------------------------------------------------------------------------


# Rows of a layer quantised at a time when it is saved: 64 rows of an 8192-wide RGBA layer are 16 MiB of float64.
SAVE_BAND_ROWS = 64

# A plane of stored values: the tensor (c, h, w), and the [lo, hi] its PNG codes v = (y − lo)/(hi − lo) span.
Plane = tuple[torch.Tensor, float, float]


def _check_stored(values: torch.Tensor, lo: float, hi: float, where: str, clip: bool) -> None:
    """Values must be finite, and inside [lo, hi] (within ``RANGE_SAVE_TOLERANCE`` of v) unless ``clip``: checked
    on the tensor as it is (no copy), before any band is quantised."""
    y = values.detach()
    finite = torch.isfinite(y)
    if not bool(finite.all()):
        raise ImageError(f"{int((~finite).sum())} values are NaN or infinite; expected finite values", where=where)
    if clip or not y.numel():
        return
    y_lo, y_hi = (float(v) for v in torch.aminmax(y))
    v_lo, v_hi = (y_lo - lo) / (hi - lo), (y_hi - lo) / (hi - lo)
    if v_lo < -RANGE_SAVE_TOLERANCE or v_hi > 1 + RANGE_SAVE_TOLERANCE:
        raise ImageError(
            f"values span [{y_lo:.6g}, {y_hi:.6g}], outside the layer's range [{lo:g}, {hi:g}]; "
            "expected values inside the range (widen `range`, or save with clip=True to clamp)",
            where=where,
        )


def _band_codes(planes: list[Plane], depth: int, r0: int, r1: int) -> np.ndarray:
    """Rows ``r0:r1`` of ``planes`` as (rows, w, channels) codes: v = (y − lo)/(hi − lo) in float64, clamped to
    [0, 1], rounded half to even at (2^depth − 1)·v (what a PNG of ``depth`` bits stores)."""
    parts = []
    for t, lo, hi in planes:
        y = t.detach()[:, r0:r1].to("cpu", torch.float64).numpy()
        parts.append(y if (lo, hi) == (0.0, 1.0) else (y - lo) / (hi - lo))
    return quantize_band(np.concatenate(parts).transpose(1, 2, 0), depth)  # type: ignore[arg-type]


def _encode_planes(planes: list[Plane], depth: int) -> bytes:
    """A PNG of ``planes`` (1 or 3 colour channels, then alpha when there is one), quantised and encoded band by
    band: a layer of any size costs one band of float64 beside its compressed bytes."""
    h, w = planes[0][0].shape[-2:]
    bands = (_band_codes(planes, depth, r, min(h, r + SAVE_BAND_ROWS)) for r in range(0, h, SAVE_BAND_ROWS))
    return encode_bands(bands, w, h, bit_depth=depth)  # type: ignore[arg-type]


def _layer_planes(stack: Stack, id: str, clip: bool) -> tuple[list[Plane], list[Plane] | None, int]:
    """Layer ``id``'s stored planes (colour range-mapped, then alpha), its mask's, checked (``_check_stored``), and
    the bit depth its PNGs are written at: 16 for a range other than [0, 1] and for learned layers, never less
    than read."""
    layer = stack.document.layer(id)
    t = stack.tensors[id]
    where = f"layer {id!r}"
    lo, hi = layer.range
    sixteen = tuple(layer.range) != (0.0, 1.0) or isinstance(layer, (LearnedLayer, SurfaceLayer))  # maps: 16-bit
    depth = 16 if sixteen else stack.bit_depths.get(id, 8)
    depth = max(depth, stack.bit_depths.get(id, 8))
    if t.color.ndim != 3:
        raise ImageError(f"colour has shape {tuple(t.color.shape)}; expected (C, h, w) to save (no batch)", where=where)
    _check_stored(t.color, lo, hi, where, clip)
    planes: list[Plane] = [(t.color, float(lo), float(hi))]
    if t.alpha is not None:
        _check_stored(t.alpha, 0.0, 1.0, f"{where} alpha", clip)
        planes.append((t.alpha.reshape(1, *t.color.shape[-2:]), 0.0, 1.0))
    mask = None
    if t.mask is not None:
        _check_stored(t.mask, 0.0, 1.0, f"{where} mask", clip)
        mask = [(t.mask.reshape(1, *t.mask.shape[-2:]), 0.0, 1.0)]
    return planes, mask, depth


def encode_layer(stack: Stack, id: str, *, clip: bool = False) -> tuple[bytes, bytes | None]:
    """PNG bytes of layer ``id``'s source and of its mask (None without one)."""
    planes, mask, depth = _layer_planes(stack, id, clip)
    return _encode_planes(planes, depth), None if mask is None else _encode_planes(mask, depth)


def encode_group_mask(stack: Stack, id: str, where: str, *, clip: bool = False) -> bytes:
    """PNG bytes of group ``id``'s mask (its tensors hold only the mask: ``group_mask_tensors``)."""
    t = stack.tensors[id]
    if t.mask is None or t.mask.ndim != 3:
        raise ImageError("group mask tensor missing or batched; expected (1, h, w)", where=f"{where}.mask")
    _check_stored(t.mask, 0.0, 1.0, f"group {id!r} mask", clip)
    return _encode_planes([(t.mask, 0.0, 1.0)], stack.bit_depths.get(id, 8))


@dataclass
class _Planes:
    """What ``decode_png`` gives ``layer_tensors``: float32 colour (C, h, w) and alpha in [0, 1]."""

    color: np.ndarray
    alpha: np.ndarray | None = None


def _decoded(planes: list[Plane], depth: int) -> np.ndarray:
    """The values ``planes`` read back from their PNG of ``depth`` bits, (channels, h, w) float32: the codes
    (``_band_codes``) divided by the float32 maximum code, as ``decode_png`` reads them; band by band."""
    h, w = planes[0][0].shape[-2:]
    out = np.empty((sum(t.shape[0] for t, _, _ in planes), h, w), dtype=np.float32)
    for r in range(0, h, SAVE_BAND_ROWS):
        codes = _band_codes(planes, depth, r, min(h, r + SAVE_BAND_ROWS)).transpose(2, 0, 1)
        np.divide(codes, np.float32(2**depth - 1), out=out[:, r : r + SAVE_BAND_ROWS], dtype=np.float32)
    return out


def stored_map(values, where: str = "normal map") -> torch.Tensor:
    """A normal map's values (3, h, w) in [0, 1] as its 16-bit PNG gives them back (float32): what a surface
    layer holds from the start, so it renders the same bits before saving and after loading."""
    t = torch.as_tensor(values)
    if not bool(torch.isfinite(t).all()) or (t.numel() and (float(t.min()) < 0.0 or float(t.max()) > 1.0)):
        raise ImageError("values are NaN or outside [0, 1]; expected a normal map's values in [0, 1]", where=where)
    return torch.from_numpy(_decoded([(t, 0.0, 1.0)], 16))


def stored_normals(normals: torch.Tensor) -> torch.Tensor:
    """Unit normals (3, h, w) as the values of their 16-bit normal map (float32): ``stored_map`` of
    ``encode_normal_map`` computed in float64 a band of rows at a time, so a 12 MP map never exists as float64."""
    h, w = normals.shape[-2:]
    out = torch.empty((3, h, w), dtype=torch.float32)
    for r in range(0, h, SAVE_BAND_ROWS):
        band = encode_normal_map(normals[None, :, r : r + SAVE_BAND_ROWS].detach().cpu().double())[0]
        out[:, r : r + SAVE_BAND_ROWS] = stored_map(band)
    return out


def stored_tensors(stack: Stack, id: str) -> tuple[LayerTensors, int]:
    """Layer ``id``'s tensors as saving and loading them gives them, and the bit depth: exactly
    ``layer_tensors(decode_png(encode_layer(...)))``, computed without encoding (the same codes, divided and
    range-mapped the same way), and noted as stored (``LayerTensors.note``) so that ``as_stored`` can skip
    them until they or the layer's range change."""
    layer = stack.document.layer(id)
    where = f"layer {id!r}"
    planes, mask, depth = _layer_planes(stack, id, clip=False)
    values = _decoded(planes, depth)
    c = planes[0][0].shape[0]
    img = _Planes(values[:c], values[c:] if len(planes) > 1 else None)
    mask_img = None if mask is None else _Planes(_decoded(mask, depth))
    tensors = layer_tensors(img, layer.range, mask_img, f"{where} mask")
    tensors.note("stored", tuple(layer.range))
    return tensors, depth


def stack_files(stack: Stack, folder: str | os.PathLike, *, clip: bool = False) -> list[tuple[Path, bytes]]:
    """Every file of ``stack`` saved in ``folder``, encoded in memory and with its path checked inside the
    folder: each layer's (and mask's) PNG, then stack.json. Nothing is written. Each path is the folder's
    own entry (``entry_inside``): a layer PNG that is a symlink is replaced by the new file, its target
    (another layer's PNG, a file of the user's) is never written."""
    folder = Path(folder)
    if folder.suffix.lower() == ".json":
        raise PathError(f"{folder} is a file name; expected a stack folder", where="save_stack")
    doc = stack.document
    missing = [layer.id for _, layer in doc.walk() if isinstance(layer, PixelsLayer) and layer.id not in stack.tensors]
    if missing:
        raise ImageError(
            f"pixels layer(s) {', '.join(missing)} have no tensors; expected add_layer/set_pixels first",
            where="save_stack",
        )
    writes: list[tuple[Path, bytes]] = []
    for loc, layer in doc.walk():
        if layer.id not in stack.tensors or isinstance(layer, SolidLayer):
            continue
        if isinstance(layer, (GroupLayer, AdjustmentLayer, GradientLayer)):
            if layer.mask is not None:  # a group's, adjustment's or gradient's tensors hold its mask only
                data = encode_group_mask(stack, layer.id, loc, clip=clip)
                writes.append((entry_inside(folder, layer.mask, f"{loc}.mask"), data))
            continue
        data, mask_data = encode_layer(stack, layer.id, clip=clip)
        writes.append((entry_inside(folder, layer.source, f"{loc}.source"), data))
        if mask_data is not None:
            if layer.mask is None:
                raise DocumentError(f"layer {layer.id!r} has a mask tensor but no `mask` path", where=f"{loc}.mask")
            writes.append((entry_inside(folder, layer.mask, f"{loc}.mask"), mask_data))
    writes.append((stack_file(folder), doc.to_json().encode("utf-8")))
    return writes


def save_stack(stack: Stack, folder: str | os.PathLike | None = None, *, clip: bool = False) -> Path:
    """Write ``stack`` into ``folder``: every layer PNG and stack.json, all or nothing
    (``lasagna.atomic.atomic_write_all``). Returns the stack.json written.

    Everything is encoded and every path checked before the first file is written, so a bad value, a bad
    path or a failed write leaves the folder as it was.
    """
    if folder is None:
        if stack.folder is None:
            raise PathError("the stack was not loaded from a folder; expected save(folder)", where="save_stack")
        folder = stack.folder
    folder = Path(folder)
    writes = stack_files(stack, folder, clip=clip)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PathError(
            f"cannot write ({exc.strerror or exc}); expected a writable folder", where=str(folder)
        ) from None
    atomic_write_all(writes)
    stack.folder = folder
    return writes[-1][0]
