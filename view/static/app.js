// sss view's page: the token comes from the URL `sss view` printed and goes with every request.
"use strict";
const TOKEN = new URLSearchParams(location.search).get("token") || "";
const $ = (id) => document.getElementById(id);
const state = { frames: 0, sessions: [], uploaded: null, socket: null };

function say(text) { $("message").textContent = text || ""; }

async function api(path, options = {}) {
  const response = await fetch(path, { ...options, headers: { "X-Token": TOKEN, ...(options.headers || {}) } });
  if (!response.ok) {
    let message = response.statusText;
    try { message = (await response.json()).error || message; } catch (e) { /* not JSON */ }
    throw new Error(message);
  }
  return response;
}

// answers come back in any order: only the latest request of each kind may change the page (a map picked
// after another, a second relight, a pixel clicked while the last one's probe is on its way)
const latest = {};
const ticket = (kind) => { const mine = (latest[kind] = (latest[kind] || 0) + 1); return () => latest[kind] === mine; };

function fill(select, items, label = (x) => x) {
  select.innerHTML = "";
  for (const item of items) {
    const option = document.createElement("option");
    option.value = typeof item === "object" ? item.value : item;
    option.textContent = typeof item === "object" ? item.label : label(item);
    select.appendChild(option);
  }
}

// --- tabs -------------------------------------------------------------------------------------------------
for (const button of document.querySelectorAll("nav button")) {
  button.onclick = () => {
    for (const b of document.querySelectorAll("nav button")) b.classList.toggle("on", b === button);
    for (const s of document.querySelectorAll("section")) s.classList.toggle("on", s.id === button.dataset.tab);
  };
}

// --- live ---------------------------------------------------------------------------------------------------
function drawHistogram(histogram) {
  const canvas = $("histogram"), g = canvas.getContext("2d");
  g.clearRect(0, 0, canvas.width, canvas.height);
  const colours = ["rgba(255,80,80,0.7)", "rgba(80,255,80,0.7)", "rgba(80,140,255,0.7)"];
  const peak = Math.max(1, ...histogram.flat());
  histogram.forEach((bins, c) => {
    g.strokeStyle = colours[c % 3];
    g.beginPath();
    bins.forEach((n, i) => {
      const x = (i + 0.5) * canvas.width / bins.length, y = canvas.height * (1 - Math.log1p(n) / Math.log1p(peak));
      if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
    });
    g.stroke();
  });
}

function sendSettings() {
  if (!state.socket || state.socket.readyState !== WebSocket.OPEN) return;
  const exposure = Number($("exposure").value), frame = Number($("psp-frame").value);
  const gain = $("gain").value === "" ? null : Number($("gain").value);
  const refused = !(exposure >= 0.001 && exposure <= 1000) ? "exposure must be between 0.001 and 1000 (times the rig's): not sent"
    : !Number.isInteger(frame) || frame < 0 ? "the PSP frame is a whole number from 0: not sent"
    : gain !== null && !(gain >= 0 && gain <= 1000) ? "the gain is a number from 0 to 1000 in the camera's unit (empty: as the rig opened it): not sent"
    : null;
  if (refused) { say(refused); state.refused = refused; return; }
  if (state.refused && $("message").textContent === state.refused) say("");  // (the settings are sent now)
  state.refused = null;
  state.socket.send(JSON.stringify({
    pattern: $("pattern").value, exposure, gain, psp_frame: frame, decode: $("decode").checked,
  }));
  $("decode-panel").hidden = !$("decode").checked;
  if (!$("decode").checked) $("depth-panel").hidden = true;
}

// The rig is one: every page of the view shares its settings. A frame taken with another page's settings
// (by_other) puts them in this page's controls, so that what the page shows is what it says.
function adoptSettings(message) {
  if (!message.by_other || !message.settings) return;
  const s = message.settings;
  if ([...$("pattern").options].some((o) => o.value === s.pattern)) $("pattern").value = s.pattern;
  $("exposure").value = s.exposure;
  $("gain").value = s.gain === null ? "" : s.gain;
  $("psp-frame").value = s.psp_frame;
  $("decode").checked = s.decode;
  $("decode-panel").hidden = !s.decode;
  if (!s.decode) $("depth-panel").hidden = true;
  state.adopted = true;
}

