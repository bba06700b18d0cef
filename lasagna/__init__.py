"""Lasagna: layered image compositing with learned layers.

The public API is filled in as the tiers land; see docs/ARCHITECTURE.md.
"""
__version__ = "0.1.0"
