"""The editor's speed in a real browser (issue #12): ``lasagna serve`` on a stack of 8 layers, measured with the
page's own clock (``performance.now()``) in Debian's headless Chromium driven by Playwright. Plain script;
ends with one JSON line.

    python benchmarks/serve.py                     # 2048² and 512² stacks (~2 min on a quiet 2-core CPU)
    python benchmarks/serve.py --sizes 256 --repeats 3   # a smoke run

For each stack size the page is opened at a 1024-pixel canvas and fitted (a 2048² stack shows at 1/2, so
the server composites the level-1 view; a 512² stack shows at 2×, level 0):

* ``toggle_ms``: a click on a visibility checkbox → the repainted canvas (the change goes to the server,
  the new state comes back, the view is composited through the prefix-cache ``Renderer`` and drawn);
  median of ``--repeats`` clicks on a middle layer.
* ``drag_fps``: an opacity slider dragged for 2 s (input events every animation frame, ~60 Hz): repaints
  drawn per second (the page keeps one view request in flight and asks for the latest value next).
* ``learned_ms``: a click on "Add (amortised)" with the shading preset → the canvas showing the layer.
* ``light_drag_fps`` (issue #24): on a second stack of the same size — the photograph and one surface layer (a
  dome's normal map over the whole canvas) — the light control's point dragged round the sphere for 2 s with
  pointer moves every animation frame (~60 Hz) between a real press and release: repaints drawn per second. Each is a
  preview view: the base from the level's cached prefix, the surface re-lit from its map. As the page does it, at the
  drag proxy's level (as an opacity drag: a 2048² stack fitted at ½ previews at 512², the release repaints at
  1024²); ``light_drag_full_fps``: every preview at the view's level (1024²); ``relief_drag_fps``: the layer's
  Relief slider dragged as an opacity slider is (×1…×2), at the drag proxy's level (``intensity_drag_fps``: its
  Intensity slider, the same way; ``gloss_drag_fps``: its Gloss slider, 0…1, the same way; ``glossy_light_drag_fps``:
  the light dragged again with that highlight committed, each preview adding a Blinn–Phong term; ``shadows_drag_fps``:
  its Shadows slider, 0…1, and ``shadowed_light_drag_fps`` the light dragged with shadows committed, each preview
  tracing them over the map's heights; ``occlusion_drag_fps``: its Occlusion slider, 0…1); ``point_drag_fps``:
  the light
  made a point light ("Point light") and dragged round a circle on the image the same way (each preview lights every
  pixel along its own vector to the point), at the drag proxy's level; ``spot_drag_fps``: that point given a cone
  ("Spot"), dragged the same way; ``shadowed_spot_drag_fps``: that spot casting shadows, dragged again.

The baseline in the same run is what a server without the cache and the view levels would do per click:
``render_stack`` of the whole stack at full size (``baseline_render_ms``, median of 3), before any transfer
or drawing. Targets (docs/BENCHMARKS.md): at 2048², toggle ≤ 100 ms (median), drag ≥ 20 repaints/s, learned
≤ 1.5 s, light drag ≥ 30 repaints/s. Measure on a quiet machine. ``--light-only`` runs the light drag alone.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))
from _common import machine_info, print_json_line  # noqa: E402

CHROMIUM = "/usr/bin/chromium"
FLAGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
CANVAS = 1024
ASIDE = 340  # the layers panel's width (app.css)


def make_stack(folder: Path, size: int) -> None:
    """8 layers on a ``size``² canvas: a photograph as the base, shading, colour, light, a masked patch, a
    tint, a screen glaze and a hidden layer — every kind and the common blends."""
    import numpy as np
    import torch
    from PIL import Image

    from lasagna.io.stack import Stack

    photo = Image.open(ROOT / "examples" / "photos" / "chelsea.png").convert("RGB").resize((size, size), Image.BICUBIC)
    base = torch.from_numpy(np.asarray(photo, np.float32) / 255.0).permute(2, 0, 1).contiguous()
    y, x = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    stack = Stack.from_image(base, name="Photo")
    stack.add_layer("shade", (0.6 + 0.8 * x * (1 - 0.5 * y))[None], blend="multiply", range=(0, 2), name="Shading")
    blob = torch.exp(-((x - 0.6) ** 2 + (y - 0.4) ** 2) / 0.02)
    stack.add_layer("paint", torch.stack([blob, 0.3 * blob, 0.6 + 0 * x]), alpha=(0.7 * blob)[None], name="Paint")
    stack.add_layer("glow", torch.stack([0.3 * y, 0.2 * y, 0.05 + 0 * y]), blend="plus", name="Glow")
    stack.add_layer("patch", torch.stack([x, y, 1 - x]), mask=(x > 0.5).float()[None] * 0.8, name="Patch")
    stack.add_solid("tint", (0.2, 0.4, 1.0, 0.15), name="Tint")
    stack.add_layer("glaze", (0.2 * torch.sin(20 * x) ** 2).expand(3, size, size).contiguous(), blend="screen")
    stack.add_solid("hidden", (1.0, 0.0, 0.0), visible=False, name="Hidden")
    stack.save(folder)


def make_surface_stack(folder: Path, size: int) -> None:
    """The photograph and one surface layer over it: a dome's normal map filling the canvas, lit from the top left."""
    import numpy as np
    import torch
    from PIL import Image

    from lasagna.io.stack import Stack

    photo = Image.open(ROOT / "examples" / "photos" / "chelsea.png").convert("RGB").resize((size, size), Image.BICUBIC)
    base = torch.from_numpy(np.asarray(photo, np.float32) / 255.0).permute(2, 0, 1).contiguous()
    y, x = torch.meshgrid(torch.linspace(1, -1, size), torch.linspace(-1, 1, size), indexing="ij")
    r2 = x * x + y * y
    inside = r2 < 0.9
    n = torch.stack([torch.where(inside, x, 0.0), torch.where(inside, y, 0.0), (1 - r2).clamp_min(0.1).sqrt()])
    stack = Stack.from_image(base, name="Photo")
    stack.add_surface("shape", n / n.norm(dim=0, keepdim=True), "top-left", name="Shape")
    stack.save(folder)


