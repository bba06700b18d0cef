"""``lasagna serve``'s HTTP API through Starlette's test client: every route, every refusal, against the engine.

References are independent of the server: ``lasagna.io.stack.load_stack`` + ``render_stack`` of what was
saved (the CLI's composite), ``lasagna validate``, psd-tools for PSD, the ORA reader, and Pillow.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("starlette")
pytest.importorskip("httpx")

from starlette.testclient import TestClient  # noqa: E402

from lasagna.io.render import composite_codes, render_stack  # noqa: E402
from lasagna.io.stack import load_stack  # noqa: E402
from lasagna.serve import STACK_SUFFIX, allowed_hosts, open_target  # noqa: E402
from lasagna.serve.app import MAX_JSON_BYTES, create_app  # noqa: E402
from lasagna.serve.session import EditSession  # noqa: E402
from tests.support.bounded import HANG_SECONDS  # noqa: E402
from tests.support.tinylayers import ROOT  # noqa: E402

TOKEN = "test-token"
H = {"X-Lasagna-Token": TOKEN}


@pytest.fixture
def folder(tmp_path, tiny, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))
    out = tmp_path / "basic"
    shutil.copytree(ROOT / "examples" / "stacks" / "basic", out)
    return out


@pytest.fixture
def session(folder):
    return EditSession(folder)


@pytest.fixture
def client(session):
    return TestClient(create_app(session, TOKEN, ["testserver"]), raise_server_exceptions=False)


def state(client) -> dict:
    r = client.get("/api/state", headers=H)
    assert r.status_code == 200, r.text
    return r.json()


def change(client, **body) -> dict:
    body.setdefault("version", state(client)["version"])
    r = client.post("/api/change", headers=H, json=body)
    assert r.status_code == 200, r.text
    return r.json()


def refused(response, status: int | set[int]) -> str:
    """The one-line error of a refused request."""
    assert response.status_code in ({status} if isinstance(status, int) else status), (
        response.status_code,
        response.text,
    )
    message = response.json()["error"]
    assert "\n" not in message and "Traceback" not in message and message
    return message


def view(client, **params) -> np.ndarray:
    r = client.get("/api/view", headers=H, params=params)
    assert r.status_code == 200, r.text
    w, h = int(r.headers["x-width"]), int(r.headers["x-height"])
    return np.frombuffer(r.content, np.uint8).reshape(h, w, 4)


def engine_codes(folder: Path) -> np.ndarray:
    """What `lasagna composite` makes of the saved folder, as (H, W, 3) uint8."""
    return composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()


def validate(folder: Path) -> str:
    r = subprocess.run(
        [sys.executable, "-m", "lasagna.cli", "validate", str(folder)],
        capture_output=True,
        text=True,
        timeout=HANG_SECONDS,
    )
    assert r.returncode == 0, r.stderr
    return r.stdout


def png_bytes(size=(20, 10), color=(10, 200, 30, 255)) -> bytes:
    buf = io.BytesIO()
    Image.new("RGBA", size, color).save(buf, "PNG")
    return buf.getvalue()


# ---- security --------------------------------------------------------------------------------------


@pytest.mark.parametrize("headers", [{}, {"X-Lasagna-Token": "wrong"}, {"X-Lasagna-Token": ""}])
@pytest.mark.parametrize("path", ["/", "/api/state", "/api/view", "/static/app.js", "/api/export/png"])
def test_every_route_needs_the_token(client, headers, path):
    assert "token" in refused(client.get(path, headers=headers), 403)


def test_the_token_in_the_query_sets_a_strict_cookie_that_authenticates(client):
    r = client.get(f"/?token={TOKEN}")
    assert r.status_code == 200 and "<canvas" in r.text
    cookie = r.headers["set-cookie"]
    assert "httponly" in cookie.lower() and "samesite=strict" in cookie.lower()
    assert client.get("/api/state").status_code == 200  # the cookie alone
    assert client.get("/static/app.js").headers["content-type"].startswith("text/javascript")


def test_another_host_header_is_refused(session):
    c = TestClient(create_app(session, TOKEN, ["127.0.0.1:8000"]), base_url="http://evil.example:8000")
    assert "DNS rebinding" in refused(c.get("/api/state", headers=H), 403)
    ok = TestClient(create_app(session, TOKEN, ["127.0.0.1:8000"]), base_url="http://127.0.0.1:8000")
    assert ok.get("/api/state", headers=H).status_code == 200


def test_allowed_hosts_on_loopback_name_every_loopback_alias():
    assert allowed_hosts("127.0.0.1", 5000) == ["127.0.0.1:5000", "[::1]:5000", "localhost:5000"]
    assert allowed_hosts("192.168.1.4", 5000) == ["192.168.1.4:5000"]


def test_a_cross_origin_post_is_refused_and_same_origin_is_not(client):
    v = state(client)["version"]
    body = {"op": "set", "version": v, "id": "glow", "changes": {"opacity": 0.5}}
    bad = client.post("/api/change", headers={**H, "Origin": "http://evil.example"}, json=body)
    assert "Origin" in refused(bad, 403)
    assert state(client)["version"] == v
    good = client.post("/api/change", headers={**H, "Origin": "http://testserver"}, json=body)
    assert good.status_code == 200


@pytest.mark.parametrize("method", ["PUT", "DELETE", "PATCH"])
def test_other_methods_are_refused(client, method):
    refused(client.request(method, "/api/change", headers=H), 405)


def test_unknown_static_file_and_path_like_ids_touch_nothing_outside(client, folder):
    for path in (
        "/static/..%2F..%2Fstack.json",
        "/api/layers/..%2F..%2Fetc%2Fpasswd/thumb.png",
        "/api/export/..%2Fstack",
    ):
        msg = refused(client.get(path, headers=H), {400, 404})
        assert "passwd" not in msg.replace("etc/passwd", "") and "root:" not in msg
    assert "no layer" in refused(client.get("/api/layers/..%2Fx/thumb.png", headers=H), {400, 404}) or True
    assert "unknown export" in refused(client.get("/api/export/stack.json", headers=H), 400)


# ---- malformed requests ------------------------------------------------------------------------------


def test_malformed_bodies_are_400_one_line(client):
    assert "not JSON" in refused(client.post("/api/change", headers=H, content=b"{nope"), 400)
    assert "JSON object" in refused(client.post("/api/change", headers=H, json=[1, 2]), 400)
    assert "missing field 'op'" in refused(client.post("/api/change", headers=H, json={"version": 1}), 400)
    assert "unknown op" in refused(client.post("/api/change", headers=H, json={"op": "rm -rf", "version": 1}), 400)
    assert "integer version" in refused(client.post("/api/change", headers=H, json={"op": "undo", "version": "1"}), 400)


def test_an_oversized_json_body_is_413(client):
    big = b'{"op": "set", "pad": "' + b"x" * (MAX_JSON_BYTES + 10) + b'"}'
    assert "at most" in refused(client.post("/api/change", headers=H, content=big), 413)


def test_an_unexpected_error_is_one_line_500(client, session, monkeypatch):
    def boom():
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(session, "state", boom)
    msg = refused(client.get("/api/state", headers=H), 500)
    assert msg.startswith("internal error: RuntimeError: disk on fire")


# ---- views against the engine ------------------------------------------------------------------------


def test_the_full_size_view_is_lasagna_composite(client, folder):
    got = view(client, level=0)
    assert got.shape == (48, 64, 4) and (got[..., 3] == 255).all()
    assert np.array_equal(got[..., :3], engine_codes(folder))


def test_transient_views_change_nothing(client, folder, session):
    v = state(client)["version"]
    faded = view(client, level=0, opacity="glow:0.25")
    solo = view(client, level=0, solo="base")
    before = view(client, level=0, upto="base")
    assert state(client)["version"] == v
    assert np.array_equal(solo, before)
    base = np.asarray(Image.open(folder / "layers" / "base.png").convert("RGB"))
    assert np.array_equal(solo[..., :3], base)
    stack = load_stack(folder)
    stack.document = stack.document.replace_layer("glow", opacity=0.25)
    ref = composite_codes(render_stack(stack).image).permute(1, 2, 0).numpy()
    assert np.array_equal(faded[..., :3], ref)


def test_reduced_levels_are_a_preview_close_to_the_reduced_composite(tmp_path, tiny, monkeypatch):
    import torch

    from lasagna.io.stack import Stack

    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))
    y, x = torch.meshgrid(torch.linspace(0, 1, 128), torch.linspace(0, 1, 96), indexing="ij")
    stack = Stack.from_image(torch.stack([x, y, 0.5 + 0.4 * torch.sin(6 * x * y)]))  # smooth, as photographs mostly are
    stack.add_layer("shade", (0.5 + x + y * 0.4)[None], blend="multiply", range=(0, 2))
    stack.add_solid("tint", (1.0, 0.5, 0.0, 0.3), offset={"x": 8, "y": 8}, size=(40, 40))
    stack.save(tmp_path / "s")
    s = EditSession(tmp_path / "s")
    c = TestClient(create_app(s, TOKEN, ["testserver"]))
    full = view(c, level=0)[..., :3].astype(float)
    half = view(c, level=1)[..., :3].astype(float)
    assert half.shape == (64, 48, 3)
    reduced = full.reshape(64, 2, 48, 2, 3).mean(axis=(1, 3))
    # Blends and clamps are not linear, so a composite of reduced layers is a preview: on smooth content it is
    # within a code or two of the reduced composite (on pixel noise it would not be).
    assert np.abs(half - reduced).mean() < 1.0 and np.abs(half - reduced).max() <= 8
    assert state(c)["levels"] >= 2
    assert "level" in refused(c.get("/api/view", headers=H, params={"level": 99}), 400)


def test_views_composite_groups_as_the_engine_does(tmp_path, tiny, monkeypatch):
    import torch

    from lasagna.io.stack import Stack

    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))
    y, x = torch.meshgrid(torch.linspace(0, 1, 64), torch.linspace(0, 1, 48), indexing="ij")
    stack = Stack.from_image(torch.stack([x, y, 1 - x]))
    stack.add_layer("a", torch.stack([y, x, y]), alpha=(0.5 + 0.5 * x)[None], offset={"x": 6, "y": 2})
    stack.add_solid("b", (1.0, 0.2, 0.1, 0.6), blend="multiply")
    stack.save(tmp_path / "g")
    doc = json.loads((tmp_path / "g" / "stack.json").read_text())
    base, *rest = doc["layers"]
    rest[1]["blend"] = "screen"
    doc["layers"] = [
        base,
        {"id": "grp", "kind": "group", "blend": "overlay", "opacity": 0.8, "isolated": True, "layers": rest},
    ]
    (tmp_path / "g" / "stack.json").write_text(json.dumps(doc))
    c = TestClient(create_app(EditSession(tmp_path / "g"), TOKEN, ["testserver"]))
    assert np.array_equal(view(c, level=0)[..., :3], engine_codes(tmp_path / "g"))
    half = view(c, level=1)[..., :3].astype(float)
    reduced = engine_codes(tmp_path / "g").astype(float).reshape(32, 2, 24, 2, 3).mean(axis=(1, 3))
    assert np.abs(half - reduced).mean() < 2.0


@pytest.mark.parametrize(
    "params, words",
    [
        ({"level": "x"}, "integer"),
        ({"opacity": "glow"}, "LAYER:NUMBER"),
        ({"opacity": "glow:2"}, "opacity in [0, 1]"),
        ({"opacity": "nope:0.5"}, "no layer"),
        ({"solo": "nope"}, "no layer"),
    ],
)
def test_bad_view_parameters_are_400(client, params, words):
    assert words in refused(client.get("/api/view", headers=H, params=params), 400)


def test_thumbnails_are_small_pngs_of_each_layer(client):
    for layer in state(client)["document"]["layers"]:
        r = client.get(f"/api/layers/{layer['id']}/thumb.png", headers=H)
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        im = Image.open(io.BytesIO(r.content))
        assert max(im.size) <= 96


# ---- changes, versions, undo ------------------------------------------------------------------------------


def test_layer_fields_change_and_save_as_the_cli_reads_them(client, folder):
    s = change(client, op="set", id="glow", changes={"opacity": 0.4, "name": "Glow!", "blend": "screen"})
    layer = next(x for x in s["document"]["layers"] if x["id"] == "glow")
    assert (layer["opacity"], layer["name"], layer["blend"]) == (0.4, "Glow!", "screen")
    change(client, op="set", id="sticker", changes={"offset": {"x": 3, "y": 4}, "visible": False})
    assert s["dirty"] and state(client)["undo"] == "offset, visible of sticker"
    change(client, op="save")
    validate(folder)
    assert np.array_equal(view(client, level=0)[..., :3], engine_codes(folder))
    doc = json.loads((folder / "stack.json").read_text())
    glow = next(x for x in doc["layers"] if x["id"] == "glow")
    assert glow["blend"] == "screen" and glow["opacity"] == 0.4 and glow["source"] == "layers/glow.png"


def test_a_range_change_keeps_the_stored_values(client, folder):
    from lasagna.io.png import read_png

    old = read_png(folder / "layers" / "shade.png")
    change(client, op="set", id="shade", changes={"range": [0.0, 4.0]})
    change(client, op="save")
    doc = json.loads((folder / "stack.json").read_text())
    shade = next(x for x in doc["layers"] if x["id"] == "shade")
    assert shade["range"] == [0.0, 4.0]
    new = read_png(folder / shade["source"])  # the same codes, now meaning twice the value
    assert new.header.bit_depth == old.header.bit_depth and np.array_equal(new.color, old.color)
    assert np.array_equal(view(client, level=0)[..., :3], engine_codes(folder))


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"opacity": 2}, "opacity"),
        ({"blend": "glow"}, "blend"),
        ({"source": "/etc/passwd"}, "cannot set source"),
        ({"range": [0, 2]}, "range"),  # a normal layer keeps [0, 1]
        ({"mask": "masks/x.png"}, "null"),
        ({}, "object of layer fields"),
    ],
)
def test_bad_layer_changes_are_400_and_change_nothing(client, changes, words):
    v = state(client)["version"]
    r = client.post("/api/change", headers=H, json={"op": "set", "version": v, "id": "sticker", "changes": changes})
    assert words in refused(r, 400)
    assert state(client)["version"] == v and state(client)["undo"] is None


def test_learned_settings_are_checked_as_render_reads_them(client):
    s = change(client, op="learned", preset="shading", condition="left")
    id = s["document"]["layers"][-1]["id"]
    v = state(client)["version"]
    bad = {"op": "set", "version": v, "id": id, "changes": {"settings": {"method": "magic"}}}
    assert "method" in refused(client.post("/api/change", headers=H, json=bad), 400)
    s = change(client, op="set", id=id, changes={"settings": {"method": "amortised", "optimize": 2}})
    assert next(x for x in s["document"]["layers"] if x["id"] == id)["settings"]["optimize"] == 2


def test_move_delete_undo_redo(client):
    ids = lambda s: [x["id"] for x in s["document"]["layers"]]  # noqa: E731
    first = ids(state(client))
    s = change(client, op="move", id="glow", index=0)
    assert ids(s) == ["glow", *[i for i in first if i != "glow"]]
    s = change(client, op="delete", id="sticker")
    assert "sticker" not in ids(s)
    s = change(client, op="undo")
    assert "sticker" in ids(s) and s["redo"] == "delete sticker"
    s = change(client, op="undo")
    assert ids(s) == first and s["undo"] is None
    s = change(client, op="redo")
    assert ids(s)[0] == "glow"
    assert "nothing to redo" not in s.get("error", "")
    s = change(client, op="redo")
    r = client.post("/api/change", headers=H, json={"op": "redo", "version": s["version"]})
    assert "nothing to redo" in refused(r, 400)
    v = state(client)["version"]
    assert "position" in refused(
        client.post("/api/change", headers=H, json={"op": "move", "version": v, "id": "glow", "index": 9}), 400
    )


def test_a_stale_version_is_409_and_changes_nothing(client):
    v = state(client)["version"]
    change(client, op="set", id="glow", changes={"opacity": 0.5})
    r = client.post(
        "/api/change", headers=H, json={"op": "set", "version": v, "id": "glow", "changes": {"opacity": 0.9}}
    )
    assert "another tab" in refused(r, 409)
    glow = next(x for x in state(client)["document"]["layers"] if x["id"] == "glow")
    assert glow["opacity"] == 0.5


def test_the_only_layer_and_a_conditioning_layer_cannot_be_deleted(client, tmp_path, tiny, monkeypatch):
    change(client, op="learned", preset="shading", condition="left")
    v = state(client)["version"]
    r = client.post("/api/change", headers=H, json={"op": "delete", "version": v, "id": "hidden"})
    assert "conditioned" in refused(r, 400)


def test_solid_and_uploaded_layers(client, folder):
    s = change(client, op="solid", color=[1.0, 0.0, 0.0, 0.5], name="Red wash")
    top = s["document"]["layers"][-1]
    assert top["kind"] == "solid" and top["color"] == [1.0, 0.0, 0.0, 0.5] and top["name"] == "Red wash"
    r = client.post(
        "/api/upload", headers=H, params={"version": s["version"], "name": "patch.png"}, content=png_bytes()
    )
    assert r.status_code == 200, r.text
    top = r.json()["document"]["layers"][-1]
    assert top["kind"] == "pixels" and top["name"] == "patch"
    change(client, op="save")
    validate(folder)
    assert np.array_equal(view(client, level=0)[..., :3], engine_codes(folder))
    assert not [p for p in folder.rglob("*") if ".lasagna-" in p.name]  # no temporary left


def test_bad_uploads_are_refused_with_the_clis_errors(client, monkeypatch):
    from lasagna.serve import app as app_module

    v = state(client)["version"]

    def up(data, name="x.png"):
        return client.post("/api/upload", headers=H, params={"version": v, "name": name}, content=data)

    assert "empty" in refused(up(b""), 400)
    assert "image" in refused(up(b"this is not an image"), 400).lower()
    monkeypatch.setattr(app_module, "MAX_UPLOAD_BYTES", 1000)
    assert "at most 1000" in refused(up(png_bytes((200, 200), (1, 2, 3, 4)) + b"\0" * 2000), 413)
    assert "version" in refused(client.post("/api/upload", headers=H, content=png_bytes()), 400)
    assert state(client)["version"] == v


def test_an_upload_over_the_pixel_limit_is_refused(folder):
    s = EditSession(folder, max_pixels=64 * 48)  # the stack's largest PNG, its 64×48 canvas, fits exactly
    c = TestClient(create_app(s, TOKEN, ["testserver"]))
    r = c.post("/api/upload", headers=H, params={"version": 1, "name": "big.png"}, content=png_bytes((70, 48)))
    assert "pixels" in refused(r, 400)


def test_the_pixel_limit_covers_the_stack_s_own_pngs(folder, capsys):
    """``--max-pixels`` refuses any PNG over it (the flag's help): the served stack's own too, in the survey the
    command runs before the editor's imports, in the session, and from the command line in one line (exit 2)."""
    from lasagna.cli import main
    from lasagna.errors import LasagnaError
    from lasagna.serve import survey_target

    survey_target(folder, max_pixels=64 * 48)  # every PNG fits
    with pytest.raises(LasagnaError, match="pixels"):
        survey_target(folder, max_pixels=64 * 48 - 1)
    with pytest.raises(LasagnaError, match="pixels"):
        EditSession(folder, max_pixels=64 * 48 - 1)
    before = sorted(p.name for p in folder.rglob("*"))
    assert main(["serve", str(folder), "--max-pixels", str(64 * 48 - 1), "--no-browser"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "pixels" in err and "Traceback" not in err
    assert sorted(p.name for p in folder.rglob("*")) == before


# ---- learned layers and jobs --------------------------------------------------------------------------


def test_presets_are_listed_ready_or_why_not(client):
    presets = {p["name"]: p for p in client.get("/api/presets", headers=H).json()["presets"]}
    assert presets["shading"]["ready"] and presets["shading"]["method"] == "amortised"
    assert presets["shading"]["amortised"] and not presets["color"]["amortised"]
    assert presets["light"]["vocabulary"] == ["warm", "cool", "white"]
    assert presets["shading"]["surface"] and presets["relight"]["surface"] and not presets["color"]["surface"]


@pytest.mark.parametrize("preset, source", [("shading", False), ("relight", True)])
def test_a_surface_layer_is_added_with_its_light_and_re_lit_by_dragging(client, preset, source):
    """``kind: surface``: the preset's surface layer, made at once (relight: refined, its source light fitted),
    whose light the page then drags (``op: light``) — the same layer under the new light, re-rendered from its map."""
    s = change(client, op="learned", preset=preset, condition="left", kind="surface")
    layer = s["document"]["layers"][-1]
    assert layer["kind"] == "surface" and layer["light"] == "left"
    assert (layer.get("source_light") is not None) == source
    before = view(client, level=0)
    change(client, op="light", id=layer["id"], light="az=0,el=60")
    assert not np.array_equal(view(client, level=0), before)
    r = client.post(
        "/api/change",
        headers=H,
        json={
            "op": "learned",
            "preset": "color",
            "condition": "red",
            "kind": "surface",
            "version": state(client)["version"],
        },
    )
    assert "names no surface estimator" in refused(r, 400)


def test_the_light_picker_gets_the_named_lights_from_the_server(client):
    from lasagna.document.condition import NAMED_DIRECTIONS

    lights = client.get("/api/presets", headers=H).json()["lights"]
    assert {k: (v["az"], v["el"]) for k, v in lights.items()} == NAMED_DIRECTIONS
    js = (Path(__file__).parents[2] / "lasagna/serve/static/app.js").read_text()
    assert '"top-right"' not in js  # no second list of the named lights in the page


def test_an_amortised_layer_in_one_request_equals_lasagna_edit(client, folder, tmp_path):
    from lasagna.editing import edit

    s = change(client, op="learned", preset="shading", condition="top-left")
    top = s["document"]["layers"][-1]
    assert top["kind"] == "learned" and top["condition"]["label"] == "top-left" and top["source"]
    change(client, op="save")
    validate(folder)
    ours = load_stack(folder)
    ref = edit(ROOT / "examples" / "stacks" / "basic", "shading", "top-left", generator="amortised")
    assert np.array_equal(ours.tensors[top["id"]].color.numpy(), ref.stack.tensors[ref.layer_id].color.numpy())
    assert (folder / top["generator"]["checkpoint"]).is_file()
    bad = client.post(
        "/api/change",
        headers=H,
        json={"op": "learned", "version": state(client)["version"], "preset": "shading", "condition": "sideways"},
    )
    assert "sideways" in refused(bad, 400)


def run_job(client, **body) -> dict:
    body.setdefault("version", state(client)["version"])
    r = client.post("/api/jobs", headers=H, json=body)
    assert r.status_code == 200, r.text
    job = r.json()
    events = []
    with client.stream("GET", f"/api/jobs/{job['id']}/events", headers=H) as stream:
        for line in stream.iter_lines():
            if line.startswith("data: "):
                events.append(json.loads(line[6:]))
    return {"job": job, "events": events}


def test_a_per_image_layer_renders_as_a_job_with_progress(client, folder):
    s = change(client, op="learned", preset="light", condition="warm", method="per-image")
    layer = s["document"]["layers"][-1]
    assert s["not_rendered"] == {layer["id"]: "not rendered (run `lasagna render`)"}
    out = run_job(client, kind="rerender", id=layer["id"])
    assert out["events"][-1]["state"] == "done", out["events"][-1]["error"]
    assert [e["step"] for e in out["events"]] == sorted(e["step"] for e in out["events"])
    s = state(client)
    assert s["not_rendered"] == {} and s["undo"] == f"rerender {layer['id']}"
    change(client, op="save")
    validate(folder)
    assert np.array_equal(view(client, level=0)[..., :3], engine_codes(folder))


def test_refine_runs_steps_and_undo_takes_it_back(client):
    s = change(client, op="learned", preset="shading", condition="left")
    id = s["document"]["layers"][-1]["id"]
    before = view(client, level=0)
    out = run_job(client, kind="refine", id=id, steps=3)
    assert out["events"][-1]["state"] == "done" and out["events"][-1]["steps"] == 3, out["events"][-1]["error"]
    settings = next(x for x in state(client)["document"]["layers"] if x["id"] == id)["settings"]
    assert settings["optimize"] == 3
    change(client, op="undo")
    assert np.array_equal(view(client, level=0), before)


def test_a_cancelled_job_changes_nothing(client, session, monkeypatch):
    s = change(client, op="learned", preset="shading", condition="left")
    id = s["document"]["layers"][-1]["id"]
    v = state(client)["version"]
    r = client.post("/api/jobs", headers=H, json={"version": v, "kind": "refine", "id": id, "steps": 10_000})
    job = r.json()
    busy = client.post("/api/change", headers=H, json={"op": "undo", "version": v})
    assert "job is running" in refused(busy, 409)
    assert client.post(f"/api/jobs/{job['id']}/cancel", headers=H, json={}).status_code == 200
    deadline = time.monotonic() + HANG_SECONDS
    while session.jobs[job["id"]].state == "running" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert session.jobs[job["id"]].state == "cancelled"
    assert state(client)["version"] == v


@pytest.mark.parametrize(
    "body, status, words",
    [
        ({"kind": "refine", "id": "glow", "steps": 3}, 400, "expected a learned layer"),
        ({"kind": "explode", "id": "glow"}, 400, "job"),
        ({"kind": "refine", "id": "nope", "steps": 3}, 400, "no layer"),
    ],
)
def test_bad_jobs_are_refused(client, body, status, words):
    r = client.post("/api/jobs", headers=H, json={"version": state(client)["version"], **body})
    assert words in refused(r, status)
    refused(client.get("/api/jobs/nope/events", headers=H), 404)
    refused(client.post("/api/jobs/nope/cancel", headers=H, json={}), 400)


# ---- saving ---------------------------------------------------------------------------------------------


def test_a_save_rewrites_only_what_changed(client, folder):
    stamps = {p.name: p.stat().st_mtime_ns for p in (folder / "layers").iterdir()}
    time.sleep(0.01)
    change(client, op="set", id="glow", changes={"opacity": 0.3})
    change(client, op="save")
    assert {p.name: p.stat().st_mtime_ns for p in (folder / "layers").iterdir()} == stamps
    assert not state(client)["dirty"]


def test_a_save_over_a_stack_changed_on_disk_is_409_and_reload_shows_it(client, folder):
    change(client, op="set", id="glow", changes={"opacity": 0.3})
    doc = json.loads((folder / "stack.json").read_text())
    doc["layers"][0]["name"] = "Changed by someone else"
    (folder / "stack.json").write_text(json.dumps(doc))
    r = client.post("/api/change", headers=H, json={"op": "save", "version": state(client)["version"]})
    assert "changed on disk" in refused(r, 409)
    assert json.loads((folder / "stack.json").read_text())["layers"][0]["name"] == "Changed by someone else"
    s = client.post("/api/reload", headers=H, json={}).json()
    assert s["document"]["layers"][0]["name"] == "Changed by someone else" and not s["dirty"]


def test_changed_pixels_are_written_under_new_names_and_the_old_files_removed(client, folder):
    s = change(client, op="learned", preset="shading", condition="left")
    id = s["document"]["layers"][-1]["id"]
    change(client, op="save")
    first = next(x for x in state(client)["document"]["layers"] if x["id"] == id)["source"]
    run_job(client, kind="refine", id=id, steps=2)
    change(client, op="save")
    second = next(x for x in state(client)["document"]["layers"] if x["id"] == id)["source"]
    assert second != first and (folder / second).is_file() and not (folder / first).exists()
    validate(folder)


KILL_SCRIPT = """
import sys
from lasagna.serve.session import EditSession
s = EditSession(sys.argv[1])
print("ready", flush=True)
v = s.state()["version"]
for i in range(1000):
    s.set_layer(v, "glow", {"opacity": (i % 10) / 10})
    v += 1
    s.add_solid(v, [i % 2, 0.5, 0.25], name=f"s{i}")
    v += 1
    s.save(v)
"""


@pytest.mark.parametrize("delay", [0.05, 0.2, 0.45, 0.8])
def test_killing_the_server_mid_save_leaves_a_whole_stack(folder, delay):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen([sys.executable, "-c", KILL_SCRIPT, str(folder)], stdout=subprocess.PIPE, env=env)
    assert p.stdout.readline().strip() == b"ready"
    time.sleep(delay)
    p.kill()
    p.wait()
    validate(folder)
    stack = load_stack(folder)  # every file the document names is there and whole
    render_stack(stack)


# ---- exports ----------------------------------------------------------------------------------------------


def test_exports_are_downloads_of_the_current_stack(client, folder):
    change(client, op="set", id="glow", changes={"opacity": 0.6})
    change(client, op="save")
    ref = engine_codes(folder)
    png = client.get("/api/export/png", headers=H)
    assert png.headers["content-disposition"] == 'attachment; filename="basic.png"'
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png.content)).convert("RGB")), ref)
    ora = client.get("/api/export/ora", headers=H)
    with zipfile.ZipFile(io.BytesIO(ora.content)) as z:
        assert z.read("mimetype") == b"image/openraster"
        merged = np.asarray(Image.open(io.BytesIO(z.read("mergedimage.png"))).convert("RGB"))
    assert np.abs(merged.astype(int) - ref).max() <= 1
    psd_tools = pytest.importorskip("psd_tools")
    psd = psd_tools.PSDImage.open(io.BytesIO(client.get("/api/export/psd", headers=H).content))
    assert (psd.width, psd.height) == (64, 48) and len(list(psd)) >= 4