function connectLive() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const socket = new WebSocket(`${scheme}://${location.host}/ws/live?token=${encodeURIComponent(TOKEN)}`);
  socket.binaryType = "blob";
  let header = null;
  socket.onopen = () => { state.socket = socket; state.failedConnects = 0; sendSettings(); $("status").textContent = "live"; };
  socket.onclose = (event) => {  // the server says why where it can (e.g. the live views already open, a wrong token)
    state.socket = null;
    const again = ![1000, 1013, 4403].includes(event.code);  // dropped (the server restarted, the network): try again
    state.failedConnects = (state.failedConnects || 0) + 1;
    const gone = again && state.failedConnects > 1 && !event.reason;  // (it never opened again since)
    $("status").textContent = gone ? "live: the view does not answer (stopped?); trying again every 2 s"
      : (event.reason ? `live view closed: ${event.reason}` : "live view closed") + (again ? " (connecting again …)" : "");
    if (event.code === 4403) say(event.reason);
    if (again) setTimeout(connectLive, 2000);
  };
  socket.onmessage = (event) => {
    if (typeof event.data !== "string") {
      const old = $("live-image").src, shown = header;
      $("live-image").onload = () => { state.shown = shown; };  // what the image on the page is, once it is drawn
      $("live-image").src = URL.createObjectURL(event.data);
      $("live-image").hidden = false;
      if (old.startsWith("blob:")) URL.revokeObjectURL(old);
      if (header) {
        clearLiveError();  // frames again: the error is over
        $("status").textContent = `live: ${header.pattern}, exposure ${header.exposure}` +  // (what this frame was taken with)
          (header.gain === null ? "" : `, gain ${header.gain}`) + (header.by_other ? " (set by another page of this view)" : "");
        state.lastFrameAt = Date.now();
        state.frames += 1;
        $("frame-count").textContent = state.frames;
        $("fps").textContent = header.fps.toFixed(1);
        $("latency").textContent = (Date.now() - header.requested_ms).toFixed(0);
        $("mean").textContent = header.mean.map((m) => m.toFixed(3)).join(" / ");
        $("clipped").textContent = (100 * header.clipped).toFixed(2) + "%";
        drawHistogram(header.histogram);
      }
      return;
    }
    const message = JSON.parse(event.data);
    adoptSettings(message);
    if (message.type === "frame") { header = message; return; }
    if (message.type === "error") {
      state.liveError = `live: ${message.message}`;
      say(state.liveError);
      $("status").textContent = "live: no frame (see the message)";
      return;
    }
    if (message.type === "decode" && $("decode").checked) {  // (one asked before the box was unticked: not shown)
      clearLiveError();
      state.decodes = (state.decodes || 0) + 1;
      $("status").textContent = `live decode: set ${state.decodes} in ${message.seconds.toFixed(1)} s, exposure ` +
        `${message.settings.exposure}` + (message.settings.gain === null ? "" : `, gain ${message.settings.gain}`) +
        (message.by_other ? " (turned on by another page of this view)" : "") + " · the live frame pauses while it decodes";
      $("decode-mask").src = "data:image/png;base64," + message.mask_png;
      $("decode-modulation").src = "data:image/png;base64," + message.modulation_png;
      $("decode-seconds").textContent = message.seconds.toFixed(2);
      $("decode-valid").textContent = (100 * message.valid).toFixed(1) + "%";
      $("modulation-range").textContent = message.modulation_range.map((v) => v.toPrecision(3)).join(" … ");
      $("threshold").textContent = message.threshold;
      $("reasons").innerHTML = Object.entries(message.reasons).map(([k, v]) => `<tr><td>${k}</td><td>${v}</td></tr>`).join("");
      $("depth-panel").hidden = false;  // the depth and surface maps where a calibration is known, else why not
      for (const kind of ["depth", "surface"]) {
        $("decode-" + kind).hidden = !message[kind + "_png"];
        if (message[kind + "_png"]) $("decode-" + kind).src = "data:image/png;base64," + message[kind + "_png"];
      }
      $("depth-range").textContent = message.depth_range ? message.depth_range.map((v) => v.toPrecision(4)).join(" … ") : "";
      $("depth-unit").textContent = message.depth_unit || "";
      $("depth-note").textContent = message.depth_note || "";
    }
  };
}

function clearLiveError() {
  if (state.liveError && $("message").textContent === state.liveError) say("");
  state.liveError = null;
}

