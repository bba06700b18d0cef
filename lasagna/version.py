"""The package version, for ``lasagna --version`` and the records an edit writes (pyproject.toml states the same),
and the distribution's name on the package index, from which every install hint is built."""

__version__ = "0.1.0"

# The name ``pip install`` takes (pyproject.toml's ``[project] name``): ``lasagna`` on the package index is an
# unrelated project, so the distribution is ``lasagna-layers`` while the import and the command stay ``lasagna``.
DISTRIBUTION = "lasagna-layers"

# The modules each optional extra (pyproject.toml's ``[project.optional-dependencies]``) makes importable.
EXTRAS: dict[str, tuple[str, ...]] = {
    "diffusers": ("diffusers", "transformers"),
    "psd": ("psd_tools",),
    "serve": ("starlette", "uvicorn"),
}


def install_hint(extra: str | None = None) -> str:
    """The command that installs this package (with the optional dependencies ``extra``):
    ``pip install 'lasagna-layers[serve]'``."""
    return f"pip install '{DISTRIBUTION}[{extra}]'" if extra else f"pip install {DISTRIBUTION}"


def missing_extra(extra: str) -> str | None:
    """The first module of the optional extra ``extra`` (``EXTRAS``) that cannot be imported here (looked up with
    ``importlib.util.find_spec``, not imported: listing a catalogue stays light), or None when all can."""
    from importlib.util import find_spec

    for module in EXTRAS[extra]:
        try:
            if find_spec(module) is None:
                return module
        except (ImportError, ValueError):  # a parent package missing, or a module left half-imported
            return module
    return None
