"""What the PSD writer and reader share about psd-tools (the optional extra ``lasagna-layers[psd]``), without
torch: a PSD import that refuses a broken file loads neither (``benchmarks/hostile.py`` times refusals)."""

from __future__ import annotations

from lasagna.document.blend import BLEND_MODES
from lasagna.errors import ExportError
from lasagna.version import install_hint

INSTALL_HINT = install_hint("psd")


def require_psd_tools():
    """(PSDImage, BlendMode) of psd-tools; an ``ExportError`` saying how to install it when it is missing."""
    try:
        from psd_tools import PSDImage
        from psd_tools.constants import BlendMode
    except ImportError:
        raise ExportError(
            f"PSD export needs psd-tools, which is not installed; expected it: {INSTALL_HINT}", where="psd"
        ) from None
    return PSDImage, BlendMode


def psd_blend_modes(BlendMode) -> dict[str, object]:
    """psd-tools' ``BlendMode`` of every blend: its own name in upper case (``color-dodge`` → ``COLOR_DODGE``,
    ``linear-dodge`` → ``LINEAR_DODGE``), and plus too is LINEAR_DODGE ("Linear Dodge (Add)"): its partial alpha
    is baked into its values on export (``lasagna.export.rasters``), on which the two agree. Read back,
    LINEAR_DODGE is ``linear-dodge`` (the last of the two in this table)."""
    return {m: BlendMode.LINEAR_DODGE if m == "plus" else BlendMode[m.upper().replace("-", "_")] for m in BLEND_MODES}
