// bokehray view: the page. No external resources; talks only to the server that served it.
//
// After every change the page asks for a preview (the proxy) first; only once the preview of the latest state is
// on screen does it ask for the sharp version, at the size the screen shows (every pixel at 100 %). A change
// while the sharp version renders asks for a new preview, which the server runs first (the sharp one is dropped),
// so a proxy always follows a change, whatever the load of the machine. Between the two, the focused region is
// rendered at the size the screen shows (a small crop, fast even on a busy machine) and drawn over the proxy, so
// the focus can be judged before the whole frame is sharp.
"use strict";

const $ = (id) => document.getElementById(id);
const SLIDERS = ["amount", "blur", "focus", "blades", "rotation", "curvature", "highlight_boost"];
const PROGRESS_POLL_MS = 250;
const F_STOPS = [1.2, 1.4, 1.8, 2, 2.8, 4, 5.6, 8, 11, 16, 22];

let info = null;
// what `bokehray render` does with the same inputs: amount 50, the subject, reconstruction as the file needs
const state = { amount: 50, blur: null, focus: null, focus_at: null, aperture: "disc", blades: 6, rotation: 0,
                curvature: 0, highlight_boost: 0, reconstruct: false, quality: "preview", grain: true,
                lens: null };  // lens: {focal_length, f_number, focus_distance (null: the clicked point)}
let version = 0;            // the state's number: every change increments it
let shownVersion = -1;      // the state of the image on screen
let previewInFlight = false, previewAgain = false, fullFor = -1, progressTimer = null;
let lastRender = null, photo = null, depth = null, disparity = null, focusDisparity = null, focusCrop = null;
let images = 0, previews = 0, fulls = 0;
const shownLog = [];  // [stage, state number] of every image shown, in order (the browser test reads it)
window.bokehrayShown = shownLog;

function params() {
  const p = { aperture: state.aperture, blades: state.blades, rotation: state.rotation, curvature: state.curvature,
              highlight_boost: state.highlight_boost, reconstruct: state.reconstruct, quality: state.quality,
              grain: state.grain };
  if (state.lens) {  // metric depth: render's physical lens (--focal-length, --f-number, --focus-distance)
    p.lens = { focal_length: state.lens.focal_length, f_number: state.lens.f_number };
    if (state.focus_at) p.focus_at = state.focus_at; else p.lens.focus_distance = state.lens.focus_distance;
    return p;
  }
  if (state.blur !== null) p.blur = state.blur; else p.amount = state.amount;
  if (state.focus_at) p.focus_at = state.focus_at; else if (state.focus !== null) p.focus = state.focus;
  return p;
}

function setStatus(text) { $("status").textContent = text; }
function setError(text) { $("error").textContent = text || ""; }
function mark(name, value) { document.body.dataset[name] = String(value); }

async function loadBitmap(url, options) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(url + ": HTTP " + r.status);
  return createImageBitmap(await r.blob(), options);
}

function zoomed() { return $("zoom").checked; }

function sizeCanvas() {
  const c = $("view");
  const w = zoomed() ? info.width : info.display.width, h = zoomed() ? info.height : info.display.height;
  if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
  c.style.width = zoomed() ? (info.width / devicePixelRatio) + "px" : "";
  $("frame").classList.toggle("zoom", zoomed());
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
    // the focused region at screen size over the proxy of the same state (until the sharp version replaces both)
    if (item === lastRender && item.stage === "preview" && focusCrop && focusCrop.v === shownVersion) {
      const [x0, y0, x1, y1] = focusCrop.box, s = c.width / info.width;
      ctx.drawImage(focusCrop.bitmap, x0 * s, y0 * s, (x1 - x0) * s, (y1 - y0) * s);
    }
  }
  drawOverlay();
}

function drawOverlay() {
  const o = $("overlay"), ctx = o.getContext("2d");
  ctx.clearRect(0, 0, o.width, o.height);
  const k = lastRender ? lastRender.k : 0;
  if (!$("infocus").checked || !disparity || focusDisparity === null) return;
  // in focus: CoC radius K * |d - d_f| below 1 pixel of the full-resolution image
  const tol = k > 0 ? 1.0 / k : 1.0;
  const img = ctx.createImageData(o.width, o.height), src = disparity.data, dst = img.data;
  for (let i = 0; i < src.length; i += 4) {
    const d = (src[i] * 256 + src[i + 1]) / 65535;
    if (Math.abs(d - focusDisparity) < tol) { dst[i] = 40; dst[i + 1] = 255; dst[i + 2] = 90; dst[i + 3] = 110; }
  }
  ctx.putImageData(img, 0, 0);
}

