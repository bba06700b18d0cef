"""Interchange exports: per-layer raw PNGs, OpenRaster (export and import), layered PSD.

png.py      export_layer_pngs: each layer's stored values, never normalised, 16-bit when ranged
ora.py      export_ora / encode_ora, import_ora / read_ora (zip-slip and bomb safe)
psd.py      export_psd / encode_psd (optional extra: pip install 'lasagna[psd]')
rasters.py  the layers as paint programs see them (dodge pairs, baked alpha, exact-composite layer)
"""

from lasagna.export.ora import encode_ora, export_ora, import_ora, read_ora
from lasagna.export.png import export_layer_pngs
from lasagna.export.psd import encode_psd, export_psd

__all__ = ["encode_ora", "export_ora", "import_ora", "read_ora", "export_layer_pngs", "encode_psd", "export_psd"]
