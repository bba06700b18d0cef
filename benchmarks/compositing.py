"""Compositing benchmark: the compose tier against Pillow, a memory copy, culling, the prefix cache,
autograd, and precision per dtype. Plain script; ends with one JSON line.

    python benchmarks/compositing.py                # 2048² (about 1-2 minutes)
    python benchmarks/compositing.py --quick        # 512², small precision table (< 30 s)

The 4-layer stack: base RGB → multiply by a 1-channel luminosity layer → normal RGBA → plus RGB,
every value on the 8-bit grid (k/255) so Pillow composes exactly the same inputs. Layer tensors and
Pillow images are built before timing. Ratios (smaller is better for us):

composite_vs_pillow   render(plan, out=buffer), float32, vs Pillow's uint8 chain ImageChops.multiply →
                      Image.alpha_composite → ImageChops.add on RGBA images (alpha 255 where opaque,
                      the multiplier pre-expanded to RGBA: the fastest form Pillow accepts)
composite_vs_memcpy   the same render vs ``dst.copy_(src)`` of as many bytes as the render's inputs and
                      output together (3+1+3+1+3 input channels + 3 output channels, float32)
culled64_vs_live4     a 64-layer stack (the 4 live layers + 60 hidden / zero-opacity / identity /
                      occluded ones) vs the 4 live layers alone, both compiled from layers on every call
top_edit_vs_full      Renderer re-render after an in-place edit of the top layer vs a plain full
                      render(plan); both allocate their output
backward_vs_forward   forward + backward with every layer tensor (and the normal layer's opacity)
                      requiring grad, clamp=None, as a training step runs it (gradients cleared
                      first, as optimizer.zero_grad() does), vs the no-grad forward with a fresh output;
                      the default grad_engine ("auto"), with ``_banded`` and ``_autograd_engine`` apart
top_edit32_vs_full    on a 32-layer stack (``random_stack``) at the same size: Renderer re-render after an
                      in-place edit of the top layer vs a full render (the prefix cache keeps 31 layers),
                      both into a preallocated ``out=`` (as composite_vs_pillow): a fresh 48 MiB output
                      costs this VM 5–35 ms of page zeroing that swings from call to call
                      (``top_edit32_fresh_vs_full``: both allocating)
modes_vs_pillow       a stack of the base and one opaque full-canvas layer per blend mode Pillow has
                      (ImageChops multiply, screen, overlay, darker, lighter, hard_light, soft_light,
                      difference, add; Image.alpha_composite for normal RGBA) vs Pillow's chain of the same
                      uint8 images; ``mode_ms`` gives each of the 17 modes' cost over the base alone
modes_vs_pillow_fused the same stack with ``set_fused(True)`` (``lasagna.compose.fused``: the W3C modes
                      compiled by torch.compile), steady state; ``mode_compile_s_fused`` gives each mode's
                      first call (the compile; inductor's on-disk cache makes repeats fast) apart, and
                      ``mode_ms_fused`` its cost over the base
adjust10_vs_normal10  a stack of the base and ten full-canvas adjustment layers (levels, curves, hue/saturation,
                      brightness/contrast, exposure, channel mixer, color balance, vibrance, gradient map, photo
                      filter; opacity 0.8, blend normal) vs the base and ten full-canvas RGB normal layers of
                      opacity 0.8, both rendered into a preallocated ``out=``; ``adjust_ms`` gives each
                      adjustment's cost over the base
fresh_modes_vs_heap_system  a fresh Python process rendering base + overlay + soft-light + hue with
                      lasagna's heap thresholds (``lasagna.heap``) vs with glibc's defaults
                      (``LASAGNA_HEAP=system``): what one ``lasagna composite`` call sees

The script sets THP_MEM_ALLOC_ENABLE=1 before importing torch (PyTorch's switch to back large CPU
allocations with transparent huge pages): a fresh 48 MiB output otherwise costs ~20 ms of page faults.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from PIL import Image, ImageChops  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import machine_info, median_time, print_json_line  # noqa: E402

from lasagna.compose import LayerTensors, Renderer, RenderLayerSpec, compile_plan, render  # noqa: E402

DTYPES = {"float64": torch.float64, "float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}


# ---- stacks --------------------------------------------------------------------------------------


def grid(g: torch.Generator, *shape: int, top: int = 255) -> torch.Tensor:
    """Random values on the 8-bit grid k/255 (k ≤ top), float32."""
    return torch.randint(0, top + 1, shape, generator=g, dtype=torch.int32).float().div_(255.0)


def four_layers(size: int, seed: int = 0) -> list[RenderLayerSpec]:
    g = torch.Generator().manual_seed(seed)
    return [
        RenderLayerSpec(id="base", tensors=LayerTensors(grid(g, 3, size, size))),
        RenderLayerSpec(id="shade", blend="multiply", tensors=LayerTensors(grid(g, 1, size, size))),
        RenderLayerSpec(id="tint", tensors=LayerTensors(grid(g, 3, size, size), grid(g, 1, size, size))),
        RenderLayerSpec(id="light", blend="plus", tensors=LayerTensors(grid(g, 3, size, size, top=64))),
    ]


def random_stack(n: int, size: int, seed: int) -> list[RenderLayerSpec]:
    """Base + n-1 full-canvas layers cycling through normal RGBA, multiply 1-ch, screen RGB, plus RGB."""
    g = torch.Generator().manual_seed(seed)
    layers = [RenderLayerSpec(id="base", tensors=LayerTensors(grid(g, 3, size, size)))]
    for i in range(1, n):
        kind = ("normal", "multiply", "screen", "plus")[i % 4]
        if kind == "normal":
            t = LayerTensors(grid(g, 3, size, size), grid(g, 1, size, size, top=96))
        elif kind == "multiply":  # mostly bright factors, so 256 layers do not all go black
            t = LayerTensors(1.0 - grid(g, 1, size, size, top=12))
        else:
            t = LayerTensors(grid(g, 3, size, size, top=10))
        layers.append(RenderLayerSpec(id=f"l{i}", blend=kind, tensors=t))
    return layers


def cast(layers: list[RenderLayerSpec], dtype: torch.dtype) -> list[RenderLayerSpec]:
    out = []
    for s in layers:
        t = s.tensors
        conv = [None if x is None else x.to(dtype) for x in (t.color, t.alpha, t.mask)]
        out.append(RenderLayerSpec(id=s.id, blend=s.blend, opacity=s.opacity, tensors=LayerTensors(*conv)))
    return out


def culled_64(live: list[RenderLayerSpec], size: int) -> list[RenderLayerSpec]:
    """The 4 live layers plus 15 each of occluded (below the opaque base), hidden, zero-opacity, identity."""
    g = torch.Generator().manual_seed(1)
    quarter = size // 4
    layers = [
        RenderLayerSpec(
            id=f"occluded{i}", offset=(i * 7 % size, i * 13 % size), tensors=LayerTensors(grid(g, 3, quarter, quarter))
        )
        for i in range(15)
    ]
    layers.append(live[0])
    extra = []
    for i in range(15):
        extra.append(
            RenderLayerSpec(id=f"hidden{i}", visible=False, tensors=LayerTensors(grid(g, 3, quarter, quarter)))
        )
        extra.append(RenderLayerSpec(id=f"zero{i}", opacity=0.0, tensors=LayerTensors(grid(g, 3, quarter, quarter))))
    ones = torch.ones(1, size, size)
    zeros = torch.zeros(3, size // 2, size // 2)
    for i in range(5):
        extra.append(RenderLayerSpec(id=f"times_one{i}", blend="multiply", tensors=LayerTensors(ones.clone())))
        extra.append(
            RenderLayerSpec(
                id=f"plus_zero{i}", blend="plus", offset=(i * 11, i * 3), tensors=LayerTensors(zeros.clone())
            )
        )
        extra.append(
            RenderLayerSpec(
                id=f"transparent{i}",
                tensors=LayerTensors(grid(g, 3, quarter, quarter), torch.zeros(1, quarter, quarter)),
            )
        )
    # Interleave the 45 no-op layers between the 3 live layers above the base.
    for k, spec in enumerate(live[1:]):
        layers.extend(extra[k * 15 : (k + 1) * 15])
        layers.append(spec)
    assert len(layers) == 64
    return layers


# ---- Pillow --------------------------------------------------------------------------------------


def to_rgba(t: LayerTensors) -> Image.Image:
    """A layer as the RGBA uint8 image Pillow composes (1 channel expanded to RGB, alpha 255 if none)."""
    c = np.rint(t.color.double().numpy() * 255).astype(np.uint8)
    c = np.broadcast_to(c, (3, *c.shape[1:]))
    if t.alpha is None:
        a = np.full((1, *c.shape[1:]), 255, np.uint8)
    else:
        a = np.rint(t.alpha.double().numpy() * 255).astype(np.uint8)
    return Image.fromarray(np.ascontiguousarray(np.concatenate([c, a]).transpose(1, 2, 0)), "RGBA")


def pillow_chain(layers: list[RenderLayerSpec]):
    images = [(s.blend, to_rgba(s.tensors)) for s in layers]
    ops = {
        "normal": Image.alpha_composite,
        "multiply": ImageChops.multiply,
        "plus": ImageChops.add,
        "screen": ImageChops.screen,
    }

    def run() -> Image.Image:
        img = images[0][1]
        for blend, im in images[1:]:
            img = ops[blend](img, im)
        return img

    return run


def pillow_float(img: Image.Image) -> torch.Tensor:
    return torch.from_numpy(np.asarray(img)[..., :3].transpose(2, 0, 1) / 255.0)


# ---- measurements --------------------------------------------------------------------------------


def precision_rows(n: int, size: int, repeats: int) -> list[dict]:
    layers = random_stack(n, size, seed=n)
    ref = render(cast(layers, torch.float64), canvas=(size, size)).image
    ref_q = torch.round(ref * 255)
    rows = []
    for name, dtype in DTYPES.items():
        plan = compile_plan(cast(layers, dtype), (size, size))
        out = torch.empty(3, size, size, dtype=dtype)
        t = median_time(lambda: render(plan, out=out), repeats)  # noqa: B023 (called at once)
        img = render(plan).image.double()
        rows.append(
            dict(
                layers=n,
                canvas=size,
                dtype=name,
                seconds=t,
                max_abs_err=(img - ref).abs().max().item(),
                max_levels_off=(torch.round(img.clamp(0, 1) * 255) - ref_q).abs().max().item(),
            )
        )
    run = pillow_chain(layers)
    t = median_time(run, repeats)
    img = pillow_float(run())
    rows.append(
        dict(
            layers=n,
            canvas=size,
            dtype="pillow-uint8",
            seconds=t,
            max_abs_err=(img - ref).abs().max().item(),
            max_levels_off=(torch.round(img * 255) - ref_q).abs().max().item(),
        )
    )
    return rows


def plot_precision(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lasagna.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    markers = {"float64": "o", "float32": "s", "bfloat16": "^", "float16": "v", "pillow-uint8": "D"}
    colours = {4: "tab:blue", 32: "tab:orange", 256: "tab:green"}
    for r in rows:
        ax.scatter(
            r["seconds"] * 1e3,
            max(r["max_abs_err"], 1e-9),
            marker=markers[r["dtype"]],
            color=colours.get(r["layers"], "k"),
            s=50,
        )
    for dt, m in markers.items():
        ax.scatter([], [], marker=m, color="gray", label=dt)
    for n, c in colours.items():
        size = next((r["canvas"] for r in rows if r["layers"] == n), "?")
        ax.scatter([], [], marker="o", color=c, label=f"{n} layers, {size}²")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per composite (ms, median)")
    ax.set_ylabel("max |error| vs float64 (float64 itself drawn at 1e-9)")
    threads = torch.get_num_threads()
    ax.set_title(f"Compositing precision vs time ({threads} CPU thread{'s' if threads > 1 else ''})")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def measure_threads(plan, out, reps: int, res: dict) -> None:
    """Measure 1 and 2 threads once on the forward composite; keep the faster for everything else."""
    per = {}
    for n in (1, 2):
        torch.set_num_threads(n)
        per[n] = median_time(lambda: render(plan, out=out), reps)
    threads = min(per, key=per.get)
    torch.set_num_threads(threads)
    res.update(threads=threads, composite_1thread_s=per[1], composite_2threads_s=per[2])
    log(f"[threads] 1: {per[1] * 1e3:.2f} ms, 2: {per[2] * 1e3:.2f} ms -> {threads}")


def measure_composite(layers, plan, out, size: int, reps: int, res: dict) -> None:
    t_comp = median_time(lambda: render(plan, out=out), reps)
    t_fresh = median_time(lambda: render(plan), reps)
    run_pil = pillow_chain(layers)
    t_pil = median_time(run_pil, reps)
    pil_err = (pillow_float(run_pil()) - render(plan).image.double()).abs().max().item()
    n_floats = size * size * (3 + 1 + 3 + 1 + 3 + 3)  # inputs 3+1+3+1+3 channels, output 3
    src, dst = torch.rand(n_floats), torch.empty(n_floats)
    t_copy = median_time(lambda: dst.copy_(src), reps)
    res.update(
        composite_s=t_comp,
        composite_fresh_output_s=t_fresh,
        pillow_s=t_pil,
        memcpy_s=t_copy,
        memcpy_bytes=n_floats * 4,
        pillow_max_abs_err=pil_err,
        composite_vs_pillow=t_comp / t_pil,
        composite_fresh_output_vs_pillow=t_fresh / t_pil,
        composite_vs_memcpy=t_comp / t_copy,
    )
    log(
        f"[composite] out=: {t_comp * 1e3:.2f} ms, fresh output: {t_fresh * 1e3:.2f} ms, Pillow: {t_pil * 1e3:.2f} ms, "
        f"copy of {n_floats * 4 / 2**20:.0f} MiB: {t_copy * 1e3:.2f} ms"
    )


def measure_culling(layers, plan, out, size: int, reps: int, res: dict) -> None:
    """64 layers (60 no-ops) vs the 4 live ones, both compiled from the layer list on every call."""
    many = culled_64(layers, size)
    check = render(many, canvas=(size, size))
    assert len(check.evaluated) == 4 and torch.equal(check.image, render(plan).image)
    reasons = list(check.skipped.values())
    res["culled64_skips"] = {r: reasons.count(r) for r in sorted(set(reasons))}
    t64 = median_time(lambda: render(many, canvas=(size, size), out=out), reps)
    t4 = median_time(lambda: render(layers, canvas=(size, size), out=out), reps)
    res.update(culled64_s=t64, live4_s=t4, culled64_vs_live4=t64 / t4)
    log(f"[culling] 64 layers: {t64 * 1e3:.2f} ms, 4 live: {t4 * 1e3:.2f} ms")


def measure_prefix_cache(layers, out, size: int, reps: int, res: dict) -> None:
    """Edit only the top layer (one pixel, in place, outside the timed region) and re-render."""
    renderer = Renderer((size, size))
    t_cold = median_time(lambda: (renderer.clear(), renderer.render(layers)), max(3, reps // 2))
    top = layers[-1].tensors.color

    def edits(use_out: bool) -> float:
        renderer.render(layers)
        times = []
        for i in range(reps + 1):
            top[0, 0, i % size] = 16 / 255 if i % 2 else 0.0  # bumps the tensor's version
            times.append(median_time(lambda: renderer.render(layers, out=out if use_out else None), 1, warmup=0))
            assert renderer.last_recomputed == ["light"]
        return float(np.median(times[1:]))

    t_top, t_top_out = edits(False), edits(True)
    assert torch.equal(renderer.render(layers).image, render(layers, canvas=(size, size)).image)
    t_full = median_time(lambda: render(layers, canvas=(size, size)), reps)
    t_full_out = median_time(lambda: render(layers, canvas=(size, size), out=out), reps)
    res.update(
        top_edit_s=t_top,
        top_edit_out_s=t_top_out,
        renderer_cold_s=t_cold,
        full_render_s=t_full,
        full_render_out_s=t_full_out,
        top_edit_vs_full=t_top / t_full,
        top_edit_vs_full_out=t_top_out / t_full_out,
        top_edit_vs_cold_renderer=t_top / t_cold,
    )
    log(
        f"[prefix cache] top edit: {t_top * 1e3:.2f} ms (out=: {t_top_out * 1e3:.2f}), full render: "
        f"{t_full * 1e3:.2f} ms "
        f"(out=: {t_full_out * 1e3:.2f}), cold renderer: {t_cold * 1e3:.2f} ms"
    )


def learned_copy(layers, learn: set[str]) -> list[RenderLayerSpec]:
    """The stack with fresh leaf copies (requires_grad) of every tensor of the layers in ``learn``."""
    out = []
    for s in layers:
        t = s.tensors
        if s.id in learn:
            t = LayerTensors(*[None if x is None else x.clone().requires_grad_() for x in t.tensors()])
        out.append(RenderLayerSpec(id=s.id, blend=s.blend, tensors=t))
    return out


def training_step(plan, layers, engine: str = "banded") -> None:
    """One forward + backward as a training step runs it: the leaves' gradients cleared first
    (``optimizer.zero_grad()``, set to None by default), so backward writes them instead of adding
    into the previous step's (an extra read-modify-write of every full-size gradient)."""
    for s in layers:
        for x in (*s.tensors.tensors(), s.opacity):
            if isinstance(x, torch.Tensor) and x.requires_grad:
                x.grad = None
    render(plan, grad_engine=engine).image.sum().backward()


