"""The README's picture of the editor re-lighting a photograph by a point light (issue #24, item 5).

    OMP_NUM_THREADS=2 python examples/editor_screenshot.py docs/img/serve_point_light.png

Needs the ``serve`` and ``dev`` extras and Debian's Chromium (as the browser tests do). The coffee photograph
(``examples/photos/large/coffee.jpg``) gets the relight preset's surface layer (``lasagna.edit(..., "relight",
"left", layer_kind="surface")``, the source light fitted); the editor opens on it, the layer's light is turned into a
point light ("Point light") and dragged on the image to the cup's upper left, its Height slider lowered, and the
page is captured: the layers panel, the light panel (sphere, Relief, Ambient, Colour, Intensity, Point light,
Height) and the canvas with the point's ring.
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")


def main(out: Path) -> int:
    import uvicorn
    from PIL import Image
    from playwright.sync_api import sync_playwright

    import lasagna
    from lasagna.serve import allowed_hosts, free_port
    from lasagna.serve.app import create_app
    from lasagna.serve.session import EditSession

    work = Path(tempfile.mkdtemp(prefix="lasagna-shot-"))
    made = lasagna.edit(
        str(ROOT / "examples" / "photos" / "large" / "coffee.jpg"), "relight", "left", layer_kind="surface"
    )
    made.stack.save(work / "coffee")
    session = EditSession(work / "coffee")
    port = free_port("127.0.0.1")
    app = create_app(session, "shot", allowed_hosts("127.0.0.1", port))
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="off"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.02)
    settled = "window.lasagna.settled()"
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(f"http://127.0.0.1:{port}/?token=shot")
            page.wait_for_function("window.lasagna.state !== null && window.lasagna.paints.count > 0")
            page.locator(f'#layers li[data-id="{made.layer_id}"] .name').click()
            page.check("#point-light")
            page.wait_for_function(f"window.lasagna.state.version > 0 && {settled}")
            box = page.locator("#canvas").bounding_box()
            ui = page.evaluate("({x: window.lasagna.panX, y: window.lasagna.panY, z: window.lasagna.zoom})")

            def at(fx: float, fy: float) -> tuple[float, float]:  # page coordinates of the image's fractions
                return box["x"] + ui["x"] + fx * 512 * ui["z"], box["y"] + ui["y"] + fy * 512 * ui["z"]

            page.mouse.move(*at(0.5, 0.5))
            page.mouse.down()
            for k in range(1, 13):
                page.mouse.move(*at(0.5 - 0.03 * k, 0.5 - 0.025 * k))
                page.wait_for_timeout(20)
            page.mouse.up()
            page.wait_for_function(f"window.lasagna.state.version > 1 && {settled}")
            page.evaluate(
                """() => { const r = document.getElementById("light-height");
                r.value = "-1.3"; r.dispatchEvent(new Event("input")); r.dispatchEvent(new Event("change")); }"""
            )
            page.wait_for_function(f"window.lasagna.state.version > 2 && {settled}")
            page.wait_for_timeout(300)
            shot = work / "shot.png"
            page.screenshot(path=str(shot))
            browser.close()
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.open(shot).convert("RGB").save(out)
        print(f"wrote {out} (light {session.stack.document.layer(made.layer_id).light})")
    finally:
        server.should_exit = True
        thread.join(timeout=10)
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/img/serve_point_light.png")))
