"""A stateful renderer with a prefix cache: after an edit, only the layers from the edit upward are recomputed.

``Renderer(canvas, ...).render(layers)`` compiles the plan, fingerprints every layer — tensor
identity and ``_version`` of colour, alpha, mask and an opacity tensor; opacity value, visibility,
offset, blend, range, ``encoded``; its skip reason and live-step flags; a group's fingerprint covers
its own fields and mask and all of its children's, recursively (a group is one step) — and finds the lowest layer
``k`` whose fingerprint changed. The canvas as it was *before* a layer ``e`` (the composite of layers
``0..e-1``) is a snapshot that stays valid while no layer below ``e`` changes, so the render restarts
from the nearest snapshot at or below ``k``.

Which snapshots are kept:

* before the topmost live layer, always (when the budget allows one canvas): the composite below it
  is built in that buffer and the top layer is blended from it into the returned image, band by
  band (``run_fast``'s switch points) — no clone of the canvas, so editing only the top layer then
  costs one blend: read the cached prefix and the layer, write the image;
* before every layer that has been edited since the renderer was created, most recently edited first.
  Taking one costs a copy of the canvas while passing that layer (made band by band, in cache);
* all within ``cache_bytes`` (default ``DEFAULT_CACHE_BYTES`` = 512 MiB: ten 2048² float32 RGB
  canvases of 48 MiB each); a canvas larger than the budget disables the cache.

Snapshots are plain tensors without autograd history. When layers require grad, only prefixes below
the first such layer are cached (the training case: a learned layer on top of fixed ones costs one
differentiable blend per step). If nothing changed and the previous image was not modified in place,
the previous image is returned again — clone it before writing into it.
"""

from __future__ import annotations

import bisect
import weakref
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from lasagna.compose.engine import canvas_shape, first_grad_step, run_fast
from lasagna.compose.plan import (
    BlendSpace,
    ClampPolicy,
    RenderGroupSpec,
    RenderPlan,
    RenderSpec,
    _check_config,
    compile_plan,
)
from lasagna.compose.render import (
    GradEngine,
    RenderResult,
    check_grad_engine,
    check_out,
    differentiable_tail,
    resolve_dtype,
)
from lasagna.errors import LasagnaError

DEFAULT_CACHE_BYTES = 512 * 2**20


def _spec_tensors(spec: RenderSpec) -> list[Tensor | None]:
    """Every tensor a spec reads (a group's: its mask, opacity and all its children's), in a fixed order."""
    op = spec.opacity if isinstance(spec.opacity, Tensor) else None
    if isinstance(spec, RenderGroupSpec):
        return [spec.mask, op, *(t for c in spec.children for t in _spec_tensors(c))]
    return [*spec.tensors.tensors(), op, *(spec.adjust.tensors() if spec.adjust is not None else ())]


def _tensor_refs(spec: RenderSpec) -> tuple[Any, ...]:
    return tuple(None if t is None else weakref.ref(t) for t in _spec_tensors(spec))


def _spec_fingerprint(spec: RenderSpec) -> tuple[Any, ...]:
    """Everything of a spec that its pixels depend on; a group's covers its children (so editing a child
    invalidates the snapshots above the group)."""
    op = spec.opacity
    op_fp = (id(op), op._version) if isinstance(op, Tensor) else float(op)
    common = (spec.id, spec.blend, spec.visible, tuple(spec.offset), op_fp, spec.requires_grad)
    if isinstance(spec, RenderGroupSpec):
        mask = None if spec.mask is None else (id(spec.mask), spec.mask._version)
        return (*common, "group", spec.isolated, spec.clip, mask, tuple(_spec_fingerprint(c) for c in spec.children))
    adjust = None if spec.adjust is None else spec.adjust.fingerprint()
    return (*common, tuple(spec.range), spec.encoded, spec.tensors.fingerprint(), adjust)


