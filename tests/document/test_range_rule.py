"""The range rule, stated once (``lasagna.document.types.range_problem``): the document's validator (``lasagna
validate``, ``lasagna composite``) and the compositor's layer specs give one verdict on every range, and a range
the rule accepts maps every 16-bit code to finite float32 values and back (numpy float32, the reference)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec
from lasagna.document import Document
from lasagna.errors import DocumentError, LasagnaError

REFUSED = [
    (0.0, 1e-300),  # subnormal in float64 already; 0 in float32
    (0.0, 1e-35),  # a normal float32, but one 16-bit step of it is not
    (1.0, 1.0 + 1e-12),  # distinct in float64, one float32
    (-1e308, 1e308),  # finite in float64, infinite in float32
    (0.0, 1e39),
    (-2e38, 2e38),  # both ends fit float32, the span does not
]
ACCEPTED = [(0.0, 1.0), (0.0, 2.0), (-1.0, 1.0), (0.0, 1e4), (0.0, 1e-30), (-1e38, 1e38)]


def _document(lo: float, hi: float) -> Document:
    layer = {"id": "shade", "kind": "solid", "blend": "multiply", "range": [lo, hi], "color": [0.5, 0.5, 0.5]}
    return Document.from_dict(
        {"format": "lasagna.stack", "version": 1, "canvas": {"width": 2, "height": 2}, "layers": [layer]}
    )


def _spec(lo: float, hi: float) -> RenderLayerSpec:
    return RenderLayerSpec(id="shade", tensors=LayerTensors(torch.zeros(3, 2, 2)), blend="multiply", range=(lo, hi))


@pytest.mark.parametrize("lo, hi", REFUSED)
def test_a_range_float32_cannot_hold_is_refused_by_the_document_and_the_compositor(lo, hi):
    with pytest.raises(DocumentError, match=r"range .* breaks the rule"):
        _document(lo, hi)
    with pytest.raises(LasagnaError, match=r"range .* breaks the rule"):
        _spec(lo, hi)


@pytest.mark.parametrize("lo, hi", ACCEPTED)
def test_an_accepted_range_round_trips_every_16_bit_code_finitely(lo, hi):
    _document(lo, hi)
    _spec(lo, hi)
    v = np.arange(65536, dtype=np.float32) / np.float32(65535)
    lo32, span32 = np.float32(lo), np.float32(hi) - np.float32(lo)
    y = lo32 + span32 * v  # as layer_tensors maps codes, in float32
    back = (y - lo32) / span32  # as the editor and save_stack read them
    assert np.isfinite(span32) and np.isfinite(y).all() and np.isfinite(back).all()
    assert np.abs(back - v).max() < 1e-3
