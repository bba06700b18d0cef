"""Learned layers for users: fill a learned layer of an image or stack, re-render one from its stack.

    from lasagna.edit import edit, render_learned
    result = edit("photo.png", "shading", "left")              # EditResult: stack, layer, composite, …
    result.save("out/relit")                                   # stack.json, layers/, generators/, composite.png, stack.ora
    render_learned("out/relit", all=True)                      # the stack document alone reproduces the layer

**What the generator sees.** A learned layer is conditioned on the layer ``conditioned_on``: its input
is the composite of the stack from the bottom up to and including that layer (for a single opaque
base layer, the base itself). ``edit`` puts the new layer on top, conditioned on the top layer
unless ``on`` names another: an image's edit is conditioned on the image, a stack's on its composite.

**How the layer is made** (``settings["method"]``, recorded in the layer with everything it used):

* ``amortised`` — the preset's amortised generator (``<catalogue>/<preset>/generator/``; the LMC-SDS
  image-to-image network) in one forward pass. Fully convolutional: any image size. Its weights are
  copied into the stack (``generators/<id>/``; the layer's ``generator`` names the file and its
  SHA-256), so the stack does not depend on the catalogue keeping them. ``optimize`` N > 0 then
  refines the layer per image: a free per-pixel layer starting from the generator's output is
  distilled for N steps (``distill_image``, the preset's loss, ω, lr and seed). It starts from an
  edit, not from the identity, so the L2 pull toward the input that eases a run out of the identity
  is off (``Weights()``: score only).
* ``per-image`` — no amortised generator (or ``generator="free"``): a free layer from the identity
  edit, distilled for the preset's ``distill.steps`` (or ``optimize``/``steps``) with its defaults.
  Images larger than the prior use the LMC-SDS patch strategy (``lasagna.distill.per_image``).

The layer itself is made by ``lasagna.learned.make_layer``, for ``edit`` and ``render_learned`` alike.
Per-image runs are seeded (``settings.distill.seed``), so ``render_learned`` reproduces them from the
stored settings, the stack's pixels and the catalogue's prior (whose SHA-256 is recorded and checked).
Learned layers are distilled on stored (sRGB-encoded) values, as the composite of a
``blend_space: "srgb"`` stack blends them; a ``linear`` stack is refused rather than edited in a
space its prior never scored.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor

from lasagna import __version__
from lasagna import catalogue as cat
from lasagna.document import LearnedLayer
from lasagna.errors import DocumentError, ImageError, LasagnaError, PathError
from lasagna.io.stack import Stack, load_stack, resolve_inside, save_stack
from lasagna.learned import LayerRun, Method, as_stored, choose_method, conditioning_input, file_sha256, make_layer

# The largest canvas ``edit`` accepts by default. The generator runs at full resolution: at 2048² its
# first level alone holds 16 channels × 4 bytes × 4.2 M pixels = 268 MB per activation, a few GB in
# all — what a CPU session can still afford. Larger images need max_pixels raised on purpose.
DEFAULT_EDIT_MAX_PIXELS = 2048 * 2048
META_KEY = "lasagna.edit"  # document metadata: per learned layer, the tool version, time, timing


@dataclass
class EditResult:
    """An edited stack in memory: ``stack`` (the new learned layer ``layer_id`` included, with pixels),
    the layer's values (C, H, W), the composite (3, H, W) in [0, 1], the per-image ``history`` (empty
    for one forward pass), seconds taken, and the files the stack folder needs besides its PNGs."""

    stack: Stack
    layer_id: str
    layer: Tensor
    composite: Tensor
    settings: dict[str, Any]
    seconds: float
    history: list[dict[str, Any]]
    files: dict[str, bytes]

    def save(self, out: str | os.PathLike, *, force: bool = False, ora: bool = True,
             warn: Callable[[str], None] | None = None) -> Path:
        """Write the stack folder ``out`` (see ``write_stack_folder``); returns it."""
        return write_stack_folder(self.stack, out, files=self.files, force=force, ora=ora, warn=warn)


# ---- inputs ----------------------------------------------------------------------------------------


def read_image(path: str | os.PathLike, max_pixels: int = DEFAULT_EDIT_MAX_PIXELS) -> Stack:
    """An image file as a one-layer stack (layer ``base``): PNG through ``lasagna.io.png`` (8/16-bit,
    bomb guards), anything else Pillow opens (JPEG, …) with its size checked before decoding and its
    EXIF orientation applied (as viewers show it)."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    from lasagna.io.png import PNG_SIGNATURE, read_png

    p = Path(path)
    where = str(p)
    try:
        with open(p, "rb") as fh:
            magic = fh.read(8)
    except OSError as exc:
        raise ImageError(f"cannot read ({exc.strerror or exc}); expected an image file or a stack folder", where) from None
    if magic == PNG_SIGNATURE:
        png = read_png(p, max_pixels=max_pixels)
        depth = 16 if png.header.bit_depth == 16 else 8
        color = torch.from_numpy(png.color)
        alpha = torch.from_numpy(png.alpha) if png.alpha is not None else None
        return Stack.from_image(color, alpha=alpha, bit_depth=depth, name=p.stem)
    try:
        with Image.open(p) as im:
            w, h = im.size
            if w * h > max_pixels:
                raise ImageError(f"image is {w}x{h} = {w * h} pixels, over the limit of {max_pixels}; expected at most "
                                 f"{max_pixels} pixels (raise --max-pixels if this is intended)", where)
            im = ImageOps.exif_transpose(im)
            im = im.convert("RGBA" if im.mode in ("RGBA", "LA", "PA") or "transparency" in im.info else "RGB")
            im.load()
    except ImageError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
        raise ImageError(f"cannot decode ({type(exc).__name__}: {exc}); expected a PNG, JPEG or another image Pillow reads",
                         where) from None
    return Stack.from_image(im, name=p.stem)