function screenLongSide() {
  // the photo's long side in device pixels as the canvas shows it (every pixel at 100 %)
  if (zoomed()) return Math.max(info.width, info.height);
  const c = $("view"), scale = c.clientWidth * devicePixelRatio / info.width;
  return Math.max(16, Math.round(Math.max(info.width, info.height) * Math.min(1, scale)));
}

function exportChoice() {
  const bits = Number($("bit_depth").value);
  return { format: $("format").value || "png", bit_depth: bits || null };
}

// one render request; answers whether it was shown
async function requestRender(stage, v) {
  const t0 = performance.now();
  const body = { ...params(), ...exportChoice(), stage };
  if (stage !== "preview") body.long_side = screenLongSide();
  let r;
  try {
    r = await fetch("/api/render", { method: "POST", headers: { "Content-Type": "application/json" },
                                     body: JSON.stringify(body) });
  } catch (e) { setError("server unreachable: " + e); return false; }
  if (r.status === 409) return false;  // a newer request replaced this one
  if (!r.ok) {
    let msg = "HTTP " + r.status;
    try { msg = (await r.json()).error || msg; } catch (e) { /* not JSON */ }
    setError(msg);
    mark("state", "error");
    return false;
  }
  const bitmap = await createImageBitmap(await r.blob());
  if (stage === "focus") {  // drawn over the proxy of the same state, if that is still what is shown
    if (v !== shownVersion || !lastRender || lastRender.stage !== "preview") return false;
    focusCrop = { bitmap, v, box: r.headers.get("X-Bokehray-Crop").split(",").map(Number) };
    mark("focusCrop", focusCrop.box.join(","));
    mark("focusCrops", (Number(document.body.dataset.focusCrops) || 0) + 1);
    shownLog.push(["focus", v]);
    setStatus($("status").textContent.replace(" — sharpening…", "") + " — focus sharp, sharpening the rest…");
    draw();
    return true;
  }
  if (v < shownVersion || (v === shownVersion && stage === "preview" && lastRender && lastRender.stage === "full")) {
    return false;  // an answer to an older state arrived late
  }
  shownVersion = v;
  setError("");
  const factor = Number(r.headers.get("X-Bokehray-Factor"));
  const focusM = r.headers.get("X-Bokehray-Focus-M");
  lastRender = { bitmap, factor, stage, k: Number(r.headers.get("X-Bokehray-K")),
                 focusM: focusM ? (focusM === "inf" ? Infinity : Number(focusM)) : null };  // "inf": sky
  focusDisparity = Number(r.headers.get("X-Bokehray-Focus-Disparity"));
  mark("focusDisparity", focusDisparity);
  mark("stage", stage);
  mark("images", ++images);
  mark(stage === "preview" ? "previews" : "fulls", stage === "preview" ? ++previews : ++fulls);
  mark("shownVersion", v);
  mark("factor", factor);
  mark("k", lastRender.k);
  shownLog.push([stage, v]);
  $("focus").value = focusDisparity;
  $("focus-out").textContent = focusDisparity.toFixed(4);
  $("blur").value = lastRender.k;
  $("blur-out").textContent = lastRender.k.toFixed(1);
  $("focus-where").textContent = decodeURIComponent(r.headers.get("X-Bokehray-Focus-Words") || "");
  if (state.lens && lastRender.focusM !== null) {
    $("focus_distance-out").textContent = lastRender.focusM.toPrecision(3);
    $("focus_distance").value = metresToSlider(lastRender.focusM);
  }
  $("command").textContent = decodeURIComponent(r.headers.get("X-Bokehray-Command") || "");
  const secs = Number(r.headers.get("X-Bokehray-Render-Seconds"));
  const w = Math.ceil(info.width / factor), h = Math.ceil(info.height / factor);
  setStatus(`${stage === "preview" ? "preview" : "sharp"} ${w}×${h}` +
            (factor > 1 ? ` (of ${info.width}×${info.height})` : "") +
            `: render ${(secs * 1000).toFixed(0)} ms, round trip ${(performance.now() - t0).toFixed(0)} ms` +
            (stage === "preview" ? " — sharpening…" : ""));
  draw();
  return true;
}

async function pollProgress() {
  try {
    const p = await (await fetch("/api/progress")).json();
    const job = p.running.find((j) => j.kind === "full");
    if (job && job.total > 0) {
      $("progress").value = job.done / job.total;
      mark("progress", (job.done / job.total).toFixed(3));
    }
  } catch (e) { /* the next poll tries again */ }
}

async function full(v) {
  fullFor = v;
  mark("state", "refining");
  $("progress").value = 0;
  $("progress").hidden = false;
  clearInterval(progressTimer);
  progressTimer = setInterval(pollProgress, PROGRESS_POLL_MS);
  try {
    await requestRender("full", v);
  } finally {
    if (fullFor === v) {
      clearInterval(progressTimer);
      $("progress").hidden = true;
      if (v === version) mark("state", shownVersion === v && lastRender.stage === "full" ? "idle" : "ready");
    }
  }
}

