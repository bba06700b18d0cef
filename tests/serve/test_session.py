"""The editor's session against independent facts: what it owns on disk (a symlinked layer's target survives a
delete and save), its memory (every render and upload admitted by the budget it was opened with, history
let go before an upload is refused), the range rule shared with the document, and layers inside groups.

References: the folder's bytes, ``load_stack`` + ``render_stack`` (the CLI's composite), weak references
for memory released, and ``/proc/self/status`` for the process's peak."""

from __future__ import annotations

import gc
import io
import json
import os
import shutil
import weakref
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

pytest.importorskip("starlette")
pytest.importorskip("httpx")

from starlette.testclient import TestClient  # noqa: E402

from lasagna.document import Document  # noqa: E402
from lasagna.errors import DocumentError  # noqa: E402
from lasagna.io.render import composite_codes, render_stack  # noqa: E402
from lasagna.io.stack import Stack, load_stack  # noqa: E402
from lasagna.limits import memory_budget_scope  # noqa: E402
from lasagna.serve.app import create_app  # noqa: E402
from lasagna.serve.session import EditSession  # noqa: E402
from tests.support.tinylayers import ROOT  # noqa: E402

TOKEN = "test-token"
H = {"X-Lasagna-Token": TOKEN}
BASIC = ROOT / "examples" / "stacks" / "basic"


def _client(session: EditSession) -> TestClient:
    return TestClient(create_app(session, TOKEN, ["testserver"]), raise_server_exceptions=False)


def _change(client: TestClient, **body) -> dict:
    body.setdefault("version", client.get("/api/state", headers=H).json()["version"])
    return client.post("/api/change", headers=H, json=body)


def _ok(response) -> dict:
    assert response.status_code == 200, response.text
    return response.json()


def _refused(response, status: int) -> str:
    assert response.status_code == status, (response.status_code, response.text)
    line = response.json()["error"]
    assert "\n" not in line and "Traceback" not in line
    return line


def _basic(tmp_path: Path) -> Path:
    folder = tmp_path / "basic"
    shutil.copytree(BASIC, folder)
    return folder


def _solid(tmp_path: Path, side: int) -> Path:
    """A stack.json of a few hundred bytes: one solid layer on a ``side``² canvas."""
    folder = tmp_path / f"solid{side}"
    folder.mkdir()
    doc = {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": side, "height": side},
        "layers": [{"id": "paper", "kind": "solid", "color": [0.9, 0.8, 0.7]}],
    }
    (folder / "stack.json").write_text(json.dumps(doc))
    return folder


def _view_codes(client: TestClient, **params) -> np.ndarray:
    r = client.get("/api/view", headers=H, params=params)
    assert r.status_code == 200, r.text
    w, h = int(r.headers["X-Width"]), int(r.headers["X-Height"])
    return np.frombuffer(r.content, np.uint8).reshape(h, w, 4)[..., :3]


def _engine_codes(doc: Document, tensors) -> np.ndarray:
    image = render_stack(Stack(doc, None, dict(tensors))).image
    return composite_codes(image).permute(1, 2, 0).numpy()


def _peak_mb() -> float:
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:")) / 1024


# ---- 2: deleting a layer whose PNG is a symlink ----------------------------------------------------------


def test_deleting_a_linked_layer_and_saving_keeps_the_links_target(tmp_path):
    folder = _basic(tmp_path)
    (folder / "layers" / "sticker.png").unlink()
    (folder / "layers" / "sticker.png").symlink_to("glow.png")  # sticker's PNG is glow's
    glow = (folder / "layers" / "glow.png").read_bytes()
    client = _client(EditSession(folder))
    _ok(_change(client, op="delete", id="sticker"))
    _ok(_change(client, op="save"))
    assert (folder / "layers" / "glow.png").read_bytes() == glow
    assert not os.path.lexists(folder / "layers" / "sticker.png")
    render_stack(load_stack(folder))


# ---- 5, 17: every render path admitted by the session's budget --------------------------------------------


