// bokehray view: the page. No external resources; talks only to the server that served it.
"use strict";

const $ = (id) => document.getElementById(id);
const SLIDERS = ["blur", "focus", "blades", "rotation", "curvature", "highlight_boost"];
const REFINE_AFTER_MS = 350;  // the full-resolution render starts when the input rests this long

let info = null;
const state = { blur: 20, focus: 0.5, focus_at: null, aperture: "disc", blades: 6, rotation: 0, curvature: 0,
                highlight_boost: 0, quality: "preview", max_spp: 128 };
let seq = 0, shownSeq = 0, previewInFlight = false, previewAgain = false, refineTimer = null;
let lastRender = null, photo = null, depth = null, disparity = null, focusDisparity = null;
let images = 0;

function params() {
  const p = { blur: state.blur, aperture: state.aperture, blades: state.blades, rotation: state.rotation,
              curvature: state.curvature, highlight_boost: state.highlight_boost, quality: state.quality,
              max_spp: state.max_spp };
  if (state.focus_at) p.focus_at = state.focus_at; else p.focus = state.focus;
  return p;
}

function setStatus(text) { $("status").textContent = text; }
function setError(text) { $("error").textContent = text || ""; }

async function loadBitmap(url, options) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(url + ": HTTP " + r.status);
  return createImageBitmap(await r.blob(), options);
}

function draw() {
  const c = $("view"), ctx = c.getContext("2d");
  const show = $("show").value;
  let item = lastRender;
  if (show === "photo" || !item) item = photo;
  if (show === "depth") item = depth;
  if (item) {
    ctx.imageSmoothingQuality = "high";
    // an image reduced by f covers ceil(W / f) pixels: the photo is its first W / f
    ctx.drawImage(item.bitmap, 0, 0, info.width / item.factor, info.height / item.factor, 0, 0, c.width, c.height);
  }
  drawOverlay();
}

function drawOverlay() {
  const o = $("overlay"), ctx = o.getContext("2d");
  ctx.clearRect(0, 0, o.width, o.height);
  if (!$("infocus").checked || !disparity || focusDisparity === null) return;
  // in focus: CoC radius K * |d - d_f| below 1 pixel of the full-resolution image
  const tol = state.blur > 0 ? 1.0 / state.blur : 1.0;
  const img = ctx.createImageData(o.width, o.height), src = disparity.data, dst = img.data;
  for (let i = 0; i < src.length; i += 4) {
    const d = (src[i] * 256 + src[i + 1]) / 65535;
    if (Math.abs(d - focusDisparity) < tol) { dst[i] = 40; dst[i + 1] = 255; dst[i + 2] = 90; dst[i + 3] = 110; }
  }
  ctx.putImageData(img, 0, 0);
}

function showCommand(cmd) { $("command").textContent = cmd; }

async function requestRender(stage) {
  const my = ++seq;
  document.body.dataset.state = "rendering";
  const t0 = performance.now();
  let r;
  try {
    r = await fetch("/api/render", { method: "POST", headers: { "Content-Type": "application/json" },
                                     body: JSON.stringify({ ...params(), stage }) });
  } catch (e) { setError("server unreachable: " + e); return; }
  if (r.status === 409) return;  // a newer request replaced this one
  if (!r.ok) {
    let msg = "HTTP " + r.status;
    try { msg = (await r.json()).error || msg; } catch (e) { /* not JSON */ }
    setError(msg);
    document.body.dataset.state = "error";
    return;
  }
  const bitmap = await createImageBitmap(await r.blob());
  if (my < shownSeq) return;  // an answer to an older request arrived late
  shownSeq = my;
  setError("");
  const factor = Number(r.headers.get("X-Bokehray-Factor"));
  lastRender = { bitmap, factor, stage };
  focusDisparity = Number(r.headers.get("X-Bokehray-Focus-Disparity"));
  document.body.dataset.focusDisparity = String(focusDisparity);
  document.body.dataset.stage = stage;
  document.body.dataset.images = String(++images);
  $("focus").value = focusDisparity;
  $("focus-out").textContent = focusDisparity.toFixed(4);
  showCommand(decodeURIComponent(r.headers.get("X-Bokehray-Command") || ""));
  const secs = Number(r.headers.get("X-Bokehray-Render-Seconds"));
  const w = Math.ceil(info.width / factor), h = Math.ceil(info.height / factor);
  setStatus(`${stage === "preview" ? "preview" : "full resolution"} ${w}×${h}` +
            (stage === "full" ? ` (of ${info.width}×${info.height})` : "") +
            `: render ${(secs * 1000).toFixed(0)} ms, round trip ${(performance.now() - t0).toFixed(0)} ms` +
            (stage === "preview" ? " — refining…" : ""));
  if (stage === "full" || refineTimer === null) document.body.dataset.state = stage === "full" ? "idle" : "refining";
  draw();
}

async function preview() {
  if (previewInFlight) { previewAgain = true; return; }  // one preview at a time; the latest values go next
  previewInFlight = true;
  try { await requestRender("preview"); } finally { previewInFlight = false; }
  if (previewAgain) { previewAgain = false; preview(); }
}

