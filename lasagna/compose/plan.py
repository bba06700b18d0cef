"""The render plan: which layers a composite needs, the rectangle each one touches, and why others are skipped.

``compile_plan`` turns a bottom-to-top list of ``RenderLayerSpec`` into a ``RenderPlan``. For every
layer it records either a live ``PlanStep`` — the canvas rectangle ``canvas ∩ layer`` and the matching
slice of the layer, whether the layer is opaque (blended with α = None), which clamps it needs — or a
skip reason, checked in this order:

``hidden``          ``visible`` is false (always skipped: a hidden layer is not part of the image);
``zero-opacity``    opacity is exactly 0 (never for an opacity tensor that requires grad: its
                    gradient is not zero);
``outside-canvas``  the layer's rectangle does not meet the canvas (always skipped: nothing to do);
``occluded``        an opaque ``normal`` layer above it (α = 1 everywhere, opacity 1, mask absent or
                    all 1) covers its clipped rectangle, so its pixels cannot reach the output. An
                    opaque normal layer covering the whole canvas hides the background and every
                    layer below it: rendering starts from it (no background fill);
``identity``        blending it changes nothing, bit for bit: multiply by 1, plus or screen of 0, or
                    alpha × mask = 0 everywhere — with finite colour (``LayerTensors.is_identity``);
                    never for a layer whose tensors require grad. Over the transparent backdrop of
                    an isolated group only alpha × mask = 0 counts (a multiply by 1 over
                    transparency paints white: W3C Compositing Level 1, section 10, Cr = (1 − αb)·Cs + …);
``empty``           a group none of whose children is live (always skipped: it changes nothing);
``outside-base``    a layer clipped to a base whose rectangle it does not meet (it shows only on the base).

**Adjustment layers** (``RenderLayerSpec(adjust=...)``, ``adjust.py``) read the canvas below them: their colour is
``adjust(Cb)``, their tensors hold only the mask (a zero-stride colour of its size). They are never occluders and
never identities by value (only a mask of zeros makes one an identity), and a clamp follows them under
``clamp="layer"``.

**Clipping chains** (``RenderGroupSpec(clip=True)``: a base and the layers clipped to it, Photoshop's clipping
mask) are isolated groups whose rectangle is the base's (cut by the base's mask, which the chain carries); the
base is compiled on its own, so no clipped layer occludes it, and a chain whose base is skipped shows nothing
(it takes the base's reason).

**Groups** (``RenderGroupSpec``; the maths is ``group.py``'s). A group is one step of its parent's plan whose
rectangle is the union of its live children's (cut by its mask's), and whose ``children`` are the steps of
its own layers, compiled by the same rules on the same canvas (offsets add up: a child's position is its
offset plus its ancestors'). Culling works inside a group (``occluded`` among siblings; ``identity`` as
above) and on the group as a whole (hidden, zero opacity, outside the canvas, occluded by an opaque
normal layer above its rectangle, empty); a group never occludes what lies below it. A pass-through group
with opacity exactly 1 and no mask *is* its children composited in its place (W3C section 8.1, group
invariance), so it is inlined: its children become steps of the parent, culled, cached and differentiated
like any other layer.

The last two are *culling* (``cull=True``, the default); with ``cull=False`` those layers are blended
like any other, which is how the tests prove that culling never changes a result. Occlusion is tested
before identity because it needs no pixel of the occluded layer. Culled layers receive no gradient
(``.grad`` stays None) — their true gradient is zero.

The statistics behind ``occluded``/``identity``/opacity and the clamp decisions are cached on each
``LayerTensors`` (``layer.py``), so compiling a plan again after an edit reads no unchanged pixels.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import reduce
from typing import Any, Literal

import torch
from torch import Tensor

from lasagna.compose.adjust import Adjustment
from lasagna.compose.blend import BLEND_MODES, broadcast_shape, check_blend_name, clamp_needed
from lasagna.compose.color import srgb_to_linear
from lasagna.compose.gradient import gradient_fill
from lasagna.compose.layer import LayerTensors
from lasagna.compose.pattern import pattern_fill
from lasagna.compose.surface import layer_surface_tensors
from lasagna.document.types import range_problem
from lasagna.errors import LasagnaError

SkipReason = Literal["hidden", "zero-opacity", "outside-canvas", "occluded", "identity", "empty", "outside-base"]
BlendSpace = Literal["srgb", "linear"]
ClampPolicy = Literal["layer", "output", None]
Opacity = float | Tensor

_ID_OK = r"any non-empty string, unique in the stack"


def _number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


@dataclass(frozen=True, kw_only=True)
class RenderLayerSpec:
    """One layer of a stack as the compositor sees it (document-free).

    ``opacity`` is a number in [0, 1] or a tensor (0-d, or ``(..., 1, 1, 1)`` per batch entry) that
    may require grad. ``offset`` is ``(x, y)`` of the layer's top-left corner on the canvas (may be
    negative or put the layer outside). ``range`` is ``(lo, hi)``, the interval the colour values were
    mapped to; it only matters for clamping a layer that carries gradients (see ``clamp_needed``).
    ``encoded``: the colour is sRGB-encoded, so it is decoded when blending in linear light —
    except for ``multiply``, whose values are factors and are never decoded.
    ``adjust``: an adjustment layer: its colour is ``adjust`` of the backdrop (of the sRGB-encoded backdrop in the
    linear blend space), and ``tensors`` carry only its mask (``adjustment_tensors``).
    """

    id: str
    tensors: LayerTensors
    blend: str = "normal"
    opacity: Opacity = 1.0
    visible: bool = True
    offset: tuple[int, int] = (0, 0)
    range: tuple[float, float] = (0.0, 1.0)
    encoded: bool = True
    adjust: Adjustment | None = None

    def __post_init__(self) -> None:
        where = _check_common(self, "RenderLayerSpec")
        if self.adjust is not None and not isinstance(self.adjust, Adjustment):
            raise LasagnaError(f"adjust is a {type(self.adjust).__name__}; expected an Adjustment or None", where=where)
        if not isinstance(self.tensors, LayerTensors):
            raise LasagnaError(f"tensors is a {type(self.tensors).__name__}; expected LayerTensors", where=where)
        r = self.range
        if not isinstance(r, (tuple, list)) or len(r) != 2 or not all(_number(v) and math.isfinite(v) for v in r):
            raise LasagnaError(f"range is {r!r}; expected (lo, hi), finite, with lo < hi", where=where)
        problem = range_problem(float(r[0]), float(r[1]))  # the document's rule, stated once
        if problem is not None:
            raise LasagnaError(f"range is {r!r}; expected (lo, hi) within the rule: {problem}", where=where)
        if not isinstance(self.encoded, bool):
            raise LasagnaError(f"encoded is {self.encoded!r}; expected true or false", where=where)

    @property
    def requires_grad(self) -> bool:
        return (
            self.tensors.requires_grad
            or (isinstance(self.opacity, Tensor) and self.opacity.requires_grad)
            or (self.adjust is not None and self.adjust.requires_grad)
        )

    def opacity_value(self) -> float | None:
        """The opacity as a number when it is one value that carries no gradient, else None."""
        return _opacity_value(self.opacity)


def _check_common(spec: Any, kind: str) -> str:
    """Check the fields a layer and a group share (id, blend, opacity, visible, offset); return ``where``."""
    where = f"layer {spec.id!r}"
    if not isinstance(spec.id, str) or not spec.id:
        raise LasagnaError(f"id is {spec.id!r}; expected {_ID_OK}", where=f"{kind}.id")
    check_blend_name(spec.blend, where=f"{where} blend")
    op = spec.opacity
    if isinstance(op, Tensor):
        if not op.is_floating_point() or not (op.ndim == 0 or (op.ndim >= 3 and op.shape[-3:] == (1, 1, 1))):
            raise LasagnaError(
                f"opacity tensor has shape {tuple(op.shape)} and dtype {op.dtype}; expected a "
                "floating-point 0-d tensor or (..., 1, 1, 1)",
                where=where,
            )
        if not op.requires_grad:
            lo, hi = torch.aminmax(op.detach())
            if not (0.0 <= float(lo) and float(hi) <= 1.0):
                raise LasagnaError(f"opacity spans [{float(lo)}, {float(hi)}]; expected values in [0, 1]", where=where)
    elif not _number(op) or not 0.0 <= op <= 1.0:
        raise LasagnaError(f"opacity is {op!r}; expected a number in [0, 1] or a tensor", where=where)
    if not isinstance(spec.visible, bool):
        raise LasagnaError(f"visible is {spec.visible!r}; expected true or false", where=where)
    if (
        not isinstance(spec.offset, (tuple, list))
        or len(spec.offset) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in spec.offset)
    ):
        raise LasagnaError(f"offset is {spec.offset!r}; expected two integers (x, y)", where=where)
    return where


def _opacity_value(op: Opacity) -> float | None:
    if not isinstance(op, Tensor):
        return float(op)
    if op.requires_grad:
        return None
    lo, hi = torch.aminmax(op.detach())
    return float(lo) if float(lo) == float(hi) else None


@dataclass(frozen=True, kw_only=True)
class RenderGroupSpec:
    """A group of layers as the compositor sees it (W3C Compositing Level 1, section 8 "Compositing Groups").

    ``children`` are ``RenderLayerSpec``s and ``RenderGroupSpec``s, bottom to top; their offsets are
    relative to the group's ``offset``. ``isolated``: the children are composited onto a transparent
    backdrop and the result blended with ``blend`` and its alpha × ``mask`` × ``opacity`` (section 8.2);
    otherwise they pass through — composited onto the group backdrop, the result mixed with that backdrop
    by ``mask`` × ``opacity`` — and ``blend`` must be ``normal``. ``mask`` ``(..., 1, h, w)`` lies with its
    top-left corner at the group's offset; the group shows only inside it. See ``group.py``.

    ``clip``: a clipping chain (Photoshop's clipping mask): ``children[0]`` is the base, the others are clipped
    to it. They are composited onto the base as in an isolated group, and the result keeps the base's alpha
    (times ``mask`` × ``opacity``: the base's own, moved onto the chain), blended with ``blend`` (the base's).
    ``plan_from_document`` builds one per chain of a document.
    """

    id: str
    children: tuple[RenderLayerSpec | RenderGroupSpec, ...] = ()
    isolated: bool = False
    blend: str = "normal"
    opacity: Opacity = 1.0
    visible: bool = True
    offset: tuple[int, int] = (0, 0)
    mask: Tensor | None = None
    clip: bool = False

    def __post_init__(self) -> None:
        where = _check_common(self, "RenderGroupSpec")
        if not isinstance(self.children, (tuple, list)) or not all(
            isinstance(c, (RenderLayerSpec, RenderGroupSpec)) for c in self.children
        ):
            raise LasagnaError("children must be RenderLayerSpecs and RenderGroupSpecs, bottom to top", where=where)
        object.__setattr__(self, "children", tuple(self.children))
        if not isinstance(self.isolated, bool):
            raise LasagnaError(f"isolated is {self.isolated!r}; expected true or false", where=where)
        if not self.isolated and self.blend != "normal":
            raise LasagnaError(
                f"a pass-through group (isolated=False) has blend {self.blend!r}; expected 'normal' (a pass-through "
                "group has no blend of its own) or isolated=True",
                where=where,
            )
        if self.clip and (not self.isolated or not self.children):
            raise LasagnaError(
                "a clipping chain (clip=True) must be isolated with its base as children[0]; expected isolated=True "
                "and at least one child",
                where=where,
            )
        m = self.mask
        if m is not None and (not isinstance(m, Tensor) or not m.is_floating_point() or m.ndim < 3 or m.shape[-3] != 1):
            got = f"{tuple(m.shape)} {m.dtype}" if isinstance(m, Tensor) else type(m).__name__
            raise LasagnaError(f"mask is {got}; expected a floating-point tensor (..., 1, h, w) or None", where=where)

    # A group's colour is computed in the blend space, never stored sRGB-encoded, and has no value range.
    range = (0.0, 1.0)
    encoded = False

    @property
    def requires_grad(self) -> bool:
        return (
            any(c.requires_grad for c in self.children)
            or (self.mask is not None and self.mask.requires_grad)
            or (isinstance(self.opacity, Tensor) and self.opacity.requires_grad)
        )

    def opacity_value(self) -> float | None:
        """The opacity as a number when it is one value that carries no gradient, else None."""
        return _opacity_value(self.opacity)

    @property
    def inlined(self) -> bool:
        """A visible pass-through group of opacity exactly 1 without a mask: its children in its place."""
        return not self.isolated and self.visible and self.mask is None and self.opacity_value() == 1.0


RenderSpec = RenderLayerSpec | RenderGroupSpec


@dataclass(frozen=True)
class PlanStep:
    """A live layer: canvas rows ``y0:y1``, columns ``x0:x1``; layer slice starts at ``(ly0, lx0)``."""

    index: int
    spec: RenderLayerSpec
    y0: int
    y1: int
    x0: int
    x1: int
    ly0: int
    lx0: int
    opaque: bool  # alpha × mask × opacity is exactly 1 and carries no gradient: blend with α = None
    clamp_lo: bool  # clamp="layer" must clamp below 0 after this blend
    clamp_hi: bool  # ... and above 1
    decode: bool  # decode the colour from sRGB (linear blend space, encoded, not multiply)
    full: bool  # the rectangle is the whole canvas
    children: tuple[PlanStep, ...] | None = None  # a group's live steps (None for a layer); ly0, lx0 index its mask

    @property
    def blend(self) -> str:
        return self.spec.blend

    @property
    def requires_grad(self) -> bool:
        return self.spec.requires_grad

    def layer_slice(self, y0: int | None = None, y1: int | None = None) -> tuple[Any, ...]:
        """Index of the layer's pixels under canvas rows ``y0:y1`` (default: the whole rectangle)."""
        y0 = self.y0 if y0 is None else y0
        y1 = self.y1 if y1 is None else y1
        ly = self.ly0 + (y0 - self.y0)
        return (..., slice(ly, ly + (y1 - y0)), slice(self.lx0, self.lx0 + (self.x1 - self.x0)))


@dataclass(frozen=True)
class RenderPlan:
    """A compiled stack: live steps bottom to top, and a skip reason for every other layer."""

    layers: tuple[RenderLayerSpec, ...]
    canvas: tuple[int, int]  # (H, W)
    background: tuple[float, float, float] | None  # None: a transparent canvas (the render carries alpha)
    blend_space: BlendSpace
    clamp: ClampPolicy
    cull: bool
    steps: tuple[PlanStep, ...]
    reasons: tuple[SkipReason | None, ...]  # one per layer; None = live
    batch_shape: torch.Size
    dtype: torch.dtype
    device: torch.device
    skipped: dict[str, SkipReason] = field(default_factory=dict)

    @property
    def evaluated(self) -> list[str]:
        """Ids of the live layers and groups, bottom to top (a group before its live children)."""
        return [s.spec.id for s in walk_steps(self.steps)]


def walk_steps(steps: Sequence[PlanStep]) -> Iterator[PlanStep]:
    """Every step, a group's children after it, depth first."""
    for s in steps:
        yield s
        if s.children is not None:
            yield from walk_steps(s.children)


def _contains(outer: tuple[int, int, int, int], inner: tuple[int, int, int, int]) -> bool:
    return outer[0] <= inner[0] and inner[1] <= outer[1] and outer[2] <= inner[2] and inner[3] <= outer[3]


def _decoded_bound(v: float) -> float:
    return float(srgb_to_linear(torch.tensor(v, dtype=torch.float64)))


def _check_config(canvas: object, background: object, blend_space: object, clamp: object) -> None:
    if (
        not isinstance(canvas, (tuple, list))
        or len(canvas) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in canvas)
    ):
        raise LasagnaError(f"canvas is {canvas!r}; expected (height, width), positive integers", where="compile_plan")
    if background is not None and (
        not isinstance(background, (tuple, list))
        or len(background) != 3
        or not all(_number(v) and 0.0 <= v <= 1.0 for v in background)
    ):
        raise LasagnaError(
            f"background is {background!r}; expected opaque RGB, three numbers in [0, 1], or None (transparent)",
            where="compile_plan",
        )
    if blend_space not in ("srgb", "linear"):
        raise LasagnaError(f"blend_space is {blend_space!r}; expected 'srgb' or 'linear'", where="compile_plan")
    if clamp not in ("layer", "output", None):
        raise LasagnaError(f"clamp is {clamp!r}; expected 'layer', 'output' or None", where="compile_plan")