def test_every_render_path_is_refused_over_the_budget_and_coarse_views_still_render(tmp_path):
    session = EditSession(_solid(tmp_path, 2048), memory_budget=16 * 2**20)
    client = _client(session)
    for path in ("/api/view?level=0", "/api/view?level=1", "/api/export/png", "/api/export/ora"):
        line = _refused(client.get(path, headers=H), 413)
        assert "16.0 MB" in line, line
    _ok(_change(client, op="set", id="paper", changes={"opacity": 0.5}))
    assert "16.0 MB" in _refused(_change(client, op="save"), 413)
    top = session.max_level()
    codes = _view_codes(client, level=top)  # 32² fits
    assert codes.shape == (32, 32, 3) and (codes == codes[0, 0]).all()
    assert client.get("/api/layers/paper/thumb.png", headers=H).status_code == 200


def test_a_16384_canvas_under_1g_is_refused_at_once_without_allocating(tmp_path):
    session = EditSession(_solid(tmp_path, 16384), memory_budget=2**30)
    client = _client(session)
    before = _peak_mb()
    line = _refused(client.get("/api/view?level=0", headers=H), 413)
    assert "1.0 GB" in line and "16384x16384" in line
    assert client.get("/api/layers/paper/thumb.png", headers=H).status_code == 200
    assert _peak_mb() - before < 500


def test_the_refusal_reports_the_budget_the_editor_was_opened_with(tmp_path):
    with memory_budget_scope("1M"):  # as `lasagna serve --memory-budget 1M` opens it
        session = EditSession(_solid(tmp_path, 2048))
    client = _client(session)  # requests run in the client's own thread, outside that scope
    line = _refused(client.get("/api/view?level=0", headers=H), 413)
    assert "1.0 MB" in line and "8.0 GB" not in line


# ---- 8: the session's total against the budget -----------------------------------------------------------


def _png(side: int, value: int) -> bytes:
    buf = io.BytesIO()
    Image.new("RGBA", (side, side), (value, value, value, 255)).save(buf, "PNG")
    return buf.getvalue()


def _upload(client: TestClient, data: bytes, name: str):
    version = client.get("/api/state", headers=H).json()["version"]
    return client.post(f"/api/upload?version={version}&name={name}", headers=H, content=data)


def test_uploads_fit_the_budget_history_goes_first_then_a_one_line_refusal(tmp_path):
    budget = 3 * 2**20  # a 256² upload is 1 MiB of float32 RGBA: two fit beside the basic stack, not three
    session = EditSession(_basic(tmp_path), memory_budget=budget)
    client = _client(session)
    n = len(session.stack.document.layers)
    _ok(_upload(client, _png(256, 10), "a.png"))
    state = _ok(_upload(client, _png(256, 20), "b.png"))
    b = state["document"]["layers"][-1]["id"]
    line = _refused(_upload(client, _png(256, 30), "c.png"), 413)
    assert "3.0 MB" in line and "needs" in line
    assert len(client.get("/api/state", headers=H).json()["document"]["layers"]) == n + 2  # nothing added
    assert session.held_bytes() <= budget

    gone = weakref.ref(session.stack.tensors[b].color)
    _ok(_change(client, op="delete", id=b))  # b's pixels now live only in the undo history
    _ok(_upload(client, _png(256, 30), "c.png"))  # fits once that history is let go
    gc.collect()
    assert gone() is None
    assert session.held_bytes() <= budget


# ---- 13: the range rule, one for validate, composite and the editor ----------------------------------------


def test_a_range_float32_cannot_hold_is_refused_and_none_turns_a_layer_nan(tmp_path):
    client = _client(session := EditSession(_basic(tmp_path)))
    original = session.stack.tensors["shade"].color.clone()
    for bad in ([0, 1e-300], [-1e308, 1e308]):
        line = _refused(_change(client, op="set", id="shade", changes={"range": bad}), 400)
        assert "range" in line and "float32" in line
    _ok(_change(client, op="set", id="shade", changes={"range": [0, 1e-30]}))  # minute, and still a float32 span
    _ok(_change(client, op="set", id="shade", changes={"range": [0, 2]}))
    back = session.stack.tensors["shade"].color
    assert bool(torch.isfinite(back).all())
    assert torch.allclose(back, original, rtol=1e-5, atol=1e-6)
    _ok(_change(client, op="save"))
    render_stack(load_stack(session.folder))