def input_stack(image, max_pixels: int = DEFAULT_EDIT_MAX_PIXELS) -> Stack:
    """The stack to edit: a stack folder (or its stack.json), an image file, a ``Stack`` (copied), or an
    image given as a tensor (values), numpy array or PIL image (``Stack.from_image``)."""
    if isinstance(image, Stack):
        stack = Stack(image.document, image.folder, dict(image.tensors), dict(image.bit_depths))
    elif isinstance(image, (str, os.PathLike)):
        p = Path(image)
        if p.is_dir() or p.suffix.lower() == ".json":
            stack = load_stack(p, max_pixels=max_pixels)
        elif not p.exists():
            raise PathError("does not exist; expected an image file (PNG, JPEG) or a stack folder", str(p))
        else:
            stack = read_image(p, max_pixels)
    else:
        stack = as_stored(Stack.from_image(image))
    if isinstance(image, Stack):
        stack = as_stored(stack)
    if stack.width * stack.height > max_pixels:
        raise ImageError(f"canvas is {stack.width}x{stack.height} = {stack.width * stack.height} pixels, over the limit "
                         f"of {max_pixels}; expected at most {max_pixels} pixels (raise --max-pixels if intended)", "image")
    if stack.document.blend_space != "srgb":
        raise DocumentError(f"blend_space is {stack.document.blend_space!r}; learned layers are distilled on stored "
                            "(sRGB-encoded) values, expected blend_space 'srgb'", "blend_space")
    return stack


def _unique_id(stack: Stack, wanted: str) -> str:
    from lasagna.document.types import check_id

    taken = {i.casefold() for i in stack.ids}
    candidate, n = wanted, 2
    while candidate.casefold() in taken:
        candidate, n = f"{wanted}-{n}", n + 1
    try:
        return check_id(candidate)
    except ValueError as exc:
        raise DocumentError(str(exc), "id") from None


