"""The editor end to end in a real headless Chromium (Debian's, driven by Playwright), as a person uses it.

After every step the canvas pixels read from the page at 1:1 zoom must equal ``lasagna composite`` of the
saved stack (``load_stack`` + ``render_stack`` of the folder) within 1/255. Marked ``browser``; skipped with
the reason where Chromium or Playwright is missing (``.ci/run`` installs Debian's ``chromium``).
"""

from __future__ import annotations

import io
import shutil
import tempfile
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from lasagna.document.condition import parse_direction
from tests.support.bounded import HANG_SECONDS
from tests.support.tinylayers import ROOT

pytestmark = pytest.mark.browser

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def _skip_reason() -> str | None:
    try:
        import playwright  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        return f"{exc.name} is not installed (pip install -e '.[dev]')"
    if not CHROMIUM.exists():
        return "Debian's chromium is not installed (apt-get install chromium)"
    return None


if _skip_reason():
    pytest.skip(_skip_reason(), allow_module_level=True)


class Server:
    """The editor app on uvicorn in a thread, on a free loopback port."""

    def __init__(self, folder: Path):
        import uvicorn

        from lasagna.serve import allowed_hosts, free_port
        from lasagna.serve.app import create_app
        from lasagna.serve.session import EditSession

        self.session = EditSession(folder)
        self.port = free_port("127.0.0.1")
        self.token = "browser-test-token"
        app = create_app(self.session, self.token, allowed_hosts("127.0.0.1", self.port))
        config = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning", lifespan="off")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started and time.monotonic() < deadline:
            time.sleep(0.02)
        self.url = f"http://127.0.0.1:{self.port}/?token={self.token}"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=HANG_SECONDS)


@pytest.fixture
def folder(tmp_path, tiny, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))
    out = tmp_path / "basic"
    shutil.copytree(ROOT / "examples" / "stacks" / "basic", out)
    return out


@pytest.fixture
def server(folder):
    s = Server(folder)
    yield s
    s.stop()


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    profile = tempfile.mkdtemp(prefix="lasagna-chromium-")
    with sync_playwright() as p:
        context = p.chromium.launch_persistent_context(
            profile,
            executable_path=str(CHROMIUM),
            headless=True,
            args=FLAGS,
            viewport={"width": 1280, "height": 800},
            accept_downloads=True,
        )
        yield context
        context.close()
    shutil.rmtree(profile, ignore_errors=True)


def open_page(browser, server):
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url)
    page.wait_for_function("window.lasagna.state !== null && window.lasagna.paints.count > 0")
    page.errors = errors
    return page


def settle(page, version: int | None = None) -> None:
    """Wait until the page shows ``version`` (default: whatever it has) and its last repaint has landed."""
    if version is not None:
        page.wait_for_function(f"window.lasagna.state.version === {version}")
    page.wait_for_function("window.lasagna.settled()")


def page_pixels(page) -> np.ndarray:
    page.click("#zoom-1")
    settle(page)
    s = page.evaluate("window.lasagna.state.document.canvas")
    data = np.array(page.evaluate("window.lasagna.readPixels()"), np.uint8)
    return data.reshape(s["height"], s["width"], 4)[..., :3]


def saved_composite(folder: Path) -> np.ndarray:
    from lasagna.io.render import composite_codes, render_stack
    from lasagna.io.stack import load_stack

    return composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy()


def save_and_check(page, folder: Path) -> None:
    """Save from the page, then the page's 1:1 pixels against the saved stack's composite (≤ 1/255)."""
    page.click("#save")
    page.wait_for_function("!window.lasagna.state.dirty")
    got = page_pixels(page).astype(int)
    ref = saved_composite(folder).astype(int)
    assert got.shape == ref.shape
    assert np.abs(got - ref).max() <= 1


def version(page) -> int:
    return page.evaluate("window.lasagna.state.version")


def row(page, id: str):
    return page.locator(f'#layers li[data-id="{id}"]')


