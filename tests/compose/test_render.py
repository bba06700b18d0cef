"""render(): against the numpy float64 reference and Pillow, batches, gradients, dtypes, out=, errors."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from PIL import Image, ImageChops

from lasagna.compose import backward, engine
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec, compile_plan
from lasagna.compose.render import half_precision_bound, render
from lasagna.compose.renderer import Renderer
from lasagna.errors import LasagnaError
from tests.compose import numpy_ref

CANVAS = (6, 8)
BG = (0.1, 0.4, 0.8)


def stack(seed=0, dtype=torch.float64, requires_grad=False):
    """A small stack touching every feature: offsets in and out, masks, ranges, 1-channel multiply."""
    g = torch.Generator().manual_seed(seed)

    def r(*shape, scale=1.0, shift=0.0):
        x = torch.rand(*shape, generator=g, dtype=torch.float64) * scale + shift
        return x.to(dtype).requires_grad_(requires_grad)

    return [
        RenderLayerSpec(id="base", tensors=LayerTensors(r(3, 6, 8))),
        RenderLayerSpec(
            id="shade",
            blend="multiply",
            range=(0.0, 2.0),
            offset=(-1, 2),
            tensors=LayerTensors(r(1, 5, 6, scale=2.0), None, r(1, 5, 6)),
        ),
        RenderLayerSpec(id="tint", offset=(5, -1), opacity=0.7, tensors=LayerTensors(r(3, 4, 4), r(1, 4, 4))),
        RenderLayerSpec(
            id="light",
            blend="plus",
            range=(-1.0, 1.0),
            offset=(2, 2),
            opacity=0.5,
            tensors=LayerTensors(r(3, 3, 3, scale=2.0, shift=-1.0)),
        ),
        RenderLayerSpec(id="glow", blend="screen", opacity=0.3, tensors=LayerTensors(r(1, 6, 8))),
        RenderLayerSpec(id="gone", offset=(9, 0), tensors=LayerTensors(r(3, 2, 2))),
    ]


def test_smoke():
    result = render([RenderLayerSpec(id="a", tensors=LayerTensors(torch.full((3, 2, 2), 0.5)))], canvas=(2, 2))
    assert result.image.shape == (3, 2, 2) and result.image.dtype == torch.float32
    assert torch.equal(result.image, torch.full((3, 2, 2), 0.5))
    assert result.evaluated == ["a"] and result.skipped == {}


def test_empty_stack_is_the_background():
    image = render([], canvas=(2, 3), background=(0.25, 0.5, 1.0)).image
    assert torch.equal(image, torch.tensor([0.25, 0.5, 1.0]).view(3, 1, 1).expand(3, 2, 3))


@pytest.mark.parametrize("clamp", ["layer", "output", None])
@pytest.mark.parametrize("blend_space", ["srgb", "linear"])
@pytest.mark.parametrize("cull", [True, False])
def test_reference_numpy(clamp, blend_space, cull):
    layers = stack(seed=1)
    got = render(layers, canvas=CANVAS, background=BG, blend_space=blend_space, clamp=clamp, cull=cull)
    expect = numpy_ref.composite(layers, CANVAS, BG, blend_space, clamp)
    np.testing.assert_allclose(got.image.numpy(), expect, atol=1e-12)
    assert got.skipped == {"gone": "outside-canvas"}


def test_reference_numpy_float32_and_bands(monkeypatch):
    monkeypatch.setattr(engine, "TILE_PIXELS", 8)  # one canvas row per band: exercises band clipping
    layers = stack(seed=2, dtype=torch.float32)
    got = render(layers, canvas=CANVAS, background=BG).image
    np.testing.assert_allclose(got.double().numpy(), numpy_ref.composite(layers, CANVAS, BG), atol=1e-6)


def test_reference_pillow_stack():
    """base RGB → 1-channel multiply → RGBA normal → plus, each done the Pillow way on uint8."""
    rng = np.random.default_rng(0)
    base, tint, light = rng.integers(0, 256, (3, 3, 8, 8), dtype=np.uint8)
    shade, alpha = rng.integers(0, 256, (2, 1, 8, 8), dtype=np.uint8)
    light //= 4

    def rgba(rgb, a=None):
        a = np.full((1, 8, 8), 255, np.uint8) if a is None else a
        return Image.fromarray(np.concatenate([np.broadcast_to(rgb, (3, 8, 8)), a]).transpose(1, 2, 0), "RGBA")

    img = ImageChops.multiply(rgba(base), rgba(shade))
    img = Image.alpha_composite(img, rgba(tint, alpha))
    img = ImageChops.add(img, rgba(light))
    pil = np.asarray(img)[..., :3].transpose(2, 0, 1).astype(np.int64)

    def t(x):
        return torch.from_numpy(x / 255.0).float()

    layers = [
        RenderLayerSpec(id="base", tensors=LayerTensors(t(base))),
        RenderLayerSpec(id="shade", blend="multiply", tensors=LayerTensors(t(shade))),
        RenderLayerSpec(id="tint", tensors=LayerTensors(t(tint), t(alpha))),
        RenderLayerSpec(id="light", blend="plus", tensors=LayerTensors(t(light))),
    ]
    ours = np.rint(render(layers, canvas=(8, 8)).image.double().numpy() * 255).astype(np.int64)
    assert np.abs(ours - pil).max() <= 2  # Pillow rounds after each of its three steps


def test_batch_broadcasts_like_separate_renders():
    g = torch.Generator().manual_seed(3)
    base = LayerTensors(torch.rand(3, 4, 5, generator=g))  # shared
    shade = LayerTensors(torch.rand(2, 1, 4, 5, generator=g))  # one per batch entry
    tint = LayerTensors(torch.rand(3, 2, 2, generator=g), torch.rand(2, 1, 2, 2, generator=g))
    op = torch.tensor([0.3, 0.9]).view(2, 1, 1, 1)

    def layers(b=None):
        pick = (lambda t: t) if b is None else (lambda t: t[b] if t is not None and t.ndim == 4 else t)
        return [
            RenderLayerSpec(id="base", tensors=base),
            RenderLayerSpec(id="shade", blend="multiply", tensors=LayerTensors(pick(shade.color))),
            RenderLayerSpec(
                id="tint",
                offset=(1, 1),
                opacity=op if b is None else float(op[b]),
                tensors=LayerTensors(tint.color, pick(tint.alpha)),
            ),
        ]

    batched = render(layers(), canvas=(4, 5)).image
    assert batched.shape == (2, 3, 4, 5)
    for b in range(2):
        assert torch.allclose(batched[b], render(layers(b), canvas=(4, 5)).image, atol=1e-7)


def test_no_autograd_graph_without_gradients():
    result = render(stack(seed=4, dtype=torch.float32), canvas=CANVAS)
    assert not result.image.requires_grad and result.image.grad_fn is None


def test_gradients_reach_every_input_and_module():
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(3, 1, 1)
    layers = stack(seed=5, dtype=torch.float32, requires_grad=True)
    shade_color = torch.sigmoid(conv(layers[0].tensors.color.detach()[None]))[0] * 2  # (1, 6, 8) from a module
    op = torch.tensor(0.7, requires_grad=True)
    layers[1] = RenderLayerSpec(id="shade", blend="multiply", range=(0.0, 2.0), tensors=LayerTensors(shade_color))
    layers[2] = RenderLayerSpec(id="tint", offset=(5, -1), opacity=op, tensors=layers[2].tensors)
    result = render(layers, canvas=CANVAS, clamp="output")
    assert result.image.requires_grad
    result.image.square().sum().backward()
    leaves = [
        layers[0].tensors.color,
        layers[2].tensors.color,
        layers[2].tensors.alpha,
        layers[3].tensors.color,
        layers[4].tensors.color,
        op,
        conv.weight,
        conv.bias,
    ]
    for leaf in leaves:
        assert leaf.grad is not None and torch.isfinite(leaf.grad).all() and leaf.grad.abs().sum() > 0
    assert layers[5].tensors.color.grad is None  # outside the canvas: culled, true gradient zero


@pytest.mark.parametrize("grad_engine", ["banded", "autograd"])
@pytest.mark.parametrize("blend_space", ["srgb", "linear"])
def test_gradcheck_whole_render(blend_space, grad_engine, monkeypatch):
    monkeypatch.setattr(backward, "BACKWARD_TILE_PIXELS", 16)  # two rows per band: band edges everywhere
    layers = stack(seed=6)
    base, shade, tint = layers[0].tensors.color, layers[1].tensors.color, layers[2].tensors.alpha
    op = torch.tensor(0.6, dtype=torch.float64)

    def f(base, shade, tint_alpha, op):
        ls = list(layers)
        ls[0] = RenderLayerSpec(id="base", tensors=LayerTensors(base))
        ls[1] = RenderLayerSpec(
            id="shade",
            blend="multiply",
            range=(0.0, 2.0),
            offset=(-1, 2),
            tensors=LayerTensors(shade, None, layers[1].tensors.mask),
        )
        ls[2] = RenderLayerSpec(
            id="tint", offset=(5, -1), opacity=op, tensors=LayerTensors(layers[2].tensors.color, tint_alpha)
        )
        return render(
            ls, canvas=CANVAS, background=BG, blend_space=blend_space, clamp=None, grad_engine=grad_engine
        ).image

    inputs = tuple(t.detach().clone().requires_grad_() for t in (base, shade, tint, op))
    assert torch.autograd.gradcheck(f, inputs)


@pytest.mark.parametrize("edge", [0.0, 1.0])
def test_gradients_finite_at_alpha_edges_and_zero_multiplier(edge):
    base = torch.rand(3, 4, 4, requires_grad=True)
    mult = torch.zeros(1, 4, 4, requires_grad=True)
    alpha = torch.full((1, 4, 4), edge, requires_grad=True)
    op = torch.tensor(edge, requires_grad=True)
    layers = [
        RenderLayerSpec(id="b", tensors=LayerTensors(base)),
        RenderLayerSpec(id="m", blend="multiply", opacity=op, tensors=LayerTensors(mult, alpha)),
    ]
    for clamp in ("layer", "output", None):
        for t in (base, mult, alpha, op):
            t.grad = None
        render(layers, canvas=(4, 4), clamp=clamp, blend_space="linear").image.sum().backward()
        for t in (base, mult, alpha, op):
            assert t.grad is not None and torch.isfinite(t.grad).all()


def test_grad_path_equals_fast_path():
    layers = stack(seed=7, dtype=torch.float32, requires_grad=True)
    with_grad = render(layers, canvas=CANVAS, background=BG).image
    with torch.no_grad():
        fast = render(layers, canvas=CANVAS, background=BG).image
    assert torch.allclose(with_grad, fast, atol=1e-6)


def test_grad_path_leaves_constant_prefix_untouched_by_autograd():
    layers = stack(seed=8, dtype=torch.float32)
    top = torch.rand(1, 6, 8, requires_grad=True)
    layers[4] = RenderLayerSpec(id="glow", blend="screen", opacity=0.3, tensors=LayerTensors(top))
    image = render(layers, canvas=CANVAS).image
    image.sum().backward()
    assert top.grad is not None and layers[0].tensors.color.grad is None


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_within_documented_bound(dtype):
    layers = stack(seed=9)
    for spec in layers:  # the bound is stated for factors <= 1 (no amplification of earlier errors)
        if spec.blend == "multiply":
            spec.tensors.color.div_(2)
    plan = compile_plan(layers, CANVAS, BG)
    got = render(plan, dtype=dtype).image
    assert got.dtype == dtype
    err = (got.double() - render(plan).image).abs().max().item()
    assert err <= half_precision_bound(dtype, len(plan.steps))


def test_dtype_override_and_default_promotion():
    layers = stack(seed=10, dtype=torch.float32)
    assert render(layers, canvas=CANVAS).image.dtype == torch.float32
    assert render(layers, canvas=CANVAS, dtype=torch.float64).image.dtype == torch.float64
    with pytest.raises(LasagnaError, match="dtype is torch.int32; expected a floating-point"):
        render(layers, canvas=CANVAS, dtype=torch.int32)


def test_out_parameter():
    layers = stack(seed=11, dtype=torch.float32)
    out = torch.empty(3, *CANVAS)
    result = render(layers, canvas=CANVAS, out=out)
    assert result.image is out and torch.equal(out, render(layers, canvas=CANVAS).image)
    with pytest.raises(LasagnaError, match="out is \\(3, 5, 8\\)"):
        render(layers, canvas=CANVAS, out=torch.empty(3, 5, 8))
    grad_layers = stack(seed=11, dtype=torch.float32, requires_grad=True)
    with pytest.raises(LasagnaError, match="needs gradients"):
        render(grad_layers, canvas=CANVAS, out=out)


def test_only_the_clipped_rectangle_is_read():
    # A layer far larger than the canvas: only its overlap is touched (rest is NaN and must not leak).
    big = torch.full((3, 50, 60), float("nan"))
    big[:, 20:26, 30:38] = 0.25
    layers = [RenderLayerSpec(id="big", offset=(-30, -20), tensors=LayerTensors(big))]
    assert torch.equal(render(layers, canvas=CANVAS).image, torch.full((3, *CANVAS), 0.25))


def test_nan_layer_is_not_hidden_by_culling():
    color = torch.rand(3, 6, 8)
    color[0, 2, 2] = float("nan")
    layers = [
        RenderLayerSpec(id="base", tensors=LayerTensors(torch.rand(3, 6, 8))),
        RenderLayerSpec(id="ghost", tensors=LayerTensors(color, torch.zeros(1, 6, 8))),
    ]
    for cull in (True, False):
        image = render(layers, canvas=CANVAS, cull=cull).image
        assert torch.isnan(image[0, 2, 2]) and torch.isfinite(image[1:]).all() and torch.isfinite(image[:, 3:]).all()


@pytest.mark.parametrize("clamp", ["layer", "output", None])
@pytest.mark.parametrize("blend_space", ["srgb", "linear"])
def test_banded_backward_equals_autograd(clamp, blend_space, monkeypatch):
    monkeypatch.setattr(backward, "BACKWARD_TILE_PIXELS", 24)  # bands of 3 rows
    layers = stack(seed=12, dtype=torch.float32, requires_grad=True)
    op = torch.tensor(0.8, requires_grad=True)
    layers[3] = RenderLayerSpec(
        id="light", blend="plus", range=(-1.0, 1.0), offset=(2, 2), opacity=op, tensors=layers[3].tensors
    )
    leaves = [t for s in layers for t in s.tensors.tensors() if t is not None] + [op]
    weights = torch.rand(3, *CANVAS)
    grads = {}
    for engine_name in ("banded", "autograd"):
        image = render(
            layers, canvas=CANVAS, background=BG, clamp=clamp, blend_space=blend_space, grad_engine=engine_name
        ).image
        grads[engine_name] = torch.autograd.grad((image * weights).sum(), leaves, allow_unused=True)
    for a, b in zip(grads["banded"], grads["autograd"]):
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.allclose(a, b, atol=1e-6)


@pytest.mark.parametrize("shared", [False, True])
def test_parallel_bands_give_the_one_thread_gradients_bit_for_bit(monkeypatch, shared):
    """Bands run on two threads (BACKWARD_BAND_THREADS) give exactly the gradients of one band at a time: the
    0-dim opacity's per-band parts are summed in band order; a tensor two steps read (``shared``) keeps the
    bands sequential."""
    monkeypatch.setattr(backward, "BACKWARD_TILE_PIXELS", 16)  # bands of 2 rows: 3 bands
    layers = stack(seed=14, dtype=torch.float32, requires_grad=True)
    op = torch.tensor(0.8, requires_grad=True)
    layers[3] = RenderLayerSpec(
        id="light", blend="overlay", offset=(2, 2), opacity=op, tensors=layers[3].tensors
    )  # a W3C mode: its band derivative runs autograd inside the worker thread
    if shared:
        layers.append(RenderLayerSpec(id="again", blend="screen", offset=(1, 0), tensors=layers[2].tensors))
    leaves = [t for s in layers for t in s.tensors.tensors() if t is not None] + [op]
    weights = torch.rand(3, *CANVAS, generator=torch.Generator().manual_seed(0))
    calls = []
    real = backward.ThreadPoolExecutor

    def counting(workers, **kw):
        calls.append(workers)
        return real(workers, **kw)

    monkeypatch.setattr(backward, "ThreadPoolExecutor", counting)
    grads = {}
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for band_threads in (1, 2):
            monkeypatch.setattr(backward, "BACKWARD_BAND_THREADS", band_threads)
            image = render(layers, canvas=CANVAS, background=BG, clamp=None, grad_engine="banded").image
            grads[band_threads] = torch.autograd.grad((image * weights).sum(), leaves, allow_unused=True)
    finally:
        torch.set_num_threads(threads)
    assert calls == ([] if shared else [2])
    assert torch.get_num_threads() == threads
    for a, b in zip(grads[1], grads[2]):
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.equal(a, b)


@pytest.mark.parametrize("engine_name", ["banded", "autograd"])
def test_backward_refuses_modified_inputs(engine_name):
    layers = stack(seed=13, dtype=torch.float32, requires_grad=True)
    image = render(layers, canvas=CANVAS, grad_engine=engine_name).image
    with torch.no_grad():
        layers[2].tensors.color.mul_(0.5)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        image.sum().backward()


def test_unknown_grad_engine():
    with pytest.raises(LasagnaError, match="grad_engine is 'magic'; expected 'auto', 'banded' or 'autograd'"):
        render(stack(), canvas=CANVAS, grad_engine="magic")
    with pytest.raises(LasagnaError, match="grad_engine is 'magic'"):
        Renderer(CANVAS, grad_engine="magic")


def test_auto_records_while_the_intermediates_fit_then_bands(monkeypatch):
    """``grad_engine="auto"`` (the default) records the tail while (live steps) × (canvas bytes) ≤
    ``AUTO_RECORD_BYTES``, and runs the banded backward above it; the gradients agree either way."""
    render_module = sys.modules["lasagna.compose.render"]  # the package's ``render`` is the function

    layers = stack(seed=15, dtype=torch.float32, requires_grad=True)
    leaves = [t for s in layers for t in s.tensors.tensors() if t is not None]
    canvas_bytes = 3 * CANVAS[0] * CANVAS[1] * 4
    live = len(compile_plan(layers, CANVAS).steps)
    grads = {}
    for cap, expect in ((live * canvas_bytes, "autograd"), (live * canvas_bytes - 1, "banded")):
        monkeypatch.setattr(render_module, "AUTO_RECORD_BYTES", cap)
        image = render(layers, canvas=CANVAS, background=BG, clamp=None).image
        assert (type(image.grad_fn).__name__ == "BandedGradBackward") == (expect == "banded")
        grads[expect] = torch.autograd.grad(image.sum(), leaves, allow_unused=True)
    for a, b in zip(grads["autograd"], grads["banded"]):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=0, atol=1e-6)


@pytest.mark.parametrize("clamp", ["layer", "output"])
def test_banded_clamp_derivative_is_inclusive_at_the_bounds(clamp):
    # 0.5 + 0.5 is exactly 1 and 0.5·0 exactly 0 before the clamp: like torch.clamp, gradient passes.
    base = torch.full((3, 2, 2), 0.5, requires_grad=True)
    light = torch.tensor([0.5, 0.25, 0.75]).view(3, 1, 1).expand(3, 2, 2).clone().requires_grad_()
    shade = torch.tensor([[[0.0, 1.0], [2.0, 0.5]]]).requires_grad_()
    layers = [
        RenderLayerSpec(id="b", tensors=LayerTensors(base)),
        RenderLayerSpec(id="s", blend="multiply", range=(0.0, 2.0), tensors=LayerTensors(shade)),
        RenderLayerSpec(id="l", blend="plus", tensors=LayerTensors(light)),
    ]
    got = {}
    for name in ("banded", "autograd"):
        image = render(layers, canvas=(2, 2), clamp=clamp, grad_engine=name).image
        got[name] = torch.autograd.grad(image.sum(), [base, shade, light])
    for a, b in zip(got["banded"], got["autograd"]):
        assert torch.equal(a, b)