async function preview() {
  if (previewInFlight) { previewAgain = true; return; }  // one preview at a time; the latest state goes next
  previewInFlight = true;
  const v = version;
  mark("state", "rendering");
  let shown = false;
  try { shown = await requestRender("preview", v); } finally { previewInFlight = false; }
  if (previewAgain || v !== version) { previewAgain = false; preview(); return; }
  // the preview of the latest state is on screen: now, and only now, the focused region and then the sharp version
  if (shown) {
    await requestRender("focus", v);
    if (v === version) full(v);
  }
}

function changed() {
  version++;
  mark("version", version);
  preview();
}

function metresToSlider(z) {
  const m = info.metric, near = m.nearest_m, far = Math.min(m.farthest_m, 1000);
  return Math.round(1000 * Math.log(Math.max(near, Math.min(far, z)) / near) / Math.log(far / near));
}

function sliderToMetres(v) {
  const m = info.metric, near = m.nearest_m, far = Math.min(m.farthest_m, 1000);
  return near * Math.pow(far / near, v / 1000);
}

function setLens(on) {
  state.lens = on ? { focal_length: Number($("focal_length").value), f_number: F_STOPS[Number($("f_stop").value)],
                      focus_distance: state.focus_at ? null : info.metric.subject_m } : null;
  for (const k of ["f_stop", "focal_length", "focus_distance"]) $(k).disabled = !on;
  $("amount").disabled = on;
  state.focus = null;
}

function syncOutputs() {
  $("f_number-out").textContent = F_STOPS[Number($("f_stop").value)];
  for (const k of ["amount", "blades", "rotation", "curvature", "highlight_boost"]) $(k + "-out").textContent = $(k).value;
  const polygon = state.aperture === "polygon";
  for (const k of ["blades", "rotation", "curvature"]) $(k).disabled = !polygon;
}

function bind() {
  for (const k of SLIDERS) {
    $(k).addEventListener("input", () => {
      const v = Number($(k).value);
      state[k] = k === "blades" ? Math.round(v) : v;
      if (k === "focus") { state.focus_at = null; $("marker").hidden = true; }
      if (k === "amount") state.blur = null;
      syncOutputs();
      changed();
    });
  }
  $("aperture").addEventListener("change", () => { state.aperture = $("aperture").value; syncOutputs(); changed(); });
  $("reconstruct").addEventListener("change", () => { state.reconstruct = $("reconstruct").checked; changed(); });
  $("grain").addEventListener("change", () => { state.grain = $("grain").checked; changed(); });  // the command
  $("quality").addEventListener("change", () => { state.quality = $("quality").value; changed(); });
  $("show").addEventListener("change", draw);
  $("infocus").addEventListener("change", drawOverlay);
  $("zoom").addEventListener("change", () => { sizeCanvas(); draw(); if (shownVersion === version) full(version); });
  $("format").addEventListener("change", () => { fillBitDepths(); changed(); });  // the shown command's -o and depth
  $("bit_depth").addEventListener("change", changed);
  $("subject").addEventListener("click", () => {
    state.focus = null; state.focus_at = null; $("marker").hidden = true;
    if (state.lens) state.lens.focus_distance = info.metric.subject_m;
    changed();
  });
  $("view").addEventListener("click", (e) => {
    const c = $("view");
    const x = Math.min(info.width - 1, Math.max(0, Math.floor(e.offsetX / c.clientWidth * info.width)));
    const y = Math.min(info.height - 1, Math.max(0, Math.floor(e.offsetY / c.clientHeight * info.height)));
    state.focus_at = [x, y];
    state.focus = null;
    if (state.lens) state.lens.focus_distance = null;
    const m = $("marker");
    m.style.left = (100 * (x + 0.5) / info.width) + "%";
    m.style.top = (100 * (y + 0.5) / info.height) + "%";
    m.hidden = zoomed();
    mark("focusAt", x + "," + y);
    changed();
  });
  $("export").addEventListener("click", exportImage);
  $("blur-mode").addEventListener("change", () => { setLens($("blur-mode").value === "lens"); syncOutputs(); changed(); });
  $("f_stop").addEventListener("input", () => {
    syncOutputs();
    if (state.lens) { state.lens.f_number = F_STOPS[Number($("f_stop").value)]; changed(); }
  });
  $("focal_length").addEventListener("change", () => {
    if (state.lens) { state.lens.focal_length = Number($("focal_length").value); changed(); }
  });
  $("focus_distance").addEventListener("input", () => {
    if (!state.lens) return;
    state.lens.focus_distance = sliderToMetres(Number($("focus_distance").value));
    state.focus_at = null; $("marker").hidden = true;
    $("focus_distance-out").textContent = state.lens.focus_distance.toPrecision(3);
    changed();
  });
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

async function pollExport() {
  try {
    const p = await (await fetch("/api/progress")).json();
    const job = p.running.find((j) => j.kind === "export");
    if (!job) return;
    const text = job.total > 0 && job.done >= job.total ? "step 2 of 2: finishing (grain) and writing the file…" :
      "step 1 of 2: rendering every pixel" + (job.total > 0 ? ` (depth layer ${job.done} of ${job.total})` : "…");
    $("export-out").textContent = text;
    $("export-progress").hidden = false;
    $("export-progress").value = job.total > 0 ? job.done / job.total : 0;
    mark("exportStep", text);
  } catch (e) { /* the next poll tries again */ }
}

async function exportImage() {
  const btn = $("export");
  btn.disabled = true;
  mark("exported", "");
  $("export-out").textContent = "step 1 of 2: rendering every pixel…";
  $("export-command").textContent = "";
  $("export-out").scrollIntoView({ block: "nearest" });
  const timer = setInterval(pollExport, PROGRESS_POLL_MS);
  try {
    const r = await fetch("/api/export", { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ params: params(), format: $("format").value, bit_depth: Number($("bit_depth").value) }) });
    const j = await r.json();
    if (!r.ok) { $("export-out").textContent = ""; setError(j.error || ("HTTP " + r.status)); return; }
    $("export-out").textContent = "wrote " + j.path + ` (${j.seconds.toFixed(1)} s); the same file from the command line:`;
    $("export-command").textContent = j.command;
    $("export-command").scrollIntoView({ block: "nearest" });
    mark("exported", j.path);
  } catch (e) {
    setError("export failed: " + e);
  } finally { clearInterval(timer); $("export-progress").hidden = true; btn.disabled = false; }
}

