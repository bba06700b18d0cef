// Lasagna's layer editor. Every change goes to the server (lasagna.serve), which runs the engine's own
// code and answers with the new state; the page draws what the server composites (no second compositor).
"use strict";

const token = new URLSearchParams(location.search).get("token") || "";
const $ = (id) => document.getElementById(id);
const SWATCHES = { warm: "#ffb35c", cool: "#7fb2ff", white: "#ffffff" };

const ui = {
  state: null,          // the server's state (document, version, history, job)
  presets: [],
  lights: {},           // the named lights, {label: {az, el}} in degrees (the server's NAMED_DIRECTIONS)
  selected: null,       // layer id
  zoom: 1, panX: 0, panY: 0, fit: true,
  solo: null,
  split: false,
  drag: null,           // {id, value} while an opacity slider is dragged (a transient view, not a change)
  light: null,          // {id, text, source} while a surface layer's light (or source light) is dragged (a view)
  relief: null,         // a surface layer's relief gain while its slider is dragged: { id, value }
  ambient: null,        // a surface layer's ambient term while its slider is dragged: { id, value }
  colour: null,         // a surface layer's light colour while its picker is moved: { id, value: "#rrggbb" }
  intensity: null,      // a surface layer's light intensity while its slider is dragged: { id, value }
  gloss: null,          // a surface layer's gloss (highlight strength) while its slider is dragged: { id, value }
  shadows: null,        // a surface layer's cast-shadow strength while its slider is dragged: { id, value }
  occlusion: null,      // a surface layer's ambient-occlusion strength while its slider is dragged: { id, value }
  shadow_depth: null,   // the heights its shadows and occlusion trace, times this, while its slider is dragged
  lightWhich: {},       // per relight surface layer: which light its sphere moves, "light" or "source"
  normals: null,        // a surface layer's id while the view shows its normal map (its relief applied)
  occlusionMap: null,   // a surface layer's id while the view shows its ambient occlusion (the share of the sky)
  lightProxy: true,     // a light drag previews at the drag proxy's level (dragLevel); false: at the view's level
  placing: null,        // {id, rect, z, point} while a surface layer's point light is placed by dragging on the canvas
  condition: null,
  image: null,          // the last view: {canvas, level, w, h}
  before: null,
  paints: { count: 0, last: 0 },
};
window.lasagna = ui;    // for tests and benchmarks: the state, paint counter and pixel reader

// ---- the server ---------------------------------------------------------------------------------

async function api(path, options = {}) {
  const headers = Object.assign({ "X-Lasagna-Token": token }, options.headers || {});
  const response = await fetch(path, Object.assign({}, options, { headers }));
  if (!response.ok) {
    let message = response.statusText;
    try { message = (await response.json()).error || message; } catch (e) { /* not JSON */ }
    const err = new Error(message);
    err.status = response.status;
    throw err;
  }
  return response;
}

async function change(body) {
  body.version = ui.state.version;
  return apply(() => api("api/change", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) }));
}

async function apply(request) {
  try {
    const response = await request();
    setState(await response.json());
    status("");
    return true;
  } catch (err) {
    fail(err);
    return false;
  }
}

function status(text, error = false) {
  $("status").textContent = text;
  $("status").className = error ? "error" : "";
}

function fail(err) {
  status(err.message, true);
  $("reload").hidden = err.status !== 409;
}

async function refresh() {
  const response = await api("api/state");
  setState(await response.json());
}

// ---- state → panels -------------------------------------------------------------------------------

function setState(state) {
  const first = ui.state === null;
  ui.state = state;
  const ids = allLayers(state.document.layers).map((l) => l.id);
  if (ui.selected && !ids.includes(ui.selected)) ui.selected = null;
  if (ui.solo && !ids.includes(ui.solo)) ui.solo = null;
  if (ui.normals && !(ui.normals in state.surfaces)) ui.normals = null;
  if (ui.occlusionMap && !(ui.occlusionMap in state.surfaces)) ui.occlusionMap = null;
  $("folder").textContent = state.folder + (state.dirty ? " •" : "");
  $("undo").disabled = !state.undo;
  $("undo").title = state.undo ? `Undo ${state.undo}` : "Nothing to undo";
  $("redo").disabled = !state.redo;
  $("redo").title = state.redo ? `Redo ${state.redo}` : "Nothing to redo";
  $("save").disabled = !state.dirty;
  for (const kind of ["ora", "psd", "png"]) $(`export-${kind}`).href = `api/export/${kind}?token=${encodeURIComponent(token)}`;
  drawLayers();
  drawProps();
  if (first) fitView();
  paint();
}

// Every layer of the tree, groups' layers too (depth first, a group before its layers).
function allLayers(layers) {
  return layers.flatMap((l) => [l, ...(l.kind === "group" ? allLayers(l.layers) : [])]);
}

function findLayer(id) {
  return allLayers(ui.state.document.layers).find((l) => l.id === id);
}