def compile_plan(
    layers: Sequence[RenderSpec],
    canvas: tuple[int, int],
    background: tuple[float, float, float] | None = (0.0, 0.0, 0.0),
    blend_space: BlendSpace = "srgb",
    clamp: ClampPolicy = "layer",
    *,
    cull: bool = True,
) -> RenderPlan:
    """Compile bottom-to-top ``layers`` (and groups) on a ``canvas = (H, W)`` into a ``RenderPlan`` (module
    docstring). The plan's ``layers`` are the top-level entries after inlining, with canvas offsets.
    ``background=None``: a transparent canvas, composited as an isolated group is (culled by its rules)."""
    _check_config(canvas, background, blend_space, clamp)
    layers = tuple(layers)
    _check_ids(layers, {}, "layers")
    H, W = canvas
    skipped: dict[str, SkipReason] = {}
    entries = _inline(layers, (0, 0))
    steps, reasons = _compile_level(entries, canvas, blend_space, clamp, cull, background is not None, skipped)

    batch: torch.Size = torch.Size()
    dtypes: list[torch.dtype] = []
    devices: set[torch.device] = set()
    for s in walk_steps(steps):
        spec = s.spec
        own = [spec.opacity] if isinstance(spec.opacity, Tensor) else []
        if s.children is None:
            shapes = [spec.tensors.batch_shape]
            dtypes.append(spec.tensors.color.dtype)
            devices.add(spec.tensors.color.device)
        else:
            shapes = [spec.mask.shape[:-3]] if spec.mask is not None else []
            own += [spec.mask] if spec.mask is not None else []
        shapes += [op.shape[:-3] for op in own if op.ndim]
        for shape in shapes:
            try:
                batch = torch.Size(broadcast_shape(batch, shape))
            except RuntimeError:
                raise LasagnaError(
                    f"batch dimensions {tuple(shape)} do not broadcast with {tuple(batch)} of the "
                    "layers below; expected equal sizes or 1",
                    where=f"layer {spec.id!r}",
                ) from None
    if len(devices) > 1:
        raise LasagnaError(
            f"live layers are on several devices {sorted(map(str, devices))}; expected one", where="compile_plan"
        )
    dtype = reduce(torch.promote_types, dtypes) if dtypes else torch.get_default_dtype()
    device = devices.pop() if devices else torch.device("cpu")
    return RenderPlan(
        entries,
        (H, W),
        None if background is None else tuple(float(v) for v in background),
        blend_space,
        clamp,
        cull,  # type: ignore[arg-type]
        steps,
        tuple(reasons),
        batch,
        dtype,
        device,
        skipped,
    )