def test_every_control_keeps_the_page_equal_to_the_saved_stack(browser, server, folder, tmp_path):
    page = open_page(browser, server)
    assert np.array_equal(page_pixels(page), saved_composite(folder))

    # toggle a layer
    v = version(page)
    row(page, "glow").locator(".eye").click()
    settle(page, v + 1)
    assert page.evaluate("window.lasagna.state.document.layers.find(l => l.id === 'glow').visible") is False
    save_and_check(page, folder)

    # drag an opacity slider with the mouse: transient repaints while dragging, one change on release
    v = version(page)
    paints = page.evaluate("window.lasagna.paints.count")
    box = row(page, "sticker").locator(".opacity").bounding_box()
    y = box["y"] + box["height"] / 2
    page.mouse.move(box["x"] + box["width"] - 2, y)
    page.mouse.down()
    for f in (0.8, 0.6, 0.45, 0.3):
        page.mouse.move(box["x"] + box["width"] * f, y)
        page.wait_for_timeout(30)
    page.mouse.up()
    settle(page, v + 1)
    assert page.evaluate("window.lasagna.paints.count") > paints + 1
    opacity = page.evaluate("window.lasagna.state.document.layers.find(l => l.id === 'sticker').opacity")
    assert 0.2 < opacity < 0.45
    save_and_check(page, folder)

    # reorder by drag and drop: glow dropped on base takes the bottom place
    v = version(page)
    row(page, "glow").drag_to(row(page, "base"))
    settle(page, v + 1)
    assert page.evaluate("window.lasagna.state.document.layers[0].id") == "glow"
    save_and_check(page, folder)
    v = version(page)
    row(page, "glow").locator(".up").click()  # and with the button
    settle(page, v + 1)
    assert page.evaluate("window.lasagna.state.document.layers[1].id") == "glow"

    # rename and blend from the panels
    v = version(page)
    row(page, "sticker").locator(".name").click()
    page.fill("#prop-name", "Blue sticker")
    page.press("#prop-name", "Enter")
    settle(page, v + 1)
    v = version(page)
    row(page, "sticker").locator(".blend").select_option("multiply")
    settle(page, v + 1)
    save_and_check(page, folder)

    # add a solid layer and an amortised learned layer from the catalogue, with the light picker
    v = version(page)
    page.click("#add-solid")
    settle(page, v + 1)
    page.select_option("#preset", "shading")
    page.click('#picker button[data-condition="top-left"]')
    v = version(page)
    page.click("#add-learned")
    settle(page, v + 1)
    top = page.evaluate("window.lasagna.state.document.layers.at(-1)")
    assert top["kind"] == "learned" and top["condition"]["label"] == "top-left"
    save_and_check(page, folder)

    # undo takes the learned layer back; redo brings it again
    v = version(page)
    page.click("#undo")
    settle(page, v + 1)
    assert page.evaluate("window.lasagna.state.document.layers.at(-1).kind") == "solid"
    save_and_check(page, folder)
    v = version(page)
    page.keyboard.press("Control+Shift+Z")
    settle(page, v + 1)
    save_and_check(page, folder)

    # solo and before/after are views, not changes
    v = version(page)
    row(page, "base").locator(".solo").click()
    settle(page)
    base = np.asarray(__import__("PIL.Image", fromlist=["Image"]).open(folder / "layers" / "base.png").convert("RGB"))
    assert np.array_equal(page_pixels(page), base)
    row(page, "base").locator(".solo").click()
    page.check("#split")
    settle(page)
    assert version(page) == v

    # exports are downloads of the saved stack
    page.uncheck("#split")
    with page.expect_download() as d:
        page.click("#export-png")
    png = Path(d.value.path()).read_bytes()
    from PIL import Image

    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png)).convert("RGB")), saved_composite(folder))
    with page.expect_download() as d:
        page.click("#export-ora")
    with zipfile.ZipFile(d.value.path()) as z:
        assert z.read("mimetype") == b"image/openraster"
    with page.expect_download() as d:
        page.click("#export-psd")
    assert Path(d.value.path()).read_bytes()[:4] == b"8BPS"
    assert page.errors == []
    page.close()


def test_a_per_image_layer_shows_progress_and_can_be_cancelled(browser, server, folder):
    page = open_page(browser, server)
    page.select_option("#preset", "light")
    page.click('#picker button[data-condition="warm"]')
    v = version(page)
    assert page.is_disabled("#add-learned")  # light has no generator
    page.click("#add-per-image")  # the layer is added, then made by a job with a progress bar
    page.wait_for_function(f"window.lasagna.state.version >= {v + 2}", timeout=HANG_SECONDS * 1000)
    settle(page)
    top = page.evaluate("window.lasagna.state.document.layers.at(-1)")
    assert top["kind"] == "learned" and page.evaluate("window.lasagna.state.not_rendered") == {}
    assert "done" in page.inner_text("#job-text")
    save_and_check(page, folder)

    page.fill("#refine-steps", "10000")
    v = version(page)
    page.click("#refine")
    # The previous job's "done" and full bar are gone at once, and cancel waits for the new job's id: a cancel
    # clicked earlier went to the finished job, and the refine (early-stopped after ~100 steps) ran on.
    assert "done" not in page.inner_text("#job-text")
    page.wait_for_function("!document.getElementById('job-cancel').disabled", timeout=HANG_SECONDS * 1000)
    page.click("#job-cancel")
    page.wait_for_function(
        "document.getElementById('job-text').textContent.includes('cancelled')", timeout=HANG_SECONDS * 1000
    )
    assert version(page) == v
    assert page.errors == []
    page.close()


