"""Lasagna: layered image compositing with learned layers.

    import lasagna
    stack = lasagna.load("examples/stacks/basic")      # a folder or its stack.json
    result = lasagna.render(stack)                     # RenderResult(image, skipped, evaluated)
    lasagna.save(stack, "out/mystack")                 # stack.json + layer PNGs (composite=True: composite.png)
    lasagna.to_pil(result)                             # the composite as an 8-bit PIL image
    lasagna.edit("photo.png", "shading", "left")       # a learned layer (lasagna.editing.edit)

The API names are loaded lazily so that ``import lasagna.document`` (pydantic only) never imports
torch. See docs/ARCHITECTURE.md for the tiers.
"""

from lasagna.version import __version__

_API = (
    "load",
    "render",
    "save",
    "Stack",
    "from_image",
    "from_tensors",
    "export_ora",
    "export_psd",
    "import_ora",
    "export_layer_pngs",
    "write_composite",
    "RenderResult",
    "to_pil",
    "to_numpy",
    "edit",
    "edit_many",
    "render_learned",
)
__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        from lasagna import api

        return getattr(api, name)
    raise AttributeError(f"module 'lasagna' has no attribute {name!r}")