function layerRow(layer, index, n, depth = 0) {
  const li = document.createElement("li");
  li.dataset.id = layer.id;
  li.style.paddingLeft = `${depth * 1.2}em`;  // a group's layers are indented under it
  li.draggable = true;
  if (layer.id === ui.selected) li.classList.add("selected");
  const stamp = ui.state.version;
  li.innerHTML = `
    <input type="checkbox" class="eye" title="visible" ${layer.visible ? "checked" : ""}>
    <img alt="" src="api/layers/${encodeURIComponent(layer.id)}/thumb.png?v=${stamp}&token=${encodeURIComponent(token)}">
    <span class="name" title="${layer.kind}: ${layer.id}"></span>
    <span class="tools">
      <button class="up" title="Move up" ${index === n - 1 ? "disabled" : ""}>▲</button><button class="down" title="Move down" ${index === 0 ? "disabled" : ""}>▼</button><button class="solo" title="Solo">S</button><button class="group" title="${layer.kind === "group" ? "Ungroup" : "Group (wrap in a new group)"}">${layer.kind === "group" ? "U" : "G"}</button><button class="del" title="Delete">×</button>
    </span>
    <span class="row2">
      <select class="blend" aria-label="blend"></select>
      <input type="range" class="opacity" min="0" max="1" step="0.01" aria-label="opacity">
      <span class="opv"></span>
    </span>`;
  li.querySelector(".name").textContent = layer.name + (ui.state.not_rendered[layer.id] ? " (not rendered)" : "");
  const blend = li.querySelector(".blend");
  for (const b of ui.state.blends) blend.add(new Option(b, b, false, b === layer.blend));
  const op = li.querySelector(".opacity");
  op.value = layer.opacity;
  li.querySelector(".opv").textContent = Math.round(layer.opacity * 100) + "%";
  if (ui.solo === layer.id) li.querySelector(".solo").classList.add("chosen");
  li.addEventListener("click", (e) => {
    if (e.target.closest("input, select, button")) return;
    ui.selected = layer.id;
    if (ui.normals && ui.normals !== layer.id) { ui.normals = null; paint(); }
    if (ui.occlusionMap && ui.occlusionMap !== layer.id) { ui.occlusionMap = null; paint(); }
    drawLayers(); drawProps();
  });
  li.querySelector(".eye").addEventListener("change", (e) => change({ op: "set", id: layer.id, changes: { visible: e.target.checked } }));
  blend.addEventListener("change", () => change({ op: "set", id: layer.id, changes: { blend: blend.value } }));
  op.addEventListener("input", () => {
    ui.drag = { id: layer.id, value: parseFloat(op.value) };
    li.querySelector(".opv").textContent = Math.round(op.value * 100) + "%";
    paint();
  });
  op.addEventListener("change", async () => {
    await change({ op: "set", id: layer.id, changes: { opacity: parseFloat(op.value) } });
    ui.drag = null;
    paint();
  });
  li.querySelector(".up").addEventListener("click", () => change({ op: "move", id: layer.id, index: index + 1 }));
  li.querySelector(".down").addEventListener("click", () => change({ op: "move", id: layer.id, index: index - 1 }));
  li.querySelector(".solo").addEventListener("click", () => { ui.solo = ui.solo === layer.id ? null : layer.id; drawLayers(); paint(); });
  li.querySelector(".del").addEventListener("click", () => change({ op: "delete", id: layer.id }));
  li.querySelector(".group").addEventListener("click", () => change(layer.kind === "group" ? { op: "ungroup", id: layer.id } : { op: "group", ids: [layer.id] }));
  // The row drags to reorder, but not from its controls: a slider dragged inside a draggable row would
  // start a row drag and lose the slider.
  li.addEventListener("pointerdown", (e) => { li.draggable = !e.target.closest("input, select, button"); });
  li.addEventListener("dragstart", (e) => { e.dataTransfer.setData("text/plain", layer.id); });
  li.addEventListener("dragover", (e) => { e.preventDefault(); li.classList.add("dragover"); });
  li.addEventListener("dragleave", () => li.classList.remove("dragover"));
  li.addEventListener("drop", (e) => {
    e.preventDefault();
    li.classList.remove("dragover");
    const id = e.dataTransfer.getData("text/plain");
    if (id && id !== layer.id) change({ op: "move", id, index });  // dropped on a row: take its place
  });
  return li;
}

function drawLayers() {
  const list = $("layers");
  list.textContent = "";
  const rows = (layers, depth) => {
    for (let i = layers.length - 1; i >= 0; i--) {
      list.appendChild(layerRow(layers[i], i, layers.length, depth));
      if (layers[i].kind === "group") rows(layers[i].layers, depth + 1);
    }
  };
  rows(ui.state.document.layers, 0);
  $("solo-label").textContent = ui.solo ? `solo: ${ui.solo}` : "";
}

// A surface layer's maps for a game or 2D-lighting engine, on the canvas, as `lasagna export --normal-map`
// (`--directx`: +Y down), `--height-map` and `--occlusion-map` write them.
function mapDownloads(layer) {
  const row = document.createElement("div");
  row.className = "map-downloads";
  row.append("Download ");
  const maps = [["normal map", "normal-map", ""], ["DirectX", "normal-map", "&directx=1"],
                ["height", "height-map", ""], ["occlusion", "occlusion-map", ""]];
  for (const [text, kind, extra] of maps) {
    const a = document.createElement("a");
    a.textContent = text;
    a.href = `api/export/${kind}?id=${encodeURIComponent(layer.id)}${extra}&token=${encodeURIComponent(token)}`;
    a.setAttribute("download", "");
    a.dataset.map = kind + extra;
    row.append(a, " ");
  }
  return row;
}

function field(label, input) {
  const l = document.createElement("label");
  l.append(label + " ", input);
  return l;
}

function numberInput(value, onChange, step = "any") {
  const input = document.createElement("input");
  input.type = "number"; input.step = step; input.value = value;
  input.addEventListener("change", () => onChange(parseFloat(input.value)));
  return input;
}

function drawProps() {
  const box = $("props");
  box.textContent = "";
  ui.placing = null;  // a surface layer's light panel sets it again while its light is a point
  const layer = findLayer(ui.selected);
  if (!layer) { box.innerHTML = '<p class="hint">Select a layer.</p>'; return; }
  const set = (changes) => change({ op: "set", id: layer.id, changes });
  const name = document.createElement("input");
  name.value = layer.name; name.id = "prop-name";
  name.addEventListener("change", () => set({ name: name.value }));
  box.append(field("Name", name));
  const info = document.createElement("div");
  info.className = "hint";
  info.textContent = `${layer.kind} layer · id ${layer.id}`;
  box.append(info);
  if (layer.range) {  // a group has none
    const [lo, hi] = layer.range;
    box.append(field("Range", numberInput(lo, (v) => set({ range: [v, layer.range[1]] }))));
    box.lastChild.append(" – ", numberInput(hi, (v) => set({ range: [layer.range[0], v] })));
  }
  box.append(field("Offset x", numberInput(layer.offset.x, (v) => set({ offset: { x: v, y: layer.offset.y } }), "1")));
  box.lastChild.append(" y ", numberInput(layer.offset.y, (v) => set({ offset: { x: layer.offset.x, y: v } }), "1"));
  if (layer.mask) {
    const remove = document.createElement("button");
    remove.textContent = "Remove mask";
    remove.addEventListener("click", () => set({ mask: null }));
    box.append(field(`Mask ${layer.mask}`, remove));
  }
  if (layer.kind === "surface") box.append(lightControl(layer));
  if (layer.kind === "learned") {
    const preset = ui.presets.find((p) => p.name === layer.preset);
    const cond = document.createElement("select");
    cond.id = "prop-condition";
    for (const v of (preset && preset.vocabulary) || [layer.condition.label]) cond.add(new Option(v, v, false, v === layer.condition.label));
    cond.addEventListener("change", () => set({ condition: Object.assign({}, layer.condition, { label: cond.value }) }));
    box.append(field(`Preset ${layer.preset}, condition`, cond));
    const settings = document.createElement("textarea");
    settings.id = "prop-settings"; settings.rows = 6; settings.spellcheck = false;
    settings.value = JSON.stringify(layer.settings, null, 1);
    const applySettings = document.createElement("button");
    applySettings.textContent = "Apply settings";
    applySettings.addEventListener("click", () => {
      let value;
      try { value = JSON.parse(settings.value); } catch (e) { status(`settings: not JSON (${e.message})`, true); return; }
      set({ settings: value });
    });
    box.append(field("Settings (used by Re-render)", settings), applySettings);
    const steps = numberInput(20, () => {}, "1");
    steps.id = "refine-steps";
    const refine = document.createElement("button");
    refine.textContent = "Refine (per-image)"; refine.id = "refine";
    refine.addEventListener("click", () => startJob("refine", layer.id, parseInt(steps.value, 10)));
    const rerender = document.createElement("button");
    rerender.textContent = "Re-render"; rerender.id = "rerender";
    rerender.addEventListener("click", () => startJob("rerender", layer.id));
    box.append(field("Steps", steps), refine, " ", rerender);
  }
}

