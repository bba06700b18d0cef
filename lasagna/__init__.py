"""Lasagna: layered image compositing with learned layers.

    import lasagna
    stack = lasagna.load("examples/stacks/basic")      # a folder or its stack.json
    result = lasagna.render(stack)                     # RenderResult(image, skipped, evaluated)
    lasagna.save(stack, "out/mystack")                 # stack.json + layer PNGs (composite=True: composite.png)
    lasagna.to_pil(result)                             # the composite as an 8-bit PIL image
    lasagna.edit("photo.png", "shading", "left")       # a learned layer (lasagna.editing.edit)

The API's names are ``lasagna.api.__all__`` (the one list) and are loaded lazily on first use, so that
``import lasagna.document`` (pydantic only) never imports torch; ``dir(lasagna)``, ``help(lasagna)`` and
``from lasagna import *`` load them. See docs/ARCHITECTURE.md for the tiers.
"""

from importlib.util import find_spec as _find_spec
from typing import TYPE_CHECKING

from lasagna.version import __version__ as __version__

if TYPE_CHECKING:  # type checkers see the real names and types; at run time they come from __getattr__
    from lasagna.api import *  # noqa: F403


def _api():
    from lasagna import api

    return api


def __getattr__(name: str):
    # A private name or a submodule (``from lasagna import catalogue`` asks here first) is not the API's: answered
    # without importing it, so the document tier stays torch-free.
    if (name.startswith("_") and name != "__all__") or _find_spec(f"lasagna.{name}") is not None:
        raise AttributeError(f"module 'lasagna' has no attribute {name!r}")
    if name == "__all__":
        return ["__version__", *_api().__all__]
    if name in _api().__all__:
        return getattr(_api(), name)
    raise AttributeError(f"module 'lasagna' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_api().__all__})
