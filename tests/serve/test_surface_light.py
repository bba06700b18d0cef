"""A surface layer's light in the editor (#24 item 5): the ``light`` change, the light-drag preview of
``/api/view`` and the normal-map view, against the engine: ``Stack.set_light`` on a freshly loaded stack, rendered
by ``render_stack`` (the CLI's composite), bit for bit; undo; one-line refusals."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

pytest.importorskip("starlette")
pytest.importorskip("httpx")

from starlette.testclient import TestClient  # noqa: E402

from lasagna.compose.surface import encode_normal_map  # noqa: E402
from lasagna.document.condition import NAMED_DIRECTIONS  # noqa: E402
from lasagna.io.render import composite_codes, render_stack  # noqa: E402
from lasagna.io.stack import load_stack  # noqa: E402
from lasagna.serve.app import create_app  # noqa: E402
from lasagna.serve.session import EditSession  # noqa: E402
from tests.serve.surface_stack import dome_normals, surface_stack  # noqa: E402

TOKEN = "test-token"
H = {"X-Lasagna-Token": TOKEN}


@pytest.fixture
def folder(tmp_path):
    return surface_stack(tmp_path / "lit")


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


def post(client, **body):
    body.setdefault("version", state(client)["version"])
    return client.post("/api/change", headers=H, json=body)


def ok(response) -> dict:
    assert response.status_code == 200, response.text
    return response.json()


def one_line_4xx(response) -> str:
    assert 400 <= response.status_code < 500, (response.status_code, response.text)
    message = response.json()["error"]
    assert "\n" not in message and "Traceback" not in message and "internal error" not in message
    return message


def pixels(response) -> np.ndarray:
    assert response.status_code == 200, response.text
    w, h = int(response.headers["x-width"]), int(response.headers["x-height"])
    return np.frombuffer(response.content, np.uint8).reshape(h, w, 4)


def view(client, **params) -> np.ndarray:
    return pixels(client.get("/api/view", headers=H, params=params))


def relit_codes(folder, light: str, **fields) -> np.ndarray:
    """The composite of the folder's stack, freshly loaded and re-lit by the engine: (H, W, 3) uint8."""
    stack = load_stack(folder).set_light("shape", light, **fields)
    return composite_codes(render_stack(stack).image).permute(1, 2, 0).numpy()


# ---- state ---------------------------------------------------------------------------------------


def test_state_gives_each_surface_layers_light(client):
    s = state(client)["surfaces"]
    az, el = NAMED_DIRECTIONS["top-left"]
    assert s == {
        "shape": {
            "light": "top-left",
            "az": az,
            "el": el,
            "point": None,
            "spot": None,
            "rect": [8, 8, 40, 32],  # the layer's offset and size on the canvas: where a point light's fractions lie
            "source_light": None,
            "source": None,
            "rereadable": False,  # plain shading, and a map of one's own: nothing to read again
            "ambient": 0.25,
            "relief": 1.0,
            "light_color": [1.0, 1.0, 1.0],
            "light_intensity": 1.0,
            "extra_lights": [],
            "gloss": 0.0,
            "shininess": 32.0,
            "shadows": 0.0,
            "occlusion": 0.0,
            "shadow_depth": 1.0,
        }
    }


# ---- the change ----------------------------------------------------------------------------------


@pytest.mark.parametrize("light", ["az=20,el=35", "bottom-right", "el=80,az=-90"])
def test_a_new_light_renders_as_a_fresh_stack_relit_by_the_engine(client, folder, light):
    before = view(client, level=0)
    after = ok(post(client, op="light", id="shape", light=light))
    assert after["document"]["layers"][1]["light"] == light and after["undo"] == "light of shape"
    got = view(client, level=0)
    assert not np.array_equal(got, before)
    assert np.array_equal(got[..., :3], relit_codes(folder, light))
    ok(post(client, op="save"))
    assert json.loads((folder / "stack.json").read_text())["layers"][1]["light"] == light
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(got[..., :3], fresh)


def test_undo_restores_the_light_and_the_pixels_redo_again(client):
    before, lit_before = view(client, level=0), state(client)["surfaces"]["shape"]
    ok(post(client, op="light", id="shape", light="az=300,el=60"))
    after = view(client, level=0)
    undone = ok(post(client, op="undo"))
    assert undone["surfaces"]["shape"] == lit_before and undone["redo"] == "light of shape"
    assert np.array_equal(view(client, level=0), before)
    ok(post(client, op="redo"))
    assert np.array_equal(view(client, level=0), after)


def test_source_light_and_ambient_absent_kept_null_removed(client, folder):
    s = ok(post(client, op="light", id="shape", light="right", source_light="left", ambient=0.4, relief=2.5))
    el = NAMED_DIRECTIONS["right"][1]
    assert s["surfaces"]["shape"] == {
        "light": "right",
        "az": 0.0,
        "el": el,
        "point": None,
        "spot": None,
        "rect": [8, 8, 40, 32],
        "source_light": "left",
        "source": [180.0, el],
        "rereadable": False,  # a relight, but a map of one's own: no preset to read it again
        "ambient": 0.4,
        "relief": 2.5,
        "light_color": [1.0, 1.0, 1.0],
        "light_intensity": 1.0,
        "extra_lights": [],
        "gloss": 0.0,
        "shininess": 32.0,
        "shadows": 0.0,
        "occlusion": 0.0,
        "shadow_depth": 1.0,
    }
    assert np.array_equal(
        view(client, level=0)[..., :3], relit_codes(folder, "right", source_light="left", ambient=0.4, relief=2.5)
    )
    s = ok(post(client, op="light", id="shape", light="top"))
    assert s["surfaces"]["shape"]["source_light"] == "left" and s["surfaces"]["shape"]["ambient"] == 0.4
    assert s["surfaces"]["shape"]["relief"] == 2.5
    s = ok(post(client, op="light", id="shape", light="top", source_light=None))
    assert s["surfaces"]["shape"]["source_light"] is None and s["surfaces"]["shape"]["ambient"] == 0.4