def edit(
    image,
    preset: str = "shading",
    condition: str = "left",
    *,
    on: str | None = None,
    id: str | None = None,
    generator: Method | None = None,
    optimize: int | None = None,
    steps: int | None = None,
    loss: str | None = None,
    guidance: float | None = None,
    seed: int | None = None,
    lr: float | None = None,
    catalogue_dirs=None,
    max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
    device: str | torch.device = "cpu",
    progress: bool = False,
) -> EditResult:
    """Add a learned layer of ``preset`` for ``condition`` on top of ``image`` (module docstring).

    ``image``: an image file, a stack folder, a ``Stack``, or a tensor/array/PIL image. ``on``: the
    layer it is conditioned on (default: the top layer). ``generator``: ``"amortised"`` or ``"free"``
    (default: amortised if the preset has a generator). ``optimize``/``steps`` (the same number; give
    one): per-image steps — after the amortised pass (default 0), or of the free layer (default the
    preset's). ``loss``, ``guidance``, ``seed``, ``lr`` override the preset's ``distill`` defaults.
    """
    start = time.monotonic()
    if preset is None or "/" in str(preset) or isinstance(preset, os.PathLike):
        raise LasagnaError(f"preset {str(preset)!r} is not a name; expected a catalogue name (add a catalogue folder "
                           "with LASAGNA_LAYERS)", "preset")
    if optimize is not None and steps is not None and optimize != steps:
        raise LasagnaError(f"optimize {optimize} and steps {steps} differ; expected one of them (they are the same number)",
                           "steps")
    n = optimize if optimize is not None else steps
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 0):
        raise LasagnaError(f"expected a non-negative integer, got {n!r}", "optimize")
    stack = input_stack(image, max_pixels)
    resolved = cat.resolve(preset, stack.folder, catalogue_dirs, need_prior=False)
    p = resolved.preset
    p.prompt_for(condition)  # ConditionError listing the vocabulary
    on = on if on is not None else stack.ids[-1]
    stack.document.index(on)  # DocumentError listing the ids
    method = choose_method(resolved, generator)
    if method == "per-image" and n == 0:
        raise LasagnaError("per-image optimisation with 0 steps would leave the identity edit; expected --optimize N > 0",
                           "optimize")
    optimize_n = (0 if method == "amortised" else p.distill.steps) if n is None else n
    layer_id = _unique_id(stack, id or f"{p.name}-{condition}")
    base = conditioning_input(stack, on)
    carried = carried_files(stack)  # before the new layer: its generator is not in the input folder
    run = make_layer(base, resolved, condition, layer_id, method=method, optimize=optimize_n,
                     generator_dir=resolved.generator, loss=loss, guidance=guidance, seed=seed, lr=lr,
                     catalogue_dirs=catalogue_dirs, device=device, progress=progress)
    place_layer(stack, layer_id, p, condition, on, run)
    seconds = time.monotonic() - start
    _record(stack, layer_id, seconds, run, image)
    composite = stack.render().image.detach().clamp(0.0, 1.0)
    return EditResult(stack=stack, layer_id=layer_id, layer=run.layer, composite=composite, settings=run.settings,
                      seconds=seconds, history=run.history, files={**carried, **run.files})


def place_layer(stack: Stack, layer_id: str, preset, label: str, on: str, run: LayerRun) -> None:
    """Add (or update) the learned layer ``layer_id`` with ``run``'s pixels, settings and generator."""
    fields = {"id": layer_id, "name": f"{preset.name.capitalize()} ({label})", "kind": "learned", "blend": preset.blend,
              "range": list(preset.range), "preset": preset.name, "condition": {"label": label},
              "conditioned_on": on, "generator": run.generator_ref, "settings": run.settings}
    if layer_id in stack.ids:
        old = stack.document.layer(layer_id).model_dump(mode="json")
        stack.document = stack.document.with_layer({**old, "generator": run.generator_ref, "settings": run.settings})
    else:
        stack.document = stack.document.with_layer(fields)
    stack.set_pixels(layer_id, run.layer, bit_depth=16)
    as_stored(stack, [layer_id])


def _record(stack: Stack, layer_id: str, seconds: float, run: LayerRun, source=None, *, rendered: bool = False) -> None:
    """metadata["lasagna.edit"][layer_id]: tool version, when, seconds, steps run and why they stopped
    (a re-render keeps the edit's record and adds when and how long it took)."""
    meta = dict(stack.document.metadata)
    entries = dict(meta.get(META_KEY) or {}) if isinstance(meta.get(META_KEY), dict) else {}
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    old = entries.get(layer_id) if isinstance(entries.get(layer_id), dict) else {}
    if rendered:
        entry = {**old, "tool": f"lasagna {__version__}", "rendered": now, "render_seconds": round(seconds, 3)}
    else:
        entry = {"tool": f"lasagna {__version__}", "created": now, "seconds": round(seconds, 3),
                 "generate_seconds": round(run.seconds, 3), "steps_run": len(run.history), "stopped": run.stopped}
        if isinstance(source, (str, os.PathLike)):
            entry["input"] = Path(source).name
    entries[layer_id] = entry
    meta[META_KEY] = entries
    stack.document = stack.document.replace(metadata=meta)


def carried_files(stack: Stack) -> dict[str, bytes]:
    """Files of the input stack folder its document needs besides layer PNGs: the generators of its
    learned layers and presets shipped in it (``layers/<preset>/preset.json``)."""
    if stack.folder is None:
        return {}
    out: dict[str, bytes] = {}
    for i, layer in enumerate(stack.document.layers):
        if not isinstance(layer, LearnedLayer):
            continue
        if layer.generator is not None:
            ckpt = resolve_inside(stack.folder, layer.generator.checkpoint, f"layers[{i}].generator.checkpoint")
            rel = Path(layer.generator.checkpoint)
            for name in (rel, rel.parent / "config.json"):
                src = stack.folder / name
                if src.is_file():
                    out[name.as_posix()] = src.read_bytes()
            if not ckpt.is_file():
                raise PathError(f"{layer.generator.checkpoint!r} does not exist; expected the generator's weights",
                                f"layers[{i}].generator.checkpoint")
        shipped = stack.folder / "layers" / layer.preset / "preset.json"
        if "/" not in layer.preset and shipped.is_file():
            out[f"layers/{layer.preset}/preset.json"] = shipped.read_bytes()
    return out