def measure_autograd(layers, size: int, reps: int, res: dict) -> None:
    """Forward + backward with every layer learned (and a learned opacity) vs the no-grad forward."""
    every = {s.id for s in layers}
    timings = {}
    for clamp in (None, "output"):
        grad_layers = learned_copy(layers, every)
        grad_layers[2] = RenderLayerSpec(
            id="tint", tensors=grad_layers[2].tensors, opacity=torch.tensor(0.9, requires_grad=True)
        )
        for engine in ("auto", "banded", "autograd"):
            plan = compile_plan(grad_layers, (size, size), clamp=clamp)
            timings[clamp, engine] = median_time(lambda: training_step(plan, grad_layers, engine), reps)  # noqa: B023
        timings[clamp, "forward_grad"] = median_time(lambda: render(plan), reps)  # noqa: B023
        nograd = compile_plan(layers, (size, size), clamp=clamp)
        timings[clamp, "forward"] = median_time(lambda: render(nograd), reps)  # noqa: B023
    if torch.get_num_threads() != 1:  # the backward's many small band ops may prefer one thread
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        grad_none = learned_copy(layers, every)
        plan_none = compile_plan(grad_none, (size, size), clamp=None)
        nograd = compile_plan(layers, (size, size), clamp=None)
        t1_fb = median_time(lambda: training_step(plan_none, grad_none), reps)
        t1_fb_banded = median_time(lambda: training_step(plan_none, grad_none, "banded"), reps)
        t1_f = median_time(lambda: render(nograd), reps)
        torch.set_num_threads(threads)
        res.update(
            backward_vs_forward_1thread=t1_fb / t1_f,
            backward_vs_forward_banded_1thread=t1_fb_banded / t1_f,
            forward_1thread_s=t1_f,
            forward_backward_1thread_s=t1_fb,
            forward_backward_banded_1thread_s=t1_fb_banded,
        )
        log(
            f"[autograd, 1 thread] clamp=None: forward {t1_f * 1e3:.2f} ms, forward+backward {t1_fb * 1e3:.2f} ms "
            f"(banded {t1_fb_banded * 1e3:.2f})"
        )
    top_layers = learned_copy(layers, {"light"})
    top_plan = compile_plan(top_layers, (size, size), clamp=None)
    t_top = median_time(lambda: training_step(top_plan, top_layers), reps)
    f = timings[None, "forward"]
    res.update(
        forward_s=f,
        forward_grad_s=timings[None, "forward_grad"],
        forward_backward_s=timings[None, "auto"],
        forward_backward_banded_s=timings[None, "banded"],
        forward_backward_autograd_engine_s=timings[None, "autograd"],
        backward_vs_forward=timings[None, "auto"] / f,
        backward_vs_forward_banded=timings[None, "banded"] / f,
        backward_vs_forward_autograd_engine=timings[None, "autograd"] / f,
        backward_vs_forward_clamp_output=timings["output", "auto"] / timings["output", "forward"],
        learned_top_fwd_bwd_vs_forward=t_top / f,
    )
    log(
        f"[autograd] clamp=None: forward {f * 1e3:.2f} ms, with grad {timings[None, 'forward_grad'] * 1e3:.2f}, "
        f"forward+backward default (auto) {timings[None, 'auto'] * 1e3:.2f} / banded "
        f"{timings[None, 'banded'] * 1e3:.2f} / autograd {timings[None, 'autograd'] * 1e3:.2f}; "
        f"clamp=output: {timings['output', 'forward'] * 1e3:.2f} vs {timings['output', 'auto'] * 1e3:.2f}; "
        f"learned top only {t_top * 1e3:.2f}"
    )