function changed() {
  preview();
  clearTimeout(refineTimer);
  refineTimer = setTimeout(() => { refineTimer = null; requestRender("full"); }, REFINE_AFTER_MS);
}

function syncOutputs() {
  for (const k of SLIDERS) {
    const out = $(k + "-out");
    if (out && k !== "focus") out.textContent = $(k).value;
  }
  const polygon = state.aperture === "polygon";
  for (const k of ["blades", "rotation", "curvature"]) $(k).disabled = !polygon;
}

function bind() {
  for (const k of SLIDERS) {
    $(k).addEventListener("input", () => {
      const v = Number($(k).value);
      state[k] = k === "blades" ? Math.round(v) : v;
      if (k === "focus") { state.focus_at = null; $("marker").hidden = true; $("focus-out").textContent = v.toFixed(4); }
      syncOutputs();
      changed();
    });
  }
  $("aperture").addEventListener("change", () => { state.aperture = $("aperture").value; syncOutputs(); changed(); });
  $("quality").addEventListener("change", () => { state.quality = $("quality").value; changed(); });
  $("max_spp").addEventListener("change", () => { state.max_spp = Math.round(Number($("max_spp").value)); changed(); });
  $("show").addEventListener("change", draw);
  $("infocus").addEventListener("change", drawOverlay);
  $("format").addEventListener("change", fillBitDepths);
  $("view").addEventListener("click", (e) => {
    const c = $("view");
    const x = Math.min(info.width - 1, Math.max(0, Math.floor(e.offsetX / c.clientWidth * info.width)));
    const y = Math.min(info.height - 1, Math.max(0, Math.floor(e.offsetY / c.clientHeight * info.height)));
    state.focus_at = [x, y];
    const m = $("marker");
    m.style.left = (100 * (x + 0.5) / info.width) + "%";
    m.style.top = (100 * (y + 0.5) / info.height) + "%";
    m.hidden = false;
    document.body.dataset.focusAt = x + "," + y;
    changed();
  });
  $("export").addEventListener("click", exportImage);
}

function fillBitDepths() {
  const sel = $("bit_depth"), fmt = $("format").value;
  sel.innerHTML = "";
  for (const b of info.export_formats[fmt]) {
    const o = document.createElement("option");
    o.value = b;
    o.textContent = fmt === "exr" ? (b === 16 ? "half" : "float") : b + "-bit" + (fmt === "tif" && b === 32 ? " float" : "");
    sel.appendChild(o);
  }
}

async function exportImage() {
  const btn = $("export");
  btn.disabled = true;
  document.body.dataset.exported = "";
  $("export-out").textContent = "rendering every pixel and writing…";
  $("export-command").textContent = "";
  try {
    const r = await fetch("/api/export", { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ params: params(), format: $("format").value, bit_depth: Number($("bit_depth").value) }) });
    const j = await r.json();
    if (!r.ok) { $("export-out").textContent = ""; setError(j.error || ("HTTP " + r.status)); return; }
    $("export-out").textContent = "wrote " + j.path + ` (${j.seconds.toFixed(1)} s); the same file from the command line:`;
    $("export-command").textContent = j.command;
    document.body.dataset.exported = j.path;
  } catch (e) {
    setError("export failed: " + e);
  } finally { btn.disabled = false; }
}

async function start() {
  info = await (await fetch("/api/info")).json();
  $("files").textContent = `${info.files.image} · ${info.files.map} · ${info.width}×${info.height}`;
  for (const c of [$("view"), $("overlay")]) { c.width = info.display.width; c.height = info.display.height; }
  $("blur").max = info.max_blur;
  $("blur").value = state.blur = info.default_blur;
  for (const q of info.qualities) {
    const o = document.createElement("option"); o.value = q; o.textContent = q; $("quality").appendChild(o);
  }
  for (const f of Object.keys(info.export_formats)) {
    const o = document.createElement("option"); o.value = f; o.textContent = f; $("format").appendChild(o);
  }
  fillBitDepths();
  photo = { bitmap: await loadBitmap("/api/photo.jpg"), factor: info.display.factor };
  depth = { bitmap: await loadBitmap("/api/depth.png"), factor: info.display.factor };
  const packed = await loadBitmap("/api/disparity16.png", { colorSpaceConversion: "none", premultiplyAlpha: "none" });
  const tmp = document.createElement("canvas");
  tmp.width = info.display.width; tmp.height = info.display.height;
  const tctx = tmp.getContext("2d", { colorSpace: "srgb", willReadFrequently: true });
  tctx.drawImage(packed, 0, 0);
  disparity = tctx.getImageData(0, 0, tmp.width, tmp.height);
  // start focused at the centre of the frame
  state.focus_at = [Math.floor(info.width / 2), Math.floor(info.height / 2)];
  bind();
  syncOutputs();
  $("blur-out").textContent = state.blur;
  draw();
  document.body.dataset.state = "ready";
  changed();
}

start().catch((e) => { setError("could not start: " + e); document.body.dataset.state = "error"; });