# ---- the light-drag preview ------------------------------------------------------------------------


@pytest.mark.parametrize("level", [0, 1, 2])
def test_a_preview_is_the_view_the_change_gives_and_changes_nothing(client, level):
    v = state(client)["version"]
    previews = [view(client, level=level, light=f"shape:az={az},el=50") for az in (0, 180, 0)]
    assert not np.array_equal(previews[0], previews[1]) and np.array_equal(previews[0], previews[2])
    s = state(client)
    assert s["version"] == v and s["undo"] is None and s["surfaces"]["shape"]["light"] == "top-left"
    ok(post(client, op="light", id="shape", light="az=180,el=50"))
    assert np.array_equal(view(client, level=level), previews[1])


def test_a_source_light_preview_is_the_view_its_change_gives(client, folder):
    """A relight surface layer's source light dragged (``/api/view?source=LAYER:LIGHT``): a preview that changes
    nothing, and, released (``op: light`` with ``source_light``), exactly the engine's re-lit stack."""
    ok(post(client, op="light", id="shape", light="right", source_light="left"))
    v = state(client)["version"]
    previews = [view(client, level=0, source=f"shape:az={az},el=30") for az in (0, 180, 0)]
    assert not np.array_equal(previews[0], previews[1]) and np.array_equal(previews[0], previews[2])
    s = state(client)
    assert s["version"] == v and s["surfaces"]["shape"]["source_light"] == "left"
    ok(post(client, op="light", id="shape", light="right", source_light="az=180,el=30"))
    assert np.array_equal(view(client, level=0), previews[1])
    assert np.array_equal(view(client, level=0)[..., :3], relit_codes(folder, "right", source_light="az=180,el=30"))
    # Both lights previewed at once: the target's and the source's overrides together.
    both = view(client, level=0, light="shape:left", source="shape:right")
    ok(post(client, op="light", id="shape", light="left", source_light="right"))
    assert np.array_equal(view(client, level=0), both)


def surface_stack_folder(session):
    """A copy of the session's stack folder: an unrelated stack of the same kind."""
    import shutil

    copy = session.folder.parent / "other"
    shutil.copytree(session.folder, copy)
    return copy


def test_re_lit_normals_are_kept_and_accounted(session):
    held = session.held_bytes()
    session.view(0, light={"shape": "left"})
    session.view(0, light={"shape": "right"})  # a second light: the map's decoded normals are kept
    sw, sh = 64 * 5 // 8, 48 * 2 // 3
    assert session.held_bytes() - held >= 3 * sw * sh * 4
    held = session.held_bytes()
    session.view(0, light={"shape": "az=200,el=80"}, shadows={"shape": 1.0})  # the map's heights are kept too
    assert session.held_bytes() > held
    # Another stack's surface in the same process, re-lit and casting shadows, is not this session's to count.
    held = session.held_bytes()
    other = load_stack(surface_stack_folder(session))
    for light in ("left", "right"):
        other.set_light("shape", light, shadows=0.5)
        render_stack(other)
    assert session.held_bytes() == held


# ---- the normal map --------------------------------------------------------------------------------