# The modes ImageChops has, as W3C names (Pillow's soft_light is not the W3C formula and its hard_light
# and overlay round differently: the timing compares the same work, the error is reported per mode).
PILLOW_MODES = {
    "normal": Image.alpha_composite,
    "multiply": ImageChops.multiply,
    "screen": ImageChops.screen,
    "overlay": ImageChops.overlay,
    "darken": ImageChops.darker,
    "lighten": ImageChops.lighter,
    "hard-light": ImageChops.hard_light,
    "soft-light": ImageChops.soft_light,
    "difference": ImageChops.difference,
    "plus": ImageChops.add,
}


def measure_top_edit32(size: int, reps: int, res: dict) -> None:
    """The prefix cache on a deep stack: edit the top of 32 layers in place and re-render."""
    layers = random_stack(32, size, seed=32)
    out = torch.empty(3, size, size)
    found = {}
    for use_out in (True, False):
        renderer = Renderer((size, size))
        renderer.render(layers)
        top = layers[-1].tensors.color
        times = []
        for i in range(2 * reps + 1):
            top[0, 0, i % size] = 8 / 255 if i % 2 else 0.0
            times.append(median_time(lambda: renderer.render(layers, out=out if use_out else None), 1, warmup=0))  # noqa: B023
            assert renderer.last_recomputed == [layers[-1].id]
        found[use_out] = float(np.median(times[1:]))
    assert torch.equal(renderer.render(layers).image, render(layers, canvas=(size, size)).image)
    t_full = median_time(lambda: render(layers, canvas=(size, size), out=out), reps)
    t_full_fresh = median_time(lambda: render(layers, canvas=(size, size)), reps)
    res.update(
        top_edit32_s=found[True],
        full_render32_s=t_full,
        top_edit32_vs_full=found[True] / t_full,
        top_edit32_fresh_s=found[False],
        full_render32_fresh_s=t_full_fresh,
        top_edit32_fresh_vs_full=found[False] / t_full_fresh,
    )
    log(
        f"[prefix cache, 32 layers] top edit: {found[True] * 1e3:.2f} ms, full render: {t_full * 1e3:.2f} ms "
        f"(fresh outputs: {found[False] * 1e3:.2f} vs {t_full_fresh * 1e3:.2f} ms)"
    )