// ---- a surface layer's light ----------------------------------------------------------------------
// A shaded sphere whose highlight follows a point dragged on its disc: the point (x, y) (y up, radius r ≤ 1)
// is the light's direction seen from the viewer, az = atan2(y, x) from +x toward +y and el = asin(r) from the
// view axis (lasagna.document.condition). Pointer moves are read once per animation frame; each frame sets a
// transient light (ui.light) and asks for a repaint, and paint() keeps one view request in flight, the latest
// light asked next. While dragging, the view is a preview (/api/view?light=…: nothing changes on the server,
// no undo step); releasing commits the light with one "light" change, one undo step.

const SPHERE_SIDE = 120;
const MAX_DRAG_ELEVATION = 89;  // el must stay below 90° (the light would graze the image plane)

function lightText(az, el) {
  return `az=${az.toFixed(1)},el=${el.toFixed(1)}`;
}

function drawSphere(canvas, az, el, ambient) {
  const ctx = canvas.getContext("2d"), n = canvas.width, R = n / 2 - 2, c = n / 2;
  const a = (az * Math.PI) / 180, e = (el * Math.PI) / 180;
  const lx = Math.sin(e) * Math.cos(a), ly = Math.sin(e) * Math.sin(a), lz = Math.cos(e);
  const img = ctx.createImageData(n, n);
  for (let py = 0; py < n; py++) {
    for (let px = 0; px < n; px++) {
      const x = (px + 0.5 - c) / R, y = (c - py - 0.5) / R, r2 = x * x + y * y;
      if (r2 > 1) continue;
      const s = ambient + (1 - ambient) * Math.max(0, x * lx + y * ly + Math.sqrt(1 - r2) * lz);
      const k = 4 * (py * n + px);
      img.data[k] = img.data[k + 1] = img.data[k + 2] = Math.round(255 * s);
      img.data[k + 3] = 255;
    }
  }
  ctx.putImageData(img, 0, 0);
  ctx.beginPath();
  ctx.arc(c + R * lx, c - R * ly, 5, 0, 2 * Math.PI);
  ctx.strokeStyle = "#e0a030"; ctx.lineWidth = 2; ctx.stroke();
}

// A surface layer's light field as a slider (input #id, its value in #id-value): dragging previews it (ui[id], sent
// as /api/view?id=LAYER:V), releasing records one "light" change of ``field``. ``scale`` maps the field's value to
// the slider's position and back (``at``, ``of``) and shows it (``text``), within [min, max] by ``step``.
function lightSlider(layer, lit, label, id, field_, value, scale) {
  const input = document.createElement("input");
  input.type = "range"; input.id = id; input.min = scale.min; input.max = scale.max; input.step = scale.step;
  input.value = String(scale.at(value));
  const shown = document.createElement("span");
  shown.id = `${id}-value`;
  shown.textContent = scale.text(value);
  const current = () => scale.of(parseFloat(input.value));
  input.addEventListener("input", () => {
    ui[id] = { id: layer.id, value: current() };
    shown.textContent = scale.text(ui[id].value);
    paint();
  });
  input.addEventListener("change", async () => {
    await change({ op: "light", id: layer.id, light: lit.light, [field_]: current() });
    ui[id] = null;
    paint();
  });
  const f = field(label, input);
  f.append(" ", shown);
  return f;
}

// A gain ×1/4…×8 on a log slider (relief, intensity).
const GAIN = {
  min: "-2", max: "3", step: "0.05", at: Math.log2, of: (x) => Math.round(2 ** x * 1000) / 1000,
  text: (v) => `×${v.toFixed(2)}`,
};
function gainSlider(layer, lit, label, id, field_, value) {
  return lightSlider(layer, lit, label, id, field_, value, GAIN);
}

// The highlight (Photoshop's Lighting Effects "Gloss", Blender's specular): a Blinn–Phong term of strength g in
// [0, 1], previewed while its slider moves (/api/view?gloss=…), one change on release; its exponent ("Shininess",
// larger: smaller and sharper) a number, one change when it is set.
const UNIT = { min: "0", max: "1", step: "0.05", at: (v) => v, of: (x) => x, text: (v) => v.toFixed(2) };
function glossControl(layer, lit) {
  const span = document.createElement("span");
  const shininess = numberInput(lit.shininess, (v) => change({ op: "light", id: layer.id, light: lit.light, shininess: v }), "1");
  shininess.id = "shininess"; shininess.min = "1"; shininess.max = "1024";
  span.append(lightSlider(layer, lit, "Gloss", "gloss", "gloss", lit.gloss, UNIT), field(" shininess", shininess));
  return span;
}