for (const id of ["pattern", "exposure", "gain", "psp-frame", "decode"]) $(id).onchange = sendSettings;

// a stream that stalls (a daemon gone: the error comes when its call times out) says so, not "live" on a still frame
setInterval(() => {
  const waited = (Date.now() - (state.lastFrameAt || Date.now())) / 1000;
  if (state.socket && !$("decode").checked && waited > 3 && !state.liveError) {
    $("status").textContent = `live: no frame for ${waited.toFixed(0)} s (waiting for the rig` +
      (waited > 8 ? ": a camera this slow, or a daemon that stopped, is told when its call times out)" : ")");
  }
}, 1000);

// The size of the frame on the page, (height, width): naturalWidth/Height read 0 while the next frame loads.
function shownSize() {
  const img = $("live-image");
  return state.shown ? state.shown.shape.slice(0, 2) : [img.naturalHeight, img.naturalWidth];
}

$("zoom").onchange = () => {
  const zoom = Number($("zoom").value), img = $("live-image");
  img.style.width = zoom ? `${shownSize()[1] * zoom}px` : "";
  img.style.maxWidth = img.style.maxHeight = zoom ? "none" : "";
};

$("live-image").onclick = async (event) => {
  const rect = $("live-image").getBoundingClientRect(), [height, width] = shownSize();
  if (!width || !rect.width) return;  // no frame yet
  const x = Math.floor((event.clientX - rect.left) * width / rect.width);
  const y = Math.floor((event.clientY - rect.top) * height / rect.height);
  const current = ticket("live-probe");
  try {
    const p = await (await api(`/api/live/pixel?x=${x}&y=${y}`)).json();
    if (!current()) return;
    $("live-probe").textContent = `(${x}, ${y}) linear ${p.linear.map((v) => v.toFixed(4)).join(" / ")}, on the sensor `
      + `${p.sensor.map((v) => v.toFixed(3)).join(" / ")}${p.sensor.some((v) => v >= p.clip) ? " CLIPPED" : ""}`;
    state.liveProbe = p;
  } catch (e) { if (current()) say(e.message); }
};

// --- sessions ---------------------------------------------------------------------------------------------
function views(sessionSelect, viewSelect) {
  const session = state.sessions.find((s) => s.name === sessionSelect.value);
  fill(viewSelect, session ? session.views.map((v) => v.view) : []);
}

// --- 3D points: the view's (or a turntable session's merged) decoded points, turned by dragging -------------------
const cloud = { xyz: null, rgb: null, count: 0, yaw: 0, pitch: 0, zoom: 1, centre: [0, 0, 0], radius: 1, draws: 0 };

function decoded(b64, Type) {
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  return new Type(bytes.buffer);
}

function loadCloud(answer) {
  cloud.xyz = decoded(answer.xyz, Float32Array);
  cloud.rgb = decoded(answer.rgb, Uint8Array);
  cloud.count = answer.count;
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < cloud.count; i++) {
    for (let k = 0; k < 3; k++) { const v = cloud.xyz[3 * i + k]; if (v < lo[k]) lo[k] = v; if (v > hi[k]) hi[k] = v; }
  }
  cloud.centre = lo.map((l, k) => (l + hi[k]) / 2);
  cloud.radius = Math.max(1e-9, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2);
  cloud.yaw = cloud.pitch = 0;
  cloud.zoom = 1;
}