def _check_ids(layers: Sequence[Any], seen: dict[str, str], where: str) -> None:
    """Every entry is a spec, and ids are unique across the whole tree."""
    for i, spec in enumerate(layers):
        here = f"{where}[{i}]"
        if not isinstance(spec, (RenderLayerSpec, RenderGroupSpec)):
            raise LasagnaError(f"is a {type(spec).__name__}; expected RenderLayerSpec or RenderGroupSpec", where=here)
        if spec.id in seen:
            raise LasagnaError(f"id {spec.id!r} is used by {seen[spec.id]} too; expected unique ids", where=here)
        seen[spec.id] = here
        if isinstance(spec, RenderGroupSpec):
            _check_ids(spec.children, seen, f"{here}.children")


def _inline(layers: Sequence[RenderSpec], origin: tuple[int, int]) -> tuple[RenderSpec, ...]:
    """``layers`` with canvas offsets (``origin`` added) and inlined pass-through groups replaced by their
    children (module docstring)."""
    out: list[RenderSpec] = []
    for spec in layers:
        offset = (spec.offset[0] + origin[0], spec.offset[1] + origin[1])
        if isinstance(spec, RenderGroupSpec) and spec.inlined:
            out.extend(_inline(spec.children, offset))
        else:
            out.append(spec if offset == tuple(spec.offset) else replace(spec, offset=offset))
    return tuple(out)