def test_add_surface_makes_a_surface_layer_under_the_picked_light(browser, server, folder):
    page = open_page(browser, server)
    page.select_option("#preset", "color")
    assert page.is_disabled("#add-surface")  # color has no surface estimator
    page.select_option("#preset", "shading")
    page.click('#picker button[data-condition="top-left"]')
    v = version(page)
    page.click("#add-surface")
    settle(page, v + 1)
    top = page.evaluate("window.lasagna.state.document.layers.at(-1)")
    assert top["kind"] == "surface" and top["light"] == "top-left" and top.get("source_light") is None
    save_and_check(page, folder)


def test_two_tabs_never_overwrite_each_other(browser, server, folder):
    a, b = open_page(browser, server), open_page(browser, server)
    v = version(a)
    row(a, "glow").locator(".eye").click()
    settle(a, v + 1)
    row(b, "sticker").locator(".eye").click()  # b still holds version v: told, not applied
    b.wait_for_function("document.getElementById('status').classList.contains('error')")
    assert "another tab" in b.inner_text("#status")
    assert b.is_visible("#reload")
    assert server.session.state()["version"] == v + 1
    b.click("#reload")
    settle(b, v + 1)
    assert b.evaluate("window.lasagna.state.document.layers.find(l => l.id === 'glow').visible") is False
    row(b, "sticker").locator(".eye").click()
    settle(b, v + 2)
    assert b.evaluate("window.lasagna.state.document.layers.find(l => l.id === 'sticker').visible") is False
    assert a.errors == [] and b.errors == []
    a.close()
    b.close()


def test_the_page_refuses_without_the_token(browser, server):
    browser.clear_cookies()  # earlier pages left the token's cookie
    page = browser.new_page()
    response = page.goto(server.url.split("?")[0])
    assert response.status == 403 and "token" in page.inner_text("body")
    page.close()


# ---- a surface layer's light -------------------------------------------------------------------------


@pytest.fixture
def surface_server(tmp_path):
    from tests.serve.surface_stack import surface_stack

    s = Server(surface_stack(tmp_path / "lit"))
    yield s
    s.stop()


def drag_light(page, dx: float, dy: float) -> None:
    """Drag the light control from its centre to (dx, dy) in units of its radius (y up), in small moves."""
    page.locator("#light-sphere").scroll_into_view_if_needed()  # a long panel (a relight's) puts it below the fold
    box = page.locator("#light-sphere").bounding_box()
    cx, cy, r = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2, box["width"] / 2 - 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    for k in range(1, 13):
        page.mouse.move(cx + r * dx * k / 12, cy - r * dy * k / 12)
        page.wait_for_timeout(25)
    page.mouse.up()


def test_dragging_a_surface_layers_light_repaints_live_and_commits_one_step(browser, surface_server):
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    before = page_pixels(page)
    assert np.array_equal(before, saved_composite(folder))
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#light-sphere")
    v, paints = version(page), page.evaluate("window.lasagna.paints.count")

    drag_light(page, -0.9, 0.0)  # the light toward the left
    settle(page, v + 1)
    assert page.evaluate("window.lasagna.paints.count") - paints >= 3  # repainted while dragging, not only at the end
    s = page.evaluate("window.lasagna.state")
    lit = s["surfaces"]["shape"]
    assert s["undo"] == "light of shape" and abs(lit["az"] - 180) < 2 and abs(lit["el"] - 64.2) < 2
    assert page.inner_text("#light-readout") == lit["light"]
    left = page_pixels(page)
    assert not np.array_equal(left, before)

    drag_light(page, 0.9, 0.0)  # and toward the right: another image
    settle(page, v + 2)
    right = page_pixels(page)
    assert not np.array_equal(right, left) and not np.array_equal(right, before)
    save_and_check(page, folder)  # the page shows what the engine renders of the saved light
    assert abs(page.evaluate("window.lasagna.state.surfaces.shape.az")) < 2

    page.click("#undo")  # one step per drag (a save is not a version)
    settle(page, v + 3)
    assert np.array_equal(page_pixels(page), left)

    page.check("#normal-map")  # the stored map, not the lit composite
    settle(page)
    from lasagna.io.stack import load_stack

    stored = load_stack(folder).tensors["shape"].color
    codes = (stored.double() * 255).round().byte().permute(1, 2, 0).numpy()
    assert np.array_equal(page_pixels(page)[8:40, 8:48], codes)
    page.check("#occlusion-map")  # the share of the sky, grey; the normal map's box cleared
    settle(page)
    assert not page.is_checked("#normal-map")
    sky = page_pixels(page)[8:40, 8:48, :3].astype(int)
    assert (sky[..., 0] == sky[..., 1]).all() and (sky[..., 1] == sky[..., 2]).all() and sky.min() < 250
    page.uncheck("#occlusion-map")
    settle(page)
    assert np.array_equal(page_pixels(page), left)
    assert page.errors == []


