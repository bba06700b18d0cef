"""The fused (compiled) W3C kernels of ``lasagna.compose.fused``, and the heap thresholds of ``lasagna.heap``.

Fused renders are checked against the float64 reference of the spec (``numpy_ref``) on the stacks of
``test_blend_modes`` (an opaque full-canvas layer, one with alpha and a mask at an offset, a 1-channel one at
opacity 0.6, kink values mixed in), and against the eager kernels in float32. Compiling takes about a
second per mode and variant with a warm inductor cache (ten with a cold one), so the default suite compiles two modes
in all, overlay and soft-light); ``-m slow`` compiles all thirteen in both blend spaces.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from lasagna.compose import fused, render, set_fused
from lasagna.compose.blend import W3C_B
from lasagna.heap import MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES, tune_heap
from tests.compose import numpy_ref
from tests.compose.test_blend_modes import BG, CANVAS, mode_stack

# The default suite compiles one mode per test (cold inductor cache: ~10 s for overlay, ~12 s for hue).
SPEC_QUICK, F32_QUICK = "overlay", "soft-light"


def modes(quick: str) -> list:
    return [m if m == quick else pytest.param(m, marks=pytest.mark.slow) for m in W3C_B]


# Inductor builds the kernels with a C++ compiler found at run time (.ci/run installs g++).
needs_compiler = pytest.mark.skipif(
    not any(shutil.which(c) for c in ("g++", "c++", "clang++")), reason="no C++ compiler for torch.compile"
)


@pytest.fixture
def fused_on():
    set_fused(True)
    yield
    set_fused(False)
    fused._failed.clear()


@needs_compiler
@pytest.mark.parametrize("name", modes(SPEC_QUICK))
@pytest.mark.parametrize("blend_space", ["srgb", pytest.param("linear", marks=pytest.mark.slow)])
def test_fused_render_matches_the_spec_in_float64(name, blend_space, fused_on):
    layers = mode_stack(name, seed=1)
    ours = render(layers, canvas=CANVAS, background=BG, blend_space=blend_space).image
    assert name in fused._compiled and name not in fused._failed  # the compiled kernel ran
    ref = numpy_ref.composite(layers, CANVAS, BG, blend_space, "layer")
    np.testing.assert_allclose(ours.numpy(), ref, rtol=0, atol=1e-12)


@needs_compiler
@pytest.mark.parametrize("name", modes(F32_QUICK))
def test_fused_float32_within_two_ulp_of_eager(name, fused_on):
    layers = mode_stack(name, seed=3, dtype=torch.float32)
    canvas = CANVAS
    fast = render(layers, canvas=canvas, background=BG).image
    set_fused(False)
    eager = render(layers, canvas=canvas, background=BG).image
    # Inductor may contract a·b + c into one fused multiply-add: a rounding or two apart, no more.
    torch.testing.assert_close(fast, eager, rtol=0, atol=2 * torch.finfo(torch.float32).eps)


@needs_compiler
def test_fused_bands_and_batches(fused_on, monkeypatch):
    """Bands of a few rows (the last one shorter) and a batch dimension reuse one compiled graph."""
    from lasagna.compose import LayerTensors, RenderLayerSpec, engine

    monkeypatch.setattr(engine, "TILE_PIXELS", 3 * 11)  # 3 rows of 11 per band, 13 rows
    g = torch.Generator().manual_seed(4)
    base = RenderLayerSpec(id="b", tensors=LayerTensors(torch.rand(2, 3, 13, 11, generator=g, dtype=torch.float64)))
    top = RenderLayerSpec(
        id="t",
        blend="overlay",
        tensors=LayerTensors(torch.rand(2, 3, 13, 11, generator=g, dtype=torch.float64)),
        opacity=0.7,
    )
    ours = render([base, top], canvas=(13, 11)).image
    set_fused(False)
    eager = render([base, top], canvas=(13, 11)).image
    torch.testing.assert_close(ours, eager, rtol=0, atol=1e-15)


def test_fused_off_by_default_and_env(monkeypatch):
    monkeypatch.setattr(fused, "_state", {"enabled": None})
    monkeypatch.delenv(fused.ENV, raising=False)
    assert not fused.fused_enabled() and fused.fused_inplace("overlay") is None
    for value, on in (("1", True), ("yes", True), ("0", False), ("", False)):
        monkeypatch.setattr(fused, "_state", {"enabled": None})
        monkeypatch.setenv(fused.ENV, value)
        assert fused.fused_enabled() is on
    monkeypatch.setattr(fused, "_state", {"enabled": None})
    assert fused.fused_inplace("multiply") is None  # the basic modes are never compiled


def test_compile_failure_warns_once_and_falls_back(fused_on, monkeypatch):
    def broken(blend):
        raise RuntimeError("no C++ compiler found\nlong trace")

    monkeypatch.setattr(fused, "_make", broken)
    monkeypatch.setattr(fused, "_compiled", {})
    monkeypatch.setattr(fused, "_wrappers", {})
    layers = mode_stack("color-dodge", seed=5)
    with pytest.warns(RuntimeWarning, match=r"fused kernel for blend 'color-dodge' could not be compiled .*no C\+\+"):
        ours = render(layers, canvas=CANVAS, background=BG).image
    assert "color-dodge" in fused._failed and fused.fused_inplace("color-dodge") is None
    ref = numpy_ref.composite(layers, CANVAS, BG, "srgb", "layer")
    np.testing.assert_allclose(ours.numpy(), ref, rtol=0, atol=1e-12)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        render(layers, canvas=CANVAS, background=BG)  # no second warning


# ---- lasagna.heap ---------------------------------------------------------------------------------

# A fresh interpreter renders base + soft-light (about a dozen band-sized temporaries per band) at 1024²
# once, then five more times, and prints the minor page faults of those five (each is a page zeroed by
# the kernel) and the pages of one float32 RGB canvas for scale.
_FAULTS = textwrap.dedent(
    """
    import resource
    import torch
    from lasagna.compose import LayerTensors, RenderLayerSpec, render
    from lasagna.heap import tune_heap
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    layers = [
        RenderLayerSpec(id="b", tensors=LayerTensors(torch.rand(3, 1024, 1024, generator=g))),
        RenderLayerSpec(id="s", blend="soft-light", tensors=LayerTensors(torch.rand(3, 1024, 1024, generator=g))),
    ]
    out = torch.empty(3, 1024, 1024)
    render(layers, canvas=(1024, 1024), out=out)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        render(layers, canvas=(1024, 1024), out=out)
    print(tune_heap(), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before, out.numel() * 4 // 4096)
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_heap_thresholds_keep_band_temporaries_resident(tmp_path):
    import os
    import platform

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    runs = {}
    for heap in ("lasagna", "system"):
        env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES", "LASAGNA_HEAP"))}
        env["THP_MEM_ALLOC_ENABLE"] = "0"
        if heap == "system":
            env["LASAGNA_HEAP"] = "system"
        out = subprocess.run([sys.executable, "-c", _FAULTS], env=env, capture_output=True, text=True, check=True)
        tuned, faults, pages = out.stdout.split()
        runs[heap] = (tuned == "True", int(faults), int(pages))
    assert runs["lasagna"][0] and not runs["system"][0]
    pages = runs["system"][2]
    # The premise: with glibc's defaults, five renders fault in several canvases' worth of temporaries.
    assert runs["system"][1] > 5 * pages
    # Tuned, the temporaries stay mapped: 0 in most runs; the heap may still grow once by a few temporaries
    # when a render's allocation order differs (up to ~5000 pages seen, against ~167 000 untuned).
    assert runs["lasagna"][1] < runs["system"][1] / 10


def test_tune_heap_is_idempotent():
    first = tune_heap()
    assert tune_heap() is first
    band = 3 * (1 << 18) * 4  # one temporary of a 2^18-pixel RGB float32 band (engine.TILE_PIXELS)
    assert MMAP_THRESHOLD_BYTES > band  # served from the heap, not by mmap
    assert TRIM_THRESHOLD_BYTES > 18 * band  # soft-light's ~18 temporaries freed without a trim


_PROFILE = textwrap.dedent(
    """
    import sys
    from lasagna.heap import heap_profile, tune_heap
    print(tune_heap(sys.argv[1]), tune_heap("compute"), heap_profile())
    """
)


@pytest.mark.parametrize(
    ("asked", "env", "expect"),
    [
        ("compute", None, "compute"),
        ("server", None, "server"),
        ("server", "compute", "compute"),
        ("compute", "system", "system"),
    ],
)
def test_heap_profiles_first_call_wins_and_env_overrides(asked, env, expect):
    import os
    import platform

    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc's mallopt")
    envs = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES", "LASAGNA_HEAP"))}
    if env is not None:
        envs["LASAGNA_HEAP"] = env
    out = subprocess.run([sys.executable, "-c", _PROFILE, asked], env=envs, capture_output=True, text=True, check=True)
    first, second, profile = out.stdout.split()
    assert first == second == str(expect != "system") and profile == expect


def test_serve_session_asks_for_the_server_profile(tmp_path):
    import os
    import platform
    import shutil

    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc's mallopt")
    stack = tmp_path / "basic"
    shutil.copytree(Path(__file__).resolve().parents[2] / "examples" / "stacks" / "basic", stack)
    code = (
        "import sys\nfrom lasagna.heap import heap_profile\nfrom lasagna.serve.session import EditSession\n"
        "EditSession(sys.argv[1])\nprint(heap_profile())"
    )
    envs = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES", "LASAGNA_HEAP"))}
    out = subprocess.run([sys.executable, "-c", code, str(stack)], env=envs, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["server"]