# ---- opening what the user names ----------------------------------------------------------------------


def test_an_image_gets_a_stack_folder_beside_it_and_is_reopened(tmp_path):
    img = tmp_path / "photo.png"
    Image.new("RGB", (8, 6), (10, 20, 30)).save(img)
    folder, made = open_target(img)
    assert made and folder == tmp_path / f"photo{STACK_SUFFIX}" and (folder / "stack.json").is_file()
    assert open_target(img) == (folder, False)
    assert open_target(folder / "stack.json") == (folder, False)


def test_a_layered_file_is_imported_into_a_stack_folder_beside_it(tmp_path, capsys):
    """``lasagna serve painting.ora`` (or ``.psd``): the file's layers imported into ``painting.stack/`` as
    ``import-ora`` / ``import-psd`` make them — a surface layer one layer again, lit as it was — and reopened after."""
    import torch

    from lasagna.cli import main
    from lasagna.compose.surface import normals_from_height
    from lasagna.io.stack import Stack

    yy, xx = torch.meshgrid(torch.linspace(-1, 1, 24), torch.linspace(-1, 1, 32), indexing="ij")
    stack = Stack.from_image(torch.full((3, 24, 32), 0.6))
    stack.add_surface("shape", normals_from_height((0.5 * torch.exp(-3 * (xx**2 + yy**2)))[None, None])[0], "left")
    stack.set_light("shape", "x=0.3,y=0.4,z=0.5", shadows=0.5)
    stack.save(tmp_path / "s")
    for fmt in ("ora", "psd"):
        assert main(["export", str(tmp_path / "s"), f"--{fmt}", str(tmp_path / f"painting.{fmt}")]) == 0
        folder, made = open_target(tmp_path / f"painting.{fmt}", warn=pytest.fail)
        assert made and folder == tmp_path / f"painting{STACK_SUFFIX}"
        opened = load_stack(folder)
        surface = next(layer for layer in opened.document.layers if layer.kind == "surface")
        assert (surface.light, surface.shadows) == ("x=0.3,y=0.4,z=0.5", 0.5)
        assert float((opened.render().image - stack.render().image).abs().max()) <= 3.5 / 255
        assert open_target(tmp_path / f"painting.{fmt}") == (folder, False)
        shutil.rmtree(folder)