class Server:
    def __init__(self, folder: Path):
        import uvicorn

        from lasagna.serve import allowed_hosts, free_port
        from lasagna.serve.app import create_app
        from lasagna.serve.session import EditSession

        self.session = EditSession(folder)
        port = free_port("127.0.0.1")
        app = create_app(self.session, "bench", allowed_hosts("127.0.0.1", port))
        self.server = uvicorn.Server(
            uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="off")
        )
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        while not self.server.started:
            time.sleep(0.02)
        self.url = f"http://127.0.0.1:{port}/?token=bench"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)


WAIT = """
(pred) => new Promise((resolve) => { const tick = () => pred() ? resolve() : requestAnimationFrame(tick); tick(); })
"""

TOGGLE = """
async (id) => {
  const L = window.lasagna, wait = __WAIT__;
  const v = L.state.version, c = L.paints.count;
  const t0 = performance.now();
  document.querySelector(`#layers li[data-id="${id}"] .eye`).click();
  await wait(() => L.state.version > v && L.settled() && L.paints.count > c);
  return L.paints.last - t0;
}
""".replace("__WAIT__", WAIT.strip())

DRAG = """
async ([selector, seconds]) => {
  const L = window.lasagna;
  const slider = document.querySelector(selector);
  const c = L.paints.count, t0 = performance.now();
  let k = 0;
  await new Promise((resolve) => {
    const tick = () => {
      const t = performance.now() - t0;
      if (t > seconds * 1000) return resolve();
      slider.value = (0.5 + 0.5 * Math.sin(k++ / 10)).toFixed(3);
      slider.dispatchEvent(new Event("input", { bubbles: true }));
      requestAnimationFrame(tick);
    };
    tick();
  });
  const frames = L.paints.count - c, elapsed = (performance.now() - t0) / 1000;
  slider.dispatchEvent(new Event("change", { bubbles: true }));
  return [frames / elapsed, k / elapsed];
}
"""