def test_a_relight_surface_layers_source_light_is_dragged_too(browser, surface_server):
    """A relight surface layer (it has a source light): the "Drag" choice moves the source light instead — the view
    repaints live, the release commits one step that changes the source light and keeps the light, the saved stack
    renders what the page shows; a shading surface layer (no source light) offers no choice."""
    folder, session = surface_server.session.folder, surface_server.session
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#light-sphere")
    assert page.locator("#light-which").count() == 0  # no source light: nothing to choose
    page.close()
    session.set_light(session.state()["version"], "shape", "right", source_light="left")
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#light-which")
    page.select_option("#light-which", "source")
    assert page.inner_text("#light-readout") == "left"
    before, v = page_pixels(page), version(page)
    paints = page.evaluate("window.lasagna.paints.count")
    drag_light(page, 0.0, 0.5)  # the source light toward the top, 30° from the view axis
    settle(page, v + 1)
    assert page.evaluate("window.lasagna.paints.count") - paints >= 3
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    assert lit["light"] == "right" and abs(lit["source"][0] - 90) < 2 and abs(lit["source"][1] - 30) < 2
    assert page.input_value("#light-which") == "source" and page.inner_text("#light-readout") == lit["source_light"]
    assert not np.array_equal(page_pixels(page), before)
    save_and_check(page, folder)
    assert page.errors == []


def test_a_dragged_source_light_is_read_again_told(browser, server, folder):
    """A relight surface layer added on the page (its source light fitted): its source light dragged, then "Read
    again from this source light" — one step more, the layer read by the preset's told estimator with the dragged
    light (recorded), its light kept, the view changed; the saved stack renders what the page shows."""
    page = open_page(browser, server)
    page.select_option("#preset", "relight")
    page.click('#picker button[data-condition="right"]')
    v = version(page)
    page.click("#add-surface")
    settle(page, v + 1)
    top = page.evaluate("window.lasagna.state.document.layers.at(-1)")
    assert top["kind"] == "surface" and top["source_light"] is not None and "told_estimator" not in top["made_by"]
    page.wait_for_selector("#reread")
    page.select_option("#light-which", "source")
    drag_light(page, 0.0, 0.5)  # the source light toward the top, 30° from the view axis
    settle(page, v + 2)
    dragged, source = page_pixels(page), page.evaluate(f"window.lasagna.state.surfaces['{top['id']}'].source_light")
    page.click("#reread")
    settle(page, v + 3)
    layer = page.evaluate("window.lasagna.state.document.layers.at(-1)")
    assert layer["made_by"]["told_estimator"] == "surface-lit-told-32"
    assert layer["source_light"] == source and layer["light"] == "right"
    assert not np.array_equal(page_pixels(page), dragged)
    # "within ±°" filled: the light a rough reading, its elevation fused with the fit; the layer holds the fused light.
    exact = page_pixels(page)
    page.fill("#reread-within", "10")
    page.click("#reread")
    settle(page, v + 4)
    fused = page.evaluate("window.lasagna.state.document.layers.at(-1)")
    assert fused["made_by"]["source_within"] == 10 and fused["made_by"]["source_read"] == source
    (az, el), (read_az, read_el) = parse_direction(fused["source_light"]), parse_direction(source)
    assert abs(az - read_az) < 1e-6 and abs(el - read_el) > 0.1  # the reader's azimuth, the elevation fused
    assert not np.array_equal(page_pixels(page), exact)
    save_and_check(page, folder)
    assert page.errors == []


def slide(page, id: str, values: list[str], release: bool = False) -> None:
    """Move the range input ``id`` through ``values`` as a drag does (an input event each), then, with ``release``,
    let it go (a change event: the commit)."""
    page.evaluate(
        """([id, values, release]) => { const r = document.getElementById(id);
        for (const x of values) { r.value = x; r.dispatchEvent(new Event("input")); }
        if (release) r.dispatchEvent(new Event("change")); }""",
        [id, values, release],
    )