def _opaque(spec: RenderLayerSpec) -> bool:
    """alpha × mask × opacity is exactly 1 and carries no gradient."""
    t = spec.tensors
    if spec.opacity_value() != 1.0:
        return False
    if t.alpha is None and t.mask is None:
        return True
    return not any(x is not None and x.requires_grad for x in (t.alpha, t.mask)) and t.is_opaque()


def _compile_level(
    entries: tuple[RenderSpec, ...],
    canvas: tuple[int, int],
    blend_space: BlendSpace,
    clamp: ClampPolicy,
    cull: bool,
    opaque_backdrop: bool,
    skipped: dict[str, SkipReason],
) -> tuple[tuple[PlanStep, ...], list[SkipReason | None]]:
    """The live steps of one layer list (entries with canvas offsets) and a skip reason per entry; the
    reasons of this list and of every group inside it go into ``skipped``. ``opaque_backdrop``: the list
    is composited onto an opaque canvas (False inside an isolated group)."""
    H, W = canvas
    n = len(entries)
    reasons: list[SkipReason | None] = [None] * n
    rects: list[tuple[int, int, int, int]] = []
    children: dict[int, tuple[PlanStep, ...]] = {}
    for i, spec in enumerate(entries):
        ox, oy = spec.offset
        rect = (0, 0, 0, 0)
        if not spec.visible:
            reasons[i] = "hidden"
        elif cull and spec.opacity_value() == 0.0:
            reasons[i] = "zero-opacity"
        elif isinstance(spec, RenderGroupSpec) and spec.clip:
            sub, reason = _compile_chain(spec, canvas, blend_space, clamp, cull, skipped)
            if sub:
                rect, children[i] = (sub[0].y0, sub[0].y1, sub[0].x0, sub[0].x1), sub
            else:
                reasons[i] = reason
        elif isinstance(spec, RenderGroupSpec):
            inner = _inline(spec.children, spec.offset)
            opaque_inside = opaque_backdrop and not spec.isolated
            sub, _ = _compile_level(inner, canvas, blend_space, clamp, cull, opaque_inside, skipped)
            if not sub:
                reasons[i] = "empty"
            else:
                rect = (min(s.y0 for s in sub), max(s.y1 for s in sub), min(s.x0 for s in sub), max(s.x1 for s in sub))
                if spec.mask is not None:  # the group shows only inside its mask
                    mh, mw = spec.mask.shape[-2:]
                    rect = (max(rect[0], oy), min(rect[1], oy + mh), max(rect[2], ox), min(rect[3], ox + mw))
                children[i] = sub
        else:
            t = spec.tensors
            rect = (max(0, oy), min(H, oy + t.height), max(0, ox), min(W, ox + t.width))
        rects.append(rect)
        if reasons[i] is None and (rect[0] >= rect[1] or rect[2] >= rect[3]):
            reasons[i] = "outside-canvas"

    opaque_flags = [False] * n
    occluders: list[tuple[int, int, int, int]] = []
    for i in range(n - 1, -1, -1):  # top down: occluders are the opaque normal layers above
        if reasons[i] is not None:
            continue
        spec = entries[i]
        if cull and any(_contains(o, rects[i]) for o in occluders):
            reasons[i] = "occluded"
            continue
        if isinstance(spec, RenderGroupSpec):
            continue  # never an identity by value, never an occluder (conservative)
        if spec.adjust is not None:  # reads its backdrop: an identity only where its mask is 0, never an occluder
            if cull and not spec.requires_grad and spec.tensors.is_transparent():
                reasons[i] = "identity"
                continue
            opaque_flags[i] = _opaque(spec)
            continue
        if cull and not spec.requires_grad:
            # Over transparency only a transparent layer is an identity (see the module docstring).
            identity = spec.tensors.is_identity(spec.blend) if opaque_backdrop else spec.tensors.is_transparent()
            if identity:
                reasons[i] = "identity"
                continue
        opaque_flags[i] = _opaque(spec)
        if opaque_flags[i] and spec.blend == "normal":
            occluders.append(rects[i])

    steps: list[PlanStep] = []
    for i, spec in enumerate(entries):
        if reasons[i] is not None:
            skipped[spec.id] = reasons[i]  # type: ignore[assignment]
            continue
        y0, y1, x0, x1 = rects[i]
        ox, oy = spec.offset
        group = isinstance(spec, RenderGroupSpec)
        adjusting = not group and spec.adjust is not None
        decode = not group and blend_space == "linear" and (adjusting or (spec.encoded and spec.blend != "multiply"))
        clamp_lo = clamp_hi = False
        if clamp == "layer":
            if adjusting:
                clamp_lo = clamp_hi = True  # its colour depends on the backdrop: no bound is proven
            elif group:
                # An isolated group's colour is a quotient c/α (an ulp outside [0, 1] is possible): clamp. A
                # pass-through group mixes two clamped canvases, which stays in range.
                clamp_lo = clamp_hi = spec.isolated
            elif not opaque_backdrop:
                clamp_lo = clamp_hi = True  # over transparency: premultiplied colour kept in [0, α]
            else:
                clamp_lo, clamp_hi = _clamps(spec, decode)
        steps.append(
            PlanStep(
                i,
                spec,  # type: ignore[arg-type]
                y0,
                y1,
                x0,
                x1,
                y0 - oy,
                x0 - ox,
                opaque_flags[i],
                clamp_lo,
                clamp_hi,
                decode,
                (y0, y1, x0, x1) == (0, H, 0, W),
                children.get(i) if group else None,
            )
        )
    return tuple(steps), reasons