def test_the_normal_map_view_is_the_stored_map_at_its_place(client, folder):
    got = pixels(client.get("/api/layers/shape/normals", headers=H, params={"level": 0}))
    stored = load_stack(folder).tensors["shape"].color  # (3, 32, 40) as its 16-bit PNG gives it back
    codes = (stored.double() * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    assert got.shape == (48, 64, 4)
    assert np.array_equal(got[8:40, 8:48, :3], codes) and (got[8:40, 8:48, 3] == 255).all()
    assert (got[:8, :, 3] == 0).all() and (got[:, 48:, 3] == 0).all()
    exact = (encode_normal_map(dome_normals(40, 32)[None])[0] * 255).permute(1, 2, 0).numpy()
    assert np.abs(got[8:40, 8:48, :3] - exact).max() <= 0.5 + 1e-6  # the map itself, not a lit image
    small = pixels(client.get("/api/layers/shape/normals", headers=H, params={"level": 1}))
    assert small.shape == (24, 32, 4) and (small[4:20, 4:24, 3] == 255).all()


def test_the_occlusion_view_is_the_share_of_the_sky_at_its_place(client, folder):
    """``/api/layers/ID/occlusion`` (the page's "Show occlusion"): grey codes of the share of a cosine-weighted sky
    the layer's heights let each pixel see — a numpy float64 mean of ray marches over the heights integrated from the
    saved map (tests/support/lights.py), within 0.05 in the mean — where the layer lies; transparent elsewhere;
    darker at the dome's foot than on its top; a deeper ``shadow_depth`` darkens it."""
    from lasagna.compose.surface import integrate_normals, surface_normals
    from tests.support.lights import sky_share

    got = pixels(client.get("/api/layers/shape/occlusion", headers=H, params={"level": 0}))
    assert got.shape == (48, 64, 4) and (got[8:40, 8:48, 3] == 255).all() and (got[:8, :, 3] == 0).all()
    grey = got[8:40, 8:48, :3].astype(float) / 255
    assert (grey[..., 0] == grey[..., 1]).all() and (grey[..., 1] == grey[..., 2]).all()
    stored = load_stack(folder).tensors["shape"].color.double()[None] * 2 - 1
    heights = integrate_normals(surface_normals(stored))[0, 0].numpy()
    assert np.abs(grey[..., 0] - sky_share(heights))[2:-2, 2:-2].mean() <= 0.05
    assert grey[16, 20, 0] > grey[31, 20, 0]  # the dome's top sees more sky than its rim near the layer's edge
    ok(post(client, op="light", id="shape", light="top-left", shadow_depth=4.0))
    deeper = pixels(client.get("/api/layers/shape/occlusion", headers=H, params={"level": 0}))
    assert (deeper[8:40, 8:48, 0] <= got[8:40, 8:48, 0]).all() and (deeper[8:40, 8:48, 0] < got[8:40, 8:48, 0]).any()


# ---- refusals ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "body, field, words",
    [
        ({"id": "base", "light": "left"}, "set_light: layer 'base'", "expected a surface layer"),
        ({"id": "tint", "light": "left"}, "set_light: layer 'tint'", "expected a surface layer"),
        ({"id": "nope", "light": "left"}, "", "nope"),
        ({"id": "shape", "light": "sideways"}, "light", "'az=A,el=E'"),
        ({"id": "shape", "light": "az=10"}, "light", "'az=A,el=E'"),
        ({"id": "shape", "light": "az=10,el=95"}, "light", "outside [0, 90)"),
        ({"id": "shape", "light": "az=nan,el=10"}, "light", "'az=A,el=E'"),
        ({"id": "shape", "light": 45}, "light", "45"),
        ({"id": "shape", "light": ["left"]}, "light", "expected"),
        ({"id": "shape"}, "light", "missing"),
        ({"id": "shape", "light": "left", "source_light": "up"}, "source_light", "'up'"),
        ({"id": "shape", "light": "left", "ambient": 1.0}, "ambient", "less than 1"),
        ({"id": "shape", "light": "left", "ambient": "0.5"}, "ambient", "'0.5'"),
        ({"id": "shape", "light": "left", "ambient": True}, "ambient", "True"),
        ({"id": "shape", "light": "left", "source_light": "top", "ambient": 0}, "layers[1].ambient", "ambient > 0"),
        ({"id": "shape", "light": "left", "az": 10}, "az", "unknown field"),
        ({"id": "shape", "light": "x=0.5,y=0.5,z=0"}, "light", "point light 'x=X,y=Y,z=Z'"),
        ({"id": "shape", "light": "left", "source_light": "x=0.5,y=0.5,z=1"}, "source_light", "'az=A,el=E'"),
    ],
)
def test_a_bad_light_change_is_a_one_line_4xx_and_changes_nothing(client, body, field, words):
    before = state(client)
    message = one_line_4xx(post(client, op="light", **body))
    assert message.startswith(field) and words in message, message
    after = state(client)
    assert after["version"] == before["version"] and after["surfaces"] == before["surfaces"]


@pytest.mark.parametrize(
    "params, words",
    [
        ({"light": "base:left"}, "expected a surface layer"),
        ({"light": "shape:up"}, "'az=A,el=E'"),
        ({"light": "shape:x=0.5,y=0.5,z=-2"}, "point light 'x=X,y=Y,z=Z'"),
        ({"source": "shape:x=0.5,y=0.5,z=1"}, "has no source light"),
        ({"light": "shape"}, "expected LAYER:LIGHT"),
        ({"light": "nope:left"}, "nope"),
        ({"source": "shape:left"}, "has no source light; expected a relight surface layer"),
        ({"source": "base:left"}, "has no source light"),
        ({"source": "shape"}, "expected LAYER:LIGHT"),
        ({"source": "nope:left"}, "nope"),
    ],
)
def test_a_bad_preview_is_a_one_line_400(client, params, words):
    assert words in one_line_4xx(client.get("/api/view", headers=H, params={"level": 0, **params}))


@pytest.mark.parametrize(
    "id, params, words",
    [("base", {}, "expected a surface layer"), ("nope", {}, "nope"), ("shape", {"level": 99}, "level")],
)
@pytest.mark.parametrize("view", ["normals", "occlusion"])
def test_a_bad_normal_map_request_is_a_one_line_4xx(client, id, params, words, view):
    assert words in one_line_4xx(client.get(f"/api/layers/{id}/{view}", headers=H, params=params))


# ---- the relief ----------------------------------------------------------------------------------


def test_the_relief_preview_is_the_change_bit_for_bit_and_one_undo_step(client, folder):
    """``/api/view?relief=LAYER:G`` (the slider while dragged) shows, bit for bit, what the change ``op: light``
    with ``relief`` G then gives, and what the engine renders of the saved stack; the map's slopes times G make
    the shading stronger (the lit side brighter, the far side darker than at relief 1)."""
    before = view(client, level=0)
    preview = view(client, level=0, relief="shape:3")
    assert not np.array_equal(preview, before)
    assert np.array_equal(view(client, level=0), before)  # a preview changes nothing on the server
    s = ok(post(client, op="light", id="shape", light="top-left", relief=3.0))
    assert s["surfaces"]["shape"]["relief"] == 3.0 and s["undo"] == "light of shape"
    assert np.array_equal(view(client, level=0), preview)
    assert np.array_equal(preview[..., :3], relit_codes(folder, "top-left", relief=3.0))
    flat, deep = before[..., :3].astype(float), preview[..., :3].astype(float)
    assert deep.std() > flat.std()  # deeper relief: more shading contrast
    ok(post(client, op="save"))
    assert json.loads((folder / "stack.json").read_text())["layers"][1]["relief"] == 3.0
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(preview[..., :3], fresh)
    ok(post(client, op="undo"))
    assert np.array_equal(view(client, level=0), before)


