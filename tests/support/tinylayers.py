"""A tiny learned-layer catalogue for tests: random networks with the real formats, built in milliseconds.

``tiny_catalogue(folder)`` writes, under ``folder``:

    shading/preset.json + shading/generator/   the real shading preset with a short distill (4 steps)
                                               and a random amortised LayerGenerator
    color/preset.json                          the real colour preset, 4 steps, no generator
    light/preset.json                          the real light preset, 4 steps, no generator
    relight/preset.json                        the real relight preset (lit image → ratio), 4 steps, no generator
    relight-32/                                a random UNetPrior (8×8, conditioned on RGB), the world's labels
    recolor-32/                                a random UNetPrior (8×8, conditioned on luma), label "natural"
    light-32/                                  a random UNetPrior (8×8, conditioned on RGB), labels warm, cool, white
    relit-32/                                  a random UNetPrior (8×8, conditioned on the lit RGB and any light
                                               direction: the world's labels or az=…,el=…)
    relight-32-bhat/                           a random LMC-SDS corrective network for relight-32
    relight-32-spectral/, recolor-32-spectral/, light-32-spectral/
                                               random spectral correctives (the presets' b̂)
    surface-albedo-32/, surface-lit-32/,       random surface estimators (unlit and lit input), working size 16
    surface-lit-closeup-32/,                   (surface-lit-told-32 also reads a source light it is told)
    surface-lit-told-32/

The names are the bundled ones, so a folder put first in ``LASAGNA_LAYERS`` shadows the real catalogue.
The weights are random but not the identity (every parameter gets noise), so outputs depend on input.

"Tiny" in the tests means this catalogue and nothing else. tests/conftest.py builds it once per session
(the ``tiny`` fixture); a module that needs a variant copies it (``tiny_variant``) and rewrites a preset
(``write_preset``), never changing the shared one.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
PRIOR_RES = 8
STEPS = 4


def _jitter(module: torch.nn.Module, seed: int, scale: float = 0.05) -> torch.nn.Module:
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=gen))
    return module


def write_preset(folder: Path, name: str, **changes) -> dict:
    """The bundled preset ``name`` with a short distill (``STEPS``) and ``changes``, written under ``folder``.

    The free per-pixel layer is the tiny presets' layer kind unless ``changes`` say otherwise: the shipped shading
    preset makes a surface, and the tests of the free layer's paths (generators, methods, refinement) need it;
    the surface route is tested with ``layer_kind="surface"`` (tests/test_surface_edit.py)."""
    data = json.loads((ROOT / "layers" / name / "preset.json").read_text(encoding="utf-8"))
    data["distill"]["steps"] = STEPS
    data["layer_kind"] = "free"
    data.update(changes)
    (folder / name).mkdir(parents=True, exist_ok=True)
    (folder / name / "preset.json").write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    return data


def _prior(cond_channels: int, vocabulary: tuple[str, ...], seed: int, directions: bool = False):
    from lasagna.priors.unet import UNetConfig, UNetPrior

    config = UNetConfig(
        image_channels=3,
        cond_channels=cond_channels,
        resolution=PRIOR_RES,
        channels=(8, 16),
        norm_groups=4,
        vocabulary=vocabulary,
        directions=directions,
    )
    torch.manual_seed(seed)
    return _jitter(UNetPrior(config), seed).eval()


def _spectral(seed: int):
    """A spectral corrective at the tiny priors' size with random gains near the identity."""
    from lasagna.losses.spectral import SpectralCorrective, SpectralCorrectiveConfig

    model = SpectralCorrective(SpectralCorrectiveConfig(channels=3, height=PRIOR_RES, width=PRIOR_RES, buckets=4))
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        model.gain_real.mul_(1 - 0.3 * torch.rand(model.gain_real.shape, generator=gen))
    return model.eval()


def tiny_catalogue(folder: str | Path, *, generator: bool = True, priors: bool = True) -> Path:
    from lasagna.generators.layer import LayerSpec
    from lasagna.generators.unet import LayerGenerator, LayerGeneratorConfig
    from lasagna.losses.corrective import Corrective, CorrectiveConfig
    from lasagna.world import GLOW_VOCABULARY, VOCABULARY

    folder = Path(folder)
    # method None: the tiny shading keeps the amortised default, so the generator paths are what the
    # default runs here; the method and refine_steps fields are tested on their own (test_edit).
    shading = write_preset(folder, "shading", method=None)
    write_preset(folder, "color")
    write_preset(folder, "light")
    write_preset(folder, "relight")
    if generator:
        cfg = LayerGeneratorConfig(
            layer=LayerSpec(blend="multiply", channels=1, range=tuple(shading["range"])),
            vocabulary=tuple(shading["vocabulary"]),
            channels=(4, 8),
        )
        torch.manual_seed(1)
        _jitter(LayerGenerator(cfg), 1, 0.2).save_pretrained(folder / "shading" / "generator")
    if priors:
        _prior(3, tuple(VOCABULARY), 2).save_pretrained(folder / "relight-32")
        _prior(1, ("natural",), 3).save_pretrained(folder / "recolor-32")
        _prior(3, tuple(GLOW_VOCABULARY), 7).save_pretrained(folder / "light-32")
        _prior(3, tuple(VOCABULARY), 9, directions=True).save_pretrained(folder / "relit-32")
        torch.manual_seed(4)
        corrective = Corrective(CorrectiveConfig(channels=3, resolution=PRIOR_RES, filters=(4, 8)))
        _jitter(corrective, 4).save_pretrained(folder / "relight-32-bhat")
        for seed, name in ((5, "relight-32-spectral"), (6, "recolor-32-spectral"), (8, "light-32-spectral")):
            _spectral(seed).save_pretrained(folder / name)
    _estimators(folder)
    return folder


def _estimators(folder: Path) -> None:
    """Random surface estimators under the bundled names, each with a silhouette head: surface-albedo-32 (reads the
    unlit base), surface-lit-32 and surface-lit-closeup-32 (read a lit image, fit its source light; the second is
    the relight preset's) and surface-lit-told-32 (reads a lit image and the source light it is told: the relight
    preset's ``surface.told``)."""
    from lasagna.generators.surface import SurfaceConfig, SurfaceEstimator

    for seed, name, kind in (
        (10, "surface-albedo-32", "albedo"),
        (11, "surface-lit-32", "lit"),
        (12, "surface-lit-closeup-32", "lit"),
        (13, "surface-lit-told-32", "lit"),
    ):
        torch.manual_seed(seed)
        # Each has a silhouette head, as the bundled ones do (the shading and relight presets' dome prior).
        told = name == "surface-lit-told-32"
        config = SurfaceConfig(
            input=kind, silhouette=True, channels=(4, 8), blocks=1, working_size=16, light_input=told
        )
        net = SurfaceEstimator(config)
        _jitter(net, seed, 0.1).save_pretrained(folder / name)


def tiny_variant(tiny: Path, folder: str | Path, *, generator: bool = True) -> Path:
    """A copy of the shared tiny catalogue ``tiny`` at ``folder`` (without the shading generator if
    ``generator`` is false), for a module to change; the shared one stays as built."""
    folder = Path(shutil.copytree(tiny, folder))
    if not generator:
        shutil.rmtree(folder / "shading" / "generator")
    return folder


def fingerprint(folder: Path) -> dict[str, int]:
    """Every file under ``folder`` and a hash of its bytes: the shared catalogue's, compared at the end of the
    session so a test that changed it fails instead of changing what later tests see."""
    return {str(p.relative_to(folder)): hash(p.read_bytes()) for p in sorted(folder.rglob("*")) if p.is_file()}