def _compile_chain(
    spec: RenderGroupSpec,
    canvas: tuple[int, int],
    blend_space: BlendSpace,
    clamp: ClampPolicy,
    cull: bool,
    skipped: dict[str, SkipReason],
) -> tuple[tuple[PlanStep, ...], SkipReason | None]:
    """The live steps of clipping chain ``spec`` — its base first, then the clipped layers that meet the base's
    rectangle — or ``((), reason)``: a chain whose base is not live shows nothing (the base's reason). The base
    is compiled on its own (a clipped layer above never occludes it: the base's alpha is the chain's), and its
    rectangle, cut by the chain's mask, is the chain's; a clipped layer outside it is skipped ``outside-base``."""
    base, _ = _compile_level(_inline(spec.children[:1], spec.offset), canvas, blend_space, clamp, cull, False, skipped)
    if not base:
        return (), skipped.get(spec.children[0].id, "empty")
    b = base[0]
    y0, y1, x0, x1 = b.y0, b.y1, b.x0, b.x1
    if spec.mask is not None:  # the chain shows only inside its (the base's) mask
        ox, oy = spec.offset
        mh, mw = spec.mask.shape[-2:]
        y0, y1, x0, x1 = max(y0, oy), min(y1, oy + mh), max(x0, ox), min(x1, ox + mw)
        if y0 >= y1 or x0 >= x1:
            return (), "outside-canvas"
        b = replace(b, y0=y0, y1=y1, x0=x0, x1=x1, ly0=b.ly0 + y0 - b.y0, lx0=b.lx0 + x0 - b.x0)
    clipped, _ = _compile_level(
        _inline(spec.children[1:], spec.offset), canvas, blend_space, clamp, cull, False, skipped
    )
    live = []
    for s in clipped:
        if s.y1 <= y0 or y1 <= s.y0 or s.x1 <= x0 or x1 <= s.x0:
            skipped[s.spec.id] = "outside-base"
        else:
            live.append(s)
    return (b, *live), None