@pytest.mark.parametrize(
    "name, param, match",
    [
        ("relief", "shape:0", r"relief.shape: expected a relief gain in \(0, 16\]"),
        ("relief", "shape:17", "relief.shape: expected a relief gain"),
        ("relief", "shape:nan", "relief.shape: expected a relief gain"),
        ("relief", "shape:deep", "relief: relief is 'shape:deep'; expected LAYER:NUMBER"),
        ("relief", "nope:2", "no layer with id 'nope'"),
        ("ambient", "shape:1", r"ambient.shape: expected an ambient term in \[0, 1\)"),
        ("ambient", "shape:-0.1", "ambient.shape: expected an ambient term"),
        ("ambient", "shape:inf", "ambient.shape: expected an ambient term"),
        ("ambient", "shape:dim", "ambient: ambient is 'shape:dim'; expected LAYER:NUMBER"),
        ("color", "shape:#ffcc8", r"color: color is 'shape:#ffcc8'; expected LAYER:#rrggbb"),
        ("color", "shape:ffcc88", "expected LAYER:#rrggbb"),
        ("color", "shape:#ggcc88", "expected LAYER:#rrggbb"),
        ("color", "base:#ffcc88", "layer 'base' is a pixels layer; expected a surface layer"),
        ("intensity", "shape:0", r"intensity.shape: expected a light intensity in \(0, 8\]"),
        ("intensity", "shape:9", "intensity.shape: expected a light intensity"),
        ("intensity", "shape:nan", "intensity.shape: expected a light intensity"),
        ("intensity", "shape:bright", "intensity: intensity is 'shape:bright'; expected LAYER:NUMBER"),
        ("intensity", "base:2", "layer 'base' is a pixels layer; expected a surface layer"),
        ("gloss", "shape:1.5", r"gloss.shape: expected a gloss in \[0, 1\]"),
        ("gloss", "shape:nan", "gloss.shape: expected a gloss"),
        ("gloss", "shape:shiny", "gloss: gloss is 'shape:shiny'; expected LAYER:NUMBER"),
        ("gloss", "base:0.5", "layer 'base' is a pixels layer; expected a surface layer"),
        ("shadows", "shape:1.5", r"shadows.shape: expected a shadows strength in \[0, 1\]"),
        ("shadows", "shape:inf", "shadows.shape: expected a shadows strength"),
        ("shadows", "shape:deep", "shadows: shadows is 'shape:deep'; expected LAYER:NUMBER"),
        ("shadows", "base:0.5", "layer 'base' is a pixels layer; expected a surface layer"),
        ("occlusion", "shape:-1", r"occlusion.shape: expected an occlusion strength in \[0, 1\]"),
        ("occlusion", "base:0.5", "layer 'base' is a pixels layer; expected a surface layer"),
        ("shadow_depth", "shape:0", r"shadow_depth.shape: expected a shadow depth in \(0, 16\]"),
        ("shadow_depth", "base:2", "layer 'base' is a pixels layer; expected a surface layer"),
    ],
)
def test_a_bad_slider_preview_is_one_line_400(client, name, param, match):
    response = client.get("/api/view", headers=H, params={"level": 0, name: param})
    assert response.status_code == 400
    error = response.json()["error"]
    assert "\n" not in error and re.search(match, error), error


@pytest.mark.parametrize("relief", [0, -1, 17, "2"])
def test_a_bad_relief_change_is_refused_and_changes_nothing(client, relief):
    before = state(client)
    response = post(client, op="light", id="shape", light="left", relief=relief)
    assert response.status_code == 400 and "relief" in response.json()["error"]
    assert state(client)["version"] == before["version"]


# ---- the ambient term ----------------------------------------------------------------------------


def test_the_ambient_preview_is_the_change_bit_for_bit(client, folder):
    """``/api/view?ambient=LAYER:A`` (the Ambient slider while dragged) shows, bit for bit, what ``op: light`` with
    ``ambient`` A gives and what the engine renders of the saved stack; a higher ambient darkens less (the
    composite's mean rises)."""
    before = view(client, level=0)
    preview = view(client, level=0, ambient="shape:0.6")
    assert np.array_equal(view(client, level=0), before)  # nothing changed on the server
    assert preview[..., :3].astype(float).mean() > before[..., :3].astype(float).mean()
    s = ok(post(client, op="light", id="shape", light="top-left", ambient=0.6))
    assert s["surfaces"]["shape"]["ambient"] == 0.6
    assert np.array_equal(view(client, level=0), preview)
    assert np.array_equal(preview[..., :3], relit_codes(folder, "top-left", ambient=0.6))
    ok(post(client, op="save"))
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(preview[..., :3], fresh)


def test_a_relight_ratios_ambient_preview_must_stay_above_zero(client, session):
    ok(post(client, op="light", id="shape", light="right", source_light="left"))
    response = client.get("/api/view", headers=H, params={"level": 0, "ambient": "shape:0"})
    assert response.status_code == 400
    assert "ambient.shape: expected an ambient term in (0, 1) (a relight ratio)" in response.json()["error"]


def test_the_light_colour_preview_is_the_change_bit_for_bit(client, folder):
    """``/api/view?color=LAYER:#rrggbb`` (the colour input while moved) shows, bit for bit, what ``op: light`` with
    ``light_color`` (the same bytes / 255) gives and what the engine renders of the saved stack; a warm light leaves
    the red channel and darkens blue where the light falls."""
    before = view(client, level=0)
    preview = view(client, level=0, color="shape:#ffcc88")
    assert np.array_equal(view(client, level=0), before)
    colour = [1.0, 0xCC / 255, 0x88 / 255]
    s = ok(post(client, op="light", id="shape", light="top-left", light_color=colour))
    assert s["surfaces"]["shape"]["light_color"] == colour
    assert np.array_equal(view(client, level=0), preview)
    assert np.array_equal(preview[..., :3], relit_codes(folder, "top-left", light_color=tuple(colour)))
    assert np.array_equal(preview[..., 0], before[..., 0]) and (preview[..., 2] <= before[..., 2]).all()
    assert (preview[..., 2] < before[..., 2]).any()
    ok(post(client, op="save"))
    assert json.loads((folder / "stack.json").read_text())["layers"][1]["light_color"] == colour
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(preview[..., :3], fresh)