def test_the_relief_slider_previews_live_and_commits_one_step(browser, surface_server):
    """A surface layer's "Relief" slider (log scale, ×1/4…×8): dragging repaints the view live with nothing changed
    on the server; the release commits one step that sets the relief and keeps the light; the saved stack renders
    what the page shows; undo restores the pixels."""
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#relief")
    assert page.inner_text("#relief-value") == "×1.00"
    before, v = page_pixels(page), version(page)
    paints = page.evaluate("window.lasagna.paints.count")
    slide(page, "relief", ["0.5", "1", "1.5"])
    page.wait_for_function(f"window.lasagna.paints.count > {paints}")
    assert version(page) == v  # a preview, not a change
    page.evaluate('() => document.getElementById("relief").dispatchEvent(new Event("change"))')
    settle(page, v + 1)
    s = page.evaluate("window.lasagna.state")
    assert s["undo"] == "light of shape" and abs(s["surfaces"]["shape"]["relief"] - 2.828) < 1e-3
    assert s["surfaces"]["shape"]["light"] == "top-left"
    assert page.inner_text("#relief-value") == "×2.83"
    deep = page_pixels(page)
    assert not np.array_equal(deep, before)
    save_and_check(page, folder)
    page.click("#undo")
    settle(page, v + 2)
    assert np.array_equal(page_pixels(page), before)
    assert page.errors == []


def test_a_surface_layers_maps_are_downloads(browser, surface_server):
    """A surface layer's panel links its maps: the normal map in the OpenGL and the DirectX convention, the height
    map and the occlusion map, each a download byte for byte what ``lasagna export`` writes for the layer."""
    from lasagna.export.png import height_map_png, normal_map_png, occlusion_map_png
    from lasagna.io.stack import load_stack

    stack = load_stack(surface_server.session.folder)
    want = {
        "normal-map": normal_map_png(stack, "shape"),
        "normal-map&directx=1": normal_map_png(stack, "shape", directx=True),
        "height-map": height_map_png(stack, "shape")[0],
        "occlusion-map": occlusion_map_png(stack, "shape"),
    }
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector(".map-downloads a")
    for key, data in want.items():
        with page.expect_download() as d:
            page.click(f'.map-downloads a[data-map="{key}"]')
        assert Path(d.value.path()).read_bytes() == data, key
    assert page.errors == []
    page.close()


def test_the_ambient_slider_previews_live_and_commits_one_step(browser, surface_server):
    """A surface layer's "Ambient" slider: dragging repaints the view live (nothing changes on the server), the
    release commits one step that sets the ambient term and keeps the light and relief; a higher ambient darkens
    less; the saved stack renders what the page shows."""
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#ambient")
    assert page.inner_text("#ambient-value") == "0.25" and page.get_attribute("#ambient", "min") == "0"
    before, v = page_pixels(page), version(page)
    paints = page.evaluate("window.lasagna.paints.count")
    slide(page, "ambient", ["0.4", "0.55", "0.7"])
    page.wait_for_function(f"window.lasagna.paints.count > {paints}")
    assert version(page) == v
    page.evaluate('() => document.getElementById("ambient").dispatchEvent(new Event("change"))')
    settle(page, v + 1)
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    assert lit["ambient"] == 0.7 and lit["light"] == "top-left" and lit["relief"] == 1.0
    after = page_pixels(page)
    assert after[..., :3].astype(float).mean() > before[..., :3].astype(float).mean()
    save_and_check(page, folder)
    assert page.errors == []


def test_the_light_colour_input_previews_and_commits_one_step(browser, surface_server):
    """A surface layer's "Colour" input (the light's colour): moving it repaints the view (nothing changes on the
    server), closing it commits one step that sets ``light_color`` and keeps the light; the saved stack renders
    what the page shows."""
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#light-color")
    assert page.input_value("#light-color") == "#ffffff"
    before, v = page_pixels(page), version(page)
    paints = page.evaluate("window.lasagna.paints.count")
    page.evaluate(
        """() => { const c = document.getElementById("light-color");
        c.value = "#ff8844"; c.dispatchEvent(new Event("input")); }"""
    )
    page.wait_for_function(f"window.lasagna.paints.count > {paints}")
    assert version(page) == v
    page.evaluate('() => document.getElementById("light-color").dispatchEvent(new Event("change"))')
    settle(page, v + 1)
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    assert lit["light"] == "top-left" and np.allclose(lit["light_color"], [1.0, 0x88 / 255, 0x44 / 255])
    after = page_pixels(page)
    assert not np.array_equal(after, before) and np.array_equal(after[..., 0], before[..., 0])
    save_and_check(page, folder)
    assert page.errors == []