def _clamps(spec: RenderLayerSpec, decode: bool) -> tuple[bool, bool]:
    """Which clamps ``clamp="layer"`` needs after this layer (``clamp_needed`` on proven bounds)."""
    t = spec.tensors
    if any(x is not None and x.requires_grad for x in (t.alpha, t.mask)) or (
        isinstance(spec.opacity, Tensor) and spec.opacity.requires_grad
    ):
        return True, True  # α is not proven to lie in [0, 1]
    a_lo, a_hi = t.alpha_range()
    if not (0.0 <= a_lo and a_hi <= 1.0):
        return True, True
    # A learned colour's parametrisation (lo + (hi - lo)·sigmoid) keeps it in its declared range;
    # a fixed colour is measured once (cached).
    if t.color.requires_grad:
        lo, hi = spec.range
    elif t.has_color_range():
        lo, hi = t.color_range()
    else:
        # A sampled value that needs a clamp proves a clamp is needed; clamping both sides then costs
        # the same pass as one side, and the layer's pixels need not be read (an edited layer).
        s_lo, s_hi = t.sample_color_range()
        if decode:
            s_lo, s_hi = _decoded_bound(s_lo), _decoded_bound(s_hi)
        if any(clamp_needed(spec.blend, s_lo, s_hi)):
            return True, True
        lo, hi = t.color_range()
    if decode:
        lo, hi = _decoded_bound(lo), _decoded_bound(hi)
    return clamp_needed(spec.blend, lo, hi)


# ---- document adapter -----------------------------------------------------------------------------


def solid_tensors(
    layer: Any, lo: float, hi: float, width: int, height: int, where: str, dtype: torch.dtype | None = None
) -> LayerTensors:
    """A solid layer's ``LayerTensors`` on a ``width`` × ``height`` canvas (its ``size`` if it has one)."""
    rgba = [float(v) for v in layer.color]
    if len(rgba) not in (3, 4):
        raise LasagnaError(f"color has {len(rgba)} components; expected RGB or RGBA", where=f"{where}.color")
    size = getattr(layer, "size", None)
    h, w = (size.height, size.width) if size is not None else (height, width)
    dtype = dtype or torch.get_default_dtype()
    # RGB is range-mapped like a PNG's values (y = lo + (hi - lo)·v, in float64), alpha never is. Zero-stride
    # views: a solid layer costs no memory however large it is.
    rgb = [lo + (hi - lo) * v for v in rgba[:3]]
    color = torch.tensor(rgb, dtype=dtype).view(3, 1, 1).expand(3, h, w)
    alpha = None
    if len(rgba) == 4 and rgba[3] != 1.0:
        alpha = torch.tensor([rgba[3]], dtype=dtype).view(1, 1, 1).expand(1, h, w)
    return LayerTensors(color, alpha)


def gradient_tensors(
    layer: Any,
    width: int,
    height: int,
    origin: tuple[int, int] = (0, 0),
    mask: Tensor | None = None,
    where: str = "layer",
    dtype: torch.dtype | None = None,
) -> LayerTensors:
    """A gradient layer's ``LayerTensors`` on a ``width`` × ``height`` canvas: its fill (``gradient.gradient_fill``)
    over its rectangle (its ``size``, else the canvas; at ``origin`` plus its offset: ``origin`` is where its
    enclosing groups put it), laid out on that rectangle (``gradient.align``) or on the canvas, and its ``mask``."""
    size = getattr(layer, "size", None)
    h, w = (size.height, size.width) if size is not None else (height, width)
    x0, y0 = origin[0] + int(layer.offset.x), origin[1] + int(layer.offset.y)
    rect = (x0, y0, x0 + w, y0 + h)
    box = rect if layer.gradient.align else (0, 0, width, height)
    if mask is not None and tuple(mask.shape[-2:]) != (h, w):
        raise LasagnaError(
            f"mask is {mask.shape[-1]}x{mask.shape[-2]}; expected the layer's size {w}x{h}", where=f"{where}.mask"
        )
    color, alpha = gradient_fill(layer.gradient.model_dump(), box, rect, dtype)
    return LayerTensors(color, alpha, mask)


