"""Adjustment runs read from a 3D lattice (``lasagna/compose/lut.py``): within ``LUT_TOLERANCE`` of the exact float64
path on random images for every adjustment type where the lattice is used, exact where its check refuses it (steps,
steep maps), and never used where a mask, a partial rectangle or gradients are involved."""

from __future__ import annotations

import pytest
import torch
from pydantic import TypeAdapter

from lasagna.compose import lut
from lasagna.compose.adjust import Adjustment
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec, adjustment_tensors, compile_plan
from lasagna.compose.render import render
from lasagna.compose.renderer import Renderer
from lasagna.document.adjustment import Adjustment as Model
from tests.compose.test_adjust import CASES

H = W = 24


@pytest.fixture(autouse=True)
def small_canvases(monkeypatch):
    monkeypatch.setattr(lut, "MIN_PIXELS", 0)
    lut._cache.clear()


def adjustment(case: dict, name: str, opacity: float = 0.8, **spec) -> RenderLayerSpec:
    p = TypeAdapter(Model).validate_python(case).model_dump(exclude={"type"})
    return RenderLayerSpec(
        id=name, tensors=adjustment_tensors(None, W, H), adjust=Adjustment(case["type"], p), opacity=opacity, **spec
    )


def base(seed: int = 0, dtype=torch.float32) -> RenderLayerSpec:
    g = torch.Generator().manual_seed(seed)
    return RenderLayerSpec(id="base", tensors=LayerTensors(torch.rand(3, H, W, generator=g).to(dtype)))


def exact(layers, monkeypatch, **kw) -> torch.Tensor:
    """The render with no lattice, in float64 (the reference)."""
    monkeypatch.setattr(lut, "MIN_PIXELS", 1 << 62)
    f64 = [base(dtype=torch.float64), *layers[1:]]
    out = render(f64, canvas=(H, W), **kw).image
    monkeypatch.setattr(lut, "MIN_PIXELS", 0)
    return out


@pytest.mark.parametrize("name", sorted(CASES))
def test_every_type_is_within_the_tolerance_or_exact(name, monkeypatch):
    case = CASES[name]
    layers = [base(), adjustment(case, "a"), adjustment({"type": "invert"}, "b", opacity=0.3)]
    plan = compile_plan(layers, (H, W))
    used = bool(lut.lattice_runs(plan, 0, len(plan.steps), torch.float32))
    got = render(plan).image.double()
    err = float((got - exact(layers, monkeypatch)).abs().max())
    # The check runs on cell centres and seeded colours; on these random pixels the lattice stays within it
    # (float32 rounding of the read aside).
    assert err <= lut.LUT_TOLERANCE + 1e-5, (name, used, err * 255)
    if name in ("posterize", "threshold"):  # steps: the check refuses them, the run is exact
        assert not used and err < 1e-5


def test_a_smooth_run_is_read_from_lattices(monkeypatch):
    # The fourth step's composed lattice fails the check: it is exact and the run before it is one lattice.
    names = ("hue-saturation", "brightness-contrast", "exposure", "vibrance")
    layers = [base(), *(adjustment(CASES[n], n) for n in names)]
    plan = compile_plan(layers, (H, W))
    assert {k: v[0] for k, v in lut.lattice_runs(plan, 0, len(plan.steps), torch.float32).items()} == {1: 4}
    err = float((render(plan).image.double() - exact(layers, monkeypatch)).abs().max())
    assert err <= lut.LUT_TOLERANCE + 1e-5


def test_a_steep_step_splits_the_run_and_is_exact():
    # Levels' gamma at its black point has an infinite slope: its lattice errs ~3/255, so it is composited exactly.
    names = ("hue-saturation", "vibrance", "levels", "brightness-contrast", "exposure")
    plan = compile_plan([base(), *(adjustment(CASES[n], n) for n in names)], (H, W))
    runs = {k: v[0] for k, v in lut.lattice_runs(plan, 0, len(plan.steps), torch.float32).items()}
    assert runs == {1: 3, 4: 6}


@pytest.mark.parametrize("what", ["mask", "offset", "grad", "dissolve", "output-clamp", "lone"])
def test_what_is_never_read_from_a_lattice(what):
    extra = {}
    layers = [base(), adjustment(CASES["hue-saturation"], "a"), adjustment(CASES["vibrance"], "b")]
    clamp = "layer"
    if what == "mask":
        layers[2] = RenderLayerSpec(
            id="b", tensors=adjustment_tensors(torch.ones(1, H, W), W, H), adjust=layers[2].adjust, opacity=0.8
        )
    elif what == "offset":
        layers[2] = RenderLayerSpec(
            id="b", tensors=adjustment_tensors(torch.ones(1, 4, 4), W, H), adjust=layers[2].adjust, offset=(3, 3)
        )
    elif what == "grad":
        layers[2] = adjustment(CASES["vibrance"], "b", opacity=torch.tensor(0.8, requires_grad=True))
    elif what == "dissolve":
        layers[2] = adjustment(CASES["vibrance"], "b", blend="dissolve")
    elif what == "output-clamp":
        clamp = "output"
    elif what == "lone":
        layers = layers[:2]
    plan = compile_plan(layers, (H, W), clamp=clamp, **extra)
    assert lut.lattice_runs(plan, 0, len(plan.steps), torch.float32) == {}


def test_gradients_take_the_exact_path():
    g = torch.Generator().manual_seed(3)
    colour = torch.rand(3, H, W, generator=g, requires_grad=True)
    layers = [RenderLayerSpec(id="base", tensors=LayerTensors(colour))]
    layers += [adjustment(CASES[n], n) for n in ("curves", "vibrance")]
    with torch.no_grad():
        fast = render(layers, canvas=(H, W)).image
    graded = render(layers, canvas=(H, W)).image
    graded.sum().backward()
    assert colour.grad is not None and torch.isfinite(colour.grad).all()
    assert float((fast - graded.detach()).abs().max()) <= lut.LUT_TOLERANCE + 1e-5


def test_the_renderer_cuts_runs_at_its_snapshots(monkeypatch):
    names = ("hue-saturation", "brightness-contrast", "exposure", "vibrance")
    layers = [base(), *(adjustment(CASES[n], n) for n in names)]
    r = Renderer((H, W))
    first = r.render(layers).image.clone()
    edited = [*layers[:-1], adjustment(CASES["vibrance"], "vibrance", opacity=0.5)]
    r.render(edited)  # restarts below the top layer: a snapshot cuts the run there
    again = r.render(layers).image
    assert torch.equal(first, again)
    err = float((again.double() - exact(layers, monkeypatch)).abs().max())
    assert err <= lut.LUT_TOLERANCE + 1e-5
