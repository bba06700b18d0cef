"""Interchange exports: per-layer raw PNGs, OpenRaster (export and import), layered PSD.

png.py      export_layer_pngs: each layer's stored values, never normalised, 16-bit when ranged
ora.py      export_ora / encode_ora; ora_import.py: import_ora / read_ora (zip-slip and bomb safe)
psd.py      export_psd / encode_psd (optional extra: pip install 'lasagna-layers[psd]')
rasters.py  the layers as paint programs see them (dodge pairs, baked alpha, exact-composite layer)
surface_import.py  a surface layer read back from its rendered multiplier over its hidden normal map
light_fit.py        the one light that renders a multiplier from a normal map, fitted to the pixels

Names are imported lazily: ``import lasagna.export.ora`` to read an OpenRaster file loads no torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "encode_ora": "ora",
    "export_ora": "ora",
    "import_ora": "ora_import",
    "read_ora": "ora_import",
    "export_layer_pngs": "png",
    "encode_psd": "psd",
    "export_psd": "psd",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'lasagna.export' has no attribute {name!r}")
    return getattr(importlib.import_module(f"lasagna.export.{module}"), name)