def pattern_tensors(
    layer: Any,
    tile: LayerTensors,
    width: int,
    height: int,
    origin: tuple[int, int] = (0, 0),
    where: str = "layer",
    dtype: torch.dtype | None = None,
) -> LayerTensors:
    """A pattern layer's ``LayerTensors`` on a ``width`` × ``height`` canvas: its ``tile`` (the stack's tensors of
    it: the tile's colour and alpha, and the mask of the layer's rectangle) repeated over its rectangle (its ``size``,
    else the canvas; at ``origin`` plus its offset) from that rectangle's corner (``pattern.align``) or the canvas's
    (``pattern.pattern_fill``), and the mask."""
    size = getattr(layer, "size", None)
    h, w = (size.height, size.width) if size is not None else (height, width)
    x0, y0 = origin[0] + int(layer.offset.x), origin[1] + int(layer.offset.y)
    rect = (x0, y0, x0 + w, y0 + h)
    anchor = rect if layer.pattern.align else (0, 0, width, height)
    mask = tile.mask
    if mask is not None and tuple(mask.shape[-2:]) != (h, w):
        raise LasagnaError(
            f"mask is {mask.shape[-1]}x{mask.shape[-2]}; expected the layer's size {w}x{h}", where=f"{where}.mask"
        )
    p = layer.pattern
    color, alpha = pattern_fill(tile.color, tile.alpha, p.scale, p.phase, anchor, rect, dtype)
    return LayerTensors(color, alpha, mask)


def adjustment_tensors(mask: Tensor | None, width: int, height: int, dtype: torch.dtype | None = None) -> LayerTensors:
    """An adjustment layer's ``LayerTensors``: its ``mask`` (``(..., 1, h, w)``, or None: the canvas), and a
    zero-stride colour of that size (an adjustment has no pixels; its colour is computed from the backdrop)."""
    dtype = dtype or (mask.dtype if mask is not None else torch.get_default_dtype())
    h, w = (mask.shape[-2], mask.shape[-1]) if mask is not None else (height, width)
    return LayerTensors(torch.zeros((), dtype=dtype).expand(3, h, w), None, mask)


def plan_from_document(
    doc: Any, tensors: Mapping[str, LayerTensors], *, cull: bool = True, dtype: torch.dtype | None = None
) -> RenderPlan:
    """Compile a ``lasagna.document`` ``Document`` with its loaded pixels into a ``RenderPlan``.

    ``tensors`` maps layer ids to their ``LayerTensors`` (colour already range-mapped, mask loaded
    when the layer names one). ``solid`` layers may be omitted: they are built from their colour
    (RGB range-mapped, alpha not) and size, in ``dtype`` (default: torch's default dtype). A ``learned``
    layer with neither a ``source`` nor tensors has no pixels yet and is left out of the plan (it appears
    neither in ``evaluated`` nor in ``skipped``). A ``group`` becomes a ``RenderGroupSpec`` of its layers; its
    mask, when it names one, is ``tensors[group.id].mask``. Reads the document through its attributes only
    (docs/ARCHITECTURE.md): the compositor imports nothing of the document tier but its blend names.
    """
    width, height = int(doc.canvas.width), int(doc.canvas.height)
    specs = _document_specs(doc.layers, tensors, width, height, dtype, "layers", (0, 0))
    bg = doc.canvas.background
    background = None if bg is None else tuple(float(v) for v in bg)
    return compile_plan(specs, (height, width), background, doc.blend_space, doc.clamp, cull=cull)  # type: ignore[arg-type]