function drawCloud() {
  const canvas = $("map-canvas"), g = canvas.getContext("2d"), W = canvas.width, H = canvas.height;
  const image = g.createImageData(W, H), depth = new Float32Array(W * H).fill(Infinity);
  for (let i = 3; i < image.data.length; i += 4) image.data[i] = 255;
  const [cx, cy, cz] = cloud.centre, s = cloud.zoom * 0.45 * Math.min(W, H) / cloud.radius;
  const cyaw = Math.cos(cloud.yaw), syaw = Math.sin(cloud.yaw), cpit = Math.cos(cloud.pitch), spit = Math.sin(cloud.pitch);
  for (let i = 0; i < cloud.count; i++) {
    const x = cloud.xyz[3 * i] - cx, y = cloud.xyz[3 * i + 1] - cy, z = cloud.xyz[3 * i + 2] - cz;
    const x1 = cyaw * x + syaw * z, z1 = -syaw * x + cyaw * z;  // turned about the vertical, then tilted
    const y2 = cpit * y - spit * z1, z2 = spit * y + cpit * z1;
    const u = Math.round(W / 2 + s * x1), v = Math.round(H / 2 + s * y2);
    for (let dv = 0; dv < 2; dv++) for (let du = 0; du < 2; du++) {  // 2 x 2 px points, nearest in front
      const uu = u + du, vv = v + dv;
      if (uu < 0 || vv < 0 || uu >= W || vv >= H || z2 >= depth[vv * W + uu]) continue;
      depth[vv * W + uu] = z2;
      const o = 4 * (vv * W + uu), near = 1 - 0.5 * Math.min(1, Math.max(0, (z2 + cloud.radius) / (2 * cloud.radius)));
      image.data[o] = near * cloud.rgb[3 * i]; image.data[o + 1] = near * cloud.rgb[3 * i + 1];
      image.data[o + 2] = near * cloud.rgb[3 * i + 2];  // the far side darker: depth at a glance
    }
  }
  g.putImageData(image, 0, 0);
  cloud.draws += 1;
}

{
  const canvas = $("map-canvas");
  let last = null;
  canvas.onpointerdown = (e) => { last = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); };
  canvas.onpointerup = () => { last = null; };
  canvas.onpointermove = (e) => {
    if (!last || !cloud.count) return;
    cloud.yaw += 0.01 * (e.clientX - last[0]);
    cloud.pitch = Math.max(-1.5, Math.min(1.5, cloud.pitch - 0.01 * (e.clientY - last[1])));
    last = [e.clientX, e.clientY];
    drawCloud();
  };
  canvas.onwheel = (e) => { e.preventDefault(); cloud.zoom *= Math.exp(-0.001 * e.deltaY); if (cloud.count) drawCloud(); };
}

async function showCloud(name, view, current) {
  const radius = $("crop").value.trim();
  const query = radius ? `?radius=${encodeURIComponent(radius)}` : "";
  const answer = await (await api(`/api/sessions/${encodeURIComponent(name)}/${view}/points${query}`)).json();
  if (!current()) return;
  loadCloud(answer);
  drawCloud();
  $("map-range").textContent = `${answer.count} points, ${answer.unit}`;
  $("map-unit").textContent = `(${answer.which}; drag to turn, wheel to zoom)`;
  state.cloud = { count: answer.count, views: answer.views, which: answer.which };
}

async function showMap() {
  const name = $("session").value, view = $("session-view").value, kind = $("map").value;
  if (!name) return;
  const current = ticket("map");
  $("map-image").hidden = kind === "points";
  $("map-canvas").hidden = kind !== "points";
  $("map-bar").hidden = kind === "points";
  $("map-hint").hidden = kind === "points";
  $("crop").hidden = $("crop-label").hidden = kind !== "points";
  try {
    if (kind === "points") { await showCloud(name, view, current); if (current()) say(""); return; }
    const response = await api(`/api/sessions/${encodeURIComponent(name)}/${view}/map/${kind}.png`);
    const blob = await response.blob();
    if (!current()) return;
    $("map-image").src = URL.createObjectURL(blob);
    $("map-range").textContent = kind === "surface" ? "" : response.headers.get("X-Range").replace(",", " … ");
    $("map-unit").textContent = response.headers.get("X-Unit");
    $("map-bar").hidden = kind === "white" || kind === "surface";  // images, not colour-mapped values
    say("");
  } catch (e) { if (current()) say(e.message); }
}

$("map-image").onclick = async (event) => {
  const img = $("map-image"), rect = img.getBoundingClientRect();
  const x = Math.floor((event.clientX - rect.left) * img.naturalWidth / rect.width);
  const y = Math.floor((event.clientY - rect.top) * img.naturalHeight / rect.height);
  const current = ticket("probe");
  try {
    const probe = await (await api(`/api/sessions/${encodeURIComponent($("session").value)}/${$("session-view").value}/pixel?x=${x}&y=${y}`)).json();
    if (!current()) return;
    $("probe").hidden = false;
    $("probe-info").textContent = `pixel (${x}, ${y}) ` + (probe.valid ? `→ projector (${probe.projector.map((v) => v.toFixed(2)).join(", ")})` : "(not decoded)");
    $("probe-patch").src = "data:image/png;base64," + probe.patch_png;
    $("probe-names").textContent = probe.footprint_names.join(" | ");
    $("probe-footprints").src = probe.footprints_png ? "data:image/png;base64," + probe.footprints_png : "";
    $("probe-skipped").textContent = Object.entries(probe.skipped).map(([k, v]) => `${k}: ${v}`).join("; ");
    state.probe = probe;
    say("");
  } catch (e) { if (current()) say(e.message); }
};