def measure_modes(size: int, reps: int, res: dict, fused: bool = True) -> None:
    """Every mode's cost over the base, and the Pillow-mode stack against Pillow's chain; then the same
    with the fused kernels (``measure_modes_fused``)."""
    from lasagna.document import BLEND_MODES

    g = torch.Generator().manual_seed(16)
    base = RenderLayerSpec(id="base", tensors=LayerTensors(grid(g, 3, size, size)))
    out = torch.empty(3, size, size)
    t_base = median_time(lambda: render([base], canvas=(size, size), out=out), reps)
    mode_ms, mode_planes = {}, {}
    for mode in BLEND_MODES:
        channels = 1 if mode == "multiply" else 3
        alpha = grid(g, 1, size, size) if mode == "normal" else None
        top = RenderLayerSpec(id="top", blend=mode, tensors=LayerTensors(grid(g, channels, size, size), alpha))
        plan = mode_planes[mode] = compile_plan([base, top], (size, size), cull=False)
        mode_ms[mode] = round((median_time(lambda: render(plan, out=out), reps) - t_base) * 1e3, 2)  # noqa: B023
    layers = [base]
    for mode in PILLOW_MODES:
        alpha = grid(g, 1, size, size, top=96) if mode == "normal" else None
        top = 12 if mode == "plus" else 255
        layers.append(
            RenderLayerSpec(id=mode, blend=mode, tensors=LayerTensors(grid(g, 3, size, size, top=top), alpha))
        )
    plan = compile_plan(layers, (size, size), cull=False)
    t_ours = median_time(lambda: render(plan, out=out), reps)
    images = [to_rgba(s.tensors) for s in layers]

    def pillow() -> Image.Image:
        img = images[0]
        for mode, im in zip(PILLOW_MODES, images[1:]):
            img = PILLOW_MODES[mode](img, im)
        return img

    t_pil = median_time(pillow, reps)
    res.update(
        modes_base_s=t_base,
        mode_ms=mode_ms,
        modes_stack_s=t_ours,
        modes_pillow_s=t_pil,
        modes_vs_pillow=t_ours / t_pil,
        modes_stack=list(PILLOW_MODES),
    )
    log(f"[modes] {len(PILLOW_MODES)}-mode stack: {t_ours * 1e3:.2f} ms, Pillow: {t_pil * 1e3:.2f} ms")
    log(f"[modes] cost over the base, ms: {mode_ms}")
    if fused:
        measure_modes_fused(plan, mode_planes, t_base, out, t_pil, reps, res)