function lightControl(layer) {
  const lit = ui.state.surfaces[layer.id];
  const box = document.createElement("div");
  box.id = "light";
  const sphere = document.createElement("canvas");
  sphere.id = "light-sphere"; sphere.width = sphere.height = SPHERE_SIDE;
  sphere.title = "Drag to move the light";
  const readout = document.createElement("div");
  readout.id = "light-readout";
  readout.textContent = lit.light;
  const show = document.createElement("input");
  show.type = "checkbox"; show.id = "normal-map"; show.checked = ui.normals === layer.id;
  show.addEventListener("change", () => {
    ui.normals = show.checked ? layer.id : null;
    if (show.checked) { ui.occlusionMap = null; showSky.checked = false; }
    paint();
  });
  // The share of the sky its heights let each pixel see (what Occlusion darkens), grey: white open.
  const showSky = document.createElement("input");
  showSky.type = "checkbox"; showSky.id = "occlusion-map"; showSky.checked = ui.occlusionMap === layer.id;
  showSky.addEventListener("change", () => {
    ui.occlusionMap = showSky.checked ? layer.id : null;
    if (showSky.checked) { ui.normals = null; show.checked = false; }
    paint();
  });
  const info = document.createElement("div");
  info.className = "hint";
  info.textContent = lit.source_light ? `relight from ${lit.source_light}` : "shading";
  // The relief gain (glTF's normalTexture.scale): the map's slopes times it before it is lit.
  const reliefField = gainSlider(layer, lit, "Relief", "relief", "relief", lit.relief);
  // The ambient term a of a + (1 − a)·max(0, n·l) (Photoshop's Lighting Effects "Ambience"): how dark the side
  // away from the light gets, and how much a shading layer darkens what it covers. A relight ratio needs a > 0.
  const ambient = document.createElement("input");
  ambient.type = "range"; ambient.id = "ambient"; ambient.max = "0.95"; ambient.step = "0.01";
  ambient.min = lit.source_light ? "0.01" : "0";
  ambient.value = String(lit.ambient);
  const ambientValue = document.createElement("span");
  ambientValue.id = "ambient-value";
  ambientValue.textContent = lit.ambient.toFixed(2);
  ambient.addEventListener("input", () => {
    ui.ambient = { id: layer.id, value: parseFloat(ambient.value) };
    ambientValue.textContent = ui.ambient.value.toFixed(2);
    paint();
  });
  ambient.addEventListener("change", async () => {
    await change({ op: "light", id: layer.id, light: lit.light, ambient: parseFloat(ambient.value) });
    ui.ambient = null;
    paint();
  });
  const ambientField = field("Ambient", ambient);
  ambientField.append(" ", ambientValue);
  box.append(sphere, readout, info, reliefField, ambientField);
  // The light's colour (its direct term; the ambient stays white): a colour input, previewed while it is moved
  // (/api/view?color=…), one change when it is closed.
  const colour = document.createElement("input");
  colour.type = "color"; colour.id = "light-color";
  const hex = (c) => "#" + c.map((v) => Math.round(v * 255).toString(16).padStart(2, "0")).join("");
  const rgb = (h) => [1, 3, 5].map((k) => parseInt(h.slice(k, k + 2), 16) / 255);
  colour.value = hex(lit.light_color);
  colour.addEventListener("input", () => { ui.colour = { id: layer.id, value: colour.value }; paint(); });
  colour.addEventListener("change", async () => {
    await change({ op: "light", id: layer.id, light: lit.light, light_color: rgb(colour.value) });
    ui.colour = null;
    paint();
  });
  // The light's intensity k (Photoshop's Lighting Effects "Intensity"): its direct term times k; above 1 a shading
  // layer brightens where the light falls.
  const intensityField = gainSlider(layer, lit, "Intensity", "intensity", "light_intensity", lit.light_intensity);
  // Cast shadows (Sprite Lamp's self-shadowing): each light's direct term, where the surface's own heights hide the
  // light, times 1 − s; previewed while the slider moves (/api/view?shadows=…), one change on release.
  const shadowsField = lightSlider(layer, lit, "Shadows", "shadows", "shadows", lit.shadows, UNIT);
  // Ambient occlusion: the ambient term, where the surface's heights hide the sky (creases), times 1 − o·(1 − A).
  const occlusionField = lightSlider(layer, lit, "Occlusion", "occlusion", "occlusion", lit.occlusion, UNIT);
  // The heights both trace, times a gain (longer shadows, deeper creases; the shading unchanged).
  const depthField = gainSlider(layer, lit, "Shadow depth", "shadow_depth", "shadow_depth", lit.shadow_depth);
  box.append(field("Colour", colour), intensityField, glossControl(layer, lit), shadowsField, depthField, occlusionField);
  box.append(field("Show normal map", show), field("Show occlusion", showSky));
  box.append(mapDownloads(layer));
  box.append(pointControl(layer, lit));
  box.append(extraLightsControl(layer, lit));
  // A relight's sphere moves either light: the target, or the source the ratio divides by (fitted to the image,
  // and off where the estimate was: a source light too frontal makes the whole relight too dark).
  // The choice is kept per layer across the control's rebuilds (every change rebuilds the panel).
  let moving = lit.source_light ? (ui.lightWhich[layer.id] || "light") : "light";
  const shown = () => (moving === "source" ? lit.source : [lit.az, lit.el]);
  if (lit.source_light) {
    const which = document.createElement("select");
    which.id = "light-which";
    which.add(new Option("the light", "light"));
    which.add(new Option("the source light", "source"));
    which.value = moving;
    which.addEventListener("change", () => {
      moving = ui.lightWhich[layer.id] = which.value;
      readout.textContent = moving === "source" ? lit.source_light : lit.light;
      drawSphere(sphere, ...shown(), lit.ambient);
    });
    box.append(field("Drag", which));
  }
  // Moving the source light only divides the old surface by another light; read again told it, the surface's
  // relief is found for the light the user gives (the preset's told estimator: lasagna edit --from). One step.
  // "Within ±°" says the light is a rough reading (lasagna light --within): its elevation is fused with the
  // estimator's own fit, and the layer then holds the fused light. Empty: the light as it is, exactly.
  if (lit.rereadable) {
    const reread = document.createElement("button");
    reread.id = "reread";
    reread.textContent = "Read again from this source light";
    reread.title = "Estimate the surface again, told the source light as it is now (about a second)";
    const within = numberInput("", () => {}, "0.5");
    within.id = "reread-within";
    within.min = "0.5"; within.max = "90"; within.placeholder = "exact";
    within.title = "How far off the source light may be, in degrees (empty: exact)";
    reread.addEventListener("click", async () => {
      reread.disabled = true;
      status("reading the surface again…");
      const body = { op: "reread", id: layer.id };
      if (within.value !== "") body.within = parseFloat(within.value);
      await change(body);
      reread.disabled = false;
    });
    box.append(reread, field(" within ±°", within));
  }
  readout.textContent = moving === "source" ? lit.source_light : lit.light;
  drawSphere(sphere, ...shown(), lit.ambient);

  let at = null, frame = 0, dragging = false;
  const direction = () => {  // the pointer's place on the disc → (az, el) in degrees
    const r = sphere.getBoundingClientRect(), R = r.width / 2 - 2;
    let x = (at.x - r.left - r.width / 2) / R, y = (r.top + r.height / 2 - at.y) / R;
    const len = Math.hypot(x, y);
    if (len > 1) { x /= len; y /= len; }
    const el = Math.min(MAX_DRAG_ELEVATION, (Math.asin(Math.min(1, len)) * 180) / Math.PI);
    const az = (((Math.atan2(y, x) * 180) / Math.PI) % 360 + 360) % 360;
    return [az, el];
  };
  const step = () => {
    frame = 0;
    const [az, el] = direction();
    ui.light = { id: layer.id, text: lightText(az, el), source: moving === "source" };
    readout.textContent = ui.light.text;
    drawSphere(sphere, az, el, lit.ambient);
    paint();
  };
  sphere.addEventListener("pointerdown", (e) => {
    e.preventDefault();
    sphere.setPointerCapture(e.pointerId);
    dragging = true; at = { x: e.clientX, y: e.clientY };
    frame = requestAnimationFrame(step);
  });
  sphere.addEventListener("pointermove", (e) => {
    if (!dragging) return;
    at = { x: e.clientX, y: e.clientY };
    if (!frame) frame = requestAnimationFrame(step);  // at most one update per frame; the latest point wins
  });
  const release = async (e) => {
    if (!dragging) return;
    dragging = false;
    if (frame) { cancelAnimationFrame(frame); frame = 0; }
    at = { x: e.clientX, y: e.clientY };
    const [az, el] = direction();
    ui.light = { id: layer.id, text: lightText(az, el), source: moving === "source" };
    await change(moving === "source"
      ? { op: "light", id: layer.id, light: lit.light, source_light: ui.light.text }
      : { op: "light", id: layer.id, light: ui.light.text });
    ui.light = null;
    paint();
  };
  sphere.addEventListener("pointerup", release);
  sphere.addEventListener("pointercancel", release);
  return box;
}