LEARNED = """
async () => {
  const L = window.lasagna, wait = __WAIT__;
  const v = L.state.version, c = L.paints.count;
  const button = document.getElementById("add-learned");
  const why = document.getElementById("preset-why").textContent;
  if (button.disabled) throw new Error(`"Add (amortised)" is disabled: ${why}`);
  const t0 = performance.now();
  button.click();
  await wait(() => L.state.version > v && L.settled() && L.paints.count > c);
  return L.paints.last - t0;
}
""".replace("__WAIT__", WAIT.strip())


DRAG_LIGHT = """
async ([id, cx, cy, r, seconds]) => {
  const L = window.lasagna, sphere = document.getElementById(id);
  const c = L.paints.count, t0 = performance.now();
  let k = 0;
  await new Promise((resolve) => {
    const tick = () => {
      const t = performance.now() - t0;
      if (t > seconds * 1000) return resolve();
      const a = (2 * Math.PI * t) / 1000;  // round the sphere once a second
      const e = { clientX: cx + r * Math.cos(a), clientY: cy - r * Math.sin(a), pointerId: 1, bubbles: true };
      sphere.dispatchEvent(new PointerEvent("pointermove", e));
      k += 1;
      requestAnimationFrame(tick);
    };
    tick();
  });
  const elapsed = (performance.now() - t0) / 1000;
  return [(L.paints.count - c) / elapsed, k / elapsed];
}
"""