# One of each adjustment the ten-layer row stacks (document units, lasagna/document/adjustment.py), away from identity.
ADJUSTMENT_STACK = {
    "levels": {"rgb": {"in_black": 0.1, "in_white": 0.85, "gamma": 1.4, "out_black": 0.05, "out_white": 0.95}},
    "curves": {"rgb": [[0.0, 0.1], [0.3, 0.5], [0.8, 0.7], [1.0, 1.0]]},
    "hue-saturation": {"hue": 40.0, "saturation": -30.0, "lightness": 12.0},
    "brightness-contrast": {"brightness": 40.0, "contrast": 30.0},
    "exposure": {"exposure": 0.8, "offset": 0.02, "gamma": 1.2},
    "channel-mixer": {
        "red": [80.0, 30.0, -20.0, 5.0],
        "green": [-10.0, 120.0, 0.0, -8.0],
        "blue": [25.0, 25.0, 60.0, 0],
    },
    "color-balance": {"shadows": [30.0, -20.0, 10.0], "midtones": [-40.0, 15.0, 55.0], "highlights": [10.0, 35.0, 0]},
    "vibrance": {"vibrance": 60.0, "saturation": -15.0},
    "gradient-map": {
        "stops": [{"location": 0.0, "color": [0.1, 0.0, 0.3]}, {"location": 1.0, "color": [1.0, 0.95, 0.6]}]
    },
    "photo-filter": {"color": [0.0, 0.43, 1.0], "density": 60.0},
}