def _step_fingerprint(step: Any) -> tuple[Any, ...] | None:
    if step is None:
        return None
    kids = None if step.children is None else tuple(_step_fingerprint(c) for c in step.children)
    return (step.opaque, step.clamp_lo, step.clamp_hi, step.decode, step.y0, step.y1, step.x0, step.x1, kids)


def _signature(plan: RenderPlan, i: int, step: Any) -> tuple[Any, ...]:
    return (_spec_fingerprint(plan.layers[i]), plan.reasons[i], _step_fingerprint(step))


class Renderer:
    """Render stacks on one canvas repeatedly, reusing cached prefix composites (module docstring)."""

    def __init__(
        self,
        canvas: tuple[int, int],
        background: tuple[float, float, float] = (0.0, 0.0, 0.0),
        blend_space: BlendSpace = "srgb",
        clamp: ClampPolicy = "layer",
        *,
        cull: bool = True,
        dtype: torch.dtype | None = None,
        cache_bytes: int = DEFAULT_CACHE_BYTES,
        grad_engine: GradEngine = "auto",
    ):
        _check_config(canvas, background, blend_space, clamp)
        check_grad_engine(grad_engine, "Renderer")
        if not isinstance(cache_bytes, int) or cache_bytes < 0:
            raise LasagnaError(f"cache_bytes is {cache_bytes!r}; expected a non-negative integer", where="Renderer")
        self.canvas = tuple(canvas)
        self.background = tuple(float(v) for v in background)
        self.blend_space = blend_space
        self.clamp = clamp
        self.cull = cull
        self.dtype = dtype
        self.cache_bytes = cache_bytes
        self.grad_engine = grad_engine
        self.last_recomputed: list[str] = []  # ids of the live layers blended by the last call
        self.last_restart: int = 0  # layer index the last call restarted from (0: from the background)
        self.clear()

    def clear(self) -> None:
        """Drop every cached composite."""
        self._snaps: dict[int, Tensor] = {}
        self._sigs: list[tuple[Any, ...]] = []
        self._refs: list[tuple[Any, ...]] = []
        self._config: tuple[Any, ...] | None = None
        self._edits: dict[int, int] = {}
        self._tick = 0
        self._last: tuple[Tensor, int, RenderResult] | None = None

    @property
    def cached_bytes(self) -> int:
        unique = {id(t): t for t in self._snaps.values()}
        return sum(t.numel() * t.element_size() for t in unique.values())

    def _changed_from(self, sigs: list[tuple[Any, ...]], refs: list[tuple[Any, ...]]) -> int:
        """Index of the lowest layer whose fingerprint differs from the last call's (len if none)."""
        for i in range(min(len(sigs), len(self._sigs))):
            same_tensors = all(
                (r is None and n is None) or (r is not None and n is not None and r() is n())
                for r, n in zip(self._refs[i], refs[i])
            )
            if sigs[i] != self._sigs[i] or not same_tensors:
                return i
        return min(len(sigs), len(self._sigs))

    def render(self, layers: Sequence[RenderSpec], *, out: Tensor | None = None) -> RenderResult:
        """Composite bottom-to-top ``layers``; the same image as ``render(layers, ...)``, usually sooner.

        ``out`` receives the image when no gradient is needed (as in ``render``).
        """
        plan = compile_plan(
            layers,
            self.canvas,
            self.background,
            self.blend_space,
            self.clamp,  # type: ignore[arg-type]
            cull=self.cull,
        )
        dtype = resolve_dtype(plan, self.dtype)
        shape = canvas_shape(plan)
        if out is not None:
            check_out(out, shape, dtype, plan)
        if (shape, dtype, plan.device) != self._config:
            self.clear()
            self._config = (shape, dtype, plan.device)
        steps = plan.steps
        n = len(steps)
        entries = [s.index for s in steps]
        step_of = {s.index: s for s in steps}
        sigs = [_signature(plan, i, step_of.get(i)) for i in range(len(plan.layers))]
        refs = [_tensor_refs(spec) for spec in plan.layers]
        k = self._changed_from(sigs, refs)
        unchanged = k == len(sigs) == len(self._sigs)
        self._tick += 1
        if self._sigs:  # remember which layers get edited: snapshots go below them
            for i in range(k, len(sigs)):
                if i >= len(self._sigs) or sigs[i] != self._sigs[i] or i == k:
                    self._edits[i] = self._tick
        self._sigs, self._refs = sigs, refs
        dropped = [t for e, t in self._snaps.items() if e > k]
        self._snaps = {e: t for e, t in self._snaps.items() if e <= k}
        g = first_grad_step(plan)

        # Nothing changed and the image we returned is untouched: return it again.
        if out is not None and g < n:
            raise LasagnaError("out= was given but the render needs gradients; expected out=None", where="Renderer")
        last = self._last
        if unchanged and g == n and last is not None and last[0]._version == last[1] and out in (None, last[0]):
            self.last_recomputed, self.last_restart = [], len(sigs)
            return self._last[2]

        # Restart from the highest snapshot at or below k: step b is the first one it does not include.
        # (A snapshot above the first learned layer, taken under no_grad, would cut the graph: skip it.)
        start = max((e for e in self._snaps if bisect.bisect_left(entries, e) <= g), default=0)
        b = bisect.bisect_left(entries, start)
        source = self._snaps.get(start) if b > 0 else None
        if source is None:
            start, b = 0, 0

        # Snapshots to keep or take: before the top live layer and before edited layers, within budget.
        nbytes = torch.empty((), dtype=dtype).element_size()
        for d in shape:
            nbytes *= d
        budget = self.cache_bytes // nbytes
        top = entries[-1] if n else -1
        candidates = {e for e in (*self._edits, top) if e > start and b < bisect.bisect_left(entries, e) <= g}
        ranked = sorted(set(self._snaps) | candidates, reverse=True, key=lambda e: (self._edits.get(e, 0), e == top, e))
        keep: list[int] = []
        buffers_used: set[Any] = set()
        for e in ranked:
            ident = id(self._snaps[e]) if e in self._snaps else ("step", bisect.bisect_left(entries, e))
            if ident in buffers_used or len(buffers_used) < budget:
                keep.append(e)
                buffers_used.add(ident)
        for e in [e for e in self._snaps if e not in keep]:
            dropped.append(self._snaps.pop(e))
        new_keys = [e for e in keep if e not in self._snaps]
        switch_of = {e: bisect.bisect_left(entries, e) for e in new_keys}
        switches = sorted(set(switch_of.values()))

        # Dropped snapshots are recycled as buffers (no page faults), unless still in use: kept under
        # another key (two keys can share one buffer) or read as the source. Each is handed out once.
        in_use = {id(t) for t in self._snaps.values()} | ({id(source)} if source is not None else set())
        recyclable = list({id(t): t for t in dropped if id(t) not in in_use}.values())

        def alloc() -> Tensor:
            return recyclable.pop() if recyclable else torch.empty(shape, dtype=dtype, device=plan.device)

        buffer_at: dict[int, Tensor] = {}
        if g == n:
            chain = [alloc() for _ in switches] + [out if out is not None else alloc()]
            run_fast(plan, b, n, dtype, source, chain, switches, post=True)
            buffer_at = dict(zip(switches, chain))
            image = chain[-1]
        else:
            prefix = source
            if b < g:  # constant layers below the first learned one: fast, and cached
                fast_switches = [j for j in switches if j < g]
                chain = [alloc() for _ in fast_switches] + [alloc()]
                run_fast(plan, b, g, dtype, source, chain, fast_switches, post=False)
                buffer_at = dict(zip(fast_switches, chain))
                prefix = buffer_at[g] = chain[-1]
            image = differentiable_tail(plan, g, dtype, prefix, self.grad_engine)
        for e in new_keys:
            if switch_of[e] in buffer_at:
                self._snaps[e] = buffer_at[switch_of[e]]
        result = RenderResult(image, dict(plan.skipped), plan.evaluated)
        self._last = (image, image._version, result) if g == n else None
        self.last_recomputed = [s.spec.id for s in steps[b:]]
        self.last_restart = start
        return result