$("session").onchange = () => { views($("session"), $("session-view")); showMap(); };
$("session-view").onchange = showMap;
$("map").onchange = showMap;
$("crop").onchange = showMap;

// --- relight ------------------------------------------------------------------------------------------------
$("relight-session").onchange = () => views($("relight-session"), $("relight-view"));
$("relight-pattern").onchange = () => {  // a named pattern chosen after an upload: that pattern, not the upload
  state.uploaded = null;
  $("upload").value = "";
  $("relight-info").textContent = `pattern: ${$("relight-pattern").value}`;
};

// only the latest upload (file or drawing) sets the pattern or says what went wrong
const uploadPattern = async (body, label) => {
  const current = ticket("upload");
  state.uploaded = null;
  $("relight-info").textContent = `uploading ${label} …`;
  $("relight-notes").textContent = "";  // (the last relight's, not this pattern's)
  try {
    const response = await api("/api/upload", { method: "POST", body });
    const answer = await response.json();
    if (!current()) return;
    state.uploaded = answer.name;
    say("");
    $("relight-info").textContent = `pattern: ${label}${answer.sequence ? " (a sequence: every frame is relit)" : ""}`;
  } catch (e) {
    if (!current()) return;
    $("relight-info").textContent = "";
    say(e.message);
  }
};

$("upload").onchange = () => {
  const file = $("upload").files[0];
  if (file) uploadPattern(file, `${file.name} (uploaded)`);
};

// a pattern drawn on the page: white strokes on black at the projector's aspect, uploaded like a file
(() => {
  const canvas = $("draw"), g = canvas.getContext("2d");
  let down = false;
  const clear = () => { g.fillStyle = "#000"; g.fillRect(0, 0, canvas.width, canvas.height); };
  const at = (e) => { const r = canvas.getBoundingClientRect();
    return [(e.clientX - r.left) * canvas.width / r.width, (e.clientY - r.top) * canvas.height / r.height]; };
  clear();
  canvas.onmousedown = (e) => { down = true; g.beginPath(); g.moveTo(...at(e)); };
  canvas.onmousemove = (e) => { if (!down) return; g.lineTo(...at(e)); g.strokeStyle = "#fff"; g.lineWidth = 12;
    g.lineCap = "round"; g.stroke(); };
  window.addEventListener("mouseup", () => { down = false; });
  $("draw-clear").onclick = clear;
  $("draw-use").onclick = () => canvas.toBlob((blob) => {
    uploadPattern(blob, "the drawing");
  }, "image/png");
})();

// a relit sequence plays as a flipbook of its display frames, at the sequence's frame rate; a click on the image
// pauses it (and plays it again), the caption says which frame is shown
function playFrames(frames, fps) {
  clearInterval(state.flipbook);
  const urls = frames.map((u) => `${u}?token=${encodeURIComponent(TOKEN)}`);
  for (const url of urls) new Image().src = url;  // loaded ahead, so that the frames follow each other smoothly
  state.frame = 0;
  const show = () => {
    $("relit-image").src = urls[state.frame % urls.length];
    $("relit-frame").textContent = `frame ${state.frame % urls.length + 1} of ${urls.length}${state.flipbook ? "" : " (paused: click to play)"}`;
    state.frame += 1;
  };
  const play = () => { state.flipbook = setInterval(show, 1000 / Math.min(Math.max(fps || 25, 1), 60)); };
  $("relit-image").hidden = false;
  $("relit-image").onclick = () => {
    if (state.flipbook) { clearInterval(state.flipbook); state.flipbook = null; state.frame -= 1; show(); } else play();
  };
  play();
  show();
}