def measure_adjustments(size: int, reps: int, res: dict) -> None:
    """Ten adjustment layers against ten normal layers over the same base (``adjust10_vs_normal10``)."""
    from pydantic import TypeAdapter

    from lasagna.compose.adjust import Adjustment
    from lasagna.compose.plan import adjustment_tensors
    from lasagna.document.adjustment import Adjustment as Model

    g = torch.Generator().manual_seed(25)
    base = RenderLayerSpec(id="base", tensors=LayerTensors(grid(g, 3, size, size)))
    out = torch.empty(3, size, size)
    t_base = median_time(lambda: render([base], canvas=(size, size), out=out), reps)
    adjust, adjust_ms = [], {}
    for kind, values in ADJUSTMENT_STACK.items():
        p = TypeAdapter(Model).validate_python({"type": kind, **values}).model_dump(exclude={"type"})
        spec = RenderLayerSpec(
            id=kind, tensors=adjustment_tensors(None, size, size), adjust=Adjustment(kind, p), opacity=0.8
        )
        adjust.append(spec)
        one = compile_plan([base, spec], (size, size))
        adjust_ms[kind] = round((median_time(lambda: render(one, out=out), reps) - t_base) * 1e3, 2)  # noqa: B023
    normal = [RenderLayerSpec(id=f"n{i}", tensors=LayerTensors(grid(g, 3, size, size)), opacity=0.8) for i in range(10)]
    plan_a = compile_plan([base, *adjust], (size, size))
    plan_n = compile_plan([base, *normal], (size, size))
    from lasagna.compose import lut

    lut._cache.clear()
    t0 = time.perf_counter()
    render(plan_a, out=out)  # the first render bakes and checks the lattices (compose/lut.py), then they are cached
    t_first = time.perf_counter() - t0
    runs = {
        plan_a.steps[j].spec.id: plan_a.steps[k - 1].spec.id
        for j, (k, _) in lut.lattice_runs(plan_a, 0, len(plan_a.steps), torch.float32).items()
    }
    t_a = median_time(lambda: render(plan_a, out=out), reps)
    t_n = median_time(lambda: render(plan_n, out=out), reps)
    res.update(
        adjust10_s=t_a,
        normal10_s=t_n,
        adjust10_vs_normal10=t_a / t_n,
        adjust_ms=adjust_ms,
        adjust10_first_s=t_first,
        adjust10_lattice_runs=runs,
    )
    log(f"[adjust] ten adjustment layers: {t_a * 1e3:.1f} ms, ten normal layers: {t_n * 1e3:.1f} ms")
    log(f"[adjust] first render (bakes the lattices) {t_first:.2f} s; runs read from a lattice: {runs}")
    log(f"[adjust] cost over the base, ms: {adjust_ms}")