def _document_specs(
    layers: Sequence[Any],
    tensors: Mapping[str, LayerTensors],
    width: int,
    height: int,
    dtype: torch.dtype | None,
    where: str,
    origin: tuple[int, int],
) -> list[RenderSpec]:
    """The compositor's specs of one layer list of a document (recursively for groups; ``origin``: the canvas
    position its offsets are relative to); each clipping chain (a base and the layers with ``clip`` above it)
    becomes one ``clip_chain``."""
    specs: list[RenderSpec] = []
    clips: list[bool] = []  # per spec: the layer is clipped to the one below
    for i, layer in enumerate(layers):
        clips.append(bool(getattr(layer, "clip", False)))
        here = f"{where}[{i}]"
        lt = tensors.get(layer.id)
        blend = getattr(layer.blend, "value", layer.blend)
        common = dict(
            id=layer.id,
            blend=blend,
            opacity=float(layer.opacity),
            visible=bool(layer.visible),
            offset=(int(layer.offset.x), int(layer.offset.y)),
        )
        mask_name = getattr(layer, "mask", None)
        if mask_name is not None and (lt is None or lt.mask is None):
            raise LasagnaError(
                f"names mask {str(mask_name)!r} but tensors[{layer.id!r}].mask is missing; expected the loaded mask",
                where=f"{here}.mask",
            )
        if layer.kind == "adjustment":
            mask = lt.mask if mask_name is not None and lt is not None else None
            adjust = Adjustment(layer.adjustment.type, layer.adjustment.model_dump(exclude={"type"}))
            lt = adjustment_tensors(mask, width, height, dtype)
            specs.append(RenderLayerSpec(tensors=lt, adjust=adjust, **common))
            continue
        if layer.kind == "group":
            inner = (origin[0] + int(layer.offset.x), origin[1] + int(layer.offset.y))
            children = _document_specs(layer.layers, tensors, width, height, dtype, f"{here}.layers", inner)
            mask = lt.mask if mask_name is not None and lt is not None else None
            specs.append(RenderGroupSpec(children=tuple(children), isolated=bool(layer.isolated), mask=mask, **common))
            continue
        if layer.kind == "gradient":  # drawn from its record; its tensors, when it has a mask, hold only the mask
            mask = lt.mask if mask_name is not None and lt is not None else None
            lt = gradient_tensors(layer, width, height, origin, mask, here, dtype)
            specs.append(RenderLayerSpec(tensors=lt, range=(0.0, 1.0), encoded=True, **common))
            continue
        if layer.kind == "pattern" and lt is not None:  # its tensors hold the tile (and its rectangle's mask)
            lt = pattern_tensors(layer, lt, width, height, origin, here, dtype)
            specs.append(RenderLayerSpec(tensors=lt, range=(0.0, 1.0), encoded=True, **common))
            continue
        rng = layer.range
        lo, hi = (rng.lo, rng.hi) if hasattr(rng, "lo") else tuple(rng)
        if lt is None:
            if layer.kind == "solid":
                lt = solid_tensors(layer, float(lo), float(hi), width, height, here, dtype)
            elif layer.kind == "learned" and getattr(layer, "source", None) is None:
                clips.pop()
                continue
            else:
                raise LasagnaError(
                    f"no tensors for {layer.kind} layer {layer.id!r}; expected tensors[{layer.id!r}] "
                    "(load its source first)",
                    where=here,
                )
        if layer.kind == "surface":  # a normal map, rendered to its multiplier under the layer's light
            lt, (lo, hi) = layer_surface_tensors(lt, layer)
        specs.append(RenderLayerSpec(tensors=lt, range=(float(lo), float(hi)), encoded=True, **common))
    chains: list[list[RenderSpec]] = []
    for spec, clipped in zip(specs, clips):
        if clipped and chains:
            chains[-1].append(spec)
        else:
            chains.append([spec])
    return [chain[0] if len(chain) == 1 else clip_chain(chain[0], chain[1:]) for chain in chains]


def clip_chain(base: RenderSpec, clipped: Sequence[RenderSpec]) -> RenderGroupSpec:
    """The clipping chain of ``base`` and the specs ``clipped`` to it (canvas offsets as siblings of ``base``):
    a ``RenderGroupSpec(clip=True)`` at the base's offset with the base's blend, opacity, visibility and mask, whose
    ``children[0]`` is the base without them (normal, opaque, unmasked; a group base is isolated: its clipped
    layers paint on its result, as Photoshop composites a group that has clipping layers)."""
    bx, by = base.offset
    moved = tuple(replace(c, offset=(c.offset[0] - bx, c.offset[1] - by)) for c in clipped)
    if isinstance(base, RenderLayerSpec) and base.adjust is not None:
        # An adjustment has no alpha of its own: its clipped layers paint on its result f(Cb) where the canvas is,
        # and the mask and opacity mix that with the backdrop (psd-tools' _apply_adjustment with clip layers) — a
        # pass-through group of the bare adjustment and the clipped layers.
        t = base.tensors
        bare = replace(
            base,
            tensors=adjustment_tensors(None, t.width, t.height, t.color.dtype),
            opacity=1.0,
            visible=True,
            offset=(0, 0),
        )
        return RenderGroupSpec(
            id=f"{base.id}:clip",
            children=(bare, *moved),
            isolated=False,
            blend="normal",
            opacity=base.opacity,
            visible=base.visible,
            offset=base.offset,
            mask=t.mask,
        )
    if isinstance(base, RenderGroupSpec):
        mask = base.mask
        inner: RenderSpec = replace(
            base, blend="normal", opacity=1.0, visible=True, offset=(0, 0), mask=None, isolated=True
        )
    else:
        t = base.tensors
        mask = t.mask
        bare = t if t.mask is None else LayerTensors(t.color, t.alpha)
        inner = replace(base, tensors=bare, blend="normal", opacity=1.0, visible=True, offset=(0, 0))
    return RenderGroupSpec(
        id=f"{base.id}:clip",
        children=(inner, *moved),
        isolated=True,
        clip=True,
        blend=base.blend,
        opacity=base.opacity,
        visible=base.visible,
        offset=base.offset,
        mask=mask,
    )


__all__ = [
    "RenderLayerSpec",
    "RenderGroupSpec",
    "walk_steps",
    "PlanStep",
    "RenderPlan",
    "SkipReason",
    "compile_plan",
    "plan_from_document",
    "solid_tensors",
    "gradient_tensors",
    "pattern_tensors",
    "adjustment_tensors",
    "clip_chain",
    "BLEND_MODES",
]