# ---- a point light ----------------------------------------------------------------------------------


def test_a_point_light_previews_commits_and_saves_bit_for_bit(client, folder):
    """A point light ``x=…,y=…,z=…`` (the editor places it on the canvas): its preview is the view its change
    gives, the state says where it is (``point``, and the direction from the layer's centre the sphere shows), and
    the saved stack renders the same bits through the engine."""
    v = state(client)["version"]
    previews = [view(client, level=lv, light="shape:x=0.1,y=0.2,z=0.3") for lv in (0, 1)]
    assert state(client)["version"] == v
    s = ok(post(client, op="light", id="shape", light="x=0.1,y=0.2,z=0.3"))
    lit = s["surfaces"]["shape"]
    assert lit["point"] == [0.1, 0.2, 0.3] and lit["light"] == "x=0.1,y=0.2,z=0.3"
    assert 90 < lit["az"] < 180 and 0 < lit["el"] < 90  # up and to the left of the layer's centre
    assert np.array_equal(view(client, level=0), previews[0]) and np.array_equal(view(client, level=1), previews[1])
    assert np.array_equal(previews[0][..., :3], relit_codes(folder, "x=0.1,y=0.2,z=0.3"))
    ok(post(client, op="save"))
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(previews[0][..., :3], fresh)


def test_a_spot_light_previews_commits_and_saves_bit_for_bit(client, folder):
    """A spot light (a point with ``cone``): its preview is the view its change gives, the state gives the point and
    the spot's cone, aim and softness (a point light's ``spot`` is None), and the saved stack renders the same bits;
    a spot lights less of the layer than the same point light does."""
    text = "x=0.3,y=0.4,z=0.3,cone=20,ax=0.6,ay=0.5,blend=0.25"
    preview = view(client, level=0, light=f"shape:{text}")
    s = ok(post(client, op="light", id="shape", light=text))
    lit = s["surfaces"]["shape"]
    assert lit["point"] == [0.3, 0.4, 0.3] and lit["spot"] == {"cone": 20.0, "aim": [0.6, 0.5], "blend": 0.25}
    assert np.array_equal(view(client, level=0), preview)
    assert np.array_equal(preview[..., :3], relit_codes(folder, text))
    point = relit_codes(folder, "x=0.3,y=0.4,z=0.3").astype(int)
    assert (preview[..., :3].astype(int) <= point + 1).all() and (preview[..., :3].astype(int) < point).any()
    ok(post(client, op="save"))
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(preview[..., :3], fresh)
    assert ok(post(client, op="light", id="shape", light="x=0.3,y=0.4,z=0.3"))["surfaces"]["shape"]["spot"] is None


def test_the_intensity_preview_is_the_change_bit_for_bit(client, folder):
    """``/api/view?intensity=LAYER:K`` (the Intensity slider while dragged) shows, bit for bit, what ``op: light``
    with ``light_intensity`` K gives and what the engine renders of the saved stack; a stronger light brightens (the
    composite's mean rises); a bad intensity change is refused in one line and changes nothing."""
    before = view(client, level=0)
    preview = view(client, level=0, intensity="shape:2.5")
    assert np.array_equal(view(client, level=0), before)
    assert preview[..., :3].astype(float).mean() > before[..., :3].astype(float).mean()
    s = ok(post(client, op="light", id="shape", light="top-left", light_intensity=2.5))
    assert s["surfaces"]["shape"]["light_intensity"] == 2.5
    assert np.array_equal(view(client, level=0), preview)
    assert np.array_equal(preview[..., :3], relit_codes(folder, "top-left", light_intensity=2.5))
    ok(post(client, op="save"))
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(preview[..., :3], fresh)
    v = state(client)["version"]
    message = one_line_4xx(post(client, op="light", id="shape", light="top-left", light_intensity=0))
    assert message.startswith("light_intensity") and state(client)["version"] == v


def test_the_gloss_preview_is_the_change_bit_for_bit(client, folder):
    """``/api/view?gloss=LAYER:G`` (the Gloss slider while dragged) shows, bit for bit, what ``op: light`` with
    ``gloss`` G gives and what the engine renders of the saved stack; a highlight brightens (the composite's mean
    rises); ``shininess`` is set the same way; bad values are refused in one line and change nothing."""
    before = view(client, level=0)
    preview = view(client, level=0, gloss="shape:0.8")
    assert np.array_equal(view(client, level=0), before)
    assert preview[..., :3].astype(float).mean() > before[..., :3].astype(float).mean()
    s = ok(post(client, op="light", id="shape", light="top-left", gloss=0.8))
    assert s["surfaces"]["shape"]["gloss"] == 0.8 and s["surfaces"]["shape"]["shininess"] == 32.0
    assert np.array_equal(view(client, level=0), preview)
    assert np.array_equal(preview[..., :3], relit_codes(folder, "top-left", gloss=0.8))
    s = ok(post(client, op="light", id="shape", light="top-left", shininess=4.0))
    assert s["surfaces"]["shape"]["gloss"] == 0.8 and s["surfaces"]["shape"]["shininess"] == 4.0
    broad = view(client, level=0)
    assert np.array_equal(broad[..., :3], relit_codes(folder, "top-left", gloss=0.8, shininess=4.0))
    ok(post(client, op="save"))
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(broad[..., :3], fresh)
    v = state(client)["version"]
    for body in ({"gloss": 2}, {"gloss": -0.5}, {"shininess": 0}, {"shininess": 2000}):
        message = one_line_4xx(post(client, op="light", id="shape", light="top-left", **body))
        assert message.startswith(next(iter(body))) and state(client)["version"] == v