def test_a_point_light_is_placed_by_dragging_on_the_image(browser, surface_server):
    """ "Point light" turns a surface layer's light into a point over it; dragging on the canvas then moves the point
    (live repaints, nothing changed on the server until the release, one step), the Height slider raises it (one
    step), the saved stack renders what the page shows, and unchecking makes the light a direction again."""
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#point-light")
    v, before = version(page), page_pixels(page)
    page.check("#point-light")
    settle(page, v + 1)
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    assert lit["light"].startswith("x=") and lit["point"] is not None and abs(lit["point"][2] - 0.5) < 1e-6
    save_and_check(page, folder)

    def at(fx: float, fy: float) -> tuple[float, float]:  # page coordinates of the layer's fractions (fx, fy)
        box = page.locator("#canvas").bounding_box()
        ui = page.evaluate("({x: window.lasagna.panX, y: window.lasagna.panY, z: window.lasagna.zoom})")
        lx, ly, w, h = lit["rect"]
        return box["x"] + ui["x"] + (lx + fx * w) * ui["z"], box["y"] + ui["y"] + (ly + fy * h) * ui["z"]

    paints = page.evaluate("window.lasagna.paints.count")
    page.mouse.move(*at(0.2, 0.5))
    page.mouse.down()
    for k in range(1, 11):
        page.mouse.move(*at(0.2 + 0.06 * k, 0.5))
        page.wait_for_timeout(25)
    assert version(page) == v + 1  # previews only while dragging
    page.mouse.up()
    settle(page, v + 2)
    assert page.evaluate("window.lasagna.paints.count") - paints >= 3
    s = page.evaluate("window.lasagna.state")
    point = s["surfaces"]["shape"]["point"]
    assert s["undo"] == "light of shape" and abs(point[0] - 0.8) < 0.05 and abs(point[1] - 0.5) < 0.05
    right = page_pixels(page)
    assert not np.array_equal(right, before)
    save_and_check(page, folder)

    slide(page, "light-height", ["-1.5", "-2"], release=True)
    settle(page, v + 3)
    assert abs(page.evaluate("window.lasagna.state.surfaces.shape.point[2]") - 0.25) < 1e-3
    save_and_check(page, folder)
    page.click("#undo")
    settle(page, v + 4)
    assert np.array_equal(page_pixels(page), right)
    page.uncheck("#point-light")
    settle(page, v + 5)
    assert page.evaluate("window.lasagna.state.surfaces.shape.point") is None
    save_and_check(page, folder)
    assert page.errors == []


def test_a_spot_light_is_aimed_by_shift_dragging_and_its_cone_set_by_sliders(browser, surface_server):
    """With a point light, "Spot" gives it a cone aimed at the point beneath it (one step); the Cone slider sets the
    half-angle (one step on release); a shift-drag moves the aim alone, a plain drag moves the light and the aim
    together; the aim is marked on the canvas; the saved stack renders what the page shows; unchecking drops the
    cone."""
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#point-light")
    v = version(page)
    page.check("#point-light")
    settle(page, v + 1)
    page.check("#spot-light")
    settle(page, v + 2)
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    x, y, _ = lit["point"]
    assert lit["spot"] == {"cone": 30.0, "aim": [x, y], "blend": 0.15}
    assert page.is_visible("#aim-marker")
    save_and_check(page, folder)
    slide(page, "spot-cone", ["40", "50"], release=True)
    settle(page, v + 3)
    assert page.evaluate("window.lasagna.state.surfaces.shape.spot.cone") == 50.0

    def at(fx: float, fy: float) -> tuple[float, float]:
        box = page.locator("#canvas").bounding_box()
        ui = page.evaluate("({x: window.lasagna.panX, y: window.lasagna.panY, z: window.lasagna.zoom})")
        lx, ly, w, h = lit["rect"]
        return box["x"] + ui["x"] + (lx + fx * w) * ui["z"], box["y"] + ui["y"] + (ly + fy * h) * ui["z"]

    page.keyboard.down("Shift")
    page.mouse.move(*at(0.5, 0.5))
    page.mouse.down()
    page.mouse.move(*at(0.7, 0.3), steps=5)
    page.mouse.up()
    page.keyboard.up("Shift")
    settle(page, v + 4)
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    assert np.allclose(lit["point"][:2], [x, y], atol=1e-3)  # the light stayed
    assert np.allclose(lit["spot"]["aim"], [0.7, 0.3], atol=0.05)
    save_and_check(page, folder)
    aim = lit["spot"]["aim"]
    page.mouse.move(*at(0.5, 0.5))
    page.mouse.down()
    page.mouse.move(*at(0.4, 0.6), steps=5)
    page.mouse.up()
    settle(page, v + 5)
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    moved = np.subtract(lit["point"][:2], [x, y])
    assert np.allclose(moved, [-0.1 + 0.5 - x, 0.1 + 0.5 - y], atol=0.05)  # the light went where it was dropped
    assert np.allclose(np.subtract(lit["spot"]["aim"], aim), moved, atol=2e-3)  # and the aim with it
    save_and_check(page, folder)
    page.uncheck("#spot-light")
    settle(page, v + 6)
    assert page.evaluate("window.lasagna.state.surfaces.shape.spot") is None
    assert not page.is_visible("#aim-marker")
    assert page.errors == []