async function start() {
  info = await (await fetch("/api/info")).json();
  // JSON has no infinity: a depth at infinity (sky) comes as null
  if (info.metric) for (const k in info.metric) if (info.metric[k] === null) info.metric[k] = Infinity;
  const d = info.defaults;
  state.amount = d.amount;
  state.reconstruct = d.reconstruct;
  $("amount").value = d.amount;
  $("reconstruct").checked = d.reconstruct;
  $("reconstruct-label").hidden = !info.display_referred;
  $("grain-label").hidden = !info.display_referred;
  $("lens-controls").hidden = !info.metric;
  if (info.metric) setLens(false);
  $("files").textContent = `${info.files.image} · ${info.files.map} · ${info.width}×${info.height}` +
    (info.metric ? ` · depth ${info.metric.nearest_m.toPrecision(3)}–${info.metric.farthest_m.toPrecision(3)} m` : "");
  $("subject").title = "focus " + d.subject.why;
  $("subject").textContent = "Focus on " + d.subject.words;
  $("overlay").width = info.display.width; $("overlay").height = info.display.height;
  sizeCanvas();
  $("blur").max = info.max_blur;
  for (const q of info.qualities) {
    const o = document.createElement("option"); o.value = q; o.textContent = q; $("quality").appendChild(o);
  }
  $("quality").parentElement.hidden = info.qualities.length < 2;  // one level for photos (the preview): no choice
  for (const f of Object.keys(info.export_formats)) {
    const o = document.createElement("option"); o.value = f; o.textContent = f; $("format").appendChild(o);
  }
  fillBitDepths();
  bind();
  syncOutputs();
  mark("state", "ready");
  changed();  // the first preview; the photo, the depth and the overlay's disparity load once it is shown
  await new Promise((resolve) => {
    const poll = setInterval(() => {
      if (shownVersion >= 0 || document.body.dataset.state === "error") { clearInterval(poll); resolve(); }
    }, 20);
  });
  photo = { bitmap: await loadBitmap("/api/photo.jpg"), factor: info.display.factor };
  if (!lastRender) draw();
  depth = { bitmap: await loadBitmap("/api/depth.png"), factor: info.display.factor };
  const packed = await loadBitmap("/api/disparity16.png", { colorSpaceConversion: "none", premultiplyAlpha: "none" });
  const tmp = document.createElement("canvas");
  tmp.width = info.display.width; tmp.height = info.display.height;
  const tctx = tmp.getContext("2d", { colorSpace: "srgb", willReadFrequently: true });
  tctx.drawImage(packed, 0, 0);
  disparity = tctx.getImageData(0, 0, tmp.width, tmp.height);
  mark("loaded", "1");
}

start().catch((e) => { setError("could not start: " + e); mark("state", "error"); });