def test_the_shadows_preview_is_the_change_bit_for_bit(client, folder):
    """``/api/view?shadows=LAYER:S`` (the Shadows slider while dragged) shows, bit for bit, what ``op: light`` with
    ``shadows`` S gives and what the engine renders of the saved stack, under a low light that makes the map's relief
    cast shadows (nowhere brighter, somewhere darker); bad values are refused in one line and change nothing."""
    ok(post(client, op="light", id="shape", light="az=200,el=80"))
    before = view(client, level=0)
    preview = view(client, level=0, shadows="shape:1")
    assert np.array_equal(view(client, level=0), before)
    assert (preview[..., :3] <= before[..., :3]).all() and (preview[..., :3] < before[..., :3]).any()
    s = ok(post(client, op="light", id="shape", light="az=200,el=80", shadows=1.0))
    assert s["surfaces"]["shape"]["shadows"] == 1.0
    assert np.array_equal(view(client, level=0), preview)
    assert np.array_equal(preview[..., :3], relit_codes(folder, "az=200,el=80", shadows=1.0))
    ok(post(client, op="save"))
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(preview[..., :3], fresh)
    v = state(client)["version"]
    for body in ({"shadows": 2}, {"shadows": -0.5}, {"shadows": "1"}, {"occlusion": 1.5}):
        message = one_line_4xx(post(client, op="light", id="shape", light="top-left", **body))
        assert message.startswith(next(iter(body))) and state(client)["version"] == v
    # The Occlusion slider likewise: its preview is the change, bit for bit, and takes ambient light from the dome's
    # foot (nowhere brighter).
    before = view(client, level=0)
    preview = view(client, level=0, occlusion="shape:1")
    assert (preview[..., :3] <= before[..., :3]).all() and (preview[..., :3] < before[..., :3]).any()
    ok(post(client, op="light", id="shape", light="az=200,el=80", occlusion=1.0))
    assert np.array_equal(view(client, level=0), preview)
    assert np.array_equal(preview[..., :3], relit_codes(folder, "az=200,el=80", shadows=1.0, occlusion=1.0))
    # The Shadow depth slider likewise: the heights traced ×3, longer shadows and deeper creases (nowhere brighter).
    deeper = view(client, level=0, shadow_depth="shape:3")
    assert (deeper[..., :3] <= preview[..., :3]).all() and (deeper[..., :3] < preview[..., :3]).any()
    s = ok(post(client, op="light", id="shape", light="az=200,el=80", shadow_depth=3.0))
    assert s["surfaces"]["shape"]["shadow_depth"] == 3.0 and np.array_equal(view(client, level=0), deeper)
    want = relit_codes(folder, "az=200,el=80", shadows=1.0, occlusion=1.0, shadow_depth=3.0)
    assert np.array_equal(deeper[..., :3], want)
    message = one_line_4xx(post(client, op="light", id="shape", light="top-left", shadow_depth=0))
    assert message.startswith("shadow_depth")


def test_extra_lights_are_set_as_a_list_one_step_and_saved(client, folder):
    """``op: light`` with ``extra_lights`` sets the whole list (one undo step), the state lists them, the view is what
    the engine renders of the stack so re-lit, ``[]`` removes them, and a bad list is a one-line 4xx that changes
    nothing."""
    before = view(client, level=0)
    extra = [{"light": "right", "color": [0.5, 0.6, 1.0], "intensity": 0.7}, {"light": "x=0.5,y=0,z=0.4"}]
    s = ok(post(client, op="light", id="shape", light="top-left", extra_lights=extra))
    got = s["surfaces"]["shape"]["extra_lights"]
    assert [e["light"] for e in got] == ["right", "x=0.5,y=0,z=0.4"] and got[1]["intensity"] == 1.0
    assert s["undo"] == "light of shape"
    lit = view(client, level=0)
    assert np.array_equal(lit[..., :3], relit_codes(folder, "top-left", extra_lights=extra))
    ok(post(client, op="save"))
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(lit[..., :3], fresh)
    v = state(client)["version"]
    for bad in ([{"light": "up"}], [{"light": "left", "intensity": 0}], [{"light": "left"}] * 9, "left"):
        message = one_line_4xx(post(client, op="light", id="shape", light="top-left", extra_lights=bad))
        assert message.startswith("extra_lights") and state(client)["version"] == v, message
    s = ok(post(client, op="light", id="shape", light="top-left", extra_lights=[]))
    assert s["surfaces"]["shape"]["extra_lights"] == [] and np.array_equal(view(client, level=0), before)


# ---- a normal map of one's own ------------------------------------------------------------------------