@pytest.mark.parametrize(
    ("slider", "field", "shown", "values", "want", "want_shown"),
    [
        ("intensity", "light_intensity", "×1.00", ["0.5", "1", "1.5"], 2.828, "×2.83"),  # log scale, ×1/4…×8
        ("gloss", "gloss", "0.00", ["0.3", "0.6", "0.9"], 0.9, "0.90"),  # the highlight's strength, 0…1
    ],
)
def test_a_light_slider_previews_live_and_commits_one_step(
    browser, surface_server, slider, field, shown, values, want, want_shown
):
    """A surface layer's "Intensity" or "Gloss" slider: dragging repaints the view live (nothing changes on the
    server), the release commits one step that sets the field and keeps the light; a stronger light, or a highlight,
    brightens; for gloss, "shininess" commits one step more and changes the pixels; the saved stack renders what the
    page shows."""
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector(f"#{slider}")
    assert page.inner_text(f"#{slider}-value") == shown
    before, v = page_pixels(page), version(page)
    paints = page.evaluate("window.lasagna.paints.count")
    slide(page, slider, values)
    page.wait_for_function(f"window.lasagna.paints.count > {paints}")
    assert version(page) == v
    page.evaluate(f'() => document.getElementById("{slider}").dispatchEvent(new Event("change"))')
    settle(page, v + 1)
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    assert abs(lit[field] - want) < 1e-3 and lit["light"] == "top-left"
    assert page.inner_text(f"#{slider}-value") == want_shown
    after = page_pixels(page)
    assert after[..., :3].astype(float).mean() > before[..., :3].astype(float).mean()
    if slider == "gloss":
        # Set and committed in one task: the panel may be rebuilt between two separate calls on a loaded machine (a
        # fill lands on the old input, the change on the new one, which still says 32: no change, no step).
        page.evaluate(
            '() => { const s = document.getElementById("shininess"); s.value = "4"; '
            's.dispatchEvent(new Event("change")); }'
        )
        settle(page, v + 2)
        assert page.evaluate("window.lasagna.state.surfaces.shape")["shininess"] == 4.0
        assert not np.array_equal(page_pixels(page), after)
    save_and_check(page, folder)
    assert page.errors == []


def test_the_shadows_slider_previews_live_and_commits_one_step(browser, surface_server):
    """A surface layer's "Shadows" slider under a low light: dragging repaints the view live (nothing changes on the
    server) and darkens where the dome hides the light, nowhere brightening; the release commits one step that sets
    ``shadows`` and keeps the light; the "Occlusion" slider then commits one step more, darker at the dome's foot;
    the saved stack renders what the page shows."""
    folder = surface_server.session.folder
    session = surface_server.session
    session.set_light(session.state()["version"], "shape", "az=135,el=80")  # a low light: the dome casts a shadow
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#shadows")
    assert page.inner_text("#shadows-value") == "0.00"
    before, v = page_pixels(page), version(page)
    paints = page.evaluate("window.lasagna.paints.count")
    slide(page, "shadows", ["0.5", "1"])
    page.wait_for_function(f"window.lasagna.paints.count > {paints}")
    assert version(page) == v
    page.evaluate('() => document.getElementById("shadows").dispatchEvent(new Event("change"))')
    settle(page, v + 1)
    lit = page.evaluate("window.lasagna.state.surfaces.shape")
    assert lit["shadows"] == 1.0 and lit["light"] == "az=135,el=80"
    after = page_pixels(page)
    assert (after[..., :3] <= before[..., :3]).all() and (after[..., :3] < before[..., :3] - 8).any()
    # The Occlusion slider the same way: the ambient light taken from where the dome hides the sky.
    paints = page.evaluate("window.lasagna.paints.count")
    slide(page, "occlusion", ["0.5", "1"], release=True)
    settle(page, v + 2)
    assert page.evaluate("window.lasagna.state.surfaces.shape")["occlusion"] == 1.0
    occluded = page_pixels(page)
    assert (occluded[..., :3] <= after[..., :3]).all() and (occluded[..., :3] < after[..., :3]).any()
    # The Shadow depth slider (log scale, ×1/4…×8): deeper heights traced, longer shadows; one step on release.
    slide(page, "shadow_depth", ["1", "2"], release=True)
    settle(page, v + 3)
    assert page.evaluate("window.lasagna.state.surfaces.shape")["shadow_depth"] == 4.0
    deeper = page_pixels(page)
    assert (deeper[..., :3] <= occluded[..., :3]).all() and (deeper[..., :3] < occluded[..., :3]).any()
    save_and_check(page, folder)
    assert page.errors == []


