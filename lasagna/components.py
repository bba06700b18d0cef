"""A learned layer's parts read from folders already found: configs, what a prior is, the networks, checksums.

``lasagna.catalogue`` turns names into folders (``find``); this module reads what is in a folder once it is
known — a ``config.json`` under the JSON limits, a prior's ``PriorSource`` files, the prior, the corrective
and the amortised generator loaded on a device, and the SHA-256 of the files a layer records. A learned
layer's recipe (``lasagna.recipe``) finds its parts through the catalogue once, and ``make_layer`` loads
them from here: the edit path never goes back to the catalogue.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from lasagna.document.preset import ControlNetRef, DiffusersOptions, Preset
from lasagna.errors import LasagnaError

# ---- a folder's config.json --------------------------------------------------------------------------


def read_config(folder: Path) -> dict:
    """``folder/config.json`` as a dict, read under the JSON limits (``lasagna.document.validation``: size,
    nesting, integer digits); {} when there is none. A file that is there but broken raises one
    ``LasagnaError``: not JSON, nested too deep, not an object, or a ``format`` that is not a string."""
    from lasagna.document.validation import parse_json, read_json_text

    file = folder / "config.json"
    if not file.is_file():
        return {}
    doc = parse_json(read_json_text(file, "a config.json"), str(file))
    if not isinstance(doc, dict):
        raise LasagnaError(f"holds a JSON {type(doc).__name__}; expected an object with a format", str(file))
    if not isinstance(doc.get("format", ""), str):
        raise LasagnaError(
            f"format is {json.dumps(doc['format'])[:40]}; expected a string such as 'lasagna.unet_prior'", str(file)
        )
    return doc


def config_doc(folder: Path) -> dict:
    """``folder/config.json`` as a dict; {} when there is none or it is broken (``read_config`` says why)."""
    try:
        return read_config(folder)
    except (LasagnaError, OSError, RecursionError):
        return {}


def format_of(folder: Path) -> str | None:
    """The ``format`` of ``folder/config.json``, or None (no file, broken, not a lasagna config)."""
    return config_doc(folder).get("format")


def is_diffusers(folder: Path) -> bool:
    """A diffusers pipeline folder: ``model_index.json``, or ``unet/`` and ``scheduler/``."""
    return (folder / "model_index.json").is_file() or ((folder / "unet").is_dir() and (folder / "scheduler").is_dir())


# ---- checksums -------------------------------------------------------------------------------------------

# (resolved path, size, mtime_ns) -> SHA-256: a multi-GB diffusers checkpoint is read once per process, not
# once per edit (a file rewritten in place changes its mtime, so a stale digest is not reused).
_SHA_CACHE: dict[tuple[str, int, int], str] = {}


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def file_sha256(path: Path) -> str:
    """SHA-256 of the file at ``path`` (cached by path, size and modification time)."""
    stat = Path(path).stat()
    key = (str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)
    if key in _SHA_CACHE:
        return _SHA_CACHE[key]
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    _SHA_CACHE[key] = digest.hexdigest()
    return _SHA_CACHE[key]


def files_sha256(files: dict[str, Path]) -> dict[str, str]:
    """SHA-256 of each file by name (the files that exist; a missing one is simply not listed)."""
    return {name: file_sha256(path) for name, path in sorted(files.items()) if Path(path).is_file()}


def listing_sha256(digests: dict[str, str]) -> str:
    """One SHA-256 for several files: of their "name digest" lines, sorted by name."""
    return sha256_bytes("".join(f"{name} {digest}\n" for name, digest in sorted(digests.items())).encode())


def changed_weights(recorded: dict[str, str], current: dict[str, str]) -> list[str]:
    """The names whose digest differs between two ``weights`` records (changed, missing or new), sorted."""
    return sorted(n for n in set(recorded) | set(current) if recorded.get(n) != current.get(n))


# ---- the prior -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PriorSource:
    """Where a prior's weights are: a ``UNetPrior`` folder (``kind="unet"``), or a diffusers pipeline folder
    and its ControlNets (``kind="diffusers"``; a link entry already followed)."""

    kind: Literal["unet", "diffusers"]
    folder: Path
    controlnets: tuple[ControlNetRef, ...] = ()

    def files(self, variant: str | None = None) -> dict[str, Path]:
        """Every file a load reads, by a stable name (``prior/…``, ``controlnet<i>/…``): what provenance hashes."""
        if self.kind == "unet":
            return {f"prior/{n}": self.folder / n for n in ("model.safetensors", "config.json")}
        from lasagna.priors.diffusers import used_files

        out = {f"prior/{f.relative_to(self.folder).as_posix()}": f for f in used_files(self.folder, variant)}
        for i, net in enumerate(self.controlnets):
            root = Path(net.path)
            out.update({f"controlnet{i}/{f.name}": f for f in used_files(root, variant, pipeline=False)})
        return out


def load_prior(
    source: PriorSource,
    *,
    preset: Preset | None = None,
    device="cpu",
    options: DiffusersOptions | None = None,
    prompts: dict[str, str] | None = None,
    negative_prompt: str | None = None,
):
    """The prior at ``source``: a ``UNetPrior`` (eval mode), or a ``DiffusersPrior`` — its vocabulary and prompt
    template from ``preset`` (required), run as ``options`` say (default the preset's ``diffusers``),
    ``prompts`` (label → free text) replacing the template and ``negative_prompt`` the unconditional prompt."""
    if source.kind == "unet":
        if prompts or negative_prompt:
            raise LasagnaError(
                "this prior is conditioned on its vocabulary's labels (a UNetPrior); expected no --prompt or "
                "--negative-prompt (free text needs a text-conditioned diffusers prior)",
                str(source.folder),
            )
        import torch

        from lasagna.priors.unet import UNetPrior

        prior = UNetPrior.from_pretrained(source.folder, device=device)
        # Every caller holds the prior frozen (edits, and the generator's and corrective's training): on the CPU,
        # NHWC is the faster layout for its convolutions.
        return prior.channels_last() if torch.device(device).type == "cpu" else prior
    if preset is None:
        raise LasagnaError(
            "a diffusers prior needs the preset (its vocabulary and prompt); expected preset=", str(source.folder)
        )
    from lasagna.priors.diffusers import DiffusersPrior

    opts = options or preset.diffusers or DiffusersOptions()
    vocabulary = tuple(prompts) if prompts else preset.vocabulary
    return DiffusersPrior.from_local(
        source.folder,
        controlnets=[net.path for net in source.controlnets],
        conditioning_scale=[
            net.scale if net.scale is not None else opts.conditioning_scale for net in source.controlnets
        ],
        vocabulary=vocabulary,
        prompt_template=preset.prompt,
        prompts=prompts,
        negative_prompt=negative_prompt or "",
        device=device,
        dtype=opts.torch_dtype,
        variant=opts.variant,
        latent=opts.latent,
        cpu_offload=opts.cpu_offload,
        attention_slicing=opts.attention_slicing,
        channels_last=opts.channels_last,
    )


def load_corrective(folder: Path, *, device="cpu"):
    """The LMC-SDS corrective b̂ in ``folder``, eval mode: a ``lasagna.losses.corrective.Corrective`` network or a
    ``lasagna.losses.spectral.SpectralCorrective``, by the format in its config.json."""
    from lasagna.losses.corrective import Corrective
    from lasagna.losses.spectral import SpectralCorrective

    cls = SpectralCorrective if format_of(folder) == SpectralCorrective.FORMAT else Corrective
    return cls.from_pretrained(folder, device=device)


# ---- the amortised generator -------------------------------------------------------------------------------


def check_generator(generator, preset: Preset, where: str) -> None:
    """The generator makes ``preset``'s layer (blend, channels, range) and knows its labels."""
    from lasagna.generators.layer import LayerSpec

    want = LayerSpec.from_preset(preset)
    got = generator.spec
    if (got.blend, got.channels, tuple(got.range)) != (want.blend, want.channels, tuple(want.range)):
        raise LasagnaError(
            f"the generator makes a {got.blend} layer of {got.channels} channel(s) in {list(got.range)}; "
            f"expected the {want.blend} layer of {want.channels} channel(s) in {list(want.range)} "
            f"of preset {preset.name!r}",
            where,
        )
    missing = [lab for lab in preset.vocabulary if lab not in generator.config.vocabulary]
    if missing:
        raise LasagnaError(
            f"the generator does not know label(s) {', '.join(missing)} of preset {preset.name!r}; "
            f"expected its vocabulary to contain {', '.join(preset.vocabulary)}",
            where,
        )


def open_generator(folder: Path, *, preset: Preset | None = None, device="cpu"):
    """The ``LayerGenerator`` in ``folder`` (eval mode); with ``preset`` checked to make its layer."""
    from lasagna.generators.unet import LayerGenerator

    net = LayerGenerator.from_pretrained(folder, device=device)
    if preset is not None:
        check_generator(net, preset, str(folder))
    return net


@dataclass
class LoadedGenerator:
    """An amortised generator loaded and checked once: the network, its files' bytes (copied into every
    stack made with it) and their SHA-256."""

    net: Any  # lasagna.generators.unet.LayerGenerator, in eval mode on its device
    weights: bytes
    config: bytes
    sha256: str
    config_sha256: str

    @classmethod
    def read(cls, folder: Path, preset: Preset, device="cpu") -> LoadedGenerator:
        """The generator in ``folder`` (model.safetensors + config.json), checked against ``preset``'s layer."""
        weights = (folder / "model.safetensors").read_bytes()
        config = (folder / "config.json").read_bytes()
        net = open_generator(folder, preset=preset, device=device)
        return cls(net, weights, config, sha256_bytes(weights), sha256_bytes(config))


__all__ = [
    "LoadedGenerator",
    "PriorSource",
    "changed_weights",
    "check_generator",
    "config_doc",
    "file_sha256",
    "files_sha256",
    "format_of",
    "is_diffusers",
    "listing_sha256",
    "load_corrective",
    "load_prior",
    "open_generator",
    "read_config",
    "sha256_bytes",
]
