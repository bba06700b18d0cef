"""The banded backward: gradients of a composite without recording autograd, band by band.

``BandedGrad`` is an ``autograd.Function``: its forward is ``run_fast`` (the same banded, in-place,
no-graph composite as a render without gradients), and its backward composites each band again,
keeping every layer's backdrop, and runs the output gradient down the stack with closed-form
derivatives (``banded_backward``). It needs a few band-sized buffers instead of the full-canvas
intermediates a recorded graph keeps, and computes channel sums as fused multiply-adds. Same
gradients as ``grad_engine="autograd"`` (tested, and with ``gradcheck``); not twice differentiable.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from lasagna.compose.blend import KERNELS, KERNELS_INPLACE, Alpha, broadcast_shape
from lasagna.compose.color import linear_to_srgb_derivative, srgb_to_linear_derivative
from lasagna.compose.engine import background_tensor, canvas_shape, rows_per_band, run_fast
from lasagna.compose.plan import PlanStep, RenderPlan
from lasagna.compose.step import _alpha, _clamp_, _color

# Band size of the banded backward, shared among the layers whose backdrop it keeps (each keeps a
# band-sized copy). Measured on the 2048² 4-layer stack, every layer learned, clamp=None, forward +
# backward, best of 9: 2^16 → 59.9 ms, 2^17 → 52.6, 2^18 → 50.1, 2^19 → 49.8, 2^20 → 52.6, one band
# for the whole canvas → 59.5 (recording autograd, grad_engine="autograd": 53.4 ms).
BACKWARD_TILE_PIXELS = 1 << 19
# Threads that run bands of the backward at once: 0 = torch's intra-op thread count (``_band_workers``); 1 =
# one band at a time, each op using the intra-op threads (the behaviour before bands ran in parallel).
BACKWARD_BAND_THREADS = 0


def grad_inputs(plan: RenderPlan, begin: int) -> list[Tensor]:
    """Every tensor of ``plan.steps[begin:]`` (colour, alpha, mask, opacity), once each."""
    seen: dict[int, Tensor] = {}
    for step in plan.steps[begin:]:
        t = step.spec.tensors
        for x in (t.color, t.alpha, t.mask, step.spec.opacity):
            if isinstance(x, Tensor):
                seen.setdefault(id(x), x)
    return list(seen.values())


class BandedGrad(torch.autograd.Function):
    """``run_fast`` forward; backward band by band with closed-form derivatives (module docstring).

    ``apply(plan, begin, dtype, source, *grad_inputs(plan, begin))`` composites ``plan.steps[begin:]``
    over ``source`` (the canvas before step ``begin``, a constant; None for the background).
    """

    @staticmethod
    def forward(
        ctx: Any, plan: RenderPlan, begin: int, dtype: torch.dtype, source: Tensor | None, *tensors: Tensor
    ) -> Tensor:
        ctx.plan, ctx.begin, ctx.dtype = plan, begin, dtype
        ctx.has_source = source is not None
        # Saved so that autograd refuses the backward if one of them was modified in place since.
        ctx.save_for_backward(*(((source,) if source is not None else ()) + tensors))
        ctx.originals = tensors  # the plan reads these very objects; ids map them to gradient slots
        image = torch.empty(canvas_shape(plan), dtype=dtype, device=plan.device)
        run_fast(plan, begin, len(plan.steps), dtype, source, [image])
        return image

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        saved = ctx.saved_tensors  # unpacking checks the version counters
        source = saved[0] if ctx.has_source else None
        grads = banded_backward(ctx.plan, ctx.begin, ctx.dtype, source, grad, ctx.originals, ctx.needs_input_grad[4:])
        return (None, None, None, None, *grads)


class _Grads:
    """Gradient buffers, one per input tensor that needs one, filled region by region.

    A tensor read by exactly one step whose clipped rectangle covers all of it gets ``empty_like``
    and each band writes its region once (no zero fill, no read-modify-write); any other tensor gets
    ``zeros_like`` and regions accumulate.
    """

    def __init__(self, plan: RenderPlan, begin: int, tensors: Sequence[Tensor], needs: Sequence[bool]):
        self.tensors = tensors
        self.slot = {id(t): k for k, (t, n) in enumerate(zip(tensors, needs)) if n}
        uses: dict[int, int] = {}
        whole: dict[int, bool] = {}
        for step in plan.steps[begin:]:
            t = step.spec.tensors
            covers = (step.ly0, step.lx0, step.y1 - step.y0, step.x1 - step.x0) == (0, 0, t.height, t.width)
            for x in (t.color, t.alpha, t.mask, step.spec.opacity):
                if isinstance(x, Tensor):
                    uses[id(x)] = uses.get(id(x), 0) + 1
                    whole[id(x)] = covers and x.ndim > 0
        self.write_once = {i for i, n in uses.items() if n == 1 and whole[i]}
        self.out: list[Tensor | None] = [None] * len(tensors)
        # Bands may run in parallel (``banded_backward``) only where the result cannot depend on their order:
        # every gradient element then gets one contribution (a tensor read by one step, not broadcast over
        # rows), except 0-dim tensors (an opacity), whose per-band parts are kept and summed in band order.
        self.band_private = all(
            uses[id(t)] == 1 and t.ndim >= 2 and t.shape[-2] > 1 or t.ndim == 0
            for t, n in zip(tensors, needs)
            if n and id(t) in uses
        )
        self.lock = threading.Lock()
        self.band: Any = threading.local()  # .parts: where this thread defers 0-dim contributions
        self.deferred: list[tuple[int, int, int, Tensor]] = []  # (band, order in band, slot, value)

    def wants(self, t: object) -> bool:
        return isinstance(t, Tensor) and id(t) in self.slot

    def _target(self, t: Tensor, sl: Any) -> tuple[Tensor, bool]:
        k = self.slot[id(t)]
        once = id(t) in self.write_once
        if self.out[k] is None:
            with self.lock:
                if self.out[k] is None:
                    self.out[k] = (torch.empty_like if once else torch.zeros_like)(self.tensors[k])
        return (self.out[k] if sl is None else self.out[k][sl]), once

    def add(self, t: object, sl: Any, g: Tensor) -> None:
        """∂L/∂t[sl] += g, summed over the dimensions g was broadcast over."""
        if not self.wants(t):
            return
        target, once = self._target(t, sl)  # type: ignore[arg-type]
        if g.shape != target.shape:
            g = g.sum_to_size(target.shape)
        parts = getattr(self.band, "parts", None)
        if parts is not None and target.ndim == 0:  # a parallel band: summed in band order at the end
            parts.append((self.slot[id(t)], g.clone()))
            return
        target.copy_(g) if once else target.add_(g)

    def start_band(self) -> None:
        self.band.parts = []

    def end_band(self, index: int) -> None:
        with self.lock:
            self.deferred += [(index, n, k, g) for n, (k, g) in enumerate(self.band.parts)]
        self.band.parts = None

    def finish(self) -> None:
        """Add the deferred 0-dim parts in band order: the same additions, in the same order, as one thread."""
        for _, _, k, g in sorted(self.deferred, key=lambda d: (d[0], d[1])):
            self.out[k].add_(g)  # type: ignore[union-attr]
        self.deferred = []

    def add_product(self, t: object, sl: Any, x: Tensor, y: Tensor | float) -> None:
        """∂L/∂t[sl] += x·y, fused (``mul(out=)``/``addcmul_``) when no reduction is needed."""
        if not self.wants(t):
            return
        target, once = self._target(t, sl)  # type: ignore[arg-type]
        if target.ndim == 0:
            return self.add(t, sl, x * y)
        fused = isinstance(y, Tensor) and target.dtype == x.dtype
        if fused and broadcast_shape(x.shape, y.shape) == tuple(target.shape):  # type: ignore[union-attr]
            torch.mul(x, y, out=target) if once else target.addcmul_(x, y)
        else:
            self.add(t, sl, x * y)


class _Workspace:
    """Band-sized buffers reused from band to band: no allocator round trip, no page faults.

    ``ws(key, shape)`` returns a buffer of ``shape`` (rows in dimension -2 may shrink for the last
    band); the caller must be done with a key's previous contents before asking for it again.
    """

    def __init__(self, dtype: torch.dtype, device: torch.device):
        self.dtype, self.device = dtype, device
        self.bufs: dict[Any, Tensor] = {}

    def __call__(self, key: Any, shape: Sequence[int], dtype: torch.dtype | None = None) -> Tensor:
        dtype = dtype or self.dtype
        shape = tuple(shape)
        buf = self.bufs.get(key)
        if (
            buf is None
            or buf.dtype != dtype
            or buf.ndim != len(shape)
            or buf.shape[:-2] != shape[:-2]
            or buf.shape[-1] != shape[-1]
            or buf.shape[-2] < shape[-2]
        ):
            buf = self.bufs[key] = torch.empty(shape, dtype=dtype, device=self.device)
        return buf[..., : shape[-2], :]


def _blend_into(blend: str, cb: Tensor, cs: Tensor, a: Alpha, out: Tensor) -> Tensor:
    """``KERNELS[blend](cb, cs, a)`` written into ``out`` (same kernels, so the same values)."""
    if blend == "normal":
        return out.copy_(cs) if a is None else torch.lerp(cb, cs, a, out=out)
    if blend == "multiply":
        return torch.mul(cb, cs if a is None else torch.mul(cs - 1.0, a).add_(1.0), out=out)
    if blend == "screen":
        s = cs if a is None else cs * a
        return torch.mul(cb, 1.0 - s, out=out).add_(s)
    if blend != "plus":  # the W3C modes: B out of place, then the same lerp as the kernel
        return out.copy_(KERNELS[blend](cb, cs, a))
    if a is None:
        return torch.add(cb, cs, out=out)
    if isinstance(a, Tensor):
        return torch.addcmul(cb, cs, a, out=out)
    return torch.add(cb, cs, alpha=a, out=out)


def _needs_cb(step: PlanStep) -> bool:
    return step.blend != "plus" and not (step.blend == "normal" and step.opaque)


def banded_backward(
    plan: RenderPlan,
    begin: int,
    dtype: torch.dtype,
    source: Tensor | None,
    grad: Tensor,
    tensors: Sequence[Tensor],
    needs: Sequence[bool],
) -> list[Tensor | None]:
    """Gradients of ``plan.steps[begin:]``'s composite w.r.t. ``tensors`` (where ``needs``), given ``grad``.

    Band by band: the band is composited again, out of place, keeping each layer's backdrop ``Cb``
    (and both sides of each clamp), then the output gradient ``g`` runs down the stack. With
    ``α = alpha·mask·opacity``, per blend (sums over channels a 1-channel input was broadcast over):

    normal    ∂Cs = α g,                 ∂α = Σ g (Cs − Cb),      ∂Cb = (1 − α) g   (α None: ∂Cs = g, ∂Cb = 0)
    multiply  f = 1 + α(Cs − 1): ∂f = Σ g Cb,  ∂Cs = α ∂f,  ∂α = (Cs − 1) ∂f,   ∂Cb = f g
    screen    s = αCs:           ∂s = g (1 − Cb),  ∂Cs = α ∂s,  ∂α = Σ Cs ∂s,   ∂Cb = (1 − s) g
    plus      ∂Cs = α g,                 ∂α = Σ g Cs,             ∂Cb = g
    others    (the W3C modes computed as lerp(Cb, B(Cb, Cs), α)): the vector–Jacobian product of
              that very kernel, by autograd on the band's tensors (``_local_vjp``) — the same
              function as ``grad_engine="autograd"`` differentiates, so the same subgradients

    then ∂alpha = ∂α·mask·opacity, ∂mask = ∂α·alpha·opacity, ∂opacity = Σ ∂α·alpha·mask; a decoded
    colour multiplies by the sRGB decode's derivative; a clamp passes ``g`` where it changed nothing
    (both bounds inclusive, as ``torch.clamp``'s own derivative).
    """
    grads = _Grads(plan, begin, tensors, needs)
    steps = plan.steps[begin:]

    def wants(step: PlanStep) -> bool:
        t = step.spec.tensors
        return any(grads.wants(x) for x in (t.color, t.alpha, t.mask, step.spec.opacity))

    if not any(wants(s) for s in steps):
        return grads.out
    lowest = min(j for j, s in enumerate(steps) if wants(s))
    # The forward is needed up to the last layer whose backdrop or clamp the derivatives read (all of
    # them when the output is clamped or encoded).
    upto = (
        len(steps) - 1
        if plan.clamp == "output" or plan.blend_space == "linear"
        else max(
            [j for j, s in enumerate(steps) if j >= lowest and (_needs_cb(s) or s.clamp_lo or s.clamp_hi)], default=-1
        )
    )
    H, W = plan.canvas
    shape = canvas_shape(plan)
    # Every layer keeps a band-sized backdrop: share the band budget among them.
    rows = rows_per_band(plan, max(W, BACKWARD_TILE_PIXELS // max(1, sum(1 for s in steps if _needs_cb(s)))))
    bands = list(range(0, H, rows))

    def band(r0: int, ws: _Workspace) -> None:
        with torch.no_grad():  # grad mode is per thread
            _backward_band(plan, steps, dtype, source, grad, grads, r0, min(H, r0 + rows), shape, lowest, upto, ws)

    workers = _band_workers(plan, len(bands), grads)
    if workers == 1:
        ws = _Workspace(dtype, plan.device)
        for r0 in bands:
            band(r0, ws)
        return grads.out
    # Bands in parallel, one intra-op thread each: the band ops are many and small, and parallelise better
    # across bands than inside each op (BENCHMARKS.md, Compositing). Results are bit-identical to one thread.
    local = threading.local()

    def run(index: int) -> None:
        if getattr(local, "ws", None) is None:
            local.ws = _Workspace(dtype, plan.device)
        grads.start_band()
        band(bands[index], local.ws)
        grads.end_band(index)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(workers, thread_name_prefix="lasagna-backward") as pool:
            list(pool.map(run, range(len(bands))))
    finally:
        torch.set_num_threads(threads)
    grads.finish()
    return grads.out


def _band_workers(plan: RenderPlan, n_bands: int, grads: _Grads) -> int:
    """Threads for the bands: torch's intra-op thread count on a CPU (1 on other devices, or when the
    result could depend on the order of the bands: ``_Grads.band_private``), at most one per band."""
    if plan.device.type != "cpu" or not grads.band_private or BACKWARD_BAND_THREADS == 1:
        return 1
    return max(1, min(torch.get_num_threads(), n_bands, BACKWARD_BAND_THREADS or n_bands))


def _backward_band(
    plan: RenderPlan,
    steps: Sequence[PlanStep],
    dtype: torch.dtype,
    source: Tensor | None,
    grad: Tensor,
    grads: _Grads,
    r0: int,
    r1: int,
    shape: tuple[int, ...],
    lowest: int,
    upto: int,
    ws: _Workspace,
) -> None:
    """Rows [r0, r1) of ``banded_backward``: the band's forward again, then its gradients down the stack."""
    W = plan.canvas[1]
    band = (*shape[:-2], r1 - r0, W)
    cur = source[..., r0:r1, :] if source is not None else background_tensor(plan, dtype).expand(band)
    owned = False  # may cur be written in place (a buffer of ours that no layer keeps)?
    # 1. the band's forward again, keeping what the derivatives read: each layer's backdrop and
    #    where its clamp changed a value. A backdrop is never written afterwards: full-band
    #    steps write a new buffer, partial ones write in place only into a canvas buffer of
    #    our own, after copying the backdrop region.
    kept = []
    for j, step in enumerate(steps):
        if step.y0 >= r1 or step.y1 <= r0:
            continue
        a0, a1 = max(step.y0, r0), min(step.y1, r1)
        sl = step.layer_slice(a0, a1)
        cs, a = _color(step, sl, dtype, False), _alpha(step, sl, dtype, False)
        full = a0 == r0 and a1 == r1 and step.x0 == 0 and step.x1 == W
        cb = clamped = None
        if j > upto:
            pass  # nothing above reads this layer's output
        elif full:
            cb = cur
            if step.opaque and step.blend == "normal":
                cur, owned = cs.expand(band), False
            else:
                cur, owned = _blend_into(step.blend, cb, cs, a, ws(("out", j), band)), True
            if step.clamp_lo or step.clamp_hi:
                clamped, cur = cur, _clamp_into(cur, step, ws(("clamped", j), band))
        else:
            if not owned:
                cur, owned = ws(("own", j), band).copy_(cur), True
            region = cur[..., a0 - r0 : a1 - r0, step.x0 : step.x1]
            cb = ws(("cb", j), region.shape).copy_(region) if j >= lowest and _needs_cb(step) else None
            KERNELS_INPLACE[step.blend](region, cs, a)
            if step.clamp_lo or step.clamp_hi:
                clamped = ws(("pre", j), region.shape).copy_(region)
                _clamp_(region, step)
        kept.append((j, step, a0, a1, sl, cs, a, cb if j >= lowest else None, clamped, full))
    # 2. the output's derivative: clamp, then encode. g is a buffer of ours, modified in place.
    g = ws("g", band).copy_(grad[..., r0:r1, :])
    if plan.blend_space == "linear":
        post = torch.clamp(cur, 0.0, 1.0, out=ws("post", band)) if plan.clamp == "output" else cur
        g.mul_(linear_to_srgb_derivative(post))
    if plan.clamp == "output":
        _clamp_grad_(g, cur, True, True)
    # 3. down the stack
    for j, step, a0, a1, sl, cs, a, cb, clamped, full in reversed(kept):
        if j < lowest:
            break
        gr = g if full else g[..., a0 - r0 : a1 - r0, step.x0 : step.x1]
        if clamped is not None:  # the values before this layer's clamp
            _clamp_grad_(gr, clamped, step.clamp_lo, step.clamp_hi)
        _step_backward(step, sl, dtype, gr, cs, a, cb, grads, j > lowest, ws)