def test_extra_lights_are_added_edited_and_removed_one_step_each(browser, surface_server):
    """The "Add light" button adds the key light's opposite at half intensity (one step; the light is added: the
    page brightens where it falls); editing its text and intensity commits the list (one step each); × removes it
    (one step, the pixels as before); the saved stack renders what the page shows at each stage."""
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    row(page, "shape").locator(".name").click()
    page.wait_for_selector("#add-light")
    before, v = page_pixels(page), version(page)
    page.click("#add-light")
    settle(page, v + 1)
    extra = page.evaluate("window.lasagna.state.surfaces.shape.extra_lights")
    assert len(extra) == 1 and extra[0]["intensity"] == 0.5 and extra[0]["light"] == "az=315.0,el=60.0"
    added = page_pixels(page)
    assert added[..., :3].astype(float).mean() > before[..., :3].astype(float).mean()
    save_and_check(page, folder)
    page.fill(".extra-light-text", "x=0.8,y=0.8,z=0.3")
    page.dispatch_event(".extra-light-text", "change")
    settle(page, v + 2)
    page.fill(".extra-light-intensity", "2")
    page.dispatch_event(".extra-light-intensity", "change")
    settle(page, v + 3)
    extra = page.evaluate("window.lasagna.state.surfaces.shape.extra_lights")
    assert extra == [{"light": "x=0.8,y=0.8,z=0.3", "color": [1.0, 1.0, 1.0], "intensity": 2.0}]
    save_and_check(page, folder)
    page.fill(".extra-light-text", "upward")  # refused: one line in the status, nothing changed
    page.dispatch_event(".extra-light-text", "change")
    page.wait_for_function("document.getElementById('status').textContent.includes('extra_lights')")
    assert version(page) == v + 3
    page.click(".extra-light-remove")
    settle(page, v + 4)
    assert page.evaluate("window.lasagna.state.surfaces.shape.extra_lights") == []
    assert np.array_equal(page_pixels(page), before)
    assert page.errors == []


def test_a_height_map_is_added_with_its_depth_and_lit(browser, surface_server, tmp_path):
    """The height field beside "Add normal map", filled, makes the upload a grey height map (white that many pixels
    above black): one step, a surface layer exactly `height_map_normals` of the file; the saved stack renders what
    the page shows."""
    import torch
    from PIL import Image

    from lasagna.io.normal_map import height_map_normals
    from lasagna.io.stack import load_stack

    yy, xx = np.mgrid[0:48, 0:64]
    Image.fromarray(np.round(127 + 120 * np.sin(xx / 4.0)).astype(np.uint8)).save(tmp_path / "waves.png")
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    v = version(page)
    page.fill("#normal-map-height", "6")
    page.set_input_files("#add-normal-map", str(tmp_path / "waves.png"))
    settle(page, v + 1)
    assert page.evaluate("window.lasagna.state.document.layers")[-1]["id"] == "waves"
    save_and_check(page, folder)
    got = load_stack(folder).tensors["waves"].color.double() * 2 - 1
    want = height_map_normals(tmp_path / "waves.png", depth=6.0).double()
    assert (torch.nn.functional.normalize(got, dim=0) - want).abs().max() <= 5e-5
    assert page.errors == []


def test_a_normal_map_of_ones_own_is_added_and_lit(browser, surface_server, tmp_path):
    """The "Add normal map" button, given a PNG of one's own, adds a surface layer (one step) whose light panel
    opens when it is selected; dragging its light re-lights it; the saved stack renders what the page shows."""
    from PIL import Image

    yy, xx = np.mgrid[0:48, 0:64]
    n = np.stack([np.sin(xx / 5.0) * 0.6, np.zeros((48, 64)), np.ones((48, 64))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    Image.fromarray(np.round((n + 1) / 2 * 255).astype(np.uint8)).save(tmp_path / "ridges.png")
    folder = surface_server.session.folder
    page = open_page(browser, surface_server)
    before, v = page_pixels(page), version(page)
    page.set_input_files("#add-normal-map", str(tmp_path / "ridges.png"))
    settle(page, v + 1)
    layers = page.evaluate("window.lasagna.state.document.layers")
    assert layers[-1]["id"] == "ridges" and layers[-1]["kind"] == "surface"
    assert not np.array_equal(page_pixels(page), before)
    save_and_check(page, folder)
    row(page, "ridges").locator(".name").click()
    page.wait_for_selector("#light-sphere")
    lit = page_pixels(page)
    drag_light(page, 0.9, 0.0)
    settle(page, v + 2)
    assert not np.array_equal(page_pixels(page), lit)
    save_and_check(page, folder)
    assert page.errors == []