// ---- more lights -----------------------------------------------------------------------------------
// A surface layer's extra lights (Lighting Effects' several lights): each one's direct term is added to the layer's
// own. One row per light — its text (a named light, az=…,el=… or x=…,y=…,z=…), colour and intensity, and a remove
// button; "Add light" adds the key light's opposite at half intensity (a fill). Every edit commits the whole list
// as one "light" change, one undo step.

function extraLightsControl(layer, lit) {
  const box = document.createElement("div");
  box.id = "extra-lights";
  const hex = (c) => "#" + c.map((v) => Math.round(v * 255).toString(16).padStart(2, "0")).join("");
  const rgb = (h) => [1, 3, 5].map((k) => parseInt(h.slice(k, k + 2), 16) / 255);
  // Edits start from the current state (a rebuilt panel's old input may still send a change as it goes) and
  // commit only what differs from it.
  const current = () => ui.state.surfaces[layer.id].extra_lights;
  const commit = (lights) => {
    if (JSON.stringify(lights) === JSON.stringify(current())) return;
    change({ op: "light", id: layer.id, light: lit.light, extra_lights: lights });
  };
  const edit = (i, fields) => current().map((x, j) => (j === i ? Object.assign({}, x, fields) : x));
  lit.extra_lights.forEach((e, i) => {
    const row = document.createElement("div");
    row.className = "extra-light";
    const text = document.createElement("input");
    text.className = "extra-light-text"; text.value = e.light; text.size = 16;
    const colour = document.createElement("input");
    colour.type = "color"; colour.className = "extra-light-color"; colour.value = hex(e.color);
    const k = numberInput(e.intensity, () => {}, "0.05");
    k.className = "extra-light-intensity"; k.min = "0.05"; k.max = "8";
    const remove = document.createElement("button");
    remove.textContent = "×"; remove.className = "extra-light-remove"; remove.title = "Remove this light";
    text.addEventListener("change", () => commit(edit(i, { light: text.value.trim() })));
    colour.addEventListener("change", () => commit(edit(i, { color: rgb(colour.value) })));
    k.addEventListener("change", () => commit(edit(i, { intensity: parseFloat(k.value) })));
    remove.addEventListener("click", () => commit(current().filter((_, j) => j !== i)));
    row.append(text, " ", colour, " ×", k, " ", remove);
    box.append(row);
  });
  const add = document.createElement("button");
  add.id = "add-light"; add.textContent = "Add light";
  add.title = "One more light, added to this one's: the opposite direction at half intensity, to edit";
  add.disabled = lit.extra_lights.length >= 8;
  add.addEventListener("click", () => commit([
    ...current(), { light: lightText((lit.az + 180) % 360, lit.el), color: [1, 1, 1], intensity: 0.5 },
  ]));
  box.append(add);
  return box;
}

// ---- a point light -------------------------------------------------------------------------------
// A surface layer's light may be a point x=…,y=…,z=… (lasagna.document.condition): x, y fractions of the layer
// from its top-left, z its height in units of the layer's longer side. "Point light" turns the light into the
// point one unit from the layer's centre along the current direction (and back into that direction); while it is
// on, dragging on the canvas moves the point (a preview per frame, one change on release, as the sphere does) and
// the Height slider (log scale) raises or lowers it. The point is drawn on the canvas as a ring.
// "Spot" gives the point a cone (…,cone=C,ax=…,ay=…,blend=B: a spot light aimed at (ax, ay), at first the point
// beneath it): the Cone and Softness sliders set C and B; a drag moves the light and its aim together, a
// shift-drag moves the aim alone (drawn as a cross).

const SPOT_START = { cone: 30, blend: 0.15 };  // a new spot's cone half-angle (degrees) and softness

function pointText(x, y, z, spot) {
  const r = (v) => String(Math.round(v * 1000) / 1000);
  const text = `x=${r(x)},y=${r(y)},z=${r(z)}`;
  if (!spot) return text;
  return `${text},cone=${r(spot.cone)},ax=${r(spot.aim[0])},ay=${r(spot.aim[1])},blend=${r(spot.blend)}`;
}

function placedText() {  // the placed light's text, as ui.placing holds it now
  const [x, y, z] = ui.placing.point;
  return pointText(x, y, z, ui.placing.spot);
}

function pointFromDirection(az, el, rect) {
  const [, , w, h] = rect, L = Math.max(w, h, 1), a = (az * Math.PI) / 180, e = (el * Math.PI) / 180;
  return [0.5 + (Math.sin(e) * Math.cos(a) * L) / w, 0.5 - (Math.sin(e) * Math.sin(a) * L) / h, Math.max(0.05, Math.cos(e))];
}

function pointControl(layer, lit) {
  const box = document.createElement("div");
  const on = document.createElement("input");
  on.type = "checkbox"; on.id = "point-light"; on.checked = lit.point !== null;
  on.addEventListener("change", async () => {
    const light = on.checked ? pointText(...pointFromDirection(lit.az, lit.el, lit.rect)) : lightText(lit.az, lit.el);
    await change({ op: "light", id: layer.id, light });
    paint();
  });
  box.append(field("Point light", on));
  if (lit.point === null) return box;
  ui.placing = { id: layer.id, rect: lit.rect, point: lit.point.slice(), spot: copySpot(lit.spot) };
  const height = document.createElement("input");
  height.type = "range"; height.id = "light-height"; height.min = "-4"; height.max = "3"; height.step = "0.05";
  height.value = String(Math.log2(lit.point[2]));
  const heightValue = document.createElement("span");
  heightValue.id = "light-height-value";
  heightValue.textContent = lit.point[2].toFixed(3);
  const z = () => Math.round(2 ** parseFloat(height.value) * 1000) / 1000;
  height.addEventListener("input", () => {
    ui.placing.point[2] = z();
    ui.light = { id: layer.id, text: placedText(), source: false };
    heightValue.textContent = z().toFixed(3);
    paint();
  });
  height.addEventListener("change", async () => {
    ui.placing.point[2] = z();
    await change({ op: "light", id: layer.id, light: placedText() });
    ui.light = null;
    paint();
  });
  const f = field("Height", height);
  f.append(" ", heightValue);
  box.append(f);
  box.append(spotControl(layer, lit));
  const hint = document.createElement("div");
  hint.className = "hint";
  hint.textContent = lit.spot
    ? "drag on the image to move the light; shift-drag to aim it"
    : "drag on the image to move the light";
  box.append(hint);
  return box;
}