# ---- 18: layers inside groups ----------------------------------------------------------------------------


def _grouped(tmp_path: Path) -> Path:
    """The basic stack with shade and sticker inside a pass-through group ``g``."""
    folder = _basic(tmp_path)
    doc = json.loads((folder / "stack.json").read_text())
    base, shade, sticker, *rest = doc["layers"]
    group = {"id": "g", "kind": "group", "layers": [shade, sticker]}
    doc["layers"] = [base, group, *rest]
    (folder / "stack.json").write_text(json.dumps(doc))
    return folder


def test_layers_inside_groups_are_set_soloed_moved_and_deleted(tmp_path):
    folder = _grouped(tmp_path)
    client = _client(session := EditSession(folder))
    _ok(_change(client, op="set", id="sticker", changes={"opacity": 0.5}))
    _ok(_change(client, op="set", id="shade", changes={"range": [0, 4]}))
    _ok(_change(client, op="move", id="sticker", index=0))
    assert [layer.id for layer in session.stack.document.layer("g").layers] == ["sticker", "shade"]

    solo = _view_codes(client, level=0, solo="sticker")
    doc = session.stack.document
    alone = doc.with_layers(
        [
            doc.layer("base").model_copy(update={"visible": False}),
            {
                **doc.layer("g").model_dump(),
                "layers": [doc.layer("sticker"), {**doc.layer("shade").model_dump(), "visible": False}],
            },
            *(layer.model_copy(update={"visible": False}) for layer in doc.layers[2:]),
        ]
    )
    assert np.array_equal(solo, _engine_codes(alone, session.stack.tensors))

    _ok(_change(client, op="save"))
    saved = load_stack(folder)
    assert saved.document.layer("sticker").opacity == 0.5 and tuple(saved.document.layer("shade").range) == (0, 4)
    assert torch.allclose(saved.tensors["shade"].color, session.stack.tensors["shade"].color, atol=4 / 65535)

    shade_file = folder / saved.document.layer("shade").source
    _ok(_change(client, op="delete", id="shade"))
    _ok(_change(client, op="save"))
    assert "shade" not in load_stack(folder).document.all_ids and not shade_file.exists()


def test_group_and_ungroup_round_trip_and_keep_the_composite(tmp_path):
    folder = _basic(tmp_path)
    client = _client(session := EditSession(folder))
    before_doc = session.stack.document.to_dict()
    before = _view_codes(client, level=0)
    state = _ok(_change(client, op="group", ids=["shade", "sticker"], name="Light"))
    ids = [layer["id"] for layer in state["document"]["layers"]]
    group = state["document"]["layers"][1]
    assert ids == ["base", group["id"], "glow", "hidden"] and group["kind"] == "group"
    assert [layer["id"] for layer in group["layers"]] == ["shade", "sticker"]
    assert np.abs(_view_codes(client, level=0).astype(int) - before).max() <= 1
    _ok(_change(client, op="save"))
    assert load_stack(folder).document.layer(group["id"]).kind == "group"

    _ok(_change(client, op="ungroup", id=group["id"]))
    assert session.stack.document.to_dict() == before_doc

    assert "siblings" in _refused(_change(client, op="group", ids=["base", "nope"]), 400)
    _ok(_change(client, op="group", ids=["glow"]))
    gid = session.stack.document.layers[-2].id
    _ok(_change(client, op="set", id=gid, changes={"opacity": 0.5}))
    assert "composite" in _refused(_change(client, op="ungroup", id=gid), 400)
    with pytest.raises(DocumentError):
        session.stack.document.ungrouped("base")