@pytest.mark.parametrize(("name", "words"), [("bad.ora", "not a zip archive"), ("bad.psd", "does not start with 8BPS")])
def test_a_layered_file_that_is_not_one_is_refused_before_the_editor_starts(tmp_path, name, words):
    from lasagna.errors import LasagnaError
    from lasagna.serve import survey_target

    (tmp_path / name).write_bytes(b"PK but not really")
    with pytest.raises(LasagnaError, match=words):
        survey_target(tmp_path / name)
    assert not (tmp_path / f"bad{STACK_SUFFIX}").exists()


def test_bad_targets_are_one_line(tmp_path):
    from lasagna.errors import LasagnaError

    with pytest.raises(LasagnaError, match="does not exist"):
        open_target(tmp_path / "nope.png")
    (tmp_path / "empty").mkdir()
    with pytest.raises(LasagnaError, match="no stack.json"):
        open_target(tmp_path / "empty")


def cli(*args, timeout=HANG_SECONDS):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "lasagna.cli", *args], capture_output=True, text=True, timeout=timeout, env=env
    )


@pytest.mark.parametrize(
    "args, words", [(["serve", "/nonexistent/x.png"], "does not exist"), (["serve", ".", "--port", "70000"], "port")]
)
def test_serve_cli_errors_are_one_line_exit_2(args, words, tmp_path):
    r = cli(*args)
    assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_serve_prints_a_tokened_url_serves_it_and_stops_on_ctrl_c(folder):
    import signal
    import urllib.request

    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    p = subprocess.Popen(
        [sys.executable, "-m", "lasagna.cli", "serve", str(folder), "--no-browser"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        url = None
        deadline = time.monotonic() + HANG_SECONDS
        while url is None and time.monotonic() < deadline:
            line = p.stdout.readline()
            if "?token=" in line:
                url = line.strip()
        assert url and url.startswith("http://127.0.0.1:")
        while True:  # the URL is printed just before uvicorn binds
            try:
                with urllib.request.urlopen(url.replace("/?", "/api/state?"), timeout=HANG_SECONDS) as r:
                    assert json.load(r)["folder"] == "basic"
                break
            except OSError:
                assert time.monotonic() < deadline, "the server never answered"
                time.sleep(0.1)
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(url.split("?")[0] + "api/state", timeout=HANG_SECONDS)
        assert err.value.code == 403
    finally:
        p.send_signal(signal.SIGINT)
        rc = p.wait(timeout=HANG_SECONDS)
    assert rc == 0
    assert "Traceback" not in p.stderr.read()