def map_bytes(green_down: bool = False) -> tuple[bytes, np.ndarray]:
    """An 8-bit RGB normal map (6 × 9) as PNG bytes, and its unit normals decoded +Y up from its codes."""
    import io

    from PIL import Image

    yy, xx = np.mgrid[0:6, 0:9]
    n = np.stack([(xx - 4.0) / 6, -(yy - 2.5) / 5, np.ones((6, 9))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    c = np.round((n + 1) / 2 * 255).astype(np.uint8)
    decoded = c.astype(np.float64) / 255 * 2 - 1
    decoded /= np.linalg.norm(decoded, axis=-1, keepdims=True)
    if green_down:
        c[..., 1] = 255 - c[..., 1]
    out = io.BytesIO()
    Image.fromarray(c).save(out, format="PNG")
    return out.getvalue(), decoded


def test_an_uploaded_normal_map_is_a_surface_layer_as_its_codes_say(client, folder):
    """``/api/upload?kind=normal-map`` (the page's "Add normal map") adds a surface layer of the map's own normals
    (stored as the stack's 16-bit map: within its step of the codes' decoding), lit from the top-left, one undo step;
    a DirectX map (``directx=1``) of the same normals adds the same map; the saved stack renders what the view shows."""
    data, decoded = map_bytes()
    v = state(client)["version"]
    r = client.post(
        "/api/upload", headers=H, params={"version": v, "name": "bumps.png", "kind": "normal-map"}, content=data
    )
    s = ok(r)
    top = s["document"]["layers"][-1]
    assert (top["kind"], top["id"], top["light"]) == ("surface", "bumps", "top-left") and s["undo"] == "add bumps"
    ok(post(client, op="save"))
    stored = load_stack(folder).tensors["bumps"].color.double().numpy().transpose(1, 2, 0) * 2 - 1
    stored /= np.linalg.norm(stored, axis=-1, keepdims=True)
    np.testing.assert_allclose(stored, decoded, atol=5e-5)
    fresh = composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()
    assert np.array_equal(view(client, level=0)[..., :3], fresh)
    dx, _ = map_bytes(green_down=True)
    params = {"version": s["version"], "name": "dx.png", "kind": "normal-map", "directx": "1"}
    ok(client.post("/api/upload", headers=H, params=params, content=dx))
    ok(post(client, op="save"))
    maps = load_stack(folder).tensors
    assert (maps["bumps"].color - maps["dx"].color).abs().max() <= 1.5 / 65535


def test_an_uploaded_height_map_is_the_surface_of_its_slopes(client, folder):
    """``/api/upload?kind=normal-map&height=PX`` (the page's height field beside "Add normal map") reads a grey PNG as
    heights, white PX pixels above black: the layer is exactly what ``lasagna add-surface --height PX`` makes of the
    same file (`height_map_normals`), one undo step, and the saved stack renders what the view shows."""
    import io

    from PIL import Image

    from lasagna.io.normal_map import height_map_normals

    yy, xx = np.mgrid[0:12, 0:16]
    grey = np.clip(1 - ((xx - 7.5) ** 2 + (yy - 5.5) ** 2) / 40, 0, 1)
    out = io.BytesIO()
    Image.fromarray(np.round(grey * 255).astype(np.uint8)).save(out, format="PNG")
    v = state(client)["version"]
    params = {"version": v, "name": "bump.png", "kind": "normal-map", "height": "2.5"}
    s = ok(client.post("/api/upload", headers=H, params=params, content=out.getvalue()))
    assert s["document"]["layers"][-1]["id"] == "bump" and s["undo"] == "add bump"
    ok(post(client, op="save"))
    stack = load_stack(folder)
    want = height_map_normals(data=out.getvalue(), depth=2.5)
    got = stack.tensors["bump"].color.double() * 2 - 1
    assert (torch.nn.functional.normalize(got, dim=0) - want.double()).abs().max() <= 5e-5
    fresh = composite_codes(render_stack(stack).image).permute(1, 2, 0).numpy()
    assert np.array_equal(view(client, level=0)[..., :3], fresh)


@pytest.mark.parametrize(
    "params, body, words",
    [
        ({"kind": "normal-map"}, b"GIF89a not a png", "not a PNG; expected a normal map"),
        ({"kind": "normal-map"}, "GRAY", "has 1 colour channel(s); expected an RGB normal map"),
        ({"kind": "normal-map", "directx": "yes"}, "MAP", "directx is 'yes'; expected 0 or 1"),
        ({"kind": "bump"}, "MAP", "kind is 'bump'; expected image or normal-map"),
        ({"kind": "normal-map", "height": "tall"}, "GRAY", "height is 'tall'; expected a number of pixels"),
        ({"kind": "normal-map", "height": "-2"}, "GRAY", "got a depth of -2.0; expected the pixels white stands"),
        ({"kind": "normal-map", "height": "2", "directx": "1"}, "GRAY", "a height map has no green to flip"),
    ],
)
def test_a_bad_normal_map_upload_is_a_one_line_400_and_changes_nothing(client, params, body, words):
    import io

    from PIL import Image

    if body == "GRAY":
        out = io.BytesIO()
        Image.fromarray(np.zeros((4, 4), np.uint8)).save(out, format="PNG")
        body = out.getvalue()
    elif body == "MAP":
        body = map_bytes()[0]
    before = state(client)
    r = client.post(
        "/api/upload", headers=H, params={"version": before["version"], "name": "n.png", **params}, content=body
    )
    assert words in one_line_4xx(r)
    assert state(client)["document"] == before["document"]


def test_a_relight_surface_layer_is_read_again_told_its_dragged_source_light(tiny, tmp_path):
    """The ``reread`` change (the editor's "Read again from this source light"): a relight surface layer added by the
    page (its source light fitted), its source light then dragged, is read again told it — its normal map exactly a
    fresh ``lasagna edit --layer-kind surface --from`` that light's (the preset's told estimator), one undo step that
    gives the dragged layer back; a layer with nothing to be told, or none, is a one-line 4xx that changes nothing."""
    from lasagna import edit
    from lasagna.io.stack import Stack
    from tests.support.tinylayers import tiny_variant, write_preset

    catalogue = tiny_variant(tiny, tmp_path / "layers")
    surface = {"estimator": "surface-lit-32", "refine_steps": 0, "working_size": 16}
    write_preset(catalogue, "relight", surface={**surface, "told": {"estimator": "surface-lit-told-32"}})
    torch.manual_seed(0)
    picture = torch.rand(3, 24, 40)
    Stack.from_image(picture).save(tmp_path / "s")
    client = TestClient(
        create_app(EditSession(tmp_path / "s", catalogue_dirs=[catalogue]), TOKEN, ["testserver"]),
        raise_server_exceptions=False,
    )
    added = ok(post(client, op="learned", preset="relight", condition="right", kind="surface"))
    id = added["document"]["layers"][-1]["id"]
    assert added["surfaces"][id]["rereadable"]  # a relight made by a preset: its fitted source light can be told
    ok(post(client, op="light", id=id, light="right", source_light="az=150,el=40"))
    dragged = view(client, level=0)
    got = ok(post(client, op="reread", id=id))
    assert got["surfaces"][id]["source_light"] == "az=150,el=40" and got["surfaces"][id]["rereadable"]
    layer = next(x for x in got["document"]["layers"] if x["id"] == id)
    assert layer["made_by"]["told_estimator"] == "surface-lit-told-32" and got["undo"] == f"re-read {id}"
    fresh = edit(
        picture, "relight", "right", layer_kind="surface", source_light="az=150,el=40", catalogue_dirs=[catalogue]
    )
    assert np.array_equal(view(client, level=0)[..., :3], composite_codes(fresh.composite).permute(1, 2, 0).numpy())
    ok(post(client, op="undo"))
    assert np.array_equal(view(client, level=0), dragged)
    # Told the dragged light within ±10°: read as `lasagna edit --from L --within 10` reads it — the same map and the
    # fused source light, held by the layer, the reading recorded.
    within = ok(post(client, op="reread", id=id, within=10))
    fused = edit(
        picture,
        "relight",
        "right",
        layer_kind="surface",
        source_light="az=150,el=40",
        source_within=10,
        catalogue_dirs=[catalogue],
    )
    want = fused.stack.document.layer(fused.layer_id)
    layer = next(x for x in within["document"]["layers"] if x["id"] == id)
    assert layer["source_light"] == want.source_light != "az=150,el=40" and layer["made_by"]["source_within"] == 10
    assert np.array_equal(view(client, level=0)[..., :3], composite_codes(fused.composite).permute(1, 2, 0).numpy())
    ok(post(client, op="undo"))
    # A shading layer (its estimator reads the unlit base) made a relight later has no light to be told.
    shaded = ok(post(client, op="learned", preset="shading", condition="left", kind="surface"))
    sid = shaded["document"]["layers"][-1]["id"]
    relit = ok(post(client, op="light", id=sid, light="left", source_light="top"))
    assert relit["surfaces"][sid]["source_light"] == "top" and not relit["surfaces"][sid]["rereadable"]
    before = state(client)
    for body, words in (
        ({"id": "base"}, "expected a surface layer"),
        ({"id": "nope"}, "nope"),
        ({"id": sid}, "no source light to give"),
        ({"id": id, "within": 0}, "greater than 0"),
        ({"id": id, "within": 91}, "less than or equal to 90"),
        ({"id": id, "within": "10"}, "within"),
    ):
        message = one_line_4xx(post(client, op="reread", **body))
        assert words in message, message
    assert state(client)["version"] == before["version"]


def test_a_zoom_level_traces_shadows_at_the_reduction_of_the_full_trace(client, session, monkeypatch):
    """A view at level k traces the layer's shadows at SHADOW_MAX_SIDE / 2^k on a side (its tensors carry
    ``reduced_by`` 2^k), what the full render traces, reduced; the level's preview is still its change, bit for bit."""
    import lasagna.compose.surface as cs

    side = max(session.stack.tensors["shape"].color.shape[-2:])  # the map's long side, 40
    monkeypatch.setattr(cs, "SHADOW_MAX_SIDE", 32)  # the full size traced at 32, so a level-1 view at 16
    ok(post(client, op="light", id="shape", light="az=200,el=80"))
    cs._HEIGHTS.clear()
    preview = view(client, level=1, shadows="shape:1")
    traced = {max(fields["heights"].shape[-2:]) for _, (_, fields) in list(cs._HEIGHTS.items())}
    assert traced == {16}, (side, traced)  # not the level's own long side, 20, which it was traced at before
    ok(post(client, op="light", id="shape", light="az=200,el=80", shadows=1.0))
    assert np.array_equal(view(client, level=1), preview)


def test_a_surface_layers_maps_download_as_the_cli_writes_them(client, folder):
    """``/api/export/<map>?id=…``: the normal map (and ``directx=1``), the height map and the occlusion map of the
    current stack, byte for byte what ``lasagna export --normal-map`` (``--directx``), ``--height-map`` and
    ``--occlusion-map`` write for the same layer; a relief changed in the editor is in them. Bad asks: one-line 400s."""
    from lasagna.export.png import height_map_png, normal_map_png, occlusion_map_png

    ok(post(client, op="light", id="shape", light="top-left", relief=1.5))
    stack = load_stack(folder)
    stack.set_light("shape", "top-left", relief=1.5)
    want = {
        "/api/export/normal-map?id=shape": normal_map_png(stack, "shape"),
        "/api/export/normal-map?id=shape&directx=1": normal_map_png(stack, "shape", directx=True),
        "/api/export/height-map?id=shape": height_map_png(stack, "shape")[0],
        "/api/export/occlusion-map?id=shape": occlusion_map_png(stack, "shape"),
    }
    assert want["/api/export/normal-map?id=shape"] != normal_map_png(load_stack(folder), "shape")  # relief 1.5 in it
    for path, data in want.items():
        r = client.get(path, headers=H)
        assert r.status_code == 200 and r.headers["content-type"] == "image/png" and r.content == data, path
        assert r.headers["content-disposition"].startswith('attachment; filename="lit-shape-')
    for path, words in [
        ("/api/export/normal-map", "is a surface layer's; expected ?id=LAYER"),
        ("/api/export/normal-map?id=tint", "no surface layer 'tint'"),
        ("/api/export/height-map?id=shape&directx=1", "directx is a normal map's convention"),
        ("/api/export/normal-map?id=shape&directx=yes", "directx is 'yes'; expected 0 or 1"),
        ("/api/export/png?id=shape", "is the stack's; expected no ?id="),
        ("/api/export/bump-map?id=shape", "unknown export 'bump-map'"),
    ]:
        assert words in one_line_4xx(client.get(path, headers=H)), path