async function followJob(id, current) {
  for (;;) {
    const job = await (await api(`/api/relight/jobs/${id}`)).json();
    if (!current()) return null;
    if (job.status === "failed" || job.status === "stopped") throw new Error(job.error);
    if (job.status === "done") return job;
    $("relight-info").textContent = job.total ? `${job.step}: ${job.done} of ${job.total} …`
      : "relighting (the first frame computes the view's footprints) …";
    await new Promise((resolve) => setTimeout(resolve, 500));
  }
}

async function relightSequence(answer, current) {
  state.job = answer.job;
  $("relight-stop").hidden = false;
  let job;
  try { job = await followJob(answer.job, current); } finally { $("relight-stop").hidden = true; }
  if (!job) return;
  playFrames(job.frames, job.fps);
  $("relight-info").textContent = `${job.frames.length} frames at ${job.fps} frames/s: ${job.seconds.toFixed(1)} s`;
  $("relight-notes").textContent = job.notes.join("\n");
  $("downloads").innerHTML = job.video ? `<a href="${job.video}?token=${encodeURIComponent(TOKEN)}" download>video (MP4, MPEG-4 Part 2)</a>` : "";
  $("compare-image").hidden = true;
  state.relit = { sequence: job };
  say("");
}

$("relight-stop").onclick = () => {
  if (state.job) api(`/api/relight/jobs/${state.job}/stop`, { method: "POST" }).catch((e) => say(e.message));
};

$("relight-button").onclick = async () => {
  const pattern = state.uploaded || $("relight-pattern").value;
  clearInterval(state.flipbook);
  state.flipbook = null;
  $("relit-image").onclick = null;
  $("relit-frame").textContent = "";
  say("");
  $("relight-info").textContent = "relighting (the first pattern of a view computes its footprints) …";
  $("relight-notes").textContent = "";
  const current = ticket("relight");
  try {
    const response = await api("/api/relight", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ session: $("relight-session").value, view: Number($("relight-view").value),
                             backend: $("backend").value, pattern, resize: "fit" }),
    });
    const result = await response.json();
    if (result.job) { await relightSequence(result, current); return; }
    const png = await (await api(result.files.display || result.files.png)).blob();
    const figure = result.figure ? await (await api(result.figure)).blob() : null;
    if (!current()) return;
    $("relit-image").src = URL.createObjectURL(png);
    $("relit-image").hidden = false;  // (no empty frame before the first relight)
    const metrics = result.metrics ? ` · PSNR ${result.metrics.psnr.toFixed(2)} dB, SSIM ${result.metrics.ssim.toFixed(3)}` : "";
    $("relight-info").textContent = `${result.backend}, ${result.pattern}: ${result.seconds.toFixed(2)} s${metrics}`;
    $("relight-notes").textContent = (result.notes || []).join("\n");
    $("downloads").innerHTML = Object.entries(result.files)
      .map(([kind, url]) => `<a href="${url}?token=${encodeURIComponent(TOKEN)}" download>${
        { png: "PNG (16-bit linear)", exr: "EXR (float, linear)", display: "PNG (display)" }[kind] || kind}</a>`).join(" · ");
    if (figure) {
      $("compare-image").src = URL.createObjectURL(figure);
      $("compare-image").hidden = false;
    } else { $("compare-image").hidden = true; }
    state.relit = result;
    say("");
  } catch (e) {
    if (!current()) return;
    $("relight-info").textContent = "";
    $("relit-image").hidden = $("compare-image").hidden = true;  // not the last relight's image beside this error
    $("downloads").innerHTML = "";
    say(e.message);
  }
};

// --- start ---------------------------------------------------------------------------------------------------
(async () => {
  try {
    const info = await (await api("/api/state")).json();
    state.sessions = info.sessions;
    fill($("pattern"), info.patterns);
    fill($("backend"), info.backends.filter((b) => info.checkpoint || !["torch", "blend"].includes(b)));
    fill($("relight-pattern"), info.relight_patterns);
    for (const select of [$("session"), $("relight-session")]) fill(select, info.sessions.map((s) => s.name));
    views($("session"), $("session-view"));
    views($("relight-session"), $("relight-view"));
    showMap();
    connectLive();
    const damaged = Object.entries(info.damaged || {});  // listed beside the sessions, not as a passing message
    $("damaged").textContent = damaged.length ? `left out, cannot be opened:\n${damaged.map(([name, why]) => `${name}: ${why}`).join("\n")}` : "";
  } catch (e) { say(e.message); }
})();