function copySpot(spot) {
  return spot ? { cone: spot.cone, aim: spot.aim.slice(), blend: spot.blend } : null;
}

// A point light's cone: the Spot box, and while it is on the Cone (half-angle, 1–90°) and Softness sliders, each
// a preview while dragged and one change on release.
function spotControl(layer, lit) {
  const box = document.createElement("div");
  const on = document.createElement("input");
  on.type = "checkbox"; on.id = "spot-light"; on.checked = lit.spot !== null;
  on.addEventListener("change", async () => {
    const [x, y, z] = lit.point;
    const spot = on.checked ? { ...SPOT_START, aim: [x, y] } : null;
    await change({ op: "light", id: layer.id, light: pointText(x, y, z, spot) });
    paint();
  });
  box.append(field("Spot", on));
  if (lit.spot === null) return box;
  const slider = (id, label, min, max, step, key) => {
    const input = document.createElement("input");
    input.type = "range"; input.id = id; input.min = min; input.max = max; input.step = step;
    input.value = String(lit.spot[key]);
    const shown = document.createElement("span");
    shown.id = `${id}-value`; shown.textContent = String(lit.spot[key]);
    const set = () => {
      ui.placing.spot[key] = parseFloat(input.value);
      shown.textContent = input.value;
    };
    input.addEventListener("input", () => {
      set();
      ui.light = { id: layer.id, text: placedText(), source: false };
      paint();
    });
    input.addEventListener("change", async () => {
      set();
      await change({ op: "light", id: layer.id, light: placedText() });
      ui.light = null;
      paint();
    });
    const f = field(label, input);
    f.append(" ", shown);
    box.append(f);
  };
  slider("spot-cone", "Cone", "1", "90", "1", "cone");
  slider("spot-blend", "Softness", "0", "1", "0.05", "blend");
  return box;
}

// The canvas point under a pointer event → the placed layer's fractions (x, y), and back.
function canvasToPoint(e) {
  const r = $("canvas").getBoundingClientRect(), [lx, ly, w, h] = ui.placing.rect;
  const ix = (e.clientX - r.left - ui.panX) / ui.zoom, iy = (e.clientY - r.top - ui.panY) / ui.zoom;
  return [(ix - lx) / w, (iy - ly) / h];
}

function wirePlacing(canvas) {
  let dragging = false, frame = 0, at = null, aiming = false;
  const clampPoint = ([x, y]) => [Math.min(17, Math.max(-16, x)), Math.min(17, Math.max(-16, y))];
  const step = () => {
    frame = 0;
    const [x, y] = clampPoint(canvasToPoint(at)), spot = ui.placing.spot;
    if (aiming) {
      spot.aim = [x, y];
    } else {
      if (spot) {  // the aim moves with the light (clamped, as the light is)
        const [px, py] = ui.placing.point;
        spot.aim = clampPoint([spot.aim[0] + x - px, spot.aim[1] + y - py]);
      }
      ui.placing.point = [x, y, ui.placing.point[2]];
    }
    ui.light = { id: ui.placing.id, text: placedText(), source: false };
    paint();
  };
  canvas.addEventListener("pointerdown", (e) => {
    if (!ui.placing) return;
    e.preventDefault(); e.stopPropagation();
    canvas.setPointerCapture(e.pointerId);
    dragging = true; at = e;
    aiming = e.shiftKey && ui.placing.spot !== null;
    frame = requestAnimationFrame(step);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!dragging) return;
    at = e;
    if (!frame) frame = requestAnimationFrame(step);
  });
  const release = async (e) => {
    if (!dragging) return;
    dragging = false;
    if (frame) { cancelAnimationFrame(frame); frame = 0; }
    at = e;
    step();
    await change({ op: "light", id: ui.placing.id, light: ui.light.text });
    ui.light = null;
    paint();
  };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
}

// ---- the catalogue and the light picker ---------------------------------------------------------

async function loadPresets() {
  const response = await api("api/presets");
  const body = await response.json();
  ui.presets = body.presets;
  ui.lights = body.lights;
  const select = $("preset");
  select.textContent = "";
  for (const p of ui.presets) {
    const o = new Option(p.ready ? p.name : `${p.name} (not ready)`, p.name);
    select.add(o);
  }
  const ready = ui.presets.find((p) => p.ready && p.amortised) || ui.presets.find((p) => p.ready);
  if (ready) select.value = ready.name;
  drawPicker();
}

function drawPicker() {
  const p = ui.presets.find((x) => x.name === $("preset").value);
  const box = $("picker");
  box.textContent = "";
  $("preset-why").textContent = p && !p.ready ? p.why : "";
  $("add-learned").disabled = !p || !p.amortised;  // a generator is installed (whatever the preset's default)
  $("add-per-image").disabled = !p || !p.ready;
  $("add-surface").disabled = !p || !p.surface;
  if (!p || !p.vocabulary) return;
  if (!p.vocabulary.includes(ui.condition)) ui.condition = p.vocabulary[0];
  const compass = p.vocabulary.every((v) => v in ui.lights);
  box.className = compass ? "" : "list";
  if (compass) {
    const ring = document.createElement("div");
    ring.className = "compass";
    box.append(ring);
  }
  for (const label of p.vocabulary) {
    const b = document.createElement("button");
    b.dataset.condition = label;
    b.title = label;
    if (compass) {
      const a = (ui.lights[label].az * Math.PI) / 180;
      b.style.left = `${50 + 42 * Math.cos(a)}%`;
      b.style.top = `${50 - 42 * Math.sin(a)}%`;
      b.textContent = "●";
    } else if (label in SWATCHES) {
      b.className = "swatch";
      b.style.background = SWATCHES[label];
    } else {
      b.textContent = label;
    }
    if (label === ui.condition) b.classList.add("chosen");
    b.addEventListener("click", () => { ui.condition = label; drawPicker(); });
    box.append(b);
  }
}

// ---- jobs ---------------------------------------------------------------------------------------