def _clamp_grad_(g: Tensor, pre: Tensor, lo: bool, hi: bool) -> None:
    """g ← g where the clamp to [0, 1] of ``pre`` changed nothing (bounds inclusive, as ``torch.clamp``'s
    derivative), else 0 — one fused pass: ``hardtanh_backward`` zeroes ``pre ≤ min`` and ``pre ≥ max``,
    so the bounds are the neighbours of 0 and 1 in the dtype (x ≤ −tiny ⇔ x < 0, x ≥ 1⁺ ⇔ x > 1)."""
    lo_v, hi_v = _clamp_grad_bounds(pre.dtype)
    torch.ops.aten.hardtanh_backward.grad_input(
        g, pre, lo_v if lo else -float("inf"), hi_v if hi else float("inf"), grad_input=g
    )


_BOUNDS: dict[torch.dtype, tuple[float, float]] = {}


def _clamp_grad_bounds(dtype: torch.dtype) -> tuple[float, float]:
    if dtype not in _BOUNDS:
        zero, one = torch.zeros((), dtype=dtype), torch.ones((), dtype=dtype)
        _BOUNDS[dtype] = (float(torch.nextafter(zero, -one)), float(torch.nextafter(one, one + one)))
    return _BOUNDS[dtype]


def _clamp_into(x: Tensor, step: PlanStep, out: Tensor) -> Tensor:
    lo = 0.0 if step.clamp_lo else None
    hi = 1.0 if step.clamp_hi else None
    return torch.clamp(x, lo, hi, out=out)


