"""The editor's view of a transparent document (``canvas.background`` null): the RGBA bytes carry the composite's
alpha (the page shows its checkerboard through it), at every view level, and the PNG export is RGBA."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from PIL import Image

pytest.importorskip("starlette")
pytest.importorskip("httpx")

from starlette.testclient import TestClient  # noqa: E402

from lasagna.io.render import composite_codes, render_stack  # noqa: E402
from lasagna.io.stack import Stack, load_stack  # noqa: E402
from lasagna.serve.app import create_app  # noqa: E402
from lasagna.serve.session import EditSession  # noqa: E402

TOKEN = "test-token"
H = {"X-Lasagna-Token": TOKEN}


def test_the_view_of_a_transparent_document_carries_its_alpha(tmp_path):
    g = torch.Generator().manual_seed(4)
    alpha = torch.rand(1, 24, 32, generator=g)
    alpha[:, :, :5] = 0.0
    stack = Stack.from_image(torch.rand(3, 24, 32, generator=g), alpha=alpha)
    stack.add_layer("paint", torch.rand(4, 8, 9, generator=g), offset=(10, 6))
    stack.save(tmp_path / "s")
    client = TestClient(create_app(EditSession(tmp_path / "s"), TOKEN, ["testserver"]), raise_server_exceptions=False)
    r = client.get("/api/view", headers=H)
    assert r.status_code == 200, r.text
    w, h = int(r.headers["X-Width"]), int(r.headers["X-Height"])
    rgba = np.frombuffer(r.content, np.uint8).reshape(h, w, 4)
    result = render_stack(load_stack(tmp_path / "s"))  # what the session holds: the saved 8-bit codes
    expected = composite_codes(torch.cat([result.image, result.alpha])).permute(1, 2, 0).numpy()
    assert np.array_equal(rgba, expected)
    assert (rgba[:, :5, 3] == 0).all()
    png = client.get("/api/export/png", headers=H)
    assert png.status_code == 200, png.text
    with Image.open(io.BytesIO(png.content)) as im:
        assert im.mode == "RGBA" and np.array_equal(np.asarray(im), expected)