async function startJob(kind, id, steps) {
  // Until the server answers, the bar and the cancel button must not speak for the previous job: a cancel
  // clicked now would go to that finished job's id, and a stale bar would read as this job's progress.
  $("job-bar").value = 0;
  $("job-text").textContent = `${kind} ${id}: starting`;
  $("job-cancel").onclick = null;
  $("job-cancel").disabled = true;
  let job;
  try {
    const response = await api("api/jobs", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ version: ui.state.version, kind, id, steps }),
    });
    job = await response.json();
  } catch (err) { fail(err); return; }
  $("job").hidden = false;
  $("job-bar").max = Math.max(1, job.steps);
  $("job-cancel").onclick = () => api(`api/jobs/${job.id}/cancel`, { method: "POST", headers: { "Content-Type": "application/json" }, body: "{}" }).catch(fail);
  $("job-cancel").disabled = false;
  const source = new EventSource(`api/jobs/${job.id}/events?token=${encodeURIComponent(token)}`);
  source.onmessage = async (event) => {
    const r = JSON.parse(event.data);
    $("job-bar").value = r.step;
    $("job-text").textContent = `${r.what} ${r.layer}: ${r.state} ${r.step}/${r.steps}`;
    if (r.state !== "running") {
      source.close();
      if (r.state === "failed") status(r.error, true); else status(`${r.what} ${r.state}`);
      await refresh();
      setTimeout(() => { $("job").hidden = true; }, 1500);
    }
  };
}

// ---- the canvas ---------------------------------------------------------------------------------

function levelFor(zoom) {
  if (zoom >= 1) return 0;
  return Math.max(0, Math.min(ui.state.levels - 1, Math.floor(Math.log2(1 / zoom))));
}

async function fetchView(params) {
  const q = new URLSearchParams({ level: params.level });
  if (params.drag) q.append("opacity", `${params.drag.id}:${params.drag.value}`);
  if (params.solo) q.set("solo", params.solo);
  if (params.upto) q.set("upto", params.upto);
  if (params.light) q.append(params.light.source ? "source" : "light", `${params.light.id}:${params.light.text}`);
  if (params.relief) q.append("relief", `${params.relief.id}:${params.relief.value}`);
  if (params.ambient) q.append("ambient", `${params.ambient.id}:${params.ambient.value}`);
  if (params.colour) q.append("color", `${params.colour.id}:${params.colour.value}`);
  if (params.intensity) q.append("intensity", `${params.intensity.id}:${params.intensity.value}`);
  if (params.gloss) q.append("gloss", `${params.gloss.id}:${params.gloss.value}`);
  if (params.shadows) q.append("shadows", `${params.shadows.id}:${params.shadows.value}`);
  if (params.occlusion) q.append("occlusion", `${params.occlusion.id}:${params.occlusion.value}`);
  if (params.shadow_depth) q.append("shadow_depth", `${params.shadow_depth.id}:${params.shadow_depth.value}`);
  const map = params.normals ? [params.normals, "normals"] : params.occlusionMap ? [params.occlusionMap, "occlusion"] : null;
  const path = map ? `api/layers/${encodeURIComponent(map[0])}/${map[1]}?level=${params.level}` : `api/view?${q}`;
  const response = await api(path);
  const w = parseInt(response.headers.get("X-Width"), 10), h = parseInt(response.headers.get("X-Height"), 10);
  const data = new Uint8ClampedArray(await response.arrayBuffer());
  const canvas = document.createElement("canvas");
  canvas.width = w; canvas.height = h;
  canvas.getContext("2d").putImageData(new ImageData(data, w, h), 0, 0);
  return { canvas, level: params.level, w, h };
}

// While a slider or a light is dragged the canvas shows a proxy: the view one level coarser when that still has
// DRAG_PROXY_SIDE pixels on its long side (a 2048² stack fitted at 1/2 is previewed at 512², a quarter of
// the bytes to composite, send and draw); releasing repaints at the full view level.
const DRAG_PROXY_SIDE = 512;
function dragLevel(level) {
  const W = ui.state.document.canvas.width, H = ui.state.document.canvas.height;
  let l = level;
  while (l + 1 < ui.state.levels && Math.ceil(Math.max(W, H) / 2 ** (l + 1)) >= DRAG_PROXY_SIDE) l += 1;
  return Math.min(l, level + 1);
}

let wanted = null, inflight = false;
function paint() {
  if (!ui.state) return;
  const level = levelFor(ui.zoom);
  wanted = {
    level: ui.drag || ((ui.light || ui.relief || ui.ambient || ui.colour || ui.intensity || ui.gloss || ui.shadows || ui.occlusion || ui.shadow_depth) && ui.lightProxy) ? dragLevel(level) : level,
    drag: ui.drag, solo: ui.solo, version: ui.state.version, split: ui.split,
    light: ui.light, relief: ui.relief, ambient: ui.ambient, colour: ui.colour, intensity: ui.intensity, gloss: ui.gloss,
    shadows: ui.shadows, occlusion: ui.occlusion, shadow_depth: ui.shadow_depth, normals: ui.normals,
    occlusionMap: ui.occlusionMap,
  };
  if (!inflight) paintLoop();
}

async function paintLoop() {
  inflight = true;
  try {
    while (wanted) {
      const p = wanted;
      wanted = null;
      const image = await fetchView(p);
      let before = null;
      if (p.split && !p.normals && !p.occlusionMap) before = await fetchView({ level: p.level, upto: ui.state.document.layers[0].id });
      ui.image = image; ui.before = before;
      draw();
    }
  } catch (err) { fail(err); }
  inflight = false;
}

function draw() {
  const canvas = $("canvas"), ctx = canvas.getContext("2d");
  const stage = $("stage");
  if (canvas.width !== stage.clientWidth || canvas.height !== stage.clientHeight) {
    canvas.width = Math.max(1, stage.clientWidth); canvas.height = Math.max(1, stage.clientHeight);
  }
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (!ui.image) return;
  const W = ui.state.document.canvas.width, H = ui.state.document.canvas.height;
  ctx.imageSmoothingEnabled = ui.zoom < 1;
  ctx.drawImage(ui.image.canvas, ui.panX, ui.panY, W * ui.zoom, H * ui.zoom);
  if (ui.before) {
    const cut = Math.round(ui.panX + W * ui.zoom * parseFloat($("split-pos").value));
    ctx.save();
    ctx.beginPath(); ctx.rect(0, 0, cut, canvas.height); ctx.clip();
    ctx.drawImage(ui.before.canvas, ui.panX, ui.panY, W * ui.zoom, H * ui.zoom);
    ctx.restore();
    ctx.fillStyle = "#e0a030"; ctx.fillRect(cut, ui.panY, 1, H * ui.zoom);
  }
  // The point light, where it is over the canvas: a ring above it (not drawn into the canvas's pixels).
  const marker = $("light-marker"), aim = $("aim-marker");
  marker.hidden = !ui.placing;
  aim.hidden = !(ui.placing && ui.placing.spot);
  canvas.style.cursor = ui.placing ? "crosshair" : "";
  const place = (el, [px, py]) => {
    const [lx, ly, w, h] = ui.placing.rect;
    el.style.left = `${ui.panX + (lx + px * w) * ui.zoom}px`;
    el.style.top = `${ui.panY + (ly + py * h) * ui.zoom}px`;
  };
  if (ui.placing) place(marker, ui.placing.point);
  if (ui.placing && ui.placing.spot) place(aim, ui.placing.spot.aim);
  ui.paints.count += 1;
  ui.paints.last = performance.now();
  $("zoom-label").textContent = `${Math.round(ui.zoom * 100)}%`;
}