def _channel_dot(x: Tensor, y: Tensor | float, shape: tuple[int, ...], out: Tensor | None = None) -> Tensor:
    """Σ x·y over the dimensions ``shape`` does not keep (x·y reduced to ``shape``).

    A sum over the channels of ``(..., 3, h, w)`` runs as two fused multiply-adds on planes
    (``addcmul_``): PyTorch's reduction over that outer dimension is several times slower.
    """
    if not isinstance(y, Tensor):
        x, y = x * y, None
    full = tuple(x.shape) if y is None else broadcast_shape(x.shape, y.shape)
    if (
        len(shape) == len(full)
        and len(full) >= 3
        and shape[-3] == 1
        and full[-3] == 3
        and tuple(shape[:-3]) == full[:-3]
        and tuple(shape[-2:]) == full[-2:]
    ):

        def plane(t: Tensor, c: int) -> Tensor:
            return t[..., c if t.shape[-3] == 3 else 0, :, :]

        o = None if out is None else out[..., 0, :, :]
        if y is None:
            o = torch.add(plane(x, 0), plane(x, 1), out=o)
            o.add_(plane(x, 2))
        else:
            o = torch.mul(plane(x, 0), plane(y, 0), out=o)
            o.addcmul_(plane(x, 1), plane(y, 1))
            o.addcmul_(plane(x, 2), plane(y, 2))
        return o.unsqueeze(-3)
    prod = x if y is None else x * y
    return prod if tuple(prod.shape) == tuple(shape) else prod.sum_to_size(shape)