def measure_modes_fused(
    plan: object, mode_planes: dict, t_base: float, out: torch.Tensor, t_pil: float, reps: int, res: dict
) -> None:
    """The same stack and per-mode costs with ``set_fused(True)`` (compiled W3C kernels, steady state),
    the first call's compile time per mode apart; outputs compared with the eager kernels'."""
    from lasagna.compose import set_fused

    eager = {}
    for mode, p in mode_planes.items():
        render(p, out=out)
        eager[mode] = out.clone()
    render(plan, out=out)
    eager_stack = out.clone()
    set_fused(True)
    try:
        compile_s, mode_ms, worst = {}, {}, 0.0
        for mode, p in mode_planes.items():
            t0 = time.perf_counter()
            render(p, out=out)
            compile_s[mode] = round(time.perf_counter() - t0, 2)
            worst = max(worst, float((out - eager[mode]).abs().max()))
            mode_ms[mode] = round((median_time(lambda: render(p, out=out), reps) - t_base) * 1e3, 2)  # noqa: B023
        render(plan, out=out)
        worst = max(worst, float((out - eager_stack).abs().max()))
        t_ours = median_time(lambda: render(plan, out=out), reps)
    finally:
        set_fused(False)
    res.update(
        mode_ms_fused=mode_ms,
        mode_compile_s_fused=compile_s,
        modes_stack_fused_s=t_ours,
        modes_vs_pillow_fused=t_ours / t_pil,
        fused_max_abs_diff_vs_eager=worst,
    )
    log(f"[modes, fused] {len(PILLOW_MODES)}-mode stack: {t_ours * 1e3:.2f} ms ({t_ours / t_pil:.2f} of Pillow)")
    log(f"[modes, fused] cost over the base, ms: {mode_ms}; first call (compile), s: {compile_s}")
    log(f"[modes, fused] largest difference from the eager kernels: {worst:.2e}")