def measure_light(context, size: int, work: Path, seconds: float = 2.0) -> dict:
    """Repaints per second while the surface layer's light is dragged round its sphere (``light_drag_fps``)."""
    folder = work / f"surface{size}"
    make_surface_stack(folder, size)
    server = Server(folder)
    page = context.new_page()
    try:
        page.goto(server.url)
        page.wait_for_function("window.lasagna.state !== null && window.lasagna.paints.count > 0")
        page.wait_for_function("window.lasagna.settled()")
        page.locator('#layers li[data-id="shape"] .name').click()
        box = page.locator("#light-sphere").bounding_box()
        cx, cy, r = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2, 0.6 * box["width"] / 2

        def drag(duration: float, on: str = "light-sphere") -> tuple[float, float]:
            # A real press (the control captures the pointer), moves dispatched once per animation frame in the
            # page (~60 Hz, as a mouse reports them), a real release (the one change).
            page.mouse.move(cx + r, cy)
            page.mouse.down()
            fps, input_hz = page.evaluate(DRAG_LIGHT, [on, cx, cy, r, duration])
            page.mouse.up()
            page.wait_for_function("window.lasagna.settled() && window.lasagna.light === null")
            return fps, input_hz

        def set_slider(id: str, value: str) -> None:
            # A slider set and released (one change), and the page settled after it.
            v = page.evaluate("window.lasagna.state.version")
            page.evaluate(
                "([id, x]) => { const g = document.getElementById(id); g.value = x;"
                " g.dispatchEvent(new Event('change')); }",
                [id, value],
            )
            page.wait_for_function(f"window.lasagna.state.version > {v} && window.lasagna.settled()")

        drag(0.5)  # warm-up: the levels' renderers built, the prefixes cached, the maps' normals decoded
        fps, input_hz = drag(seconds)
        page.evaluate("window.lasagna.lightProxy = false")
        drag(0.5)
        full_fps, _ = drag(seconds)
        page.evaluate("window.lasagna.lightProxy = true")
        # The Relief slider dragged the same way as an opacity slider (input events every frame, ×1…×2), then
        # released (one change): each preview re-lights the stored map with its slopes times the gain.
        v = page.evaluate("window.lasagna.state.version")
        relief_fps, _ = page.evaluate(DRAG, ["#relief", seconds])
        page.wait_for_function(f"window.lasagna.state.version > {v} && window.lasagna.settled()")
        v = page.evaluate("window.lasagna.state.version")  # the Intensity slider likewise (×1…×2)
        intensity_fps, _ = page.evaluate(DRAG, ["#intensity", seconds])
        page.wait_for_function(f"window.lasagna.state.version > {v} && window.lasagna.settled()")
        v = page.evaluate("window.lasagna.state.version")  # the Gloss slider likewise (0…1), released where it ends
        gloss_fps, _ = page.evaluate(DRAG, ["#gloss", seconds])
        page.wait_for_function(f"window.lasagna.state.version > {v} && window.lasagna.settled()")
        # The light dragged again with that highlight on: each preview adds a Blinn–Phong term to the direct one.
        drag(0.5)
        glossy_fps, _ = drag(seconds)
        set_slider("gloss", "0")  # the highlight off again for the shadows and the point light
        # The Shadows slider dragged the same way (0…1: each preview traces the light over the map's heights), then
        # the light dragged with the shadows committed.
        v = page.evaluate("window.lasagna.state.version")
        shadows_fps, _ = page.evaluate(DRAG, ["#shadows", seconds])
        page.wait_for_function(f"window.lasagna.state.version > {v} && window.lasagna.settled()")
        drag(0.5)
        shadowed_fps, _ = drag(seconds)
        set_slider("shadows", "0")
        v = page.evaluate("window.lasagna.state.version")  # the Occlusion slider (0…1), its sky share traced once
        occlusion_fps, _ = page.evaluate(DRAG, ["#occlusion", seconds])
        page.wait_for_function(f"window.lasagna.state.version > {v} && window.lasagna.settled()")
        set_slider("occlusion", "0")
        # A point light (one change to make it one), then dragged round a circle on the image: each preview lights
        # every pixel along its own vector to the point.
        v = page.evaluate("window.lasagna.state.version")
        page.check("#point-light")
        page.wait_for_function(f"window.lasagna.state.version > {v} && window.lasagna.settled()")
        box = page.locator("#canvas").bounding_box()
        cx, cy, r = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2, 0.25 * min(box["width"], box["height"])
        drag(0.5, "canvas")
        point_fps, _ = drag(seconds, "canvas")
        # The same point given a cone ("Spot": one change), dragged the same way: light and aim move together.
        v = page.evaluate("window.lasagna.state.version")
        page.check("#spot-light")
        page.wait_for_function(f"window.lasagna.state.version > {v} && window.lasagna.settled()")
        drag(0.5, "canvas")
        spot_fps, _ = drag(seconds, "canvas")
        set_slider("shadows", "1")  # the spot dragged again, casting shadows: each preview traces from the point
        drag(0.5, "canvas")
        shadowed_spot_fps, _ = drag(seconds, "canvas")
        level = page.evaluate(
            "(() => { const z = window.lasagna.zoom; return z >= 1 ? 0 : Math.floor(Math.log2(1 / z)); })()"
        )
        return {
            "point_drag_fps": round(point_fps, 1),
            "spot_drag_fps": round(spot_fps, 1),
            "light_drag_fps": round(fps, 1),
            "light_drag_input_hz": round(input_hz, 1),
            "light_drag_full_fps": round(full_fps, 1),
            "relief_drag_fps": round(relief_fps, 1),
            "intensity_drag_fps": round(intensity_fps, 1),
            "gloss_drag_fps": round(gloss_fps, 1),
            "glossy_light_drag_fps": round(glossy_fps, 1),
            "shadows_drag_fps": round(shadows_fps, 1),
            "shadowed_light_drag_fps": round(shadowed_fps, 1),
            "shadowed_spot_drag_fps": round(shadowed_spot_fps, 1),
            "occlusion_drag_fps": round(occlusion_fps, 1),
            "light_view_level": level,
        }
    finally:
        page.close()
        server.stop()