# ---- re-rendering -------------------------------------------------------------------------------------


def render_learned(
    stack, *, all: bool = False, catalogue_dirs=None, device: str | torch.device = "cpu", progress: bool = False,
    write: bool = True, warn: Callable[[str], None] | None = None,
) -> tuple[Stack, list[str]]:
    """Render the learned layers of ``stack`` (a folder or a ``Stack``) that have no pixels (every one
    with ``all``), bottom to top, from their stored generator and settings; returns (stack, ids rendered).

    A layer whose settings are empty is made as ``edit`` would make it and its settings are filled
    in. With ``write`` (and a folder), the layer PNGs, generator copies, stack.json, composite.png —
    and stack.ora if the folder has one — are written back, each atomically, stack.json after the
    layers it names.
    """
    from lasagna.io.atomic import atomic_write_bytes

    if not isinstance(stack, Stack):
        stack = load_stack(stack)
    if stack.document.blend_space != "srgb":
        raise DocumentError(f"blend_space is {stack.document.blend_space!r}; expected 'srgb' for learned layers",
                            "blend_space")
    rendered: list[str] = []
    files: dict[str, bytes] = {}
    for layer in list(stack.document.layers):
        if not isinstance(layer, LearnedLayer) or (layer.id in stack.tensors and not all):
            continue
        start = time.monotonic()
        run = _rerun(stack, layer, catalogue_dirs, device, progress)
        place_layer(stack, layer.id, cat.load_preset(layer.preset, stack.folder, catalogue_dirs), layer.condition.label,
                    layer.conditioned_on, run)
        files.update(run.files)
        _record(stack, layer.id, time.monotonic() - start, run, rendered=True)
        rendered.append(layer.id)
    if write and stack.folder is not None and rendered:
        from lasagna.export.ora import export_ora
        from lasagna.io.render import write_composite

        folder = stack.folder
        for rel, data in files.items():
            atomic_write_bytes(resolve_inside(folder, rel, rel), data)
        save_stack(stack, folder)
        result = stack.render()
        write_composite(result, folder / "composite.png")
        if (folder / "stack.ora").is_file():
            export_ora(stack, folder / "stack.ora", composite=result.image, warn=warn)
    return stack, rendered


def _rerun(stack: Stack, layer: LearnedLayer, catalogue_dirs, device, progress) -> LayerRun:
    """A learned layer made again from what the stack stores (see ``render_learned``)."""
    where = f"layer {layer.id!r}"
    resolved = cat.resolve(layer.preset, stack.folder, catalogue_dirs, need_prior=False)
    preset = resolved.preset
    preset.prompt_for(layer.condition.label)
    s = dict(layer.settings)
    method = s.get("method")
    if method is None:
        method = choose_method(resolved, None)
    if method not in ("amortised", "per-image"):
        raise DocumentError(f"settings.method is {method!r}; expected 'amortised' or 'per-image'", f"{where}.settings.method")
    optimize = s.get("optimize", 0 if method == "amortised" else preset.distill.steps)
    if isinstance(optimize, bool) or not isinstance(optimize, int) or optimize < 0:
        raise DocumentError(f"settings.optimize is {optimize!r}; expected a non-negative integer", f"{where}.settings.optimize")
    distill = s.get("distill")
    if distill is not None and not isinstance(distill, dict):
        raise DocumentError("settings.distill is not an object; expected the distillation settings", f"{where}.settings.distill")
    generator_dir = resolved.generator
    if method == "amortised" and layer.generator is not None:
        if stack.folder is None:
            raise PathError("the stack has no folder to find its generator in; expected a stack loaded from a folder", where)
        ckpt = resolve_inside(stack.folder, layer.generator.checkpoint, f"{where}.generator.checkpoint")
        if not ckpt.is_file():
            raise PathError(f"{layer.generator.checkpoint!r} does not exist; expected the generator's weights",
                            f"{where}.generator.checkpoint")
        if layer.generator.sha256 is not None and file_sha256(ckpt) != layer.generator.sha256:
            raise LasagnaError("the generator's weights do not match the recorded sha256; expected the file the "
                               "layer was made with", f"{where}.generator.checkpoint")
        generator_dir = ckpt.parent
    base = conditioning_input(stack, layer.conditioned_on)
    refs = {k: s[k] for k in ("prior", "corrective") if isinstance(s.get(k), str)}
    working = s.get("working_size", "full")  # a layer recorded without one was made at the base's size
    if working != "full" and (isinstance(working, bool) or not isinstance(working, int) or not 8 <= working <= 4096):
        raise DocumentError(f"settings.working_size is {working!r}; expected an integer in [8, 4096]",
                            f"{where}.settings.working_size")
    run = make_layer(base, resolved, layer.condition.label, layer.id, method=method, optimize=optimize,
                     generator_dir=generator_dir, distill=distill, refs=refs, catalogue_dirs=catalogue_dirs,
                     device=device, progress=progress, working=working)
    recorded = s.get("prior_sha256")
    if recorded is not None and run.settings.get("prior_sha256") not in (None, recorded):
        warnings.warn(f"{where}: the catalogue's prior {run.settings.get('prior')!r} differs from the one the layer was "
                      "made with (sha256); the layer is re-rendered with the current one", stacklevel=2)
    if layer.generator is not None and method == "amortised":
        run.generator_ref = layer.generator.model_dump(mode="json")
        run.files = {}  # already in the stack folder
    return run