function setZoom(zoom, cx, cy) {
  const canvas = $("canvas");
  cx = cx === undefined ? canvas.width / 2 : cx; cy = cy === undefined ? canvas.height / 2 : cy;
  const ix = (cx - ui.panX) / ui.zoom, iy = (cy - ui.panY) / ui.zoom;
  ui.zoom = Math.min(32, Math.max(1 / 64, zoom));
  ui.panX = Math.round(cx - ix * ui.zoom); ui.panY = Math.round(cy - iy * ui.zoom);
  paint();
}

function fitView() {
  const stage = $("stage"), W = ui.state.document.canvas.width, H = ui.state.document.canvas.height;
  const z = Math.min(stage.clientWidth / W, stage.clientHeight / H);
  ui.zoom = z >= 1 ? Math.floor(z) : Math.pow(2, Math.floor(Math.log2(z)));  // exact pixels: integer or 1/2^k
  ui.panX = Math.round((stage.clientWidth - W * ui.zoom) / 2); ui.panY = Math.round((stage.clientHeight - H * ui.zoom) / 2);
  paint();
}

function oneToOne() {
  const stage = $("stage"), W = ui.state.document.canvas.width, H = ui.state.document.canvas.height;
  ui.zoom = 1;
  ui.panX = Math.max(0, Math.round((stage.clientWidth - W) / 2)); ui.panY = Math.max(0, Math.round((stage.clientHeight - H) / 2));
  paint();
}

// The composite's pixels as drawn at 1:1 (for tests): [w, h, RGBA bytes of the visible canvas region].
ui.readPixels = function () {
  const W = ui.state.document.canvas.width, H = ui.state.document.canvas.height;
  const data = $("canvas").getContext("2d").getImageData(ui.panX, ui.panY, W, H).data;
  return Array.from(data);
};
ui.settled = () => !inflight && wanted === null;

// ---- wiring -------------------------------------------------------------------------------------

function wire() {
  $("undo").onclick = () => change({ op: "undo" });
  $("redo").onclick = () => change({ op: "redo" });
  $("save").onclick = async () => { if (await change({ op: "save" })) status("saved"); };
  $("reload").onclick = async () => {
    // Another tab changed the open stack: fetch it. Another program changed the folder: read it again
    // (this tab's unsaved changes are dropped, as the message said).
    const fromDisk = $("status").textContent.includes("changed on disk");
    if (fromDisk) await apply(() => api("api/reload", { method: "POST", headers: { "Content-Type": "application/json" }, body: "{}" }));
    else await refresh();
    status(fromDisk ? "read the folder again" : "reloaded");
    $("reload").hidden = true;
  };
  $("zoom-in").onclick = () => setZoom(ui.zoom * 2);
  $("zoom-out").onclick = () => setZoom(ui.zoom / 2);
  $("zoom-fit").onclick = fitView;
  $("zoom-1").onclick = oneToOne;
  $("split").onchange = (e) => { ui.split = e.target.checked; paint(); };
  $("split-pos").oninput = () => draw();
  $("preset").onchange = drawPicker;
  const addLearned = async (method, kind) => {
    const p = ui.presets.find((x) => x.name === $("preset").value);
    status(kind === "surface" ? "estimating a surface…" : "adding a learned layer…");
    const before = new Set(ui.state.document.layers.map((l) => l.id));
    const body = { op: "learned", preset: p.name, condition: ui.condition, method };
    if (kind) body.kind = kind;
    if (!(await change(body))) return;
    const added = ui.state.document.layers.find((l) => !before.has(l.id));
    if (added) ui.selected = added.id;
    drawLayers(); drawProps();
    if (method === "per-image" && added) startJob("rerender", added.id);
  };
  $("add-learned").onclick = () => addLearned("amortised");
  $("add-per-image").onclick = () => addLearned("per-image");
  $("add-surface").onclick = () => addLearned("amortised", "surface");
  $("add-solid").onclick = () => {
    const hex = $("solid-color").value;
    const rgb = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
    change({ op: "solid", color: rgb, name: `Solid ${hex}` });
  };
  $("add-normal-map").onchange = async (e) => {
    const file = e.target.files[0];
    if (!file) return;
    const q = new URLSearchParams({ version: ui.state.version, name: file.name, kind: "normal-map", directx: $("normal-map-directx").checked ? "1" : "0" });
    if ($("normal-map-height").value) q.set("height", $("normal-map-height").value);  // a grey height map instead
    await apply(() => api(`api/upload?${q}`, { method: "POST", body: file }));
    e.target.value = "";
  };
  $("add-image").onchange = async (e) => {
    const file = e.target.files[0];
    if (!file) return;
    const q = new URLSearchParams({ version: ui.state.version, name: file.name });
    await apply(() => api(`api/upload?${q}`, { method: "POST", body: file }));
    e.target.value = "";
  };
  const canvas = $("canvas");
  let panning = null;
  wirePlacing(canvas);  // while a point light is placed, a drag on the canvas moves it instead of the view
  canvas.addEventListener("mousedown", (e) => { if (!ui.placing) panning = { x: e.clientX - ui.panX, y: e.clientY - ui.panY }; });
  window.addEventListener("mouseup", () => { panning = null; });
  window.addEventListener("mousemove", (e) => {
    if (!panning) return;
    ui.panX = Math.round(e.clientX - panning.x); ui.panY = Math.round(e.clientY - panning.y);
    draw();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const r = canvas.getBoundingClientRect();
    setZoom(ui.zoom * (e.deltaY < 0 ? 2 : 0.5), e.clientX - r.left, e.clientY - r.top);
  }, { passive: false });
  window.addEventListener("resize", draw);
  window.addEventListener("keydown", (e) => {
    if (!(e.ctrlKey || e.metaKey)) return;
    if (e.key === "z" && !e.shiftKey) { e.preventDefault(); change({ op: "undo" }); }
    else if ((e.key === "z" && e.shiftKey) || e.key === "y" || e.key === "Z") { e.preventDefault(); change({ op: "redo" }); }
    else if (e.key === "s") { e.preventDefault(); $("save").click(); }
  });
  window.addEventListener("beforeunload", (e) => { if (ui.state && ui.state.dirty) { e.preventDefault(); e.returnValue = ""; } });
}

wire();
Promise.all([refresh(), loadPresets()]).catch(fail);