def measure(context, size: int, repeats: int, work: Path) -> dict:
    import torch

    from lasagna.io.render import render_stack
    from lasagna.io.stack import load_stack

    folder = work / f"stack{size}"
    make_stack(folder, size)
    stack = load_stack(folder)
    render_stack(stack)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        render_stack(stack)
        times.append(1000 * (time.perf_counter() - t0))
    del stack
    torch.set_num_threads(torch.get_num_threads())
    server = Server(folder)
    page = context.new_page()
    try:
        page.goto(server.url)
        page.wait_for_function(
            "window.lasagna.state !== null && window.lasagna.paints.count > 0 && window.lasagna.settled()"
        )
        page.wait_for_function("window.lasagna.presets.length > 0")
        level = page.evaluate(
            "(() => { const z = window.lasagna.zoom; return z >= 1 ? 0 : Math.floor(Math.log2(1 / z)); })()"
        )
        zoom = page.evaluate("window.lasagna.zoom")
        page.evaluate(TOGGLE, "glow")  # warm-up: every view level's renderer built, caches filled
        page.evaluate(TOGGLE, "glow")
        toggles = [page.evaluate(TOGGLE, "glow") for _ in range(repeats)]
        page.wait_for_function("window.lasagna.settled()")
        drag_fps, input_hz = page.evaluate(DRAG, ['#layers li[data-id="paint"] .opacity', 2.0])
        page.wait_for_function("window.lasagna.settled()")
        page.select_option("#preset", "shading")
        learned = page.evaluate(LEARNED)
        return {
            "size": size,
            "zoom": zoom,
            "view_level": level,
            "toggle_ms": round(statistics.median(toggles), 1),
            "toggle_ms_all": [round(t, 1) for t in toggles],
            "drag_fps": round(drag_fps, 1),
            "drag_input_hz": round(input_hz, 1),
            "learned_ms": round(learned, 1),
            "baseline_render_ms": round(statistics.median(times), 1),
        }
    finally:
        page.close()
        server.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[2048, 512])
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--light-only", action="store_true", help="only the light drag on the surface stack")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    from lasagna.heap import tune_heap

    tune_heap("server")  # the server runs in this process: the profile `lasagna serve` sets before anything renders

    work = Path(tempfile.mkdtemp(prefix="lasagna-serve-bench-"))
    profile = work / "chromium"
    rows = []
    try:
        with sync_playwright() as p:
            context = p.chromium.launch_persistent_context(
                str(profile),
                executable_path=CHROMIUM,
                headless=True,
                args=FLAGS,
                viewport={"width": CANVAS + ASIDE, "height": CANVAS + 80},
            )
            for size in args.sizes:
                row = {"size": size} if args.light_only else measure(context, size, args.repeats, work)
                row.update(measure_light(context, size, work))
                rows.append(row)
                print(row, file=sys.stderr)
            context.close()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    big = rows[0]
    keys = [
        "toggle_ms",
        "drag_fps",
        "learned_ms",
        "baseline_render_ms",
        "light_drag_fps",
        "light_drag_full_fps",
        "relief_drag_fps",
        "intensity_drag_fps",
        "gloss_drag_fps",
        "glossy_light_drag_fps",
        "shadows_drag_fps",
        "shadowed_light_drag_fps",
        "shadowed_spot_drag_fps",
        "occlusion_drag_fps",
        "point_drag_fps",
        "spot_drag_fps",
    ]
    print_json_line(
        {
            "benchmark": "serve",
            **machine_info(),
            "threads": int(os.environ.get("OMP_NUM_THREADS", "0")) or None,
            **{k: big[k] for k in keys if k in big},
            "sizes": rows,
        }
    )


if __name__ == "__main__":
    main()