# ---- writing -----------------------------------------------------------------------------------------


def check_output_folder(out: str | os.PathLike, *, force: bool = False) -> Path:
    """Refuse an output folder that cannot be (re)written, before any work: a file, a non-empty folder
    (unless ``force`` and it holds a stack.json: then it is replaced as a whole), an unwritable place."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise PathError("exists and is not a folder; expected a folder to write the stack into", str(out))
    if out.is_dir() and any(out.iterdir()):
        if not force:
            raise PathError("is not empty; expected a new or empty folder (or --force to replace a stack folder)", str(out))
        if not (out / "stack.json").is_file():
            raise PathError("is not empty and holds no stack.json; --force replaces only a stack folder", str(out))
    probe = out.parent
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise PathError(f"{probe} is not a writable folder; expected a writable location", str(out))
    return out


def write_stack_folder(stack: Stack, out: str | os.PathLike, *, files: dict[str, bytes] | None = None,
                       force: bool = False, ora: bool = True, warn: Callable[[str], None] | None = None) -> Path:
    """Write ``stack`` as the folder ``out``: stack.json, layers/, masks/, ``files`` (relative path →
    bytes, e.g. generators/), composite.png and (``ora``) stack.ora.

    Everything is written into a temporary sibling folder which is then renamed to ``out``: a failure
    leaves no half-written stack and ``out`` as it was. With ``force`` an existing stack folder is
    replaced (renamed aside, the new one renamed in, the old one removed).
    """
    from lasagna.export.ora import export_ora
    from lasagna.io.atomic import atomic_write_bytes
    from lasagna.io.render import write_composite

    out = check_output_folder(out, force=force)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    old_folder = stack.folder
    try:
        save_stack(stack, tmp)
        for rel, data in (files or {}).items():
            atomic_write_bytes(resolve_inside(tmp, rel, rel), data)
        result = stack.render()
        write_composite(result, tmp / "composite.png")
        if ora:
            export_ora(stack, tmp / "stack.ora", composite=result.image, warn=warn)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; a folder made by mkdir would not be
        _swap_in(tmp, out)
    except BaseException:
        stack.folder = old_folder
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    stack.folder = out
    return out


def _swap_in(tmp: Path, out: Path) -> None:
    """Rename ``tmp`` to ``out``; an existing ``out`` (empty, or a stack when forced) is replaced."""
    if not out.exists():
        os.rename(tmp, out)
        return
    if not any(out.iterdir()):
        out.rmdir()
        os.rename(tmp, out)
        return
    aside = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
    aside.rmdir()
    os.rename(out, aside)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(aside, out)
        raise
    shutil.rmtree(aside, ignore_errors=True)


def summary(result: EditResult) -> dict[str, Any]:
    """A JSON-able one-look summary of an edit (what the CLI prints)."""
    s = result.settings
    return {"layer": result.layer_id, "method": s.get("method"), "optimize": s.get("optimize"),
            "seconds": round(result.seconds, 3), "range": [float(result.layer.min()), float(result.layer.max())]}


__all__ = ["DEFAULT_EDIT_MAX_PIXELS", "EditResult", "check_output_folder", "edit", "input_stack", "read_image",
           "render_learned", "write_stack_folder"]