def _step_backward(
    step: PlanStep,
    sl: Any,
    dtype: torch.dtype,
    gr: Tensor,
    cs: Tensor,
    a: Alpha,
    cb: Tensor | None,
    grads: _Grads,
    need_cb: bool,
    ws: _Workspace,
) -> None:
    """Accumulate one layer's gradients from ``gr`` (∂L/∂output on its region, a buffer of ours) and
    turn ``gr`` into ∂L/∂Cb in place (when ``need_cb``: a layer below needs it)."""
    t, op = step.spec.tensors, step.spec.opacity
    need_cs = grads.wants(t.color)
    # dissolve's α is a step of alpha × mask × opacity (blend.dissolve_alpha): no gradient reaches them.
    need_a = step.blend != "dissolve" and any(grads.wants(x) for x in (t.alpha, t.mask, op))
    blend = step.blend
    g_a: Tensor | None = None
    color_shape = (*t.color[sl].shape,) if need_cs else ()

    def cs_grad(x: Tensor, y: Tensor | float | None = None) -> None:
        if step.decode:  # ∂L/∂colour = ∂L/∂Cs · decode'(colour)
            dec = srgb_to_linear_derivative(t.color[sl].to(dtype))
            grads.add(t.color, sl, _channel_dot(x, 1.0 if y is None else y, tuple(dec.shape)) * dec)
        elif y is None:
            grads.add(t.color, sl, _channel_dot(x, 1.0, color_shape) if x.shape != color_shape else x)
        elif isinstance(y, Tensor) and broadcast_shape(x.shape, y.shape) == color_shape:
            grads.add_product(t.color, sl, x, y)
        else:
            grads.add(t.color, sl, _channel_dot(x, y, color_shape))

    def alpha_shape(like: Tensor) -> tuple[int, ...]:
        return _alpha_shape(like, a)

    def temp(key: str, *shapes: Sequence[int]) -> Tensor:
        return ws(key, broadcast_shape(*shapes))

    if blend == "normal":
        if a is None:
            if need_cs:
                cs_grad(gr)
            if need_cb:
                gr.zero_()
        else:
            if need_cs:
                cs_grad(gr, a)
            if need_a:
                diff = torch.sub(cs, cb, out=temp("diff", cs.shape, cb.shape))
                g_a = _channel_dot(gr, diff, alpha_shape(gr), out=temp("g_a", alpha_shape(gr)))
            if need_cb:  # (1 − α) g = g − α g
                gr.addcmul_(gr, a if isinstance(a, Tensor) else torch.tensor(a, dtype=dtype), value=-1.0)
    elif blend == "multiply":
        f = cs if a is None else torch.mul(cs - 1.0, a).add_(1.0)
        if need_cs or need_a:
            f_shape = broadcast_shape(f.shape, (*gr.shape[:-3], 1, *gr.shape[-2:]))
            g_f = _channel_dot(gr, cb, f_shape, out=temp("g_f", f_shape))
            if a is None:
                cs_grad(g_f)
            else:
                if need_cs:
                    cs_grad(g_f, a)
                if need_a:
                    g_a = _channel_dot(g_f, cs - 1.0, alpha_shape(g_f), out=temp("g_a", alpha_shape(g_f)))
        if need_cb:
            gr.mul_(f)
    elif blend == "screen":
        s = cs if a is None else cs * a
        if need_cs or need_a:
            g_s = torch.mul(cb, -1.0, out=temp("diff", cb.shape)).add_(1.0).mul_(gr)  # g (1 − Cb)
            if need_cs:
                cs_grad(g_s) if a is None else cs_grad(g_s, a)
            if need_a and a is not None:
                g_a = _channel_dot(g_s, cs, alpha_shape(g_s), out=temp("g_a", alpha_shape(g_s)))
        if need_cb:
            gr.mul_(1.0 - s)
    elif blend != "plus":
        g_a = _local_vjp(blend, gr, cs, a, cb, cs_grad if need_cs else None, need_a, need_cb, alpha_shape(gr))
    else:  # plus: ∂Cb = g unchanged
        if need_cs:
            cs_grad(gr) if a is None else cs_grad(gr, a)
        if need_a and a is not None:
            g_a = _channel_dot(gr, cs, alpha_shape(gr), out=temp("g_a", alpha_shape(gr)))
    if g_a is not None:
        opv = op.detach().to(dtype) if isinstance(op, Tensor) else float(op)
        alpha = None if t.alpha is None else t.alpha[sl].to(dtype)
        mask = None if t.mask is None else t.mask[sl].to(dtype)
        if alpha is not None:
            grads.add_product(t.alpha, sl, g_a, opv if mask is None else mask * opv)
        if mask is not None:
            grads.add_product(t.mask, sl, g_a, opv if alpha is None else alpha * opv)
        if isinstance(op, Tensor):
            am = alpha if mask is None else (mask if alpha is None else alpha * mask)
            grads.add(op, None, g_a if am is None else g_a * am)