FRESH_PROCESS = """
import statistics, sys, time
import torch
from lasagna.compose import LayerTensors, RenderLayerSpec, compile_plan, render
torch.set_num_threads(int(sys.argv[1]))
size = int(sys.argv[2])
g = torch.Generator().manual_seed(0)
def grid(*shape):
    return torch.randint(0, 256, shape, generator=g, dtype=torch.int32).float().div_(255.0)
layers = [RenderLayerSpec(id="base", tensors=LayerTensors(grid(3, size, size)))]
for mode in ("overlay", "soft-light", "hue"):
    layers.append(RenderLayerSpec(id=mode, blend=mode, tensors=LayerTensors(grid(3, size, size))))
plan = compile_plan(layers, (size, size), cull=False)
out = torch.empty(3, size, size)
times = []
for _ in range(int(sys.argv[3])):
    t0 = time.perf_counter()
    render(plan, out=out)
    times.append(time.perf_counter() - t0)
print(statistics.median(times))
"""


def measure_fresh_process(size: int, reps: int, threads: int, res: dict) -> None:
    """A fresh process rendering base + overlay + soft-light + hue, with lasagna's heap thresholds
    (``lasagna.heap``) and with glibc's defaults (``LASAGNA_HEAP=system``): what one CLI call sees."""
    import subprocess

    times = {}
    for heap in ("lasagna", "system"):
        env = {k: v for k, v in os.environ.items() if k != "LASAGNA_HEAP"}
        if heap == "system":
            env["LASAGNA_HEAP"] = "system"
        cmd = [sys.executable, "-c", FRESH_PROCESS, str(threads), str(size), str(reps)]
        times[heap] = float(subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout)
    res.update(
        fresh_modes_s=times["lasagna"],
        fresh_modes_heap_system_s=times["system"],
        fresh_modes_vs_heap_system=times["lasagna"] / times["system"],
    )
    log(
        f"[fresh process] base + overlay + soft-light + hue: {times['lasagna'] * 1e3:.1f} ms, with glibc's "
        f"default heap thresholds {times['system'] * 1e3:.1f} ms"
    )


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=2048, help="canvas side of the 4-layer stack (default 2048)")
    ap.add_argument("--repeats", type=int, default=9, help="timed runs per measurement, median reported")
    ap.add_argument("--quick", action="store_true", help="512² and a small precision table (< 30 s)")
    ap.add_argument("--precision-size", type=int, default=512, help="canvas side of the 32/256-layer rows")
    ap.add_argument(
        "--plot",
        default=None,
        help="where to write the precision plot ('' = none; default docs/img/compositing_precision.png, "
        "none with --quick)",
    )
    ap.add_argument("--no-fused", action="store_true", help="skip the compiled kernels (no C++ compiler)")
    args = ap.parse_args()
    if args.quick:
        args.size, args.repeats, args.precision_size = min(args.size, 512), min(args.repeats, 3), 128
    if args.plot is None:
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        args.plot = "" if args.quick else os.path.join(root, "docs", "img", "compositing_precision.png")
    size, reps = args.size, args.repeats
    res: dict = {"size": size, "repeats": reps, "thp_mem_alloc_enable": os.environ.get("THP_MEM_ALLOC_ENABLE")}

    layers = four_layers(size)
    plan = compile_plan(layers, (size, size))
    out = torch.empty(3, size, size)
    measure_threads(plan, out, reps, res)
    measure_composite(layers, plan, out, size, reps, res)
    measure_culling(layers, plan, out, size, reps, res)
    measure_prefix_cache(layers, out, size, reps, res)
    measure_autograd(layers, size, reps, res)
    measure_top_edit32(size, reps, res)
    measure_modes(size, reps, res, fused=not args.no_fused)
    measure_adjustments(size, reps, res)
    measure_fresh_process(size, reps, torch.get_num_threads(), res)

    prec_reps = max(1, min(reps, 3))
    rows = (
        precision_rows(4, size, prec_reps)
        + precision_rows(32, args.precision_size, prec_reps)
        + precision_rows(256, args.precision_size, prec_reps)
    )
    res["precision"] = [{k: (round(v, 9) if isinstance(v, float) else v) for k, v in r.items()} for r in rows]
    log(f"{'layers':>6} {'canvas':>6} {'dtype':>13} {'ms':>9} {'max|err|':>10} {'levels':>6}")
    for r in rows:
        log(
            f"{r['layers']:>6} {r['canvas']:>6} {r['dtype']:>13} {r['seconds'] * 1e3:>9.2f} {r['max_abs_err']:>10.2e} "
            f"{r['max_levels_off']:>6.0f}"
        )
    if args.plot:
        plot_precision(rows, args.plot)
    res["machine"] = machine_info()
    print_json_line(res)


if __name__ == "__main__":
    main()
