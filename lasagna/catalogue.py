"""The learned-layer catalogue: presets, priors, correctives and amortised generators found by name.

A catalogue is a folder of named entries (``layers/`` in a checkout, ``lasagna/_layers/`` in an
installed wheel; see layers/README.md)::

    <catalogue>/
      shading/preset.json      kind "preset": what a learned layer is (lasagna.document.Preset)
      shading/generator/       kind "generator": the preset's amortised LayerGenerator
                               (model.safetensors + config.json, format lasagna.layer_generator)
      relight-32/              kind "prior": a UNetPrior (config.json, format lasagna.unet_prior), or
                               a diffusers folder (model_index.json or unet/ + scheduler/, optional controlnet/),
                               or a link to one elsewhere (config.json, format lasagna.prior_link: its path
                               and ControlNets; ``add_prior`` writes it with a preset beside it)
      relight-32-bhat/         kind "corrective": LMC-SDS's b̂ (config.json, format lasagna.corrective)

**Search order** (the first entry of the asked kind wins): ``<stack>/layers/`` (presets only, when a
stack folder is given: a preset shipped inside a stack), the folders of ``$LASAGNA_LAYERS``
(``os.pathsep``-separated), the checkout's ``layers/`` — the order of
``lasagna.document.default_catalogues()`` — then the installed package's copy. A reference
containing '/' (or a ``Path``) is a path, not a name; a preset's ``prior``/``corrective`` paths are
relative to the preset's folder (layers/README.md). An unknown name is one ``LasagnaError`` listing
where it looked and every name of that kind it found.

    from lasagna import catalogue
    preset = catalogue.load_preset("shading")
    parts = catalogue.resolve("shading")        # preset, preset_file, prior, corrective, generator (paths)
    prior = catalogue.load_prior(parts.prior)
    catalogue.available()                       # {"preset": [...], "prior": [...], ...}
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from lasagna import components
from lasagna.components import PriorSource, config_doc, format_of, is_diffusers, read_config
from lasagna.document.preset import (
    ControlNetRef,
    DiffusersOptions,
    Preset,
    PriorLink,
    default_catalogues,
)
from lasagna.document.preset import load_preset as _load_preset_file
from lasagna.errors import DocumentError, LasagnaError
from lasagna.version import install_hint, missing_extra

Kind = Literal["preset", "prior", "corrective", "generator", "estimator"]
KINDS: tuple[str, ...] = ("preset", "prior", "corrective", "generator", "estimator")

# The ``format`` in an entry's config.json that makes it a prior, a corrective or a generator
# (the FORMAT constants of lasagna.priors.unet, lasagna.losses.corrective, lasagna.generators.unet,
# repeated here so that listing a catalogue imports no torch).
FORMATS: dict[str, str] = {
    "lasagna.unet_prior": "prior",
    "lasagna.corrective": "corrective",
    "lasagna.spectral_corrective": "corrective",
    "lasagna.layer_generator": "generator",
    "lasagna.prior_link": "prior",
    "lasagna.surface_estimator": "estimator",
}
PRESET_GENERATOR = "generator"  # <catalogue>/<preset>/generator/: the preset's amortised generator


def catalogues(extra: Sequence[str | os.PathLike] | None = None) -> list[Path]:
    """Catalogue folders in search order: ``extra`` first, then ``default_catalogues()`` (the one statement of
    the order: ``$LASAGNA_LAYERS``, the user's, the checkout's, the installed package's copy). Folders that do
    not exist are left out; duplicates (one folder reached twice, e.g. through an editable install) are listed
    once."""
    out: list[Path] = []
    seen: set[Path] = set()
    for folder in [*(Path(p) for p in (extra or ())), *default_catalogues()]:
        key = folder.resolve()
        if folder.is_dir() and key not in seen:
            seen.add(key)
            out.append(folder)
    return out


def _places(catalogue_dirs: Sequence[str | os.PathLike] | None) -> list[Path]:
    return catalogues() if catalogue_dirs is None else [Path(p) for p in catalogue_dirs if Path(p).is_dir()]


def entry_problem(folder: Path) -> str | None:
    """Why the catalogue entry ``folder`` is broken, in one line (its config.json, or its generator's, cannot
    be read as a config), or None. A broken entry is left out of the listing; the others are listed."""
    for where in (folder, folder / PRESET_GENERATOR):
        try:
            read_config(where)
        except LasagnaError as err:
            return str(err)
        except (OSError, RecursionError) as exc:
            return str(LasagnaError(f"cannot read ({exc}); expected a config.json", str(where / "config.json")))
    return None


def problems(catalogue_dirs: Sequence[str | os.PathLike] | None = None) -> list[str]:
    """One line per broken entry of the catalogues (``entry_problem``), in search order."""
    return [
        why
        for place in _places(catalogue_dirs)
        for folder in sorted(p for p in place.iterdir() if p.is_dir())
        if (why := entry_problem(folder)) is not None
    ]


def entry_kinds(folder: Path) -> set[str]:
    """The kinds the catalogue entry ``folder`` provides (a preset folder may also hold its generator)."""
    kinds = set()
    if (folder / "preset.json").is_file():
        kinds.add("preset")
        if format_of(folder / PRESET_GENERATOR) == "lasagna.layer_generator":
            kinds.add("generator")
    fmt = FORMATS.get(format_of(folder) or "")
    if fmt is not None:
        kinds.add(fmt)
    if is_diffusers(folder):
        kinds.add("prior")
    return kinds


def _entry_path(folder: Path, kind: str) -> Path:
    """What ``find`` returns for an entry: preset.json, the generator's folder, or the entry itself."""
    if kind == "preset":
        return folder / "preset.json"
    if kind == "generator" and (folder / PRESET_GENERATOR / "config.json").is_file():
        return folder / PRESET_GENERATOR
    return folder


def available(
    kind: Kind | None = None, catalogue_dirs: Sequence[str | os.PathLike] | None = None
) -> dict[str, list[str]]:
    """Names per kind in the catalogues (all four kinds, or only ``kind``), each list sorted."""
    kinds = KINDS if kind is None else (_check_kind(kind),)
    found: dict[str, set[str]] = {k: set() for k in kinds}
    for place in _places(catalogue_dirs):
        for folder in sorted(p for p in place.iterdir() if p.is_dir()):
            for k in entry_kinds(folder) & set(kinds):
                found[k].add(folder.name)
    return {k: sorted(v) for k, v in found.items()}


def _check_kind(kind: str) -> str:
    if kind not in KINDS:
        raise LasagnaError(f"unknown kind {kind!r}; expected one of {', '.join(KINDS)}", "catalogue")
    return kind


class NotFound(LasagnaError):
    """No catalogue entry of that name and kind: ``find`` raises it, ``locate`` answers None."""


def _search_places(
    kind: str, stack_dir: str | os.PathLike | None, catalogue_dirs: Sequence[str | os.PathLike] | None
) -> list[Path]:
    """Where a name of ``kind`` is looked for, first wins: a preset in the stack folder's ``layers/``, then the
    catalogues (``catalogues()``'s order)."""
    places = _places(catalogue_dirs)
    if kind == "preset" and stack_dir is not None:
        places = [Path(stack_dir) / "layers", *places]
    return places


def locate(
    name: str,
    kind: Kind = "preset",
    stack_dir: str | os.PathLike | None = None,
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
) -> Path | None:
    """``find`` for a name, but None when no catalogue has it (a malformed name still raises)."""
    _check_kind(kind)
    _check_name(name, kind)
    try:
        return find(name, kind, stack_dir, catalogue_dirs)
    except NotFound:
        return None


def find(
    name: str | os.PathLike,
    kind: Kind = "preset",
    stack_dir: str | os.PathLike | None = None,
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
    relative_to: str | os.PathLike | None = None,
) -> Path:
    """The path of catalogue entry ``name`` of ``kind``: a preset's preset.json, a generator's folder,
    a prior's or corrective's folder. The one lookup of a named thing (``locate``, ``preset_path`` and
    ``component_path`` call it).

    A ``Path`` or a string containing '/' is taken as a path (relative to ``relative_to`` or, for a
    preset, to ``stack_dir``: a learned layer's relative preset path needs its stack folder; else to the
    current folder) and must exist. A name is searched in ``_search_places``' order; ``NotFound`` lists the
    names of that kind if it is not found.
    """
    _check_kind(kind)
    if isinstance(name, os.PathLike) or "/" in name or os.sep in name:
        base = relative_to if relative_to is not None else (stack_dir if kind == "preset" else None)
        if kind == "preset" and base is None and isinstance(name, str) and not Path(name).is_absolute():
            raise DocumentError(f"preset path {name!r} needs the stack folder to resolve against", "preset")
        path = Path(base) / name if base is not None and not Path(name).is_absolute() else Path(name)
        if kind == "preset" and path.is_dir():
            path = path / "preset.json"
        if not path.exists():
            raise LasagnaError(
                f"{kind} path {str(name)!r} does not exist (looked for {path}); expected a "
                f"{'preset.json' if kind == 'preset' else 'folder written by save_pretrained'}",
                kind,
            )
        return path
    _check_name(name, kind)
    places = _search_places(kind, stack_dir, catalogue_dirs)
    for place in places:
        folder = place / name
        if folder.is_dir() and kind in entry_kinds(folder):
            return _entry_path(folder, kind)
    known = available(kind, catalogue_dirs)[kind]
    hint = {
        "prior": " (train one: lasagna train-prior)",
        "corrective": " (train one: lasagna train-corrective)",
        "generator": " (train one: lasagna train-layer --preset NAME)",
    }.get(kind, "")
    raise NotFound(
        f"no {kind} named {name!r} in {', '.join(map(str, places)) or 'no catalogue folder'}; "
        f"expected one of {', '.join(known) or '(none found)'}{hint}",
        kind,
    )


def _check_name(name: str, kind: str) -> None:
    from lasagna.document.types import check_id

    try:
        check_id(name)
    except (DocumentError, ValueError) as exc:
        raise LasagnaError(f"{exc}; expected a catalogue name (or a path containing '/')", kind) from None


# ---- loading -------------------------------------------------------------------------------------


def load_preset(
    name_or_path: str | os.PathLike,
    stack_dir: str | os.PathLike | None = None,
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
) -> Preset:
    """The validated ``Preset`` named ``name_or_path`` (or at that path); see ``find``."""
    return _load_preset_file(preset_path(name_or_path, stack_dir, catalogue_dirs))


def preset_path(
    name_or_path: str | os.PathLike,
    stack_dir: str | os.PathLike | None = None,
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
) -> Path:
    """The preset.json of a learned layer's ``preset`` reference: ``find`` for a preset."""
    return find(name_or_path, "preset", stack_dir, catalogue_dirs)


def component_path(
    preset: Preset,
    kind: Literal["prior", "corrective"],
    preset_file: str | os.PathLike,
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
) -> Path | None:
    """The folder of a preset's prior or corrective (None for a preset without a corrective); a
    reference with '/' is relative to the preset's folder."""
    ref = preset.prior if kind == "prior" else preset.corrective
    if ref is None:
        return None
    return find(ref, kind, catalogue_dirs=catalogue_dirs, relative_to=Path(preset_file).parent if "/" in ref else None)


PRESET = "<preset>"  # ``resolve``'s default for a component: the one the preset names (never a name or path)


@dataclass(frozen=True)
class Resolved:
    """A preset and what it names, each found once: ``prior`` (its folder; None when it is not found) and
    ``source`` (what kind of prior it is), ``corrective`` (None when none is named or it is not found) and the
    amortised ``generator`` (None until one is trained and installed in the preset's folder), the surface
    ``estimator`` and the ``told_estimator`` a surface layer told its source light reads (``surface.told``).

    ``prior_ref``/``corrective_ref`` are the references resolved (the preset's, or those asked for);
    ``missing`` holds, per component that was named but not found, the one-line error a caller that needs
    it raises (listing the names of that kind there are)."""

    preset: Preset
    preset_file: Path
    prior: Path | None
    corrective: Path | None
    generator: Path | None
    estimator: Path | None = None
    told_estimator: Path | None = None
    prior_ref: str | None = None
    corrective_ref: str | None = None
    source: PriorSource | None = None
    missing: Mapping[str, LasagnaError] = field(default_factory=dict)


def resolve(
    preset: str | os.PathLike,
    stack_dir: str | os.PathLike | None = None,
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
    *,
    need_prior: bool = True,
    prior: str | None = PRESET,
    corrective: str | None = PRESET,
    controlnets: Sequence[ControlNetRef] = (),
) -> Resolved:
    """The preset ``preset`` and its parts, found once (``Resolved``): the one lookup of an edit.

    ``prior``/``corrective``: references instead of the preset's (a name, or a path taken as it is: a
    user's folder or a stack's confined path; None: no corrective), ``controlnets`` the prior's ControlNets.
    The preset's own references with '/' are relative to its folder. A missing prior is an error listing
    the priors found unless ``need_prior`` is False (then ``Resolved.missing`` holds it)."""
    if not isinstance(preset, (str, os.PathLike)):
        # A Preset object has no folder to resolve its relative prior, corrective and generator against.
        raise LasagnaError(
            f"got {type(preset).__name__}; expected a catalogue name or the path of a preset.json "
            "(write a Preset with preset.to_json() into <folder>/<name>/preset.json)",
            "preset",
        )
    file = preset_path(preset, stack_dir, catalogue_dirs)
    p = _load_preset_file(file)
    refs = {
        "prior": p.prior if prior == PRESET else prior,
        "corrective": p.corrective if corrective == PRESET else corrective,
    }
    own = {"prior": prior != PRESET, "corrective": corrective != PRESET}
    found: dict[str, Path | None] = {"prior": None, "corrective": None}
    missing: dict[str, LasagnaError] = {}
    source = None
    for kind in ("prior", "corrective"):
        ref = refs[kind]
        if ref is None:
            continue
        relative = file.parent if "/" in str(ref) and not own[kind] else None
        try:
            found[kind] = find(ref, kind, catalogue_dirs=catalogue_dirs, relative_to=relative)
            if kind == "prior":
                source = _source_at(found[kind], controlnets)
        except LasagnaError as err:
            if kind == "prior" and need_prior:
                raise
            missing[kind] = err
    generator = file.parent / PRESET_GENERATOR
    if format_of(generator) != "lasagna.layer_generator":
        generator = None
    estimators: dict[str, Path | None] = {"estimator": None, "told_estimator": None}
    if p.surface is not None:
        refs_of = {"estimator": p.surface.estimator, "told_estimator": p.surface.told and p.surface.told.estimator}
        for key, ref in refs_of.items():
            if ref is None:
                continue
            try:
                estimators[key] = find(
                    ref, "estimator", catalogue_dirs=catalogue_dirs, relative_to=file.parent if "/" in ref else None
                )
            except LasagnaError as err:
                missing[key] = err
    return Resolved(
        p,
        file,
        found["prior"],
        found["corrective"],
        generator,
        **estimators,
        prior_ref=None if refs["prior"] is None else str(refs["prior"]),
        corrective_ref=None if refs["corrective"] is None else str(refs["corrective"]),
        source=source,
        missing=missing,
    )


def preset_status(preset: str, catalogue_dirs: Sequence[str | os.PathLike] | None = None) -> dict[str, object]:
    """Whether ``preset`` can make layers here, read from configs only (no weights, no torch):
    ``{"usable": bool, "method": "surface" | "amortised" | "per-image" | None, "amortised": bool, "why": str}``
    (``surface``: the preset's default layer is a surface from its estimator).

    Usable means: an amortised generator is installed, or the prior is found and knows every label
    of the preset's vocabulary (and the corrective is found when the default loss is LMC-SDS). ``method``
    is what ``edit`` does by default; ``amortised`` whether the one-pass generator is there to ask for
    (``--generator amortised``; the editor's one-click add), whatever the default.
    """
    try:
        parts = resolve(preset, catalogue_dirs=catalogue_dirs, need_prior=False)
    except LasagnaError as err:
        return {"usable": False, "method": None, "amortised": False, "why": str(err)}
    p = parts.preset
    has_generator = parts.generator is not None
    if p.layer_kind == "surface":  # the choice recipe.layer_kind makes for a request that names no other
        if parts.estimator is None:
            why = f"its surface estimator {p.surface.estimator!r} is not in the catalogue"
            return {"usable": False, "method": None, "amortised": has_generator, "why": why}
        return {"usable": True, "method": "surface", "amortised": has_generator, "why": f"estimator {parts.estimator}"}
    if has_generator and p.method != "per-image":  # the choice learned.choose_method makes
        return {"usable": True, "method": "amortised", "amortised": True, "why": f"generator {parts.generator}"}
    if parts.prior is None:
        why = f"its prior {p.prior!r} is not in the catalogue"
        return {"usable": False, "method": None, "amortised": has_generator, "why": why}
    if parts.source is not None and parts.source.kind == "diffusers" and missing_extra("diffusers") is not None:
        why = f"its prior {p.prior!r} is a diffusers folder and needs the diffusers extra ({install_hint('diffusers')})"
        return {"usable": False, "method": None, "amortised": has_generator, "why": why}
    config = config_doc(parts.prior).get("config")
    vocabulary = config.get("vocabulary") if isinstance(config, dict) else None
    known = tuple(vocabulary) if isinstance(vocabulary, list) and all(isinstance(v, str) for v in vocabulary) else ()
    missing = [lab for lab in p.vocabulary if known and lab not in known]
    if missing:
        return {
            "usable": False,
            "method": None,
            "amortised": has_generator,
            "why": f"its prior {p.prior!r} was not trained on {', '.join(missing)} (it knows {', '.join(known)})",
        }
    if p.distill.loss == "lmc-sds" and parts.corrective is None:
        why = f"its corrective {p.corrective!r} is not in the catalogue"
        return {"usable": False, "method": None, "amortised": has_generator, "why": why}
    why = f"prior {p.prior}, {p.distill.loss} ω = {p.distill.guidance:g}"
    return {"usable": True, "method": "per-image", "amortised": has_generator, "why": why}


def prior_source(
    name_or_path: str | os.PathLike,
    *,
    controlnets: Sequence[ControlNetRef] = (),
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
    relative_to: str | os.PathLike | None = None,
) -> PriorSource:
    """What prior ``name_or_path`` (a catalogue name or a folder) is: a UNetPrior, a diffusers folder (its
    ControlNets: ``controlnets``, else a nested ``controlnet/``), or a link entry (its path and ControlNets)."""
    folder = find(name_or_path, "prior", catalogue_dirs=catalogue_dirs, relative_to=relative_to)
    return _source_at(folder, controlnets)


def _source_at(folder: Path, controlnets: Sequence[ControlNetRef] = ()) -> PriorSource:
    """What the prior found at ``folder`` is (``prior_source``)."""
    fmt = format_of(folder)
    if fmt == "lasagna.unet_prior":
        if controlnets:
            raise LasagnaError("a UNetPrior takes no ControlNet; expected a diffusers prior", str(folder))
        return PriorSource("unet", folder)
    if fmt == "lasagna.prior_link":
        link = read_link(folder)
        if controlnets:
            raise LasagnaError(
                "this catalogue prior names its own ControlNets; expected no --controlnet (or a prior folder)",
                str(folder),
            )
        return PriorSource("diffusers", Path(link.path), link.controlnets)
    if is_diffusers(folder):
        for net in controlnets:
            if not (Path(net.path) / "config.json").is_file():
                raise LasagnaError(
                    "is not a ControlNet folder (no config.json); expected a folder written by save_pretrained",
                    net.path,
                )
        if not controlnets and (folder / "controlnet").is_dir():
            controlnets = (ControlNetRef(path=str(folder / "controlnet")),)
        return PriorSource("diffusers", folder, tuple(controlnets))
    raise LasagnaError(
        f"format is {fmt!r}; expected a prior: a diffusers folder (model_index.json, or unet/ and scheduler/), "
        "a lasagna UNetPrior or a lasagna.prior_link",
        str(folder if fmt is None else folder / "config.json"),
    )


def read_link(folder: Path) -> PriorLink:
    """A link entry's ``PriorLink`` (``folder/config.json``), its diffusers folder checked to exist."""
    from pydantic import ValidationError

    from lasagna.errors import describe_validation_error

    try:
        link = PriorLink.model_validate(config_doc(folder))
    except ValidationError as err:
        raise describe_validation_error(err, str(folder / "config.json"), PriorLink) from None
    if not is_diffusers(Path(link.path)):
        raise LasagnaError(
            f"links to {link.path}, which is not a diffusers folder (moved or deleted?); expected model_index.json "
            "or unet/ and scheduler/ there",
            str(folder / "config.json"),
        )
    return link


def load_prior(
    name_or_path: str | os.PathLike | PriorSource,
    *,
    preset: Preset | None = None,
    device="cpu",
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
    relative_to: str | os.PathLike | None = None,
    options: DiffusersOptions | None = None,
    prompts: dict[str, str] | None = None,
    negative_prompt: str | None = None,
):
    """A prior by catalogue name or folder (or a ``PriorSource``), loaded by ``lasagna.components.load_prior``."""
    source = (
        name_or_path
        if isinstance(name_or_path, PriorSource)
        else prior_source(name_or_path, catalogue_dirs=catalogue_dirs, relative_to=relative_to)
    )
    return components.load_prior(
        source, preset=preset, device=device, options=options, prompts=prompts, negative_prompt=negative_prompt
    )


def load_corrective(
    name_or_path: str | os.PathLike,
    *,
    device="cpu",
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
    relative_to: str | os.PathLike | None = None,
):
    """The LMC-SDS corrective b̂ by catalogue name or folder (``lasagna.components.load_corrective``)."""
    folder = find(name_or_path, "corrective", catalogue_dirs=catalogue_dirs, relative_to=relative_to)
    return components.load_corrective(folder, device=device)


def load_generator(
    name_or_path: str | os.PathLike,
    *,
    preset: Preset | None = None,
    device="cpu",
    catalogue_dirs: Sequence[str | os.PathLike] | None = None,
    relative_to: str | os.PathLike | None = None,
):
    """A preset's amortised ``LayerGenerator`` (eval mode), by preset name or folder; with ``preset``
    it must produce that preset's layer and know its whole vocabulary."""
    folder = find(name_or_path, "generator", catalogue_dirs=catalogue_dirs, relative_to=relative_to)
    return components.open_generator(folder, preset=preset, device=device)


# ---- adding a prior of one's own -----------------------------------------------------------------


def writable_catalogue() -> Path:
    """Where new entries go: the first folder of ``$LASAGNA_LAYERS``, else the user's catalogue
    (``lasagna.document.preset.user_catalogue``: ``$XDG_DATA_HOME/lasagna/layers``)."""
    from lasagna.document.preset import user_catalogue

    first = next((p for p in os.environ.get("LASAGNA_LAYERS", "").split(os.pathsep) if p), None)
    return Path(first) if first else user_catalogue()


def add_prior(
    path: str | os.PathLike,
    name: str,
    *,
    like: str = "shading",
    controlnets: Sequence[ControlNetRef] = (),
    corrective: str | os.PathLike | None = None,
    vocabulary: Sequence[str] | None = None,
    prompt: str | None = None,
    options: DiffusersOptions | None = None,
    catalogue: str | os.PathLike | None = None,
    force: bool = False,
) -> Path:
    """Register the diffusers folder ``path`` as catalogue entry ``name``, so ``lasagna edit --layer NAME``
    uses it; returns the entry's preset.json.

    Writes ``<catalogue>/<name>/`` — ``config.json`` (a ``PriorLink``: the folder and its ControlNets, by
    absolute path; the weights are not copied) and ``preset.json`` (the preset ``like``'s layer and
    distillation defaults, with this prior, ``vocabulary``/``prompt`` if given and the ``options``) — and,
    with a ``corrective`` folder (``lasagna train-corrective``'s ``OUT/corrective``), a copy of it as
    ``<name>-corrective``, which the preset names; its loss then defaults to LMC-SDS, else to SDS. Each
    folder is built beside its place and renamed into it, so a failure leaves the catalogue as it was.
    ``catalogue`` defaults to ``writable_catalogue()``; an entry already there is replaced only with ``force``.
    """
    import shutil

    from lasagna.atomic import copy_tree, folder_lock, make_temp_folder, temp_path

    _check_name(name, "prior")
    source = prior_source(_resolved(path), controlnets=[_absolute(n) for n in controlnets])
    if source.kind != "diffusers":
        raise LasagnaError("is a lasagna UNetPrior; expected a diffusers folder (it can be named as it is)", str(path))
    base = load_preset(like)
    data = base.model_dump(mode="json")
    data.update(
        name=name,
        description=f"{base.description} Scored by the diffusers prior at {source.folder}.",
        prior=name,
        corrective=f"{name}-corrective" if corrective is not None else None,
        method="per-image",  # no amortised generator was trained for this prior
        layer_kind="free",  # a free layer scored by this prior (the template's surface estimator is not this prior's)
        surface=None,
        diffusers=(options or base.diffusers or DiffusersOptions()).model_dump(mode="json"),
    )
    data["distill"] = {**data["distill"], "loss": "lmc-sds" if corrective is not None else "sds"}
    if vocabulary is not None:
        data["vocabulary"] = list(vocabulary)
    if prompt is not None:
        data["prompt"] = prompt
    preset = Preset.from_dict(data, f"preset for {name!r}")
    link = PriorLink(format="lasagna.prior_link", version=1, path=str(source.folder), controlnets=source.controlnets)
    if corrective is not None:
        fmt = format_of(Path(corrective))
        if FORMATS.get(fmt or "") != "corrective":
            raise LasagnaError(
                f"format is {fmt!r}; expected a corrective folder (lasagna train-corrective's OUT/corrective)",
                str(corrective),
            )
    root = Path(catalogue) if catalogue is not None else writable_catalogue()
    root.mkdir(parents=True, exist_ok=True)
    entries = {name: {"preset.json": preset.to_json(), "config.json": link.model_dump_json(indent=2) + "\n"}}
    staged: list[tuple[Path, Path]] = []
    try:
        for entry, files in entries.items():
            tmp = make_temp_folder(root / entry)
            staged.append((tmp, root / entry))
            for file, text in files.items():
                (tmp / file).write_text(text, encoding="utf-8")
        if corrective is not None:
            tmp = make_temp_folder(root / f"{name}-corrective")
            staged.append((tmp, root / f"{name}-corrective"))
            copy_tree(_resolved(corrective), tmp)  # bounded; no link inside it followed
        with folder_lock(root):
            taken = [str(target) for _, target in staged if target.exists()]
            if taken and not force:
                raise LasagnaError(
                    f"{', '.join(taken)} already exist(s); expected a new name (or --force to replace)", name
                )
            for tmp, target in staged:
                if target.exists():
                    aside = temp_path(target, "old")
                    os.rename(target, aside)
                    os.rename(tmp, target)
                    shutil.rmtree(aside, ignore_errors=True)
                else:
                    os.rename(tmp, target)
    finally:
        for tmp, _ in staged:
            shutil.rmtree(tmp, ignore_errors=True)
    return root / name / "preset.json"


def install_generator(
    generator: str | os.PathLike,
    preset: str,
    *,
    catalogue: str | os.PathLike | None = None,
    force: bool = False,
) -> Path:
    """Install a trained generator folder (``model.safetensors`` + ``config.json``) as preset ``preset``'s
    amortised generator; returns ``<catalogue>/<preset>/generator``.

    ``catalogue`` defaults to ``writable_catalogue()`` (``$LASAGNA_LAYERS``'s first folder, else the user's), so
    an install never writes inside the package. Where the preset's folder is elsewhere (the checkout's or the
    package's ``layers/``), a copy of its preset.json — references with '/' made absolute — goes beside the
    generator, and, searched first, shadows it. A generator the preset already has (there or in the catalogue
    it was found in) is replaced only with ``force``. The folder is built beside its place and renamed in.
    """
    import shutil

    from lasagna.atomic import folder_lock, make_temp_folder, temp_path

    parts = resolve(preset, need_prior=False)
    p = parts.preset
    root = Path(catalogue) if catalogue is not None else writable_catalogue()
    if parts.generator is not None and not force:
        raise LasagnaError(
            f"preset {p.name!r} already has a generator at {parts.generator}; expected --force to replace it "
            f"(installed in {root / p.name})",
            "--install",
        )
    source = Path(generator)
    if format_of(source) != "lasagna.layer_generator":
        raise LasagnaError("is not a trained generator; expected model.safetensors + config.json", str(source))
    target = root / p.name
    own_folder = target.resolve() == parts.preset_file.parent.resolve()
    if target.exists() and not own_folder:
        raise LasagnaError(
            f"exists and is not preset {p.name!r}'s folder; expected it free (or the preset's own)", str(target)
        )
    root.mkdir(parents=True, exist_ok=True)
    place = target / PRESET_GENERATOR if own_folder else target
    tmp = make_temp_folder(place)
    try:
        folder = tmp if own_folder else tmp / PRESET_GENERATOR
        folder.mkdir(exist_ok=True)
        for name in ("model.safetensors", "config.json"):  # the generator; a run folder's other files stay there
            shutil.copyfile(source / name, folder / name)
        if not own_folder:  # the preset beside its generator, its relative references kept pointing where they did
            data = p.model_dump(mode="json")
            here = parts.preset_file.parent.resolve()
            for key in ("prior", "corrective"):
                if data.get(key) and "/" in data[key]:
                    data[key] = str(here / data[key])
            surface = data.get("surface") or {}
            for part in (surface, surface.get("told") or {}):
                if "/" in part.get("estimator", ""):
                    part["estimator"] = str(here / part["estimator"])
            (tmp / "preset.json").write_text(Preset.from_dict(data, "preset.json").to_json(), encoding="utf-8")
        with folder_lock(place.parent):
            if place.exists():  # the preset's own earlier generator (checked above): moved aside, then removed
                aside = temp_path(place, "old")
                os.rename(place, aside)
                os.rename(tmp, place)
                shutil.rmtree(aside, ignore_errors=True)
            else:
                os.rename(tmp, place)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target / PRESET_GENERATOR


def _resolved(path: str | os.PathLike) -> Path:
    """``path`` made absolute, its links followed; a link loop is one line."""
    try:
        return Path(path).resolve(strict=True)
    except FileNotFoundError:
        return Path(path).absolute()  # reported as missing where it is looked for
    except (RuntimeError, OSError) as exc:  # Python < 3.13 raises RuntimeError on a loop, later OSError(ELOOP)
        detail = getattr(exc, "strerror", None) or "symlink loop"
        raise LasagnaError(f"cannot be resolved ({detail}); expected a folder (not a link loop)", str(path)) from None


def _absolute(net: ControlNetRef) -> ControlNetRef:
    return net.model_copy(update={"path": str(_resolved(net.path))})