def _local_vjp(
    blend: str,
    gr: Tensor,
    cs: Tensor,
    a: Alpha,
    cb: Tensor,
    cs_grad: Any,
    need_a: bool,
    need_cb: bool,
    a_shape: tuple[int, ...],
) -> Tensor | None:
    """One W3C-mode layer's derivatives on a band by autograd through its kernel: ∂Cs goes to
    ``cs_grad``, ``gr`` becomes ∂Cb in place (when ``need_cb``), and ∂α (per pixel, ``a_shape``) is
    returned when ``need_a``. The graph spans this one blend of one band, never the stack."""
    leaves: list[Tensor] = []
    with torch.enable_grad():
        cs_l = cs.detach().requires_grad_(cs_grad is not None)
        cb_l = cb.detach().requires_grad_(need_cb)
        a_l: Alpha = a
        if need_a and a is not None:
            a_t = a if isinstance(a, Tensor) else torch.tensor(a, dtype=gr.dtype, device=gr.device)
            a_l = a_t.detach().expand(a_shape).clone().requires_grad_()
        elif isinstance(a, Tensor):
            a_l = a.detach()
        leaves = [x for x in (cs_l, cb_l, a_l) if isinstance(x, Tensor) and x.requires_grad]
        if not leaves:
            return None
        out = KERNELS[blend](cb_l, cs_l, a_l)
        # allow_unused: an opaque dissolve layer (normal, α = None) does not read Cb, whose gradient is then 0.
        got = torch.autograd.grad(out, leaves, gr, allow_unused=True)
        grads = {id(x): torch.zeros_like(x) if g is None else g for x, g in zip(leaves, got)}
    if cs_grad is not None:
        cs_grad(grads[id(cs_l)])
    if need_cb:
        gr.copy_(grads[id(cb_l)])
    return grads.get(id(a_l)) if need_a and a is not None else None


def _alpha_shape(g: Tensor, a: Alpha) -> tuple[int, ...]:
    """The shape ∂α reduces to: α's own (1 channel) where α is a tensor, a per-pixel map otherwise."""
    if isinstance(a, Tensor) and a.ndim >= 3:
        return broadcast_shape(a.shape, (*g.shape[:-3], 1, *g.shape[-2:]))
    return (*g.shape[:-3], 1, *g.shape[-2:])
