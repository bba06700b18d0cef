"""``lasagna demo``: relight, colourise and add light to the bundled examples, and draw one sheet a person can look at.

Inputs (a checkout's ``examples/``): held-out world scenes (``examples/world/``, made by
``examples/make_world.py`` with ``write_world``) and small real photographs (``examples/photos/``, crops of
scikit-image's CC0 / public-domain samples). Outside a checkout (an installed wheel) the same inputs come from
the package alone (``packaged_examples``): the world scenes rendered again — the world is procedural, so they
are the committed files bit for bit — and the photographs the package ships (``lasagna/_data/photos``). For each:

* **relight** (preset ``shading``) in several directions: a world scene's albedo, or a photograph,
  gets a learned multiply layer; the world's true shading stays in the stack, hidden, and the truth
  column shows the scene rendered under that direction (``lasagna.world``);
* **colourise** (preset ``color``): the Rec. 709 gray of the image gets a learned RGBA layer; the
  truth column shows the original colours;
* **add light** (preset ``light``): the image as it is gets a learned ``plus`` layer of a warm or
  cool fill light; for a world scene the truth column shows the world's own fill light of that
  label added (``lasagna.world.tasks.additive_light``);
* **relight what is lit** (preset ``relight``, the Lasagna paper's setting): a lit image — a world
  scene lit by its relight task's source light (``lasagna.world.tasks.relight_sources``), or a
  photograph as it is — gets a luminosity-ratio layer in [0, 4] toward a named light and toward a
  direction between the named ones (``RELIGHT_TO``); for a world scene the truth column shows the
  scene rendered under that light.

Each edit is ``lasagna.editing.edit`` with the preset's default method (``lasagna edit``'s: the preset's
``method``, else its amortised generator when the catalogue has one, else a per-image optimisation with
the preset's settings) — written as a stack folder under
``OUT/stacks/``. ``OUT/sheet.png`` has one labelled row per edit: input | layer | composite | truth.
The layer is drawn as stored (v = (y − lo)/(hi − lo): a shading of 1 is mid-gray; an RGBA layer over
a checkerboard). A preset whose prior and generator are both missing is skipped with one line; if
nothing can run, the demo composites and exports the example stack instead (``fallback``).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from lasagna import catalogue as cat
from lasagna.atomic import atomic_write_bytes
from lasagna.errors import LasagnaError
from lasagna.learned import choose_method

DIRECTIONS = ("left", "right", "top", "bottom")  # relighting directions shown for every input
WORLD_SCENES = 2  # held-out scenes relit and colourised
PHOTOS = ("coffee", "helmet", "chelsea")  # photographs relit; the first COLOURISED_PHOTOS are also colourised
COLOURISED_PHOTOS = 2
GLOWS = ("warm", "cool")  # world scene / photograph k gets a GLOWS[k % 2] light; the first LIT_PHOTOS photos
LIT_PHOTOS = 2
RELIGHT_TO = ("right", "az=135,el=40")  # relight targets: a named light and any direction (az, el in degrees)
# Per-image steps when a preset has no amortised generator: None = the preset's own distill.steps
# (150 for shading: ~1.5 s per 64² edit on this CPU with the 32² relighting prior, early stopping included).
DEMO_STEPS: int | None = None
# Per-image steps after an amortised generator's pass (``lasagna edit --optimize``). None: the preset's
# refine_steps — the demo shows what ``lasagna edit`` does by default.
DEMO_REFINE: int | None = None
# The world scenes: examples/make_world.py writes them into examples/world/, and the demo renders the same bits
# where there is no checkout (a world scene is its split, seed, index and resolution: lasagna.world is procedural).
WORLD_SPLIT, WORLD_COUNT, WORLD_SEED, WORLD_RESOLUTION = "heldout", 4, 0, 64
# The demo's photographs shipped in the package (examples/make_photos.py copies them there from examples/photos).
PACKAGED_PHOTOS = Path(__file__).resolve().parent / "_data" / "photos"
CELL = 128  # pixels per image cell in the sheet (64² scenes and 96² photos, enlarged without smoothing)
LABEL_WIDTH = 200


@dataclass
class Row:
    title: str  # e.g. "coffee.png · shading · left"
    detail: str  # how it was made and how long it took
    input: Tensor  # (3, H, W) in [0, 1]
    layer: Tensor  # (3, H, W) in [0, 1]: the layer as drawn
    composite: Tensor
    truth: Tensor | None


def examples_root() -> Path | None:
    """The ``examples`` folder of a checkout (beside the package), or under the current folder; None outside one."""
    for root in (Path(__file__).resolve().parents[1], Path.cwd()):
        if (root / "examples" / "photos").is_dir() and (root / "examples" / "world").is_dir():
            return root / "examples"
    return None


def write_world(out: str | Path) -> list[Path]:
    """Write the demo's world scenes (``WORLD_*``) as stack folders under ``out``, and ``world.json``: what
    ``examples/make_world.py`` commits to ``examples/world/``."""
    from lasagna.world.export import write_world_stacks

    return write_world_stacks(out, WORLD_SPLIT, WORLD_COUNT, WORLD_SEED, WORLD_RESOLUTION, "shading")


def packaged_examples(folder: str | Path) -> Path:
    """An ``examples`` folder made from the package alone, for an install without a checkout: ``folder/world``
    rendered by ``write_world`` (the checkout's ``examples/world`` bit for bit) and ``folder/photos`` the
    photographs the package ships (``PACKAGED_PHOTOS``, the checkout's ``examples/photos`` files). Returns
    ``folder``."""
    folder = Path(folder)
    write_world(folder / "world")
    (folder / "photos").mkdir(parents=True, exist_ok=True)
    for name in PHOTOS:
        shutil.copyfile(PACKAGED_PHOTOS / f"{name}.png", folder / "photos" / f"{name}.png")
    return folder


@contextmanager
def demo_examples(examples: Path | None = None, say: Callable[[str], None] | None = None) -> Iterator[Path]:
    """The examples folder the demo reads: ``examples`` if given, else a checkout's (``examples_root``), else
    ``packaged_examples`` in a temporary folder removed afterwards (a stack written from it records only file
    names, never that folder)."""
    found = examples or examples_root()
    if found is not None:
        yield found
        return
    with tempfile.TemporaryDirectory(prefix="lasagna-demo-") as tmp:
        if say is not None:
            say(
                f"demo: no examples/ here (not a checkout): rendering the world scenes ({WORLD_SPLIT}, seed "
                f"{WORLD_SEED}) and using the photographs shipped in {PACKAGED_PHOTOS}"
            )
        yield packaged_examples(tmp)


# ---- drawing -----------------------------------------------------------------------------------------


def layer_view(layer: Tensor, range_: tuple[float, float]) -> Tensor:
    """(3, H, W) in [0, 1]: the layer's stored values v; 1 channel as gray, RGBA over a checkerboard."""
    lo, hi = range_
    if layer.shape[0] == 4:
        colour, alpha = (layer[:3] - lo) / (hi - lo), layer[3:]
        h, w = layer.shape[-2:]
        yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        checker = (0.6 + 0.2 * (((yy // 8) + (xx // 8)) % 2)).float()[None].expand(3, h, w)
        return (alpha * colour + (1 - alpha) * checker).clamp(0, 1)
    v = ((layer - lo) / (hi - lo)).clamp(0, 1)
    return v.expand(3, -1, -1) if v.shape[0] == 1 else v


def _to_pil(image: Tensor):
    from PIL import Image

    arr = (image.detach().double().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    return Image.fromarray(arr, "RGB").resize((CELL, CELL), Image.Resampling.NEAREST)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)  # Pillow's bundled font, scalable where FreeType is present
    except (TypeError, OSError, ImportError):  # older Pillow or no FreeType: the fixed bitmap font
        return ImageFont.load_default()


def draw_sheet(rows: list[Row], note: str, blocks: int = 1) -> bytes:
    """The PNG bytes of the sheet: a header, then one row per edit (labels left, four image cells),
    the rows split into ``blocks`` side-by-side columns."""
    import io

    from PIL import Image, ImageDraw

    pad, head = 8, 52
    columns = ("input", "layer (as stored)", "composite", "truth")
    per_block = -(-len(rows) // blocks)
    block_w = LABEL_WIDTH + len(columns) * (CELL + pad) + 2 * pad
    width = blocks * block_w
    height = head + per_block * (CELL + pad) + pad
    sheet = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    title, small = _font(15), _font(12)
    draw.text((pad, 6), note, fill=(0, 0, 0), font=title)
    for b in range(blocks):
        for j, name in enumerate(columns):
            draw.text((b * block_w + LABEL_WIDTH + j * (CELL + pad) + pad, head - 18), name, fill=(0, 0, 0), font=small)
    for i, row in enumerate(rows):
        b, r = divmod(i, per_block)
        x0, y = b * block_w, head + r * (CELL + pad)
        draw.text((x0 + pad, y + 4), row.title, fill=(0, 0, 0), font=small)
        for k, line in enumerate(_wrap(row.detail, 28)):
            draw.text((x0 + pad, y + 24 + 15 * k), line, fill=(90, 90, 90), font=small)
        for j, image in enumerate((row.input, row.layer, row.composite, row.truth)):
            x = x0 + LABEL_WIDTH + j * (CELL + pad) + pad
            if image is None:
                draw.rectangle((x, y, x + CELL - 1, y + CELL - 1), outline=(200, 200, 200))
                draw.text((x + CELL // 2 - 10, y + CELL // 2 - 7), "n/a", fill=(150, 150, 150), font=small)
            else:
                sheet.paste(_to_pil(image), (x, y))
    buf = io.BytesIO()
    sheet.save(buf, format="PNG")
    return buf.getvalue()


def _wrap(text: str, width: int) -> list[str]:
    lines, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return lines + ([line] if line else [])


# ---- the edits -----------------------------------------------------------------------------------------


def _gray(image: Tensor) -> Tensor:
    """(1, H, W) Rec. 709 luma of (3, H, W) stored values (the colourisation prior's conditioning)."""
    from lasagna.world.tasks import luma

    return luma(image[None])[0].clamp(0, 1)


def _how(result) -> str:
    s = result.settings
    layer = result.stack.document.layer(result.layer_id)
    if layer.kind == "surface":
        how = "surface" + (f", from {layer.source_light}" if layer.source_light else "")
    elif s["method"] == "amortised":
        how = "amortised generator" + (f" + {s['optimize']} steps" if s["optimize"] else ", one pass")
    else:
        d = s["distill"]
        how = f"per-image {d['loss']}, {len(result.history)} steps, w={d['guidance']:g}"
        if d.get("particles", 1) > 1:
            how += f", {d['particles']} particles"  # averaged (lasagna.distill.per_image); the sheet's font has no ×
    return f"{how}; {result.seconds:.2f} s"


def run_demo(
    out: str | Path,
    *,
    catalogue_dirs=None,
    steps: int | None = DEMO_STEPS,
    refine: int | None = DEMO_REFINE,
    examples: Path | None = None,
    say: Callable[[str], None] | None = None,
    warn: Callable[[str], None] | None = None,
) -> Path | None:
    """Run the demo into ``out``; returns the sheet's path (None when it fell back to the example stack).

    ``say`` receives the lines a person should read (what ran, what was skipped, where things are); the
    CLI prints them. ``warn`` receives export warnings. ``examples``: the folder of ``world/`` and ``photos/``
    (default ``demo_examples``': a checkout's, else made from the package).
    """
    say = say or (lambda line: None)
    out = Path(out)
    start = time.monotonic()
    runnable, missing = runnable_presets(catalogue_dirs)
    places = ", ".join(map(str, cat.catalogues() if catalogue_dirs is None else catalogue_dirs)) or "no catalogue"
    if not runnable:
        say(
            f"demo: no learned layer can run ({'; '.join(missing)}; looked in {places}); "
            "compositing and exporting the example stack instead"
        )
        with demo_examples(examples, say) as ex:
            fallback(ex, out, say, warn)
        return None
    for reason in missing:
        say(f"demo: skipping {reason} (looked in {places})")

    edits = _Edits(out, runnable, catalogue_dirs, steps, refine, warn)
    with demo_examples(examples, say) as ex:
        scenes = sorted(p for p in (ex / "world").iterdir() if (p / "stack.json").is_file())[:WORLD_SCENES]
        for k, scene in enumerate(scenes):
            edits.world_scene(scene, GLOWS[k % len(GLOWS)])
        photos = [ex / "photos" / f"{name}.png" for name in PHOTOS if (ex / "photos" / f"{name}.png").is_file()]
        for k, photo in enumerate(photos):
            glow = GLOWS[k % len(GLOWS)] if k < LIT_PHOTOS else None
            edits.photo(photo, colourise=k < COLOURISED_PHOTOS, glow=glow)

    seconds = time.monotonic() - start
    made = ", ".join(f"{k}: {v}" for k, v in runnable.items())
    note = (
        f"lasagna demo: {len(edits.rows)} edits in {seconds:.0f} s ({made}). "
        "Shading layer: mid-gray = unchanged, lighter = brighter."
    )
    sheet = out / "sheet.png"
    atomic_write_bytes(sheet, draw_sheet(edits.rows, note, blocks=2 if len(edits.rows) > 10 else 1))
    say(f"demo: {len(edits.rows)} edits in {seconds:.1f} s ({made})")
    say(
        f"wrote {len(edits.written)} stack folders under {out / 'stacks'}/ (stack.json, layers/, composite.png, "
        "stack.ora)"
    )
    say(f"wrote the sheet {sheet} (input | layer | composite | truth)")
    return sheet


def runnable_presets(catalogue_dirs=None) -> tuple[dict[str, str], list[str]]:
    """({preset: "surface" | "amortised" | "per-image"} of the demo's presets that can run, [why each other
    cannot]): what ``lasagna edit`` makes by default (the preset's layer kind, then its method)."""
    runnable: dict[str, str] = {}
    missing: list[str] = []
    for preset in ("shading", "color", "light", "relight"):
        try:
            parts = cat.resolve(preset, catalogue_dirs=catalogue_dirs, need_prior=False)
        except LasagnaError as err:
            missing.append(f"{preset}: {err}")
            continue
        if parts.preset.layer_kind == "surface" and parts.estimator is not None:
            runnable[preset] = "surface"
            continue
        method = choose_method(parts, None)  # lasagna edit's default for the preset
        if method == "amortised":
            runnable[preset] = "amortised"
        elif _has_prior(parts, catalogue_dirs):
            runnable[preset] = "per-image"
        elif parts.generator is not None:
            runnable[preset] = "amortised"  # the preset prefers per-image, but only its generator is here
        else:
            missing.append(
                f"{preset}: its prior {parts.preset.prior!r} is not in the catalogue and it has no generator"
            )
    return runnable, missing


class _Edits:
    """The demo's edits, each written as a stack folder under ``out/stacks/`` and drawn as one sheet row."""

    def __init__(
        self, out: Path, runnable: dict[str, str], catalogue_dirs, steps: int | None, refine: int | None, warn
    ):
        self.out, self.runnable, self.catalogue_dirs = out, runnable, catalogue_dirs
        self.steps, self.refine, self.warn = steps, refine, warn
        self.rows: list[Row] = []
        self.written: list[Path] = []

    def one(
        self, image, preset: str, label: str, name: str, title: str, truth: Tensor | None, on: str | None = None
    ) -> None:
        from lasagna.editing import conditioning_input, edit

        method = self.runnable[preset]
        options = {}
        if method != "surface":  # a surface is the preset's own default: nothing to choose
            options = {
                "generator": "free" if method == "per-image" else "amortised",
                "optimize": self.refine if method == "amortised" else self.steps,
            }
        result = edit(image, preset, label, on=on, catalogue_dirs=self.catalogue_dirs, **options)
        # force: replaces a previous run's stack
        self.written.append(result.save(self.out / "stacks" / name, force=True, warn=self.warn))
        layer = result.stack.document.layer(result.layer_id)
        # What the generator (or a surface's estimator) saw.
        below = layer.made_by["conditioned_on"] if layer.kind == "surface" else layer.conditioned_on
        seen = conditioning_input(result.stack, below)
        self.rows.append(Row(title, _how(result), seen, layer_view(result.layer, layer.range), result.composite, truth))

    def world_scene(self, scene: Path, glow: str) -> None:
        """Relight a held-out scene's albedo in every direction, colourise its gray image, add a ``glow`` light."""
        from lasagna.io.stack import Stack, load_stack
        from lasagna.world import additive_light, generate

        stack = load_stack(scene)
        meta = stack.document.metadata.get("lasagna.world", {})
        as_rendered = stack.document  # albedo × shading: the light edit's input
        stack.document = stack.document.replace_layer("shading", visible=False, name="True shading (hidden)")
        index, split, seed = meta.get("index", 0), meta.get("split", "heldout"), meta.get("seed", 0)
        if "shading" in self.runnable:
            for label in DIRECTIONS:
                truth = generate(split, 1, seed, stack.width, start=index, labels=[label]).image[0]
                self.one(
                    stack, "shading", label, f"{scene.name}-{label}", f"{scene.name} · {label}", truth, on="albedo"
                )
        if "color" in self.runnable:
            colour = stack.tensors["albedo"].color * stack.tensors["shading"].color  # the scene as rendered
            self.one(
                Stack.from_image(_gray(colour.clamp(0, 1)), name="gray"),
                "color",
                "natural",
                f"{scene.name}-color",
                f"{scene.name} · colourise",
                colour.clamp(0, 1),
            )
        if "light" in self.runnable:
            truth = additive_light(generate(split, 1, seed, stack.width, start=index), glow).lit[0]
            stack.document = as_rendered
            self.one(stack, "light", glow, f"{scene.name}-{glow}-light", f"{scene.name} · {glow} light", truth)
        if "relight" in self.runnable:  # the relight task: the scene lit by its own source light A, relit to B
            from lasagna.world.tasks import relight_sources, relighting

            world = generate(split, 1, seed, stack.width, start=index)
            for label in RELIGHT_TO:
                rel = relighting(world, relight_sources(world.params), [label])
                lit = Stack.from_image(rel.base[0].clamp(0, 1), name="Lit")
                name = f"{scene.name}-relit-{_slug(label)}"
                self.one(lit, "relight", label, name, f"{scene.name} · relit {label}", rel.target[0].clamp(0, 1))

    def photo(self, photo: Path, *, colourise: bool, glow: str | None) -> None:
        """Relight a photograph in every direction; colourise its gray image and add a ``glow`` light if asked."""
        from lasagna.editing import read_image
        from lasagna.io.stack import Stack

        if "shading" in self.runnable:
            for label in DIRECTIONS:
                self.one(photo, "shading", label, f"{photo.stem}-{label}", f"{photo.name} · {label}", None)
        if "color" in self.runnable and colourise:
            rgb = read_image(photo).tensors["base"].color
            self.one(
                Stack.from_image(_gray(rgb), name="gray"),
                "color",
                "natural",
                f"{photo.stem}-color",
                f"{photo.name} · colourise",
                rgb,
            )
        if "light" in self.runnable and glow is not None:
            self.one(photo, "light", glow, f"{photo.stem}-{glow}-light", f"{photo.name} · {glow} light", None)
        if "relight" in self.runnable:
            for label in RELIGHT_TO:
                self.one(
                    photo, "relight", label, f"{photo.stem}-relit-{_slug(label)}", f"{photo.name} · relit {label}", None
                )


def _slug(label: str) -> str:
    """A condition as a folder-name part: ``az=135,el=40`` → ``az135-el40``."""
    return label.replace("=", "").replace(",", "-")


def _has_prior(parts, catalogue_dirs) -> bool:
    try:
        cat.component_path(parts.preset, "prior", parts.preset_file, catalogue_dirs)
    except LasagnaError:
        return False
    return True


def fallback(examples: Path, out: Path, say: Callable[[str], None], warn) -> None:
    """Composite and export the example stack (what the demo did before learned layers existed): a checkout's
    ``examples/stacks/basic``, else (the package alone) the first world scene, albedo × its true shading."""
    from lasagna.export.ora import export_ora
    from lasagna.export.png import export_layer_pngs
    from lasagna.io.render import render_stack, write_composite
    from lasagna.io.stack import load_stack

    source = examples / "stacks" / "basic"
    if not source.is_dir():
        source = sorted(p for p in (examples / "world").iterdir() if (p / "stack.json").is_file())[0]
    stack = load_stack(source)
    result = render_stack(stack)
    written = [
        write_composite(result, out / "composite.png"),
        export_ora(stack, out / f"{source.name}.ora", composite=result.image, warn=warn),
    ]
    try:
        from lasagna.export.psd import export_psd

        written.append(export_psd(stack, out / f"{source.name}.psd", composite=result.image, warn=warn))
    except LasagnaError as err:  # psd-tools missing: the rest of the demo still stands
        say(f"demo: {err}")
    export_layer_pngs(stack, out / "layers")
    stack.save(out / "stack")
    say(f"example stack: {source}")
    for path in written:
        say(f"wrote {path}")
    say(f"wrote {out / 'layers'}/ (raw layer values) and {out / 'stack'}/ (a copy of the stack)")
